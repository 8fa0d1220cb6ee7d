"""Model choice for small campaigns: least squares, MAP with the priors, or a reduced set,
chosen by the cross-validated held-out error on the training poses only.

Candidates (docs/priors.md):

- ``lsq``: the base parameters by least squares (the paper's);
- ``map``: MAP with the tolerance priors (campaign.model.priors), the prior's precision scaled
  by a strength s from :data:`STRENGTHS`; the CV curve is the held-out error against s;
- ``reduced``: least squares with the base parameters whose least-squares σ exceeds their
  prior σ held at zero (FIGAROH's rule: a parameter the data know worse than the drawings).

The held-out error of each candidate is its closed-form leave-one-out error for the
linearised problem at its fit (the MAP candidates: at the Gauss-Newton step from the least-squares
fit to each strength's MAP, on one linearisation of the redundant model): a pose's block of whitened residuals ``e_i`` becomes
``(I - H_ii)⁻¹ e_i`` with ``H_ii = J_i (JᵀJ + P)⁻¹ J_iᵀ`` (exact for the linear problem with the
prior rows kept; Hastie et al., Elements of Statistical Learning §7.10 for the single-row case).
Its mean position error (m) is the score. ``auto`` takes the least restrictive candidate
(least squares, then MAP by rising strength, then the reduced set) whose score is within
:data:`CHOICE_SE` standard errors of the best one's (the paired per-pose differences; Hastie et
al. §7.10's one-standard-error rule, made stricter), and it replaces least squares only when it is
also :data:`CHOICE_MARGIN` better. From :data:`CV_MAX_TRAIN_POSES` training poses on,
``auto`` is least squares outright: the priors change nothing there and the fit stays today's.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from campaign.errors import ConfigError
from campaign.identify.solver import CalibrationModel

#: ``auto`` cross-validates below this many training poses, and is least squares from there
CV_MAX_TRAIN_POSES = 300

#: prior strengths s (factor on the prior's precision) of the MAP candidates: the CV curve's x.
#: Half decades from 0.001: a real robot's errors can be ten times its drawings' tolerances
#: (FIGAROH's TIAGo: its best held-out strength is 0.03, between the decades 0.01 and 0.1)
STRENGTHS = (0.001, 0.003, 0.01, 0.03, 0.1, 0.3, 1.0, 3.0, 10.0, 100.0, 1000.0)

#: another candidate replaces least squares only when its CV error is lower by this fraction:
#: the CV estimate of a 20-120 pose campaign scatters by a few percent, and least squares is
#: the unbiased default (benchmarks/bench_small.py)
CHOICE_MARGIN = 0.03

#: ``auto`` takes the least restrictive candidate whose CV error is within this many standard errors
#: (of the paired per-pose differences) of the lowest one. Measured on 500 fresh poses per campaign
#: (UR10, Panda, COMAU, 20 poses within ±0.15 rad, 5 seeds each; one reflector and 6-D): with 1,
#: a seed's held-out error was up to 5 % above least squares'; with 2, at most 0.5 %; on 30 random
#: splits of FIGAROH's TIAGo, with 2 the held-out mean was 0.993x an independent fit's on average
#: and more than 2 % behind it on 1 split (with 1: 0.937x, but 6 splits 2-16 % behind)
CHOICE_SE = 2.0

MODELS = ("lsq", "map", "auto")

#: the MAP candidates' form (CalibrationModel's ``physical``): False, the base parameters with the
#: prior carried to them (the least-squares model, shrunk). The redundant model (True: every
#: physical parameter in the second-order terms too) fits its barely identifiable directions to
#: the noise: benchmarks/results/small.json's grid chose it on 20-pose campaigns by a cross-
#: validation 3 % better and it was up to 29 % worse on the test poses
MAP_PHYSICAL = False

#: Monte-Carlo draws per pose for the expected norm of a Gaussian error (fixed seed)
_NORM_DRAWS = 512


def check_model(model: str) -> str:
    """``--model``: one of lsq, map, auto; ConfigError otherwise."""
    if model not in MODELS:
        raise ConfigError(f"--model must be one of {', '.join(MODELS)}, got {model!r}")
    return model


@dataclass(frozen=True)
class ModelChoice:
    """Which model `calibrate` identified and why (metrics.json's ``"model"``).

    choice: "lsq", "map" or "reduced"; strength: the MAP's prior strength (None otherwise);
    dropped: base parameters held at zero (reduced); candidates: [{"model", "strength",
    "dropped", "cv_mean_position_mm", "n_effective"}]; cv_curve: [{"strength",
    "cv_mean_position_mm"}] of the MAP candidates; reason: one sentence."""

    choice: str
    asked: str
    reason: str
    strength: float | None = None
    dropped: tuple = ()
    candidates: list = field(default_factory=list)
    cv_curve: list = field(default_factory=list)
    method: str | None = None
    fixed: dict = field(default_factory=dict)
    tolerances: dict | None = None

    def model_kwargs(self) -> dict:
        """The CalibrationModel hyperparameters of the choice (for a model with effects, too)."""
        if self.choice == "map":
            return {"prior": "tolerances", "prior_strength": self.strength, "physical": MAP_PHYSICAL}
        if self.choice == "reduced":
            return {"drop": self.dropped}
        return {}

    def as_json(self) -> dict:
        return {"choice": self.choice, "asked": self.asked, "reason": self.reason, "strength": self.strength,
                "dropped": list(self.dropped), "candidates": self.candidates, "cv_curve": self.cv_curve,
                "cv_method": self.method, "fixed": self.fixed, "tolerances": self.tolerances}


def loo_position_errors(model: CalibrationModel) -> np.ndarray:
    """(n,) m: each training pose's leave-one-out position error (closed form, linearised at the
    fit): the norm of its position rows (pose data), or the mean norm over its seen reflectors."""
    return _loo(model.fit_jacobian_, model.fit_residual_, model.fit_prior_precision_, model.row_sigma_,
                model.points is not None)


def _loo(J, e, P, sig, points: bool) -> np.ndarray:
    """:func:`loo_position_errors` of a linear problem: whitened J (n, m, f) and residuals
    e (n, m) at its solution, prior precision P (f, f), rows' σ (m,)."""
    n, m, f = J.shape
    J2 = J.reshape(-1, f)
    A_inv = np.linalg.pinv(J2.T @ J2 + P, hermitian=True)
    H = np.einsum("nif,fg,njg->nij", J, A_inv, J)
    Imh = np.eye(m)[None] - H
    try:
        e_loo = np.linalg.solve(Imh, e[:, :, None])[:, :, 0]
    except np.linalg.LinAlgError:  # a pose with leverage 1: no prediction without it
        e_loo = np.einsum("nij,nj->ni", np.linalg.pinv(Imh), e)
    e_loo = e_loo * sig[None, :]
    if not points:
        return np.linalg.norm(e_loo[:, :3], axis=1)
    seen = (np.abs(J).sum(axis=2) > 0).reshape(n, -1, 3).all(axis=2)
    d = np.linalg.norm(e_loo.reshape(n, -1, 3), axis=2)
    return np.where(seen, d, 0.0).sum(axis=1) / np.maximum(seen.sum(axis=1), 1)


