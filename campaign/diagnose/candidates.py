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
held-out errors against a full :class:`~campaign.identify.solver.CalibrationModel` refit. As the
solver, it stops before a step whose predicted decrease of the cost is below its tolerance
(:func:`~campaign.identify.solver.step_converged`): at the optimum such a step is round-off.

The candidate's columns share the fold's work where its hooks allow (exactly the same
derivatives, computed once per fold instead of once per candidate): an effect with only a
``pose_map`` maps the current model's poses at x̂, computed once per fold, so its central
differences cost no kinematics; an effect with only a ``joint_offset`` Δq(θ) moves the pose
as an offset of the joints does, so its columns are Σ_j ∂r/∂Δq_j · ∂Δq_j/∂θ, the first factor
computed once per fold and shared by every such candidate (for the geometric model the joint-offset
columns of the fold fit's last Jacobian; with effects in the model central differences in one joint
offset at a time, 2N evaluations of the model), the second of the effect's own hook. Other effects
(twists, several hooks) take central differences of the whole model.

Which candidate parameters the current unknowns already span (*absorbed*, held at zero) is
decided as the solver decides it: the QR of the column-normalised weighted regressor at the
start point, the candidate's columns after the current ones, a diagonal below
``max(BASE_PARAM_RANK_RTOL, 1e-6)`` of the base columns' largest.
"""

from __future__ import annotations

from dataclasses import dataclass, field, replace

import numpy as np
import scipy.linalg

from campaign.effects.base import Effect, EffectSet, has_twist, model_pose
from campaign.identify.solver import step_converged
from campaign.model.kinematics import error_jacobian, pose_error
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
    absorbed); H: JᵀJ over those; J_free: (n·rows, len(free)) their columns of J (J itself when
    none is absorbed), which every candidate's step takes.
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
    J_free: np.ndarray = field(repr=False)
    #: what every candidate of the fold shares, computed on first use (:func:`_shared`)
    shared: dict = field(default_factory=dict, repr=False, compare=False)


def _weighted(dz, rows, sigma):
    return (dz[:, rows] / sigma).reshape(-1)


def linearise(model, q, T_meas, context) -> FoldLinearisation:
    """Linearise a fitted current model (CalibrationModel, fixed noise weights) at its optimum,
    on the poses it was fitted on: q (n, N) rad, T_meas (n, 4, 4), context per pose."""
    rows = slice(0, 3) if model.position_only else slice(0, 6)
    noise = model.noise_sigma_
    sigma = np.array([noise["position_m"]] * 3 + [noise["orientation_rad"] or 1.0] * 3)[rows]
    kept = getattr(model, "jacobian_at_fit_", None)  # the fit's own, at the optimum on these poses
    if kept is not None and model.points is None and kept.shape[:2] == (len(q), rows.stop):
        Jfull = kept[:, rows, :] / sigma[None, :, None]
        residual = _weighted(model.residual_at_fit_, rows, sigma)
    else:
        Jfull = model.jacobian(q, T_meas, context)[:, rows, :] / sigma[None, :, None]
        residual = _weighted(model.residuals(q, T_meas, context), rows, sigma)
    J = Jfull.reshape(-1, Jfull.shape[2])
    norms = np.linalg.norm(J, axis=0)
    Q, R = scipy.linalg.qr(J / np.where(norms > 0, norms, 1.0), mode="economic", check_finite=False)
    r = model.base_.n_base
    d = np.abs(np.diag(R))
    ref = float(d[:r].max() if r else d.max())
    free = np.array([i for i in range(J.shape[1]) if i not in set(model.absorbed_)], dtype=int)
    Jf = J if len(free) == J.shape[1] else J[:, free]
    return FoldLinearisation(model, rows, sigma, J, residual, Q, ref, free, Jf.T @ Jf, Jf)


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


def fit_candidate(lin: FoldLinearisation, effect, q, T_meas, context, q_out, T_out, context_out,
                  hold=()) -> CandidateFit:
    """Fit ``effect`` (an Effect instance) jointly with the fold's current model on its fitting
    poses (q, T_meas, context: those :func:`linearise` saw) and predict the held-out poses.
    ``hold``: indices of the current unknowns held at zero (an effect of the model, or one joint
    of it, taken out while the candidate takes its place)."""
    hold = np.asarray(hold, dtype=int)
    if len(hold):
        lin = _holding(lin, hold)
    m = lin.model
    robot = m.robot
    es = EffectSet((*m.effect_set_.effects, effect))
    r = m.base_.n_base
    u = lin.J.shape[1]
    k = effect.n_params
    x0 = np.concatenate([m.x_, np.asarray(effect.initial_params(), dtype=float)])
    x0[hold] = 0.0

    def dz(x, qq, TT, ctx):
        return pose_error(model_pose(robot, qq, m.base_.expand(x[:r]), es, x[r:], ctx), TT)

    def weighted_residual(x):
        return _weighted(dz(x, q, T_meas, context), lin.rows, lin.sigma)

    res, C = _start(lin, effect, x0, q, T_meas, context, weighted_residual)
    if len(hold):  # the start residual of the model at x̂ does not hold: the unknowns held moved
        res = weighted_residual(x0)
    # absorbed: what is left of each normalised candidate column after the current columns
    # and the candidate's earlier ones (the diagonal of the joint QR)
    norms = np.linalg.norm(C, axis=0)
    Cn = C / np.where(norms > 0, norms, 1.0)
    Cp = Cn - lin.Q @ (lin.Q.T @ Cn)
    d = np.abs(np.diag(np.linalg.qr(Cp, mode="r"))) if k else np.zeros(0)
    absorbed_c = [i for i in range(k) if d[i] < ABSORBED_RTOL * lin.ref_diag or norms[i] == 0]
    free_c = np.array([i for i in range(k) if i not in absorbed_c], dtype=int)
    x = x0
    n_steps = 0
    if len(free_c):
        Jf = lin.J_free
        Cf = C[:, free_c]
        cross = Jf.T @ Cf
        H = np.block([[lin.H, cross], [cross.T, Cf.T @ Cf]])
        free = np.concatenate([lin.free, u + free_c])
        cost = float(res @ res)
        lam = 0.0
        for n_steps in range(1, MAX_STEPS + 1):
            g = np.concatenate([Jf.T @ res, Cf.T @ res])
            if step_converged(H, g, cost):
                break
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


def _holding(lin: FoldLinearisation, hold) -> FoldLinearisation:
    """The fold's linearisation with the current unknowns ``hold`` out of the fit: not free, not in
    the basis that decides what a candidate's columns add (its shared columns kept: the chord
    method takes the Jacobian at x̂ with them)."""
    held = set(hold.tolist())
    free = np.array([i for i in lin.free if i not in held], dtype=int)
    rest = [i for i in range(lin.J.shape[1]) if i not in held]
    J = lin.J[:, rest]
    norms = np.linalg.norm(J, axis=0)
    Q = scipy.linalg.qr(J / np.where(norms > 0, norms, 1.0), mode="economic", check_finite=False)[0] if rest \
        else np.zeros((lin.J.shape[0], 0))
    Jf = lin.J[:, free]
    return replace(lin, Q=Q, free=free, H=Jf.T @ Jf, J_free=Jf)


def _hooks(effect) -> set:
    """The hooks an effect overrides: a subset of {"joint_offset", "joint_twist", "pose_map"}."""
    out = {h for h in ("joint_offset", "pose_map") if getattr(type(effect), h) is not getattr(Effect, h)}
    return out | ({"joint_twist"} if has_twist(effect) else set())


class _JointShift(Effect):
    """Δq = δ on one joint: the model's derivative in a joint offset (:func:`_joint_columns`)."""

    name = "_joint_shift"
    param_names = ("delta",)
    param_units = ("rad or m",)

    def __init__(self, robot, joint: int):
        super().__init__(robot)
        self.joint = joint

    def joint_offset(self, params, q, context):
        dq = np.zeros_like(q)
        dq[:, self.joint] = params[0]
        return dq


