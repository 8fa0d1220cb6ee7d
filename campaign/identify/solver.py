"""Geometric identification (eqs. 13-19), jointly with any enabled physical effects.

:class:`CalibrationModel` is an estimator in the scikit-learn shape: hyperparameters in a
keyword-only ``__init__``, ``fit`` returns ``self``, what was learned ends in ``_``,
``predict`` gives the model's pose.

The unknowns are the identifiable base parameters of the 48 geometric error parameters
(:mod:`campaign.model.base_params`) and the parameters θ of the enabled effects. The
identifiability analysis runs on the combined regressor: an effect parameter whose
column the geometric base parameters already span is reported in ``absorbed_`` and
held at zero rather than silently fitted.

Rows are weighted by the noise of their block (position in m, orientation in rad),
estimated from the residuals (variance components), so σ of every parameter is in its
own unit. Levenberg-Marquardt steps from zero (eq. 19 with damping).

With ``points`` (k, 3) m in the tool frame (raw reflector data), the rows are the positions of
the seen reflectors, ``T_model(q)·p_m − measured_m`` (3 per seen reflector; a missed one gives
zero rows), and the base parameters are those of the reflectors' positions
(:func:`campaign.model.base_params.base_parameters` with ``points``): no pose is fitted first,
so a pose with one or two reflectors seen still contributes.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from campaign.effects.base import EffectSet, chain_pose, make_effect, model_pose
from campaign.errors import DataError, IdentificationError, NotFittedError
from campaign.model.base_params import BaseParameters, base_parameters, point_rows
from campaign.model.kinematics import error_jacobian, pose_error
from campaign.model.priors import base_prior
from campaign.model.rotations import rotvec_to_matrix
from campaign.tolerances import BASE_PARAM_RANK_RTOL, IDENT_COST_RTOL, IDENT_STEP_TOL, STRONG_CORRELATION

#: finite-difference step for effect parameters, relative to a typical magnitude of 1
_FD_STEP = 1e-6


def _normal_equations(J, r):
    """(JᵀJ, Jᵀr) for a whitened Jacobian J (n, m, f) and residual r (n, m), summed over the
    parameter-major layout the error Jacobian has (its transpose (f, m, n) is contiguous): no
    (n·m, f) copy, which costs more than the products themselves."""
    Jt = J.transpose(2, 1, 0).reshape(J.shape[2], -1)
    return Jt @ Jt.T, Jt @ r.T.reshape(-1)


def step_converged(H, g, cost) -> bool:
    """Whether the Gauss-Newton step of the linear model (H = JᵀJ, g = Jᵀr, at the weighted cost
    ``cost``) would end the iteration by its own tests: its predicted decrease of the cost, gᵀH⁻¹g,
    below IDENT_COST_RTOL of the cost, or the step below IDENT_STEP_TOL. Tested before the step
    is taken: at the optimum (a fit started at another's, the last steps of any fit) such a step
    costs a model evaluation and a Jacobian, and a series of them when round-off rejects it."""
    try:
        step = np.linalg.solve(H, g)
    except np.linalg.LinAlgError:
        return False
    return float(g @ step) < IDENT_COST_RTOL * cost or float(np.max(np.abs(step), initial=0.0)) < IDENT_STEP_TOL


@dataclass(frozen=True)
class Unknowns:
    """The fit's unknowns: r geometric (base parameters, or every error parameter for a MAP fit on
    the redundant model) then k effect parameters, by name."""

    r: int
    k: int
    map_fit: bool
    redundant: bool
    names: tuple

    def base_columns(self, base) -> list:
        """Indices of the base parameters' columns (and the effects') among the unknowns."""
        if self.redundant:
            return list(base.independent) + list(range(self.r, self.r + self.k))
        return list(range(self.r + self.k))


@dataclass(frozen=True)
class RowLayout:
    """The rows fitted a pose: ``rows`` (a slice of Δz's 6) for poses, None for points; ``mask``
    (n, m) 1 where measured; ``sigma`` (m,) the starting noise of each row (m or rad); ``blocks``
    the rows sharing a noise (variance components); ``measured`` (n, m) the points' positions."""

    rows: slice | None
    mask: np.ndarray
    sigma: np.ndarray
    blocks: list
    measured: np.ndarray | None

    @property
    def n_rows(self) -> int:
        return int(self.mask.sum())


class FitProblem:
    """The fit's residual (n, m) and Jacobian (n, m, r + k) as functions of the unknowns x on fixed
    poses. The Jacobian at the last point asked for is kept (the start's is the first step's too),
    with the derivative in the joint offsets there (for diagnose's candidates)."""

    def __init__(self, model, q, T_meas, context, layout: RowLayout, r: int):
        self.model, self.q, self.T_meas, self.context, self.layout, self.r = model, q, T_meas, context, layout, r
        self._last = {}

    def unpack(self, x):
        """(the 6N + 12 error parameters, the effect parameters) of the unknowns x."""
        p_e = np.zeros(self.model.robot.n_params)
        p_e[self.model.cols_] = x[:self.r]
        return p_e, x[self.r:]

    def seed(self, x, J):
        """Take J as the Jacobian at x (another fit's, at the same values)."""
        self._last.update(x=x.copy(), J=J)

    def residual(self, x) -> np.ndarray:
        m, lay = self.model, self.layout
        p_e, th = self.unpack(x)
        if lay.rows is None:
            return (m._model_points(self.q, p_e, th, self.context).reshape(len(self.q), -1) - lay.measured) * lay.mask
        return pose_error(m._model_T(self.q, p_e, th, self.context), self.T_meas)[:, lay.rows]

    def jacobian(self, x) -> np.ndarray:
        last, lay = self._last, self.layout
        if last.get("x") is not None and np.array_equal(last["x"], x):
            return last["J"]
        if lay.rows is None:
            J = self.model._point_jacobian(self.q, *self.unpack(x), self.context)
            J = J.reshape(len(self.q), -1, J.shape[-1]) * lay.mask[:, :, None]
        else:
            J, J_q = self.model._jacobian(self.q, *self.unpack(x), self.context, self.T_meas, joints=True)
            J = J[:, lay.rows, :]
            last["J_q"] = None if J_q is None else J_q[:, lay.rows, :]
        last.update(x=x.copy(), J=J)
        return J

    @property
    def joint_jacobian(self):
        """The derivative (n, m, N) in the joint offsets at the last Jacobian computed here (None
        with effects, points, or none computed)."""
        return self._last.get("J_q")


@dataclass(frozen=True)
class _PriorTerm:
    """The prior on the free unknowns: precision (f, f) (zeros for least squares), mean (f,)."""

    precision: np.ndarray
    mean: np.ndarray
    active: bool
    free: np.ndarray

    def cost(self, x) -> float:
        d = x[self.free] - self.mean
        return float(d @ self.precision @ d) if self.active else 0.0


@dataclass(frozen=True)
class FitState:
    """Where the iteration ended: unknowns x, residual (n, m), weighted cost, rows' noise σ (m,),
    the cost after every step, the steps taken."""

    x: np.ndarray
    residual: np.ndarray
    cost: float
    sigma: np.ndarray
    history: list
    n_iter: int


def levenberg_marquardt(problem, x, res, cost, sig, free, prior, *, max_iter):
    """Levenberg-Marquardt steps (eq. 19 with damping) on the free unknowns at fixed row noise σ,
    from x with its residual and cost: (x, residual, cost, costs after each step, steps)."""
    lam = 1e-6
    history, n_iter = [], 0
    for _ in range(max_iter):
        J = problem.jacobian(x)[:, :, free] / sig[None, :, None]
        H, g = _normal_equations(J, res / sig)
        if prior.active:
            g = g + prior.precision @ (x[free] - prior.mean)
            H = H + prior.precision
        if step_converged(H, g, cost):
            break
        n_iter += 1
        step_ok = False
        for _ in range(20):
            A = H + lam * np.diag(np.diag(H))
            try:
                dx = -np.linalg.solve(A, g)
            except np.linalg.LinAlgError:
                lam *= 10
                continue
            x_new = x.copy()
            x_new[free] += dx
            res_new = problem.residual(x_new)
            cost_new = float(np.sum((res_new / sig) ** 2)) + prior.cost(x_new)
            if cost_new <= cost:
                step_ok = True
                break
            lam *= 10
        if not step_ok:
            break
        rel = (cost - cost_new) / max(cost, 1e-300)
        x, res, cost = x_new, res_new, cost_new
        lam = max(lam / 10, 1e-12)
        history.append(cost)
        if np.max(np.abs(dx)) < IDENT_STEP_TOL or rel < IDENT_COST_RTOL:
            break
    return x, res, cost, history, n_iter


def hat_inverse(J, P) -> np.ndarray:
    """(f, f): ``(JᵀJ + P)⁺`` of the whitened Jacobian J (n, m, f) and the prior's precision P (f, f),
    the middle of the hat matrix ``J (JᵀJ + P)⁺ Jᵀ``."""
    H, _ = _normal_equations(J, np.zeros(J.shape[:2]))
    return np.linalg.pinv(H + P, hermitian=True)


def row_leverage(J, P) -> np.ndarray:
    """(n, m): each row's share of the unknowns the data determine, the diagonal of the hat matrix
    ``J (JᵀJ + P)⁺ Jᵀ`` of the whitened Jacobian J (n, m, f) (P (f, f): the prior's precision, zeros
    for least squares). The shares sum to tr H (H + P)⁻¹, the effective unknowns."""
    return np.sum((J @ hat_inverse(J, P)) * J, axis=-1)


def variance_components(res, sig, layout: RowLayout, leverage) -> np.ndarray:
    """Each block's noise (m,) re-estimated from its residuals res (n, m) over its own degrees of
    freedom: its measured rows less the unknowns they determine (``leverage`` (n, m),
    :func:`row_leverage`). The unknowns are not shared equally between the blocks: a link length
    is seen by the positions alone, so with an equal share a campaign of 12 6-D poses put the
    positions' variance 22 % low and the orientations' 30 % high (tests/test_edges_late.py)."""
    new_sig = sig.copy()
    for cols in layout.blocks:
        dof = float(layout.mask[:, cols].sum() - np.sum(leverage[:, cols]))
        new_sig[cols] = np.sqrt(np.sum(res[:, cols] ** 2) / max(dof, 1.0))
    return np.maximum(new_sig, 1e-12)


def iterate(problem, x, free, prior, layout: RowLayout, *, max_iter, estimate_noise) -> FitState:
    """Levenberg-Marquardt from x, alternating (with ``estimate_noise``, at most 10 rounds) with the
    rows' noise re-estimated from the residuals until it changes by less than 1 % (each block's share
    of the unknowns moves with the weights: stopping at 5 % left the positions' variance 16 % low on
    8 poses, 6 % at 1 %; a round after the fit has converged takes no step)."""
    sig = layout.sigma
    res = problem.residual(x)
    cost = float(np.sum((res / sig) ** 2)) + prior.cost(x)
    history = [cost]
    n_iter = 0
    for _ in range(10 if estimate_noise else 1):
        x, res, cost, steps, n = levenberg_marquardt(problem, x, res, cost, sig, free, prior, max_iter=max_iter)
        history += steps
        n_iter += n
        if not estimate_noise:
            break
        new_sig = variance_components(res, sig, layout,
                                      row_leverage(problem.jacobian(x)[:, :, free] / sig[None, :, None], prior.precision))
        if np.allclose(new_sig, sig, rtol=0.01):
            sig = new_sig
            break
        sig = new_sig
        cost = float(np.sum((res / sig) ** 2)) + prior.cost(x)
        history.append(cost)
    return FitState(x=x, residual=res, cost=cost, sigma=sig, history=history, n_iter=n_iter)


@dataclass(frozen=True)
class Posterior:
    """The linearisation at the fit: ``jacobian`` (n, m, r + k) not whitened, ``whitened_jacobian``
    (n, m, f) of the free unknowns, ``covariance`` (r + k, r + k) (zero rows for the held),
    ``variance_factor`` (cost / dof), ``n_effective`` unknowns, ``singular_values`` of the
    column-scaled regressor of the base parameters (and effects), largest first."""

    jacobian: np.ndarray
    whitened_jacobian: np.ndarray
    covariance: np.ndarray
    variance_factor: float
    n_effective: float
    singular_values: np.ndarray


def posterior(problem, fit: FitState, free, prior, layout: RowLayout, unknowns, *, effective_unknowns) -> Posterior:
    """The covariance of the unknowns at the fit: least squares (JᵀJ)⁺ s², or MAP (JᵀJ / s² + P)⁺,
    with s² the a posteriori variance factor; and the conditioning of the base parameters' columns."""
    x, sig = fit.x, fit.sigma
    J_final = problem.jacobian(x)
    J = J_final[:, :, free] / sig[None, :, None]
    H, _ = _normal_equations(J, fit.residual / sig)
    n_eff = effective_unknowns(J, prior.precision) if prior.active else len(free)
    dof = max(layout.n_rows - n_eff, 1)
    s2 = (fit.cost - prior.cost(x)) / dof  # a posteriori variance factor (≈ 1 when the noise model holds)
    if prior.active:  # the posterior: the data's information (at the fit's variance factor) plus the prior's
        cov_free = np.linalg.pinv(H / s2 + prior.precision, hermitian=True)
    else:
        cov_free = np.linalg.pinv(H) * s2
    n_unknown = unknowns.r + unknowns.k
    cov = np.zeros((n_unknown, n_unknown))
    cov[np.ix_(free, free)] = cov_free
    # condition number of the column-scaled regressor of the base parameters (and effects)
    if unknowns.redundant:
        free_set = set(free.tolist())
        base_cols = unknowns.base_columns(problem.model.base_)
        Jb = (J_final / sig[None, :, None])[:, :, [i for i in base_cols if i in free_set]]
        H_b = Jb.reshape(-1, Jb.shape[2]).T @ Jb.reshape(-1, Jb.shape[2])
    else:
        H_b = H
    d = np.sqrt(np.clip(np.diag(H_b), 1e-300, None))
    ev = np.clip(np.linalg.eigvalsh(H_b / np.outer(d, d)), 0.0, None)
    return Posterior(jacobian=J_final, whitened_jacobian=J, covariance=cov, variance_factor=float(s2),
                     n_effective=float(n_eff), singular_values=np.sqrt(ev[::-1]))


class CalibrationModel:
    """Kinematic model with geometric base parameters and optional physical effects.

    Parameters
    ----------
    robot : RobotModel
    effects : sequence of effect names or Effect objects
    position_only : fit positions only (orientation rows dropped)
    max_iter : Levenberg-Marquardt iterations at most
    sigma_position_m, sigma_orientation_rad : initial noise guesses for row weights
    estimate_noise : re-estimate the block noise from the residuals (variance components)
    points : (k, 3) m in the tool frame, or None: fit measured positions of these points
        (raw reflectors; ``fit(q, P_meas)`` with P_meas (n, k, 3), NaN where missed) instead of poses
    prior : campaign.model.priors.Prior, "tolerances" (the robot's and the effects') or None: None fits
        the base parameters by least squares (the paper's); a prior makes the fit MAP, the prior's
        rows ``√s · p / σ_p`` added to the same Levenberg-Marquardt problem (docs/priors.md)
    physical : with a prior, the unknowns are every physical parameter (all 6N + 12, the redundant
        model: the prior splits correlated ones and the second-order terms see the split); False:
        the base parameters with the prior carried to them (``C Σ Cᵀ``), the split by the prior
        afterwards (the same first-order model as least squares)
    prior_strength : s, the factor on the prior's precision (1: the tolerances as stated)
    fixed : {parameter name: value (SI) or None (nominal)}: held, not fitted (robot error
        parameters or ``<effect>.<param>``; campaign.model.priors.resolve_fix expands groups)
    drop : names of base parameters held at zero (a reduced model, campaign.identify.model_choice)
    """

    def __init__(self, *, robot, effects=(), position_only=False, max_iter=50,
                 sigma_position_m=1e-5, sigma_orientation_rad=1e-4, estimate_noise=True, points=None,
                 prior=None, prior_strength=1.0, fixed=None, drop=(), physical=True):
        self.robot = robot
        self.effects = effects
        self.position_only = position_only
        self.max_iter = max_iter
        self.sigma_position_m = sigma_position_m
        self.sigma_orientation_rad = sigma_orientation_rad
        self.estimate_noise = estimate_noise
        self.points = points
        self.prior = prior
        self.prior_strength = prior_strength
        self.fixed = fixed
        self.drop = drop
        self.physical = physical

    # -- helpers ----------------------------------------------------------------------
    def _effect_set(self) -> EffectSet:
        return EffectSet(tuple(make_effect(e, self.robot) if isinstance(e, str) else e for e in self.effects))

    def _rows(self):
        return slice(0, 3) if self.position_only else slice(0, 6)

    def _model_T(self, q, p_e, theta, context):
        return model_pose(self.robot, q, p_e, self.effect_set_, theta, context)

    def _jacobian(self, q, p_e, theta, context, T_meas, *, joints=False):
        """Columns for the base parameters and every effect parameter: (n, 6, r + k). With
        ``joints``, also the derivative (n, 6, N) in an offset of each joint for the geometric
        model (the error Jacobian's joint-offset columns; None with effects)."""
        es = self.effect_set_
        if not es.effects:
            J = error_jacobian(self.robot, q, p_e, T_meas)
            cols = J[:, :, self._geometric_columns()]
            return (cols, J[:, :, list(self.robot.joint_offset_index)]) if joints else cols
        if joints:
            return self._jacobian(q, p_e, theta, context, T_meas), None
        qq = q + es.joint_offset(theta, q, context)
        xi = es.joint_twist(theta, q, context)  # the chain with any joint twists
        T_chain = chain_pose(self.robot, q, p_e, es, theta, context)
        # pose maps after the chain: propagate the chain's derivative through them, and
        # differentiate the effects numerically (no kinematics re-run)
        T0 = es.pose_map(theta, T_chain, q, context)
        dz0 = pose_error(T0, T_meas)
        eps = 1e-7
        # J_map: derivative of Δz w.r.t. a perturbation (dt, ω) of the chain's pose, the
        # rotation taken about the tool point, which is the convention of error_jacobian
        J_map = np.empty((len(q), 6, 6))
        for a in range(6):
            Tp = T_chain.copy()
            if a < 3:
                Tp[:, a, 3] += eps
            else:
                w = np.zeros(3)
                w[a - 3] = eps
                Tp[:, :3, :3] = rotvec_to_matrix(w) @ Tp[:, :3, :3]
            J_map[:, :, a] = (pose_error(es.pose_map(theta, Tp, q, context), T_meas) - dz0) / eps
        J_chain = error_jacobian(self.robot, qq, p_e, joint_twists=xi)
        J_b = J_map @ J_chain[:, :, self._geometric_columns()]
        cols = [J_b]
        if es.n_params:
            J_th = np.empty((len(q), 6, es.n_params))
            J_q = J_map @ J_chain[:, :, list(self.robot.joint_offset_index)]  # d dz / d q
            twist = es.twist_params()
            for k in range(es.n_params):
                th = theta.copy()
                th[k] += _FD_STEP
                th_m = theta.copy()
                th_m[k] -= _FD_STEP
                if twist[k]:
                    # joint twists move the chain itself: central differences of the whole model
                    J_th[:, :, k] = (pose_error(self._model_T(q, p_e, th, context), T_meas)
                                     - pose_error(self._model_T(q, p_e, th_m, context), T_meas)) / (2 * _FD_STEP)
                    continue
                ddq = (es.joint_offset(th, q, context) - es.joint_offset(th_m, q, context)) / (2 * _FD_STEP)
                col = np.einsum("nij,nj->ni", J_q, ddq)
                Tp = es.pose_map(th, T_chain, q, context)
                Tm = es.pose_map(th_m, T_chain, q, context)
                col = col + (pose_error(Tp, T_meas) - pose_error(Tm, T_meas)) / (2 * _FD_STEP)
                J_th[:, :, k] = col
            cols.append(J_th)
        return np.concatenate(cols, axis=2)

    def _geometric_columns(self) -> list:
        """Indices of the geometric unknowns among the 6N + 12 error parameters: the base
        parameters' (least squares) or all (MAP on the redundant model)."""
        return getattr(self, "cols_", None) or list(self.base_.independent)

    def _points(self):
        return None if self.points is None else np.asarray(self.points, dtype=float).reshape(-1, 3)

    def _model_points(self, q, p_e, theta, context):
        """The points' positions (n, k, 3) m in F_I under the model."""
        T = self._model_T(q, p_e, theta, context)
        return self._points() @ np.swapaxes(T[:, :3, :3], 1, 2) + T[:, None, :3, 3]

    def _point_jacobian(self, q, p_e, theta, context):
        """Derivative of the points' model positions: (n, k, 3, r + k_effects). The pose's own
        derivative (δt at the tool origin, δφ in F_I) carried to each point, δt + δφ × R·p_m."""
        T = self._model_T(q, p_e, theta, context)
        J = self._jacobian(q, p_e, theta, context, T if self.effect_set_.effects else None)
        d = self._points() @ np.swapaxes(T[:, :3, :3], 1, 2)
        return point_rows(J, d)

    # -- estimator API ----------------------------------------------------------------
    def fit(self, q, T_meas, context=None, *, base: BaseParameters | None = None, init: dict | None = None,
            init_jacobian=None):
        """Identify the base parameters (and effect parameters) from measured poses.

        q: (n, N) rad (m for prismatic joints); T_meas: (n, 4, 4) measured T_IE (m), or with
        ``points`` the measured positions of those points (n, k, 3) m, NaN where one was missed
        (a pose with none seen adds no row); context: per-pose values.
        init: optional start values by unknown name (e.g. another fit's ``values_``);
        unknowns not named start at 0 (the paper's start point). init_jacobian: optional
        (n, 6, r + k) Jacobian of Δz at the start values on these poses, when the caller has it
        (another fit's ``jacobian_at_fit_`` rows at the values ``init`` gives): not computed again.

        The steps, each a method a test can call: :meth:`check_data`, :meth:`choose_unknowns`,
        :meth:`row_layout`, :meth:`start_values`, :class:`FitProblem`, :meth:`free_unknowns`,
        :func:`levenberg_marquardt` with :func:`variance_components`, :func:`posterior`.
        """
        q, T_meas, context = self.check_data(q, T_meas, context)
        unknowns = self.choose_unknowns(base)
        layout = self.row_layout(q, T_meas)
        if layout.n_rows < self.base_.n_base + unknowns.k:  # the redundant model's extras are the prior's to fix
            raise IdentificationError(f"{len(q)} poses give {layout.n_rows} equations for "
                                      f"{self.base_.n_base + unknowns.k} unknowns")
        x, mu, held = self.start_values(unknowns, init)
        problem = FitProblem(self, q, T_meas, context, layout, unknowns.r)
        if init_jacobian is not None and layout.rows is not None:
            problem.seed(x, np.asarray(init_jacobian, dtype=float)[:, layout.rows, :])
        free = self.free_unknowns(problem, x, held, unknowns, layout.sigma)
        prior = _PriorTerm(self._prior_precision(free, unknowns.r, unknowns.redundant) if unknowns.map_fit
                           else np.zeros((len(free), len(free))), mu[free], unknowns.map_fit, free)
        fit = iterate(problem, x, free, prior, layout, max_iter=self.max_iter, estimate_noise=self.estimate_noise)
        post = posterior(problem, fit, free, prior, layout, unknowns, effective_unknowns=self._effective_unknowns)
        self._store(problem, fit, post, free, prior, held, unknowns, layout)
        return self

    def check_data(self, q, T_meas, context):
        """(q (n, N), T_meas (n, 4, 4) or measured points (n, k, 3), context {name: (n,)}) as float
        arrays, checked against the robot, the ``points`` and the effects' context; sets
        ``effect_set_``."""
        q = np.asarray(q, dtype=float)
        T_meas = np.asarray(T_meas, dtype=float)
        N = self.robot.n_joints
        P = self._points()
        if P is None and (q.ndim != 2 or q.shape[1] != N or T_meas.shape != (len(q), 4, 4)):
            raise DataError(f"fit: expected q (n, {N}) and T_meas (n, 4, 4), got {q.shape} and {T_meas.shape}")
        if P is not None and (q.ndim != 2 or q.shape[1] != N or T_meas.shape != (len(q), len(P), 3)):
            raise DataError(f"fit: expected q (n, {N}) and measured points (n, {len(P)}, 3), got {q.shape} and "
                            f"{T_meas.shape}")
        context = {k: np.asarray(v, dtype=float) for k, v in (context or {}).items()}
        self.effect_set_ = self._effect_set()
        self.effect_set_.check_context(context, len(q))
        return q, T_meas, context

    def choose_unknowns(self, base=None) -> "Unknowns":
        """The unknowns: the base parameters (``base``, or computed for the robot and the rows
        fitted) or, for a MAP fit on the redundant model, every error parameter; then the effects'.
        Sets ``base_``, ``cols_`` (the geometric unknowns' indices among the error parameters) and
        ``prior_``."""
        P = self._points()
        if P is None:
            self.base_ = base or base_parameters(self.robot, position_only=self.position_only)
        else:
            self.base_ = base or base_parameters(self.robot, position_only=True, points=P)
        map_fit = self.prior is not None
        redundant = map_fit and self.physical
        self.cols_ = list(range(self.robot.n_params)) if redundant else list(self.base_.independent)
        names = (tuple(self.robot.param_names) if redundant else self.base_.names) + self.effect_set_.param_names
        self.prior_ = self._resolve_prior() if map_fit else None
        return Unknowns(r=len(self.cols_), k=self.effect_set_.n_params, map_fit=map_fit, redundant=redundant,
                        names=names)

    def row_layout(self, q, T_meas) -> "RowLayout":
        """The rows fitted and their starting noise: Δz's 3 or 6 components a pose, or 3 a seen point
        (a missed reflector: zero rows, weight 0, never NaN in the solver)."""
        P = self._points()
        if P is None:
            rows = self._rows()
            mask = np.ones((len(q), rows.stop))
            sig = np.array([self.sigma_position_m] * 3 + [self.sigma_orientation_rad] * 3)[rows]
            blocks = [np.arange(3)] + ([] if self.position_only else [np.arange(3, 6)])
            return RowLayout(rows=rows, mask=mask, sigma=sig, blocks=blocks, measured=None)
        mask = np.repeat(np.isfinite(T_meas).all(axis=2).astype(float), 3, axis=1)
        return RowLayout(rows=None, mask=mask, sigma=np.full(3 * len(P), self.sigma_position_m),
                         blocks=[np.arange(3 * len(P))], measured=np.nan_to_num(T_meas).reshape(len(q), -1))

    def start_values(self, unknowns, init=None):
        """(x (r + k,), μ (r + k,), held (r + k,) bool): the start (0, the effects' initial values, or
        ``init`` by name; held unknowns at their held value), the prior's mean and which are held."""
        r = unknowns.r
        x = np.zeros(unknowns.r + unknowns.k)
        x[r:] = self.effect_set_.initial_params()
        if init:
            for i, name in enumerate(unknowns.names):
                if name in init:
                    x[i] = init[name]
        mu, held = self._prior_and_held(x, r, unknowns.redundant)
        x[held] = mu[held]
        return x, mu, held

    def free_unknowns(self, problem, x, held, unknowns, sig) -> np.ndarray:
        """Indices of the unknowns fitted: all but the held and the effect parameters the base
        columns already span at the start point (those in ``absorbed_``, held at their start)."""
        r, k = unknowns.r, unknowns.k
        r_base = self.base_.n_base
        self.absorbed_ = []
        if k:  # without effects there is nothing to absorb
            J0 = problem.jacobian(x) / sig[None, :, None]
            J0b = J0[:, :, unknowns.base_columns(self.base_)] if unknowns.redundant else J0
            self.absorbed_ = [i + r - r_base for i in self._absorbed(J0b.reshape(-1, r_base + k), r_base)]
        out = set(self.absorbed_) | set(np.flatnonzero(held).tolist())
        return np.array([i for i in range(r + k) if i not in out], dtype=int)

    def _store(self, problem, fit, post, free, prior, held, unknowns, layout):
        """The learned attributes (ending in ``_``) from the fit and its posterior."""
        x, r, names = fit.x, unknowns.r, unknowns.names
        cov = post.covariance
        #: the Jacobian (n, rows, r + k) of Δz at the fitted values on the fitting poses, not
        #: whitened, every unknown (rows: 3 or 6 of Δz; with points, the points' rows): what
        #: self.jacobian(q, T_meas, context) gives there, kept for who needs it again
        #: (campaign.diagnose: the candidates' linearisation, the fold fits' start)
        self.jacobian_at_fit_ = post.jacobian
        #: the geometric model's derivative (n, rows, N) of Δz in an offset of each joint there (the
        #: error Jacobian's joint-offset columns; None with effects, points, or a fit that took no step)
        self.joint_jacobian_at_fit_ = problem.joint_jacobian
        #: the residual (n, rows) of Δz at the fitted values on the fitting poses (with points,
        #: the points' rows, zero where missed): what self.residuals(q, T_meas, context) gives there
        self.residual_at_fit_ = fit.residual
        self.x_ = x
        self.params_ = problem.unpack(x)[0]
        # the base parameters the estimate stands for (first order), with their covariance
        C_cols = self.base_.combination[:, self.cols_]
        self.base_params_ = C_cols @ x[:r]
        self.base_covariance_ = C_cols @ cov[:r, :r] @ C_cols.T
        self.params_min_norm_ = self.base_.min_norm(self.base_params_)
        self.effect_params_ = x[r:].copy()
        self.covariance_ = cov
        #: "lsq" (least squares) or "map" (with the prior)
        self.kind_ = "map" if unknowns.map_fit else "lsq"
        #: the held unknowns: name -> value (SI)
        self.held_ = {names[i]: float(x[i]) for i in np.flatnonzero(held)}
        #: the effective number of unknowns the data determine (tr H (H + P)⁻¹; the free count for lsq)
        self.n_effective_ = float(post.n_effective)
        # the physical parameters the estimate stands for (the prior's split), with their covariance
        if unknowns.redundant:
            self.physical_params_, self.physical_covariance_ = self.params_.copy(), cov[:r, :r].copy()
        else:
            self.physical_params_, self.physical_covariance_ = self.base_prior_.physical(self.base_params_,
                                                                                        cov[:r, :r])
        #: the last linearisation, for closed-form leave-one-out (campaign.identify.model_choice):
        #: whitened Jacobian (n, m, f) of the free unknowns ``free_``, whitened residuals (n, m), the
        #: prior's precision on them (f, f) and the rows' noise σ (m,)
        self.fit_jacobian_, self.fit_residual_ = post.whitened_jacobian, fit.residual / fit.sigma
        self.free_, self.fit_prior_precision_, self.row_sigma_ = free, prior.precision, fit.sigma
        self.fit_prior_mean_ = prior.mean
        #: the a posteriori variance factor in covariance_ (cost / degrees of freedom; ≈ 1 when
        #: the row weights are the noise): covariance_ / variance_factor_ is the weights' own
        self.variance_factor_ = float(post.variance_factor)
        sd = np.sqrt(np.clip(np.diag(cov), 0, None))
        self.sigma_ = sd
        self.base_sigma_ = np.sqrt(np.clip(np.diag(self.base_covariance_), 0, None))
        self.effect_sigma_ = sd[r:]
        with np.errstate(invalid="ignore", divide="ignore"):
            corr = cov / np.outer(sd, sd)
        corr[~np.isfinite(corr)] = 0.0
        self.correlation_ = corr
        svals = post.singular_values
        self.condition_number_ = float(svals[0] / svals[-1]) if svals[-1] > 0 else float("inf")
        sig = fit.sigma
        self.noise_sigma_ = {"position_m": float(sig[0]),
                             "orientation_rad": float(sig[3]) if layout.rows is not None and not self.position_only
                             else None}
        #: equations used (rows with a measured value; with points: 3 per seen reflector)
        self.n_equations_ = layout.n_rows
        self.n_iter_ = fit.n_iter
        self.cost_history_ = fit.history
        self.unknown_names_ = names
        self.unknown_units_ = (tuple(self.robot.param_units) if unknowns.redundant else self.base_.units) + \
            self.effect_set_.param_units
        self.values_ = dict(zip(self.unknown_names_, (float(v) for v in x)))
        iu = np.triu_indices(len(x), 1)
        strong = np.abs(corr[iu]) > STRONG_CORRELATION
        self.correlated_pairs_ = [(self.unknown_names_[i], self.unknown_names_[j], float(corr[i, j]))
                                  for i, j in zip(iu[0][strong], iu[1][strong])]

    def _resolve_prior(self):
        """The prior: ``prior`` itself, or ``"tolerances"``: the robot's (robot.yaml) and the effects'."""
        from campaign.model.priors import make_prior

        prior = make_prior(self.robot, self.effect_set_.effects) if isinstance(self.prior, str) else self.prior
        if prior.sigma.shape != (self.robot.n_params,) or prior.effect_sigma.shape != (self.effect_set_.n_params,):
            raise IdentificationError(f"prior: {prior.sigma.shape[0]} + {prior.effect_sigma.shape[0]} standard "
                                      f"deviations for {self.robot.n_params} error parameters and "
                                      f"{self.effect_set_.n_params} effect parameters")
        return prior

    def _prior_and_held(self, x, r, redundant):
        """(μ (r + k,), held (r + k,) bool): the prior's mean of the unknowns (the held values; for
        base parameters the held physical parameters' part of them; effects 0) and which are held."""
        from campaign.model.priors import resolve_fix

        es = self.effect_set_
        fixed = resolve_fix(self.robot, self.fixed or {}, es.param_names) if self.fixed else {}
        physical = {n: v for n, v in fixed.items() if n in self.robot.param_names}
        self.base_prior_ = base_prior(self.base_, self.prior_, physical)
        mu = np.zeros(len(x))
        held = np.zeros(len(x), dtype=bool)
        if redundant:
            mu[:r] = self.base_prior_.p_held
            held[:r] = self.base_prior_.held_params
        else:
            mu[:r] = self.base_prior_.mean
            held[:r] = self.base_prior_.held
        for name in self.drop or ():
            j = (self.robot.param_names if redundant else self.base_.names).index(name)
            held[j], mu[j] = True, 0.0
        x0 = es.initial_params()
        for i, name in enumerate(es.param_names):
            if name in fixed:
                held[r + i] = True
                mu[r + i] = x0[i] if fixed[name] is None else fixed[name]
        return mu, held

    def _prior_precision(self, free, r, redundant) -> np.ndarray:
        """(f, f): s × the prior's precision of the free unknowns (physical parameters and effects:
        diagonal; base parameters: a dense block)."""
        s = float(self.prior_strength)
        fb = [i for i in free if i < r]
        fe = [i - r for i in free if i >= r]
        P = np.zeros((len(free), len(free)))
        if redundant:
            P[:len(fb), :len(fb)] = np.diag(s * self.prior_.precision()[fb])
        else:
            P[:len(fb), :len(fb)] = s * self.base_prior_.precision(fb)
        pe = self.prior_.precision()[self.robot.n_params:]
        P[len(fb):, len(fb):] = np.diag(s * pe[fe])
        return P

    @staticmethod
    def _effective_unknowns(J, P) -> float:
        """tr(H (H + P)⁻¹): the unknowns the data determine (J (n, m, f) whitened, P (f, f))."""
        J2 = J.reshape(-1, J.shape[-1])
        H = J2.T @ J2
        return float(np.trace(np.linalg.solve(H + P, H)))

    def _absorbed(self, J, r):
        """Effect columns that the geometric base columns (and earlier effect columns) span."""
        if J.shape[1] == r:
            return []
        norms = np.linalg.norm(J, axis=0)
        Js = J / np.where(norms > 0, norms, 1.0)
        import scipy.linalg

        _, R = scipy.linalg.qr(Js, mode="economic")
        d = np.abs(np.diag(R))
        ref = d[:r].max() if r else d.max()
        # a looser bound than for exact dependence: effects nearly spanned are not identifiable
        tol = max(BASE_PARAM_RANK_RTOL, 1e-6)
        return [i for i in range(r, J.shape[1]) if d[i] < tol * ref or norms[i] == 0]

    def _check(self):
        if not hasattr(self, "x_"):
            raise NotFittedError("CalibrationModel is not fitted; call fit() first")

    def predict(self, q, context=None) -> np.ndarray:
        """Model pose T_IE (n, 4, 4) for joint coordinates q (n, N) rad (m for prismatic joints)."""
        self._check()
        return self._model_T(np.asarray(q, dtype=float), self.params_, self.effect_params_, context or {})

    def residuals(self, q, T_meas, context=None) -> np.ndarray:
        """Δz (n, 6) of the fitted model against measured poses."""
        return pose_error(self.predict(q, context), T_meas)

    def predict_points(self, q, context=None) -> np.ndarray:
        """Model positions (n, k, 3) m in F_I of the fitted ``points`` for joint coordinates q (n, N)."""
        self._check()
        if self.points is None:
            raise DataError("predict_points: the model was fitted without points")
        return self._model_points(np.asarray(q, dtype=float), self.params_, self.effect_params_, context or {})

    def point_residuals(self, q, P_meas, context=None) -> np.ndarray:
        """(n, k, 3) m: model minus measured positions of the fitted ``points`` (NaN where missed)."""
        return self.predict_points(q, context) - np.asarray(P_meas, dtype=float)

    def point_jacobian(self, q, context=None, *, base_params=None, effect_params=None) -> np.ndarray:
        """(n, k, 3, r + k_effects): the derivative of the ``points``' model positions with respect
        to the r base parameters and the effect parameters, at the given values (default: the
        fitted ones); base_params (r,) m / rad, effect_params in their units."""
        self._check()
        if self.points is None:
            raise DataError("point_jacobian: the model was fitted without points")
        p_e = self.params_ if base_params is None else self.base_.expand(np.asarray(base_params, dtype=float))
        theta = self.effect_params_ if effect_params is None else np.asarray(effect_params, dtype=float)
        return self._point_jacobian(np.asarray(q, dtype=float), p_e, theta, context or {})

    def jacobian(self, q, T_meas, context=None, *, base_params=None, effect_params=None) -> np.ndarray:
        """(n, 6, r + k): the derivative of Δz against the measured poses T_meas (n, 4, 4) with
        respect to the r geometric unknowns (the base parameters; every error parameter for a MAP
        fit on the redundant model) and the k effect parameters, at the given values (default: the
        fitted ones); base_params (n_base,) m / rad, effect_params (k,) in their units."""
        self._check()
        p_e = self.params_ if base_params is None else self.base_.expand(np.asarray(base_params, dtype=float))
        theta = self.effect_params_ if effect_params is None else np.asarray(effect_params, dtype=float)
        return self._jacobian(np.asarray(q, dtype=float), p_e, theta, context or {}, T_meas)

    def parameter_table(self) -> list:
        """Rows (name, unit, value, sigma): the base parameters (a MAP fit's estimate projected on
        them, with their posterior σ), then the effect parameters."""
        self._check()
        es = self.effect_set_
        return [(n, u, float(v), float(s)) for n, u, v, s in
                zip(self.base_.names + es.param_names, self.base_.units + es.param_units,
                    np.concatenate([self.base_params_, self.effect_params_]),
                    np.concatenate([self.base_sigma_, self.effect_sigma_]))]
