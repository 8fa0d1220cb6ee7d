"""How well the calibrated model is known, pose by pose: ``sigma_mm`` at the tool point.

The unknowns' posterior covariance is carried to all 6N + 12 error parameters and the effects'
parameters ``[p_e, θ]``: ``Σ = (JᵀWJ / s² + P)⁺`` with J the training rows' Jacobian in every one
of them (the tracker pose is the base transform's six), W the fitted rows' weights, s² the a
posteriori variance factor and P the prior's precision (campaign.model.priors, the tolerances)
on what the fit did not determine from the data: a least-squares fit's held and dependent
parameters (the fitted ones carry no prior, so their σ is least squares'), a MAP fit's every
parameter at its fitted strength. A direction the training poses do not see (a joint that never
moved) thus keeps its tolerance, and shows at the poses that move it.

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


def posterior_covariance(model, q, Y, context=None) -> tuple:
    """(Σ (6N + 12 + k, 6N + 12 + k), names): the covariance of ``[p_e, θ]`` of a fitted
    CalibrationModel on its training data (q, Y as given to ``fit``), in SI units."""
    robot, es = model.robot, model.effect_set_
    n_p = robot.n_params
    points = model._points()
    J = full_jacobian(robot, es, q, model.params_, model.effect_params_, context, points=points,
                      T_meas=None if points is not None else np.asarray(Y, dtype=float))
    sig = model.row_sigma_
    if points is None:
        J = J[:, model._rows(), :]
    else:
        J = J * np.repeat(np.isfinite(np.asarray(Y)).all(axis=2), 3, axis=1)[:, :, None]
    Jw = (J / sig[None, :, None]).transpose(2, 1, 0).reshape(J.shape[2], -1)
    H = Jw @ Jw.T
    e = model.residual_at_fit_ / sig
    dof = max(model.n_equations_ - model.n_effective_, 1.0)
    s2 = float(np.sum(e ** 2)) / dof  # the variance factor at the fit's final weights
    from campaign.model.priors import make_prior

    prior = make_prior(robot, es.effects)
    precision = prior.precision().copy()
    if model.kind_ == "map":
        precision *= float(model.prior_strength)
    else:  # least squares: no prior on what the fit determined from the data
        fitted = [model.cols_[i] if i < len(model.cols_) else n_p + i - len(model.cols_) for i in model.free_]
        precision[fitted] = 0.0
    A = H / s2 + np.diag(precision)
    w, V = np.linalg.eigh(A)
    keep = w > max(w.max(), 1e-300) * 1e-14
    cov = (V[:, keep] / w[keep]) @ V[:, keep].T
    names = tuple(robot.param_names) + tuple(es.param_names)
    return 0.5 * (cov + cov.T), names


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


def model_uncertainty(model, q, Y, context=None, noise_floor=None) -> Uncertainty:
    """The :class:`Uncertainty` of a fitted CalibrationModel (q, Y, context: its training data)."""
    cov, names = posterior_covariance(model, q, Y, context)
    sys_m, basis = systematic_sigma(model, noise_floor)
    return Uncertainty(names, cov, sys_m, basis)