def _shared(lin: FoldLinearisation, key, compute):
    if key not in lin.shared:
        lin.shared[key] = compute()
    return lin.shared[key]


def _start(lin: FoldLinearisation, effect, x0, q, T_meas, context, weighted_residual):
    """The weighted residual at the start point (n·rows,) and the candidate's columns (n·rows, k)
    there, central differences in its parameters (see the module: shared work by hooks)."""
    m = lin.model
    k = effect.n_params
    th0 = x0[len(x0) - k:]
    hooks = _hooks(effect)
    one = EffectSet((effect,))  # the hooks called through the set: a broken user effect is one line
    step = lambda i: FD_STEP * np.eye(k)[i]  # noqa: E731
    if hooks == {"pose_map"}:
        r = m.base_.n_base
        T_cur = _shared(lin, "pose", lambda: model_pose(m.robot, q, m.base_.expand(m.x_[:r]), m.effect_set_,
                                                        m.x_[r:], context))

        def mapped(th):
            return _weighted(pose_error(one.pose_map(th, T_cur, q, context), T_meas), lin.rows, lin.sigma)

        res = mapped(th0)
        C = np.column_stack([(mapped(th0 + step(i)) - mapped(th0 - step(i))) / (2 * FD_STEP) for i in range(k)]) \
            if k else np.zeros((len(res), 0))
        return res, C
    if hooks == {"joint_offset"}:
        D = _shared(lin, "joint_offset", lambda: _joint_columns(lin, q, T_meas, context))
        off0 = one.joint_offset(th0, q, context)
        res = lin.residual if not np.any(off0) else weighted_residual(x0)
        rows = D.shape[0] // len(q)
        C = np.empty((len(res), k))
        for i in range(k):
            g = (one.joint_offset(th0 + step(i), q, context) - one.joint_offset(th0 - step(i), q, context)) \
                / (2 * FD_STEP)  # (n, N): ∂Δq/∂θ_i
            C[:, i] = np.einsum("rj,rj->r", D, np.repeat(g, rows, axis=0))
        return res, C
    res = weighted_residual(x0)
    C = np.empty((len(res), k))
    for i in range(k):
        xp, xm = x0.copy(), x0.copy()
        xp[len(x0) - k + i] += FD_STEP
        xm[len(x0) - k + i] -= FD_STEP
        C[:, i] = (weighted_residual(xp) - weighted_residual(xm)) / (2 * FD_STEP)
    return res, C