def least_restrictive_within_se(loo: list, n_se: float = CHOICE_SE) -> int:
    """The index of the first candidate (ordered from the least to the most restrictive) whose mean
    leave-one-out error is within ``n_se`` standard errors of the lowest one's; ``loo``: one (n,)
    array of per-pose errors per candidate. The standard error is that of the paired per-pose
    differences: the candidates are scored on the same poses, and a CV error lower by less than
    its scatter is no evidence for a stronger prior. The lowest CV error among near-equal
    candidates is the one the scatter favours: on 30 random splits of FIGAROH's TIAGo (decades
    0.1-1000) it was 2-52 % behind an independent fit on 8 splits' test poses."""
    means = [float(np.mean(e)) for e in loo]
    best = int(np.argmin(means))
    for i, e in enumerate(loo):
        d = np.asarray(e) - np.asarray(loo[best])
        se = float(np.std(d, ddof=1) / np.sqrt(len(d))) if len(d) > 1 else 0.0
        if np.mean(d) <= n_se * se:
            return i
    return best


def fit_model(make, q, Y, context=None, *, model: str = "auto", fixed=None, progress=None):
    """Fit the geometric model of a campaign and choose among the candidates.

    make: ``make(**hyperparameters)`` -> an unfitted CalibrationModel (robot, kind, points...);
    q (n, N), Y: the training data as ``CalibrationModel.fit`` takes them; model: "lsq", "map"
    or "auto"; fixed: ``--fix`` ({name: value or None}). Returns (fitted model, ModelChoice)."""
    say = progress or (lambda msg: None)
    check_model(model)
    n_train = len(q)
    lsq = make(fixed=fixed).fit(q, Y, context)
    tolerances = None
    if model == "lsq" or (model == "auto" and n_train >= CV_MAX_TRAIN_POSES):
        reason = ("asked for (--model lsq)" if model == "lsq" else
                  f"{n_train} training poses: at or above {CV_MAX_TRAIN_POSES}, where least squares is chosen "
                  "without cross-validation (the priors no longer change the fit)")
        return lsq, ModelChoice("lsq", model, reason, fixed=dict(lsq.held_))
    say(f"model choice: closed-form leave-one-out on the {n_train} training poses")
    init = dict(lsq.values_)
    loo = [loo_position_errors(lsq)]  # per pose, m; in the candidates' order, least restrictive first
    candidates = [{"model": "lsq", "strength": None, "dropped": [], "cv_mean_position_mm": 1e3 * float(np.mean(loo[0])),
                   "n_effective": lsq.n_effective_}]
    fitted = {("lsq", None): lsq}
    curve = []
    # the MAP candidates from one linearisation of the redundant model at the least-squares fit:
    # a Gauss-Newton step to each strength's MAP, scored by its closed-form leave-one-out
    sig = lsq.row_sigma_
    probe = make(fixed=fixed, prior="tolerances", prior_strength=1.0, physical=MAP_PHYSICAL, max_iter=0,
                 estimate_noise=False,
                 sigma_position_m=float(sig[0]), sigma_orientation_rad=float(sig[3]) if len(sig) == 6 else 1.0
                 ).fit(q, Y, context, init=init)
    tolerances = probe.prior_.tolerances
    J, e0, P1 = probe.fit_jacobian_, probe.fit_residual_, probe.fit_prior_precision_
    J2 = J.reshape(-1, J.shape[2])
    H, g = J2.T @ J2, J2.T @ e0.reshape(-1)
    x0 = probe.x_[probe.free_] - probe.fit_prior_mean_
    for s in STRENGTHS:
        dx = -np.linalg.solve(H + s * P1, g + s * P1 @ x0)
        e = e0 + J @ dx
        loo.append(_loo(J, e, s * P1, sig, probe.points is not None))
        score = 1e3 * float(np.mean(loo[-1]))
        n_eff = float(np.trace(np.linalg.solve(H + s * P1, H)))
        curve.append({"strength": s, "cv_mean_position_mm": score})
        candidates.append({"model": "map", "strength": s, "dropped": [], "cv_mean_position_mm": score,
                           "n_effective": n_eff})
    # FIGAROH's rule: the base parameters the data know worse than the prior does
    prior_sd = np.sqrt(np.diag(probe.base_prior_.covariance))
    free_base = [j for j in range(lsq.base_.n_base) if lsq.base_.names[j] not in lsq.held_]
    dropped = tuple(lsq.base_.names[j] for j in free_base if lsq.base_sigma_[j] > prior_sd[j])
    if dropped and len(dropped) < len(free_base):  # a model with nothing left to fit is no candidate
        m = make(fixed=fixed, drop=dropped).fit(q, Y, context, init=init)
        loo.append(loo_position_errors(m))
        candidates.append({"model": "reduced", "strength": None, "dropped": list(dropped),
                           "cv_mean_position_mm": 1e3 * float(np.mean(loo[-1])), "n_effective": m.n_effective_})
        fitted[("reduced", None)] = m
    if model == "auto":
        best = candidates[least_restrictive_within_se(loo)]
    else:
        best = min((c for c in candidates if c["model"] == "map"), key=lambda c: c["cv_mean_position_mm"])
    lsq_cv = candidates[0]["cv_mean_position_mm"]
    if model == "auto" and best["model"] != "lsq" and best["cv_mean_position_mm"] > (1 - CHOICE_MARGIN) * lsq_cv:
        best = candidates[0]
    if best["model"] == "map":  # the chosen strength's MAP, fitted on the nonlinear model
        fitted[("map", best["strength"])] = make(fixed=fixed, prior="tolerances", prior_strength=best["strength"],
                                                 physical=MAP_PHYSICAL).fit(q, Y, context, init=init)
    chosen = fitted[(best["model"], best["strength"])]
    what = {"lsq": lambda: "least squares", "map": lambda: f"MAP with the priors at strength {best['strength']:g}",
            "reduced": lambda: f"least squares without {len(dropped)} base parameters the data know worse than "
                               "the prior"}[best["model"]]()
    reason = (f"{what}: leave-one-out mean {best['cv_mean_position_mm']:.4f} mm on the {n_train} training poses "
              f"(least squares {lsq_cv:.4f} mm)" + (f"; the least restrictive model within {CHOICE_SE:g} standard errors "
                                                    "of the best, and another than least squares only when it is at "
                                                    f"least {100 * CHOICE_MARGIN:.0f} % better" if model == "auto" else ""))
    return chosen, ModelChoice(best["model"], model, reason, best["strength"], tuple(best["dropped"]), candidates,
                               curve, "leave-one-out, closed form for the linearised problem", dict(lsq.held_),
                               tolerances)


