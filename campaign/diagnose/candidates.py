"""Scoring a candidate effect on one diagnosis fold without refitting the current model.

On each fold the current model (geometry + the effects already in it) has been fitted on the
fold's other poses; it is at its least-squares optimum x̂. Adding a candidate effect at its
start values (zeros for every built-in) leaves every model pose unchanged, so at the start
point of the joint fit ``[x̂, θ₀]`` the Jacobian's columns of the current unknowns are those
of the current model at x̂: :func:`linearise` computes them once per fold and every candidate
reuses them. Only the candidate's own columns are new (central differences of the model in
its parameters, step :data:`FD_STEP` of the parameter's unit, as the solver's).

The joint fit is then Levenberg-Marquardt with that start Jacobian kept (the chord method):
each step solves the normal equations of the start Jacobian for the true residual at the
current point, so a step costs one evaluation of the model instead of a new Jacobian. The
effects are small (µm to mm on a metre-sized arm), the problem is nearly linear and the
iteration converges to the joint least-squares optimum up to a term of the order of the
Jacobian's change times the residual (noise); tests/test_diagnose_candidates.py checks the
held-out errors against a full :class:`~campaign.identify.solver.CalibrationModel` refit.

Which candidate parameters the current unknowns already span (*absorbed*, held at zero) is
decided as the solver decides it: the QR of the column-normalised weighted regressor at the
start point, the candidate's columns after the current ones, a diagonal below
``max(BASE_PARAM_RANK_RTOL, 1e-6)`` of the base columns' largest.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from campaign.effects.base import EffectSet, model_pose
from campaign.model.kinematics import pose_error
from campaign.tolerances import BASE_PARAM_RANK_RTOL, IDENT_COST_RTOL, IDENT_STEP_TOL

#: central-difference step of a candidate's parameters, in the parameter's unit (the solver's)
FD_STEP = 1e-6
#: chord-method Levenberg-Marquardt steps at most (converges in 2-4 on small effects)
MAX_STEPS = 30
#: a candidate column nearly spanned by the current ones is absorbed (the solver's looser bound)
ABSORBED_RTOL = max(BASE_PARAM_RANK_RTOL, 1e-6)


@dataclass(frozen=True)
class FoldLinearisation:
    """The current model fitted on one fold's fitting poses, linearised at its optimum.

    model: the fitted CalibrationModel; rows: the Δz rows used (positions, or all six);
    sigma: (len(rows),) row weights (m, rad); J: (n·rows, u) weighted Jacobian of the u current
    unknowns; residual: (n·rows,) weighted residual at the optimum; Q: (n·rows, u) orthonormal
    basis of J's normalised columns (the QR behind ``absorbed``); ref_diag: the largest QR
    diagonal of the base columns; free: indices of the current unknowns that are fitted (not
    absorbed); H: JᵀJ over those.
    """

    model: object
    rows: slice
    sigma: np.ndarray
    J: np.ndarray = field(repr=False)
    residual: np.ndarray = field(repr=False)
    Q: np.ndarray = field(repr=False)
    ref_diag: float
    free: np.ndarray
    H: np.ndarray = field(repr=False)


def _weighted(dz, rows, sigma):
    return (dz[:, rows] / sigma).reshape(-1)


def linearise(model, q, T_meas, context) -> FoldLinearisation:
    """Linearise a fitted current model (CalibrationModel, fixed noise weights) at its optimum,
    on the poses it was fitted on: q (n, N) rad, T_meas (n, 4, 4), context per pose."""
    rows = slice(0, 3) if model.position_only else slice(0, 6)
    noise = model.noise_sigma_
    sigma = np.array([noise["position_m"]] * 3 + [noise["orientation_rad"] or 1.0] * 3)[rows]
    Jfull = model.jacobian(q, T_meas, context)[:, rows, :] / sigma[None, :, None]
    J = Jfull.reshape(-1, Jfull.shape[2])
    residual = _weighted(model.residuals(q, T_meas, context), rows, sigma)
    norms = np.linalg.norm(J, axis=0)
    Q, R = np.linalg.qr(J / np.where(norms > 0, norms, 1.0))
    r = model.base_.n_base
    d = np.abs(np.diag(R))
    ref = float(d[:r].max() if r else d.max())
    free = np.array([i for i in range(J.shape[1]) if i not in set(model.absorbed_)], dtype=int)
    Jf = J[:, free]
    return FoldLinearisation(model, rows, sigma, J, residual, Q, ref, free, Jf.T @ Jf)


@dataclass(frozen=True)
class CandidateFit:
    """A candidate fitted jointly with the current model on one fold.

    heldout_dz: (n_out, 6) Δz at the held-out poses; absorbed: names of the candidate's
    parameters held at zero; params: the candidate's fitted parameters; n_steps: chord steps.
    """

    heldout_dz: np.ndarray = field(repr=False)
    absorbed: tuple
    params: np.ndarray
    n_steps: int


def fit_candidate(lin: FoldLinearisation, effect, q, T_meas, context, q_out, T_out, context_out) -> CandidateFit:
    """Fit ``effect`` (an Effect instance) jointly with the fold's current model on its fitting
    poses (q, T_meas, context: those :func:`linearise` saw) and predict the held-out poses."""
    m = lin.model
    robot = m.robot
    es = EffectSet((*m.effect_set_.effects, effect))
    r = m.base_.n_base
    u = lin.J.shape[1]
    k = effect.n_params
    x0 = np.concatenate([m.x_, np.asarray(effect.initial_params(), dtype=float)])

    def dz(x, qq, TT, ctx):
        return pose_error(model_pose(robot, qq, m.base_.expand(x[:r]), es, x[r:], ctx), TT)

    def weighted_residual(x):
        return _weighted(dz(x, q, T_meas, context), lin.rows, lin.sigma)

    res = weighted_residual(x0)
    # the candidate's columns at the start point, central differences
    C = np.empty((len(res), k))
    for i in range(k):
        xp, xm = x0.copy(), x0.copy()
        xp[u + i] += FD_STEP
        xm[u + i] -= FD_STEP
        C[:, i] = (weighted_residual(xp) - weighted_residual(xm)) / (2 * FD_STEP)
    # absorbed: what is left of each normalised candidate column after the current columns
    # and the candidate's earlier ones (the diagonal of the joint QR)
    norms = np.linalg.norm(C, axis=0)
    Cn = C / np.where(norms > 0, norms, 1.0)
    Cp = Cn - lin.Q @ (lin.Q.T @ Cn)
    d = np.abs(np.diag(np.linalg.qr(Cp)[1])) if k else np.zeros(0)
    absorbed_c = [i for i in range(k) if d[i] < ABSORBED_RTOL * lin.ref_diag or norms[i] == 0]
    free_c = np.array([i for i in range(k) if i not in absorbed_c], dtype=int)
    x = x0
    n_steps = 0
    if len(free_c):
        Jf = lin.J[:, lin.free]
        Cf = C[:, free_c]
        cross = Jf.T @ Cf
        H = np.block([[lin.H, cross], [cross.T, Cf.T @ Cf]])
        free = np.concatenate([lin.free, u + free_c])
        cost = float(res @ res)
        lam = 0.0
        for n_steps in range(1, MAX_STEPS + 1):
            g = np.concatenate([Jf.T @ res, Cf.T @ res])
            accepted = False
            for _ in range(12):
                try:
                    step = -np.linalg.solve(H + lam * np.diag(np.diag(H)), g)
                except np.linalg.LinAlgError:
                    lam = max(10 * lam, 1e-6)
                    continue
                x_new = x.copy()
                x_new[free] += step
                res_new = weighted_residual(x_new)
                cost_new = float(res_new @ res_new)
                if cost_new <= cost:
                    accepted = True
                    break
                lam = max(10 * lam, 1e-6)
            if not accepted:
                break
            rel = (cost - cost_new) / max(cost, 1e-300)
            x, res, cost = x_new, res_new, cost_new
            lam /= 10
            if np.max(np.abs(step)) < IDENT_STEP_TOL or rel < IDENT_COST_RTOL:
                break
    names = tuple(f"{effect.name}.{effect.param_names[i]}" for i in absorbed_c)
    return CandidateFit(dz(x, q_out, T_out, context_out), names, x[u:].copy(), n_steps)
