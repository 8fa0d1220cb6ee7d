"""The signature of an unexplained residual, in words a person can act on.

* **depends on**: the inputs of the model-free test ranked by permutation importance.
* **periodic in q_j with order k**: the held-out position residual, resolved in joint j's
  frame after its motion (there an error that turns with joint j, such as a bearing run-out,
  is a function of q_j times a lever that does not depend on q_j), is fitted by harmonics
  sin(k q_j), cos(k q_j), k ≤ 3, against a polynomial with as many coefficients; when the
  harmonics win by BIC and beat a constant, the order is that of the largest harmonic.
* **grows with time**: partial dependence of the regressor — the mean size of its held-out
  prediction ‖f̂‖ with every pose's time set to the campaign's 90 % quantile over that with
  the 10 % quantile, reported when ≥ 1.5 (or ≤ 1/1.5).
* **grows with the gravity load**: Spearman correlation between ‖f̂‖ and the gravity
  torques' norm ‖τ(q)‖ (Pinocchio), ρ ≥ 0.3 at p < 0.01.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np
from scipy import stats

#: largest harmonic order tried
MAX_ORDER = 3
#: a rank correlation this strong (and significant) is reported as growth
MIN_RHO = 0.3
#: the regressor's error grows (or shrinks) by this factor between the first and last tenth of time
MIN_GROWTH_RATIO = 1.5
#: BIC advantage (nats) the harmonic model needs over the constant and the polynomial
MIN_BIC_GAIN = 10.0


@dataclass(frozen=True)
class Signature:
    depends_on: tuple
    periodic: dict = field(default_factory=dict)  # "q2" -> order
    growth: dict = field(default_factory=dict)  # "time_s" -> late/early ratio; "gravity load" -> Spearman ρ
    not_on: tuple = ()  # inputs tested and not depended on (time_s, context)

    def as_json(self) -> dict:
        return {"depends_on": list(self.depends_on), "periodic": dict(self.periodic),
                "growth": dict(self.growth), "not_on": list(self.not_on)}

    def text(self) -> str:
        parts = []
        if self.depends_on:
            dep = list(self.depends_on)
            parts.append("depends on " + (", ".join(dep[:-1]) + " and " + dep[-1] if len(dep) > 1 else dep[0]))
        for name, k in self.periodic.items():
            parts.append(f"periodic in {name} with order {k}")
        for name, value in self.growth.items():
            if name == "time_s":
                parts.append(f"{'grows' if value > 1 else 'shrinks'} with time (×{value:.2g} from the first to "
                             "the last tenth of the campaign)")
            else:
                parts.append(f"grows with the {name} (Spearman ρ {value:+.2f})")
        if self.not_on:
            parts.append("not on " + ", ".join("time" if n == "time_s" else n for n in self.not_on))
        return "; ".join(parts) if parts else "no clear dependence"


def _bic(Y, A):
    coef, *_ = np.linalg.lstsq(A, Y, rcond=None)
    rss = float(np.sum((Y - A @ coef) ** 2))
    n = Y.size
    return n * np.log(max(rss, 1e-300) / n) + A.shape[1] * Y.shape[1] * np.log(n), coef


def harmonic_order(x, Y) -> int | None:
    """Dominant harmonic order of Y (n, m) against an angle x (n,) rad, or None when the
    dependence is not periodic (see the module's docstring)."""
    x = np.asarray(x, dtype=float)
    Y = np.asarray(Y, dtype=float)
    ones = np.ones((len(x), 1))
    bic0, _ = _bic(Y, ones)
    best = None
    xs = (x - x.mean()) / max(x.std(), 1e-12)
    for K in range(1, MAX_ORDER + 1):
        H = np.column_stack([ones] + [f(k * x) for k in range(1, K + 1) for f in (np.sin, np.cos)])
        P = np.column_stack([xs ** p for p in range(0, 2 * K + 1)])
        bic_h, coef = _bic(Y, H)
        bic_p, _ = _bic(Y, P)
        if bic_h < bic0 - MIN_BIC_GAIN and bic_h < bic_p and (best is None or bic_h < best[0]):
            amp = [np.sqrt(np.sum(coef[1 + 2 * (k - 1)] ** 2 + coef[2 + 2 * (k - 1)] ** 2)) for k in range(1, K + 1)]
            best = (bic_h, int(np.argmax(amp)) + 1)
    return None if best is None else best[1]


def describe(robot, q, X, input_names, struct, depends_on, residual_frame1, time_s) -> Signature:
    """Words for an unexplained residual; q (n, N) rad and residual (n, 3) m of the held-out poses."""
    from campaign.model.kinematics import frames

    periodic = {}
    joints = [name for name in depends_on if name.startswith("q") and name[1:].isdigit()]
    if joints:
        R, _ = frames(robot, q)
        R1 = R[:, robot.joint_frame_index[0]]
        dt = np.einsum("nij,nj->ni", R1, residual_frame1)  # back in F_I
        for name in joints:
            j = int(name[1:]) - 1
            Rj = R[:, robot.joint_frame_index[j]]
            order = harmonic_order(q[:, j], np.einsum("nji,nj->ni", Rj, dt))
            if order is not None:
                periodic[name] = order
    size = np.linalg.norm(struct.prediction, axis=1)
    growth = {}
    if "time_s" in depends_on:
        # partial dependence: every held-out pose as if measured early, then late in the campaign
        j = list(input_names).index("time_s")
        early, late = X.copy(), X.copy()
        early[:, j], late[:, j] = np.quantile(X[:, j], 0.1), np.quantile(X[:, j], 0.9)
        e = np.linalg.norm(struct.predict_heldout(early), axis=1).mean()
        l_ = np.linalg.norm(struct.predict_heldout(late), axis=1).mean()
        ratio = l_ / max(e, 1e-300)
        if ratio >= MIN_GROWTH_RATIO or ratio <= 1.0 / MIN_GROWTH_RATIO:
            growth["time_s"] = float(ratio)
    try:
        from campaign.effects.gravity import gravity_torques

        tau = np.linalg.norm(gravity_torques(robot, q), axis=1)
        rho, p = stats.spearmanr(tau, size)
        if rho >= MIN_RHO and p < 0.01:
            growth["gravity load"] = float(rho)
    except Exception:  # a robot without inertias: no gravity statement
        pass
    not_on = tuple(n for n in input_names if not n.startswith("q") and n not in depends_on)
    return Signature(tuple(depends_on), periodic, growth, not_on)
