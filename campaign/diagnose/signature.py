"""The signature of an unexplained residual, in words a person can act on.

* **depends on**: the inputs of the model-free test ranked by permutation importance.
* **periodic in q_j with order k**: the held-out position residual, resolved in joint j's
  frame after its motion (there an error that turns with joint j, such as a bearing run-out,
  is a function of q_j times a lever that does not depend on q_j), is fitted by harmonics
  sin(k q_j), cos(k q_j), k ≤ 3, against a polynomial with as many coefficients; when the
  harmonics win by BIC and beat a constant, the order is that of the largest harmonic.
* **grows with time**: partial dependence of the regressor on time. Every held-out pose is
  predicted as if measured at each tenth of the campaign (time set to the 10 %, 20 %, …, 90 %
  quantiles); the change since the first, ``D(t) = mean ‖f̂(x; t) − f̂(x; t₁₀)‖``, must reach
  half the prediction's mean size. It *grows* when D rises steadily (no step back by more than a
  tenth of its total), else it *varies*. The change, not the residual's size: the geometric
  model absorbs the mean of an effect, so the residual of an effect that grows linearly with
  time is largest at both ends of the campaign, while its change since the start grows.
* **grows with the gravity load**: a second regressor, on the gravity load alone (the joints'
  gravity torques and the overturning moment's size, Pinocchio on the URDF's inertias), fitted
  on the same folds to the same residuals: when it reaches :data:`GRAVITY_SHARE` of the main
  regressor's held-out gain the residual is a function of the load; a load-times-configuration
  error (joint compliance: the deflection also depends on the arm's pose) reaches less, so
  :data:`GRAVITY_SHARE_WITH_RHO` is enough when the main regressor's error size also rises
  with ‖τ‖ (Spearman ρ ≥ :data:`MIN_RHO`, p < 0.01); a strong rank correlation alone
  (ρ ≥ :data:`MIN_RHO_ALONE`) also counts. A residual periodic in a joint angle
  (a run-out) is not a function of the torques, which do not tell q from its mirror image
  about the horizontal; one in exactly cos q_j of a horizontal joint is, and may be named both.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np
from scipy import stats

#: largest harmonic order tried
MAX_ORDER = 3
#: BIC advantage (nats) the harmonic model needs over the constant and the polynomial
MIN_BIC_GAIN = 10.0
#: time quantiles at which every held-out pose is predicted (the tenths of the campaign)
TIME_QUANTILES = np.linspace(0.1, 0.9, 9)
#: the change since the first tenth must reach this share of the prediction's mean size
MIN_TIME_CHANGE = 0.5
#: a steady change may step back by at most this share of its total between tenths
STEADY_SLACK = 0.1
#: share of the main regressor's held-out gain a regressor on the gravity load alone must reach
GRAVITY_SHARE = 0.8
#: ... or this share when the error's size also rises with the load (rank correlation)
GRAVITY_SHARE_WITH_RHO = 0.6
#: the rank correlation of the regressor's error size with ‖τ‖ (significant at p < 0.01)
MIN_RHO = 0.3
#: ... that alone says the error grows with the load (the elastic ground: its tilt turns with q1,
#: which the load's features do not carry, but its size follows the overturning moment)
MIN_RHO_ALONE = 0.5


@dataclass(frozen=True)
class Signature:
    depends_on: tuple
    periodic: dict = field(default_factory=dict)  # "q2" -> order
    #: "time_s" -> {"change_mm", "steady"}; "gravity load" -> {"share_of_gain", "spearman_rho", "spearman_p"}
    growth: dict = field(default_factory=dict)
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
                parts.append(f"{'grows' if value['steady'] else 'varies'} with time (changes by "
                             f"{1e3 * value['change_mm']:.3g} µm from the first to the last tenth of the campaign"
                             f"{'' if value['steady'] else ', not steadily'})")
            else:
                share = min(100 * value["share_of_gain"], 100)
                load = (f"a regressor on the load alone finds {share:.0f} % of what one on all inputs finds; "
                        if share >= 100 * GRAVITY_SHARE_WITH_RHO else "")
                # "grows" only where the error's size rises with the load; a function of the load whose
                # size does not (ρ near 0: the geometry absorbed its mean) is that, no more
                rises = value["spearman_rho"] >= MIN_RHO and value.get("spearman_p", 0.0) < 0.01
                parts.append(f"{'grows with' if rises else 'is a function of'} the {name} ({load}the error's size "
                             f"against ‖τ‖: Spearman ρ {value['spearman_rho']:+.2f}"
                             + ("" if rises else ", so its size does not rise with the load") + ")")
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


def time_change(struct, X, j) -> tuple:
    """The regressor's partial dependence on input j (time): (D (len(TIME_QUANTILES),) mm, the
    mean change since the first tenth per tenth of the campaign; steady: bool)."""
    grid = np.quantile(X[:, j], TIME_QUANTILES)
    preds = []
    for t in grid:
        Xt = X.copy()
        Xt[:, j] = t
        preds.append(struct.predict_heldout(Xt))
    D = np.array([np.linalg.norm(p - preds[0], axis=1).mean() * 1e3 for p in preds])
    steady = bool(np.all(np.diff(D) >= -STEADY_SLACK * D.max()))
    return D, steady


def load_features(robot, q) -> tuple:
    """The gravity load of each pose, Pinocchio on the URDF's inertias: (L (n, m) N·m: the joints'
    gravity torques that vary and the overturning moment's size; their names; ‖τ‖ (n,) N·m)."""
    from campaign.effects.gravity import gravity_torques, overturning_moment

    tau = np.asarray(gravity_torques(robot, q), dtype=float)
    M = np.linalg.norm(overturning_moment(robot, q), axis=1)
    keep = np.ptp(tau, axis=0) > 1e-9 * max(float(np.ptp(tau)), 1e-300)
    names = [f"tau{j + 1}" for j in np.flatnonzero(keep)] + ["|M|"]
    return np.column_stack([tau[:, keep], M]), tuple(names), np.linalg.norm(tau, axis=1)