def expected_heldout_mm(model: CalibrationModel, q, context=None) -> float:
    """The expected held-out mean position error (mm) of ``model`` at the joint vectors ``q``
    (n, N): E‖e‖ for e ~ N(0, σ̂² I + J Σ Jᵀ), the fit's noise σ̂ (the floor in the model's own
    terms) plus its posterior covariance Σ carried to the positions (at the tool point; raw
    reflectors: at each reflector, averaged)."""
    q = np.asarray(q, dtype=float)
    cov = model.covariance_
    if model.points is None:
        J = model.jacobian(q, model.predict(q, context), context)[:, :3, :]
        sig = model.row_sigma_[:3]
        C = (J @ cov) @ J.transpose(0, 2, 1) + np.diag(sig ** 2)[None]  # J Σ Jᵀ + σ̂² I, (n, 3, 3)
    else:
        Jp = model.point_jacobian(q, context)  # (n, k, 3, p)
        n, k = Jp.shape[:2]
        J = Jp.reshape(n * k, 3, -1)
        C = (J @ cov) @ J.transpose(0, 2, 1) + np.diag(model.row_sigma_[:3] ** 2)[None]
    z = np.random.default_rng(0).standard_normal((_NORM_DRAWS, 3))
    w, V = np.linalg.eigh(C)
    L = V * np.sqrt(np.clip(w, 0, None))[:, None, :]
    e = L @ z.T  # (n, 3, draws): the draws of e at each pose (matmul: a tenth of einsum's time)
    norms = np.sqrt(np.einsum("nid,nid->nd", e, e)).mean(axis=1)
    return 1e3 * float(norms.mean())