def _joint_columns(lin: FoldLinearisation, q, T_meas, context) -> np.ndarray:
    """(n·rows, N): the weighted residual's derivative in an offset of each joint, at the
    current model's optimum: for the geometric model the analytic columns of its joint offsets
    (those of the fit's last Jacobian, instead of 2N evaluations of the model), with effects
    central differences (FD_STEP rad or m)."""
    m = lin.model
    r = m.base_.n_base
    p_e = m.base_.expand(m.x_[:r])
    if not m.effect_set_.effects:  # the geometric model: its error Jacobian's joint-offset columns
        D = getattr(m, "joint_jacobian_at_fit_", None)  # the fit's own, at the optimum on these poses
        if D is None or D.shape[:2] != (len(q), lin.rows.stop):
            D = error_jacobian(m.robot, q, p_e, T_meas)[:, lin.rows, list(m.robot.joint_offset_index)]
        return (D / lin.sigma[None, :, None]).reshape(-1, q.shape[1])
    cols = []
    for j in range(q.shape[1]):
        es = EffectSet((*m.effect_set_.effects, _JointShift(m.robot, j)))
        res = [_weighted(pose_error(model_pose(m.robot, q, p_e, es, np.r_[m.x_[r:], d], context), T_meas),
                         lin.rows, lin.sigma) for d in (FD_STEP, -FD_STEP)]
        cols.append((res[0] - res[1]) / (2 * FD_STEP))
    return np.column_stack(cols)


def combined_effect(robot, effects) -> Effect:
    """Several effects as one candidate (their parameters in order, their hooks summed or, for
    ``pose_map``, composed, as a model's :class:`EffectSet` does), fitted at once with a fold's
    current model: an effect over some joints beside another one on a joint it gave up (the
    comparison of two effects on one joint, :mod:`campaign.diagnose.joints`). It overrides only
    the hooks its parts override, so joint offsets alone keep the shared columns."""
    es = EffectSet(tuple(effects))
    hooks = set().union(*(_hooks(e) for e in es.effects))
    ns = {"name": "+".join(es.names), "description": " and ".join(e.description for e in es.effects),
          "context_keys": tuple(dict.fromkeys(k for e in es.effects for k in e.context_keys)),
          "param_names": es.param_names, "param_units": es.param_units,
          "initial_params": lambda self: es.initial_params()}
    if "joint_offset" in hooks:
        ns["joint_offset"] = lambda self, params, q, context: es.joint_offset(params, q, context)
    if "joint_twist" in hooks:
        ns["joint_twist"] = lambda self, params, q, context: es.joint_twist(params, q, context)
    if "pose_map" in hooks:
        ns["pose_map"] = lambda self, params, T_IE, q, context: es.pose_map(params, T_IE, q, context)
    out = type("CombinedEffect", (Effect,), ns)(robot)
    out.spec = "+".join(e.spec for e in es.effects)
    return out
