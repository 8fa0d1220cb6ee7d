"""How well the calibrated model is known, pose by pose: ``sigma_mm`` at the tool point.

The fit's unknowns (base parameters, or every error parameter of a MAP fit on the redundant model;
the effects' parameters; the tracker pose is the base transform's six) have the posterior covariance
``Σ = (JᵀWJ / s² + P)⁺``, J the training rows' Jacobian at the optimum in every unknown (held ones
too), W the fitted rows' weights, s² the a posteriori variance factor and P the prior's precision
(campaign.model.priors, the tolerances) on what the fit did not determine from the data: a
least-squares fit's held unknowns only (the fitted ones carry no prior, so their σ is least
squares'), a MAP fit's every unknown at its fitted strength. A direction the training poses do not
see (a joint that never moved) thus keeps its tolerance, and shows at the poses that move it. It is
carried to all 6N + 12 error parameters and the effects' ``[p_e, θ]`` (the dependent parameters at
zero: the predictions depend on the base parameters only).

At a pose q the model's position covariance is ``J_t(q) Σ J_t(q)ᵀ`` (J_t the tool point's rows),
plus, per axis, the model's systematic error beyond the noise, ``s_sys² = σ_fit² − σ_floor²``
when the measured noise floor says the fit leaves more than the noise (significantly: beyond
twice the difference's standard error); without a floor there is no telling systematic error
from noise and it is left out, said so. ``sigma_mm = √trace`` in mm. A neural stage's own
uncertainty is not estimated: its rows carry the physical model's, said so.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from campaign.identify.solver import CalibrationModel
from campaign.tolerances import TRACKER_NOISE_MIN_M, UNSEEN_TOOL_RTOL


def full_jacobian(robot, effect_set, q, p_e, theta, context=None, *, T_meas=None, points=None) -> np.ndarray:
    """The derivative of the model's rows in every error parameter and effect parameter at
    (p_e, θ): (n, 6, 6N + 12 + k) of Δz against T_meas (default: the model's own pose), or with
    ``points`` (k, 3) m in the tool frame (n, k·3, 6N + 12 + k) of those points' positions."""
    m = CalibrationModel(robot=robot, effects=effect_set.effects, points=points)
    m.effect_set_ = effect_set
    m.cols_ = list(range(robot.n_params))
    q = np.asarray(q, dtype=float)
    context = context or {}
    if points is not None:
        J = m._point_jacobian(q, p_e, theta, context)
        return J.reshape(len(q), -1, J.shape[-1])
    if T_meas is None and effect_set.effects:
        T_meas = m._model_T(q, p_e, theta, context)
    return m._jacobian(q, p_e, theta, context, T_meas)


def unknowns_covariance(model) -> np.ndarray:
    """(r + k, r + k): the covariance of a fitted CalibrationModel's unknowns (its ``unknown_names_``:
    base parameters, or every error parameter for MAP on the redundant model, then the effects'),
    from the fit's own Jacobian at the optimum on its training rows (``jacobian_at_fit_``, every
    unknown, held ones too): ``(JᵀWJ / s² + P)⁺``, P the fit's prior on its free unknowns (none for
    least squares) and the tolerance prior on the held ones (a base parameter's marginal prior
    variance, ``C Σ₀ Cᵀ``)."""
    from campaign.identify.solver import _normal_equations
    from campaign.model.priors import make_prior

    robot, es = model.robot, model.effect_set_
    n_p, r = robot.n_params, len(model.cols_)
    sig = model.row_sigma_
    J = model.jacobian_at_fit_
    e = model.residual_at_fit_ / sig
    dof = max(model.n_equations_ - model.n_effective_, 1.0)
    s2 = float(np.sum(e ** 2)) / dof  # the variance factor at the fit's final weights
    # a fit with hardly more equations than unknowns passes through its positions (noise 0.02 µm on 6
    # poses): no tracker measures so well (noise_below_floor), and its covariance would say the model is
    # exact at the poses it measured; the positions' noise is then the fit's starting guess
    position = np.ones(len(sig), dtype=bool) if model.points is not None else np.arange(len(sig)) < 3
    sig = np.where(position & (sig * np.sqrt(s2) < TRACKER_NOISE_MIN_M), model.sigma_position_m / np.sqrt(s2), sig)
    H, _ = _normal_equations(J / sig[None, :, None], np.zeros(J.shape[:2]))
    prior = make_prior(robot, es.effects)
    strength = float(model.prior_strength) if model.kind_ == "map" else 1.0
    if r == n_p and model.kind_ == "map" and model.physical:  # the redundant model: every physical parameter
        geometric = prior.precision()[:n_p]
    else:
        var = np.diag(prior.base_covariance(model.base_))
        geometric = np.where(var > 0, 1.0 / np.where(var > 0, var, 1.0), 0.0)
    tolerance_precision = np.concatenate([geometric, prior.precision()[n_p:]])
    # a prior weaker than the tolerances (leave-one-out's choice when the data determine the rest) is
    # no knowledge that a direction the data do not see lies wider than the tolerances: at strength
    # 0.001 a joint that never moved gave sigma_mm 100 mm where the model was 2 mm off
    at_least_tolerance = max(strength, 1.0) / strength if strength > 0 else 1.0
    held = strength * at_least_tolerance * tolerance_precision
    P = np.diag(held)
    free = np.asarray(model.free_, dtype=int)
    P[np.ix_(free, free)] = model.fit_prior_precision_ * at_least_tolerance if model.kind_ == "map" else 0.0
    A = H / s2 + P
    w, V = np.linalg.eigh(A)
    # A direction whose information is lost in A's round-off (a joint that never moved, beside rows of
    # a fit whose variance factor is tiny: 1e-16 of the largest) has at least the tolerance's precision
    # there, never an infinite one: dropped, it gave the least known direction a variance of zero
    # (sigma_mm 0.03 mm where the model was 2 mm off, 8 poses, joint 6 never moved)
    tolerance = np.einsum("ij,i,ij->j", V, tolerance_precision, V)
    lost = w <= max(w.max(), 1e-300) * 1e-14
    w = np.where(lost, np.maximum(w, tolerance), w)
    keep = w > 0
    cov = (V[:, keep] / w[keep]) @ V[:, keep].T
    return 0.5 * (cov + cov.T)


def posterior_covariance(model) -> tuple:
    """(Σ (6N + 12 + k, 6N + 12 + k), names): the unknowns' covariance (:func:`unknowns_covariance`)
    carried to ``[p_e, θ]`` (the error parameters outside the unknowns, dependent on the base
    parameters, at zero: the model's predictions do not depend on them), SI units."""
    robot, es = model.robot, model.effect_set_
    n_p = robot.n_params
    idx = list(model.cols_) + [n_p + i for i in range(es.n_params)]
    cov = np.zeros((n_p + es.n_params, n_p + es.n_params))
    cov[np.ix_(idx, idx)] = unknowns_covariance(model)
    if model.points is not None and len(model.cols_) < n_p:  # a pose's parameters the points never see
        unseen = unseen_covariance(model)
        if unseen is not None:
            cov[:n_p, :n_p] += unseen
    return cov, tuple(robot.param_names) + tuple(es.param_names)


def unseen_covariance(model) -> np.ndarray:
    """(6N + 12, 6N + 12): the tolerances' covariance in the directions of the error parameters that
    the measured rows do not see (given the base parameters ``C p``: ``Σ₀ − Σ₀Cᵀ(CΣ₀Cᵀ)⁻¹CΣ₀``). Nothing
    at the tool point for 6-D poses or its own position (the base set is that of the tool pose); the
    rotation about two reflectors' line moves the tool frame's origin, which they never measured
    (sigma_mm 0.007 mm where the model was 0.08 mm off, 40 poses of two reflectors). None when the tool
    point's nominal rows lie within what the points see (three reflectors): at the fitted parameters they
    leave it by their first order only, which the tolerances of the base's pose would magnify tenfold."""
    from campaign.model.priors import make_prior

    N = _unseen_projector(model)
    if N is None:
        return None
    out = (N * make_prior(model.robot, ()).sigma ** 2) @ N.T
    return 0.5 * (out + out.T)


def _unseen_projector(model):
    """(6N + 12, 6N + 12) the projector onto the error parameters' directions the fit's base set does
    not see, when the tool point's nominal position moves along them (UNSEEN_TOOL_RTOL); else None."""
    from campaign.model.kinematics import error_jacobian

    robot = model.robot
    C = np.asarray(model.base_.combination, dtype=float)
    N = np.eye(C.shape[1]) - np.linalg.pinv(C) @ C
    q = np.random.default_rng(0).uniform(robot.q_lower, robot.q_upper, size=(20, robot.n_joints))
    J = error_jacobian(robot, q)[:, :3, :]
    return N if np.linalg.norm(J @ N) > UNSEEN_TOOL_RTOL * np.linalg.norm(J) else None


def unseen_at_tool(model) -> list:
    """[names of the largest parameters of a direction]: the directions the measured points do not see
    that move the tool point (two reflectors: the tool's rotation about their line); [] when none."""
    from campaign.model.kinematics import error_jacobian
    from campaign.model.priors import make_prior

    if model.points is None or len(model.cols_) == model.robot.n_params:
        return []
    N = _unseen_projector(model)
    if N is None:
        return []
    robot = model.robot
    q = np.random.default_rng(0).uniform(robot.q_lower, robot.q_upper, size=(20, robot.n_joints))
    JN = (error_jacobian(robot, q)[:, :3, :] @ N) * make_prior(robot, ()).sigma  # at the tolerances
    _, s, vt = np.linalg.svd(JN.reshape(-1, robot.n_params), full_matrices=False)
    out = []
    for k in np.flatnonzero(s > 0.1 * s[0]):
        v = np.abs(vt[k])
        out.append([robot.param_names[i] for i in np.argsort(-v)[:3] if v[i] >= 0.25 * v.max()])
    return out


def systematic_sigma(model, noise_floor: dict | None) -> tuple:
    """(s_sys m per axis, basis text): the fit's position noise beyond the measured floor, when
    significant; 0 with the reason otherwise."""
    fit_m = model.noise_sigma_["position_m"]
    sig = (noise_floor or {}).get("sigma_position_mm")
    if not sig or model.points is not None:
        what = "no noise floor" if not sig else "raw reflectors (the floor is the tool point's)"
        return 0.0, (f"parameter uncertainty only ({what}: the model's systematic error cannot be told from the "
                     "noise)")
    floor_m = float(np.mean(sig)) * 1e-3
    dof = max(model.n_equations_ - model.n_effective_, 1.0)
    diff = fit_m ** 2 - floor_m ** 2
    rel = (noise_floor or {}).get("relative_uncertainty") or 0.0
    se = np.hypot(fit_m ** 2 * np.sqrt(2.0 / dof), 2.0 * rel * floor_m ** 2)
    if diff > 2.0 * se:
        return float(np.sqrt(diff)), (f"parameter uncertainty plus the fit's error beyond the noise floor "
                                      f"({np.sqrt(diff) * 1e6:.1f} µm per axis)")
    return 0.0, "parameter uncertainty (the fit leaves no error beyond the noise floor)"


@dataclass(frozen=True)
class Uncertainty:
    """The calibrated model's uncertainty: ``covariance`` of ``[p_e, θ]`` (``names``), SI, and the
    systematic ``systematic_sigma_m`` per axis; ``basis`` says what is in it."""

    names: tuple
    covariance: np.ndarray
    systematic_sigma_m: float = 0.0
    basis: str = ""

    def sigma_m(self, robot, effect_set, p_e, theta, q, context=None) -> np.ndarray:
        """(n,) m: √trace of the position covariance at the tool point for joint coordinates q (n, N)."""
        q = np.asarray(q, dtype=float).reshape(-1, robot.n_joints)
        if not len(q):
            return np.zeros(0)
        w, V = np.linalg.eigh(self.covariance)
        keep = w > 0
        L = V[:, keep] * np.sqrt(w[keep])
        out = np.empty(len(q))
        for s in range(0, len(q), 4096):  # bounded memory for long programs
            J = full_jacobian(robot, effect_set, q[s:s + 4096], p_e, theta,
                              {k: np.asarray(v)[s:s + 4096] for k, v in (context or {}).items()})[:, :3, :]
            out[s:s + 4096] = np.sqrt(np.sum((J @ L) ** 2, axis=(1, 2)) + 3 * self.systematic_sigma_m ** 2)
        return out

    def sigma_from_jacobian(self, J, model) -> np.ndarray:
        """(n,) m: the same from the tool point's position rows J (n, 3, r + k) in a fitted model's
        unknowns (its ``jacobian_at_fit_[:, :3]`` at its own poses: no kinematics again)."""
        n_p = model.robot.n_params
        idx = list(model.cols_) + [n_p + i for i in range(model.effect_set_.n_params)]
        w, V = np.linalg.eigh(self.covariance[np.ix_(idx, idx)])
        L = V[:, w > 0] * np.sqrt(w[w > 0])
        JL = np.asarray(J, dtype=float).reshape(-1, J.shape[-1]) @ L
        return np.sqrt(np.sum(JL.reshape(len(J), -1) ** 2, axis=1) + 3 * self.systematic_sigma_m ** 2)

    def as_json(self) -> dict:
        return {"names": list(self.names), "covariance": [[float(v) for v in row] for row in self.covariance],
                "systematic_sigma_m": float(self.systematic_sigma_m), "basis": self.basis}

    @classmethod
    def from_json(cls, d, where: str) -> "Uncertainty":
        from campaign.errors import DataError

        try:
            names = tuple(str(n) for n in d["names"])
            cov = np.asarray(d["covariance"], dtype=float)
            sys_m = float(d.get("systematic_sigma_m", 0.0))
        except (KeyError, TypeError, ValueError) as exc:
            raise DataError(f"{where}: malformed ({exc.__class__.__name__}: {exc})") from None
        if cov.shape != (len(names), len(names)) or not np.all(np.isfinite(cov)) or not np.isfinite(sys_m):
            raise DataError(f"{where}: covariance must be {len(names)} x {len(names)} finite values")
        return cls(names, cov, sys_m, str(d.get("basis", "")))


def model_uncertainty(model, noise_floor=None) -> Uncertainty:
    """The :class:`Uncertainty` of a fitted CalibrationModel (noise_floor: NoiseFloor.as_json() or None)."""
    cov, names = posterior_covariance(model)
    sys_m, basis = systematic_sigma(model, noise_floor)
    return Uncertainty(names, cov, sys_m, basis)