def check_model_options(robot, effects, model: str, fix) -> dict:
    """Validate ``--model`` and ``--fix`` before any fit: ``fix`` (a ``NAME[=VALUE],...`` string or
    a {name: value or None} dict) resolved to {parameter name: value or None}; ConfigError naming
    the option otherwise."""
    from campaign.effects.base import make_effect
    from campaign.model.priors import parse_fix, resolve_fix

    check_model(model)
    fix = parse_fix(fix) if isinstance(fix, str) else dict(fix or {})
    effect_names = tuple(f"{e.name}.{p}" for e in (make_effect(x, robot) for x in effects) for p in e.param_names)
    return resolve_fix(robot, fix, effect_names)


def geometric_fix(fix) -> dict:
    """The geometric error parameters among resolved ``--fix`` names (not ``<effect>.<param>``)."""
    return {k: v for k, v in (fix or {}).items() if "." not in k}


def choice_json(choice: ModelChoice, model: CalibrationModel, q_test, *, ctx_te=None, stages=None, stage=None,
                fix=None) -> dict:
    """metrics.json's ``"model"``: the choice, its candidates and CV curve, what was held, and the
    expected held-out mean position error of the identified model next to the measured one."""
    out = choice.as_json()
    out["fixed"] = {k: (0.0 if v is None else float(v)) for k, v in (fix or {}).items()}
    out["held_base_parameters"] = dict(model.held_)
    out["kind"] = model.kind_
    expected = expected_heldout_mm(model, q_test, ctx_te) if len(q_test) else None
    measured = None
    if stages is not None and stage in stages:
        test = stages[stage]["test"]
        block = test.get("reflector_position_mm") if model.points is not None else test.get("position_mm")
        measured = None if block is None else block.get("mean")
    out["expected_heldout_mean_position_mm"] = expected
    out["measured_heldout_mean_position_mm"] = measured
    out["expected_at"] = "each reflector" if model.points is not None else "the tool point"
    out["stage"] = stage
    return out


def choice_text(choice: dict) -> str:
    """The model choice in a few lines (the printed summary and the report)."""
    stage = choice.get("stage")
    scope = "" if stage in (None, "geometric") else \
        f" for the geometry alone, chosen before the effects of {stage} (scored on the test set below)"
    lines = [f"model: {choice['choice']}{scope} ({choice['reason']})"]
    if choice.get("cv_curve"):
        lines.append("leave-one-out mean position error on the training poses (mm) against the prior strength: "
                     + ", ".join(f"{c['strength']:g}: {c['cv_mean_position_mm']:.4f}" for c in choice["cv_curve"]))
    if choice.get("fixed"):
        lines.append("held (--fix): " + ", ".join(f"{k} = {v:g}" for k, v in choice["fixed"].items()))
    e, m = choice.get("expected_heldout_mean_position_mm"), choice.get("measured_heldout_mean_position_mm")
    if e is not None and m is not None:
        lines.append(f"test-set mean position error at {choice['expected_at']}: expected {e:.4f} mm (the fit's noise "
                     f"and its posterior), measured {m:.4f} mm ({m / e:.2f}x the expected)")
    return "\n".join(lines)