def describe(robot, q, X, input_names, struct, depends_on, residual_frame1, time_s, residual_fit=None) -> Signature:
    """Words for an unexplained residual; q (n, N) rad and residual (n, 3) m of the held-out poses
    (in the frame after joint 1); residual_fit: fold -> residuals of the fold's model at its
    fitting poses (what the structure test was fitted to), for the gravity-load regressor."""
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
        D, steady = time_change(struct, X, list(input_names).index("time_s"))
        if D.max() >= MIN_TIME_CHANGE * size.mean() * 1e3:
            growth["time_s"] = {"change_mm": float(D[-1] if steady else D.max()), "steady": steady}
    if joints and residual_fit is not None and struct.heldout_gain > 0:
        try:
            L, names, tau_norm = load_features(robot, q)
        except Exception:  # a robot without inertias: no gravity statement
            L = None
        if L is not None:
            from campaign.diagnose.structure import structure_test

            load = structure_test(L, names, struct.fold, residual_fit, residual_frame1,
                                  importance=False)
            share = load.heldout_gain / struct.heldout_gain
            rho, p = stats.spearmanr(tau_norm, size)
            rho = float(rho) if np.isfinite(rho) else 0.0
            strong = rho >= MIN_RHO_ALONE and p < 0.01
            if strong or share >= GRAVITY_SHARE or (share >= GRAVITY_SHARE_WITH_RHO and rho >= MIN_RHO and p < 0.01):
                growth["gravity load"] = {"share_of_gain": float(share), "spearman_rho": rho,
                                          "spearman_p": float(p) if np.isfinite(p) else 1.0}
    not_on = tuple(n for n in input_names if not n.startswith("q") and n not in depends_on)
    return Signature(tuple(depends_on), periodic, growth, not_on)
