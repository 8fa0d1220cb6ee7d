"""Optimal experiment design: the suitable poses that teach the model most, per pose or per hour.

The unknowns are those `calibrate` identifies: the geometric base parameters
(:mod:`campaign.model.base_params`) plus the parameters of the physical effects to plan for.
Their Jacobian is the identification's own (``CalibrationModel``'s rows ``∂Δz/∂x`` at the start
point ``x = 0``: analytic for the geometry, numerical for the effects, as the solver does).

What the tracker measures is the tool's reflectors, each coordinate with noise σ (m).

* Three reflectors or more: the pose derived from them by Kabsch carries, to first order, the
  information of their coordinates: ``Λ_i = Aᵢᵀ Aᵢ / σ²`` (6×6) with ``Aᵢ`` (3k×6) the map of a
  twist of F_E (δt at E's origin, δφ in F_I) to the reflectors' displacements. Every candidate
  contributes a 6-row block ``Bᵢ = Lᵢᵀ Jᵢ`` (``Λᵢ = Lᵢ Lᵢᵀ``).
* One or two reflectors (position-only data): no pose is derived; the k reflector positions are
  the measurement, 3k rows ``Bᵢ = (∂ reflector positions/∂ unknowns) / σ``. The unknowns are
  then the position-only base parameters, as `calibrate` identifies them from one-reflector
  data: those of the robot whose tool point is the (first) reflector
  (``RobotModel.with_tool_point``), of the positions of all k reflectors.

The information matrix is ``M = Σ Bᵢᵀ Bᵢ``. Columns are scaled to unit mean information over the
candidates (D-optimality does not depend on that scale).

Criteria: ``D`` maximises log det M; ``A`` minimises tr M⁻¹ (scaled parameters); ``I``
minimises the mean variance of the predicted tool position over the candidates
(tr W M⁻¹, ``W = mean Jₜᵀ Jₜ``). Greedy selection keeps, for every candidate, ``Gⱼ = Bⱼ M⁻¹ Bⱼᵀ``
(b×b, b the rows of a block: 6, or 3 for one reflector) up to date with rank-b (Woodbury)
updates, so adding ``Bⱼ`` gains ``log det(I + Gⱼ)`` (matrix determinant lemma). DETMAX exchange
passes (Mitchell 1974: add the best candidate, remove the least useful pose, stop when that is
the one just added) then improve the greedy set. With a time cost per pose, the greedy step
maximises gain per second.

The predicted accuracy (:func:`predict_accuracy`) is the covariance of the estimator that
`calibrate` runs (row weights by block, from the noise: a sandwich ``H⁻¹ S H⁻¹``), carried to
the tool pose at every candidate (for position-only data: to the measured reflector positions;
no orientation): the expected error of the model against the truth, and the expected held-out
error (model error plus the measurement's own noise).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from campaign.effects.base import EffectSet, effect_context, make_effect, model_pose
from campaign.errors import ConfigError
from campaign.model.base_params import base_parameters, point_rows
from campaign.model.kinematics import forward
from campaign.plan.defaults import DEFAULT_SELECT, REPEAT_POSES, REPEAT_TIMES  # noqa: F401 (re-exported)

#: Leica LTD800: σ per coordinate of a reflector centre (m), the simulated tracker's default too;
#: `campaign plan` takes campaign.yaml's ``tracker: {noise_m: ...}`` instead when it is given
TRACKER_NOISE_M = 10e-6
#: ridge of the information matrix before any pose is chosen, relative to the mean
#: information of one pose per (scaled) parameter: it only orders the first few picks
RIDGE = 1e-6
#: G is recomputed from M⁻¹ every this many rank-b updates (bounds round-off drift)
REFRESH_EVERY = 64
#: normal samples per pose for the expected norm of a 3-D Gaussian error
NORM_SAMPLES = 256
#: poses per chunk of those samples (4096 × 256 × 3 doubles: 25 MB)
NORM_CHUNK = 4096
CRITERIA = ("D", "A", "I")
#: the prediction's mean errors are averaged over a random sample of the suitable poses large
#: enough that the sample's mean is within this fraction of the mean over all of them, at 95 %
#: confidence (issue 22: ±2 %; every suitable pose took 19 s of the COMAU's default plan)
PREDICTION_REL_HALF_WIDTH = 0.02
#: poses of the pilot sample whose spread of per-pose errors sizes the sample
PREDICTION_PILOT = 1000
PREDICTION_SEED = 20260522


@dataclass(frozen=True)
class Information:
    """Per-candidate information about the unknowns.

    names, units: (p,) of the unknowns (base parameters, then effect parameters);
    J: (m, r, p) the derivative of what is measured per unit of each unknown: with
    ``measured`` "pose", ``∂Δz/∂x`` (r = 6 rows: position m, orientation rad); with "points",
    the positions (m) of the k measured reflectors, (r = 3k rows: x, y, z of each in turn);
    noise_cov: (m, r, r) covariance of the measurement (m², m·rad, rad²);
    blocks: (m, r, p) whitened, column-scaled rows (``blocksᵀ blocks`` = information);
    scale: (p,) the column scale (``blocks = Lᵀ J / scale``);
    measured: "pose" (a 6-D pose from three reflectors or more) or "points" (the positions of
    one or two reflectors).
    """

    names: tuple
    units: tuple
    J: np.ndarray
    noise_cov: np.ndarray
    blocks: np.ndarray
    scale: np.ndarray
    measured: str = "pose"
    #: (p, p) the unknowns' prior precision (campaign.model.priors.unknowns_precision), or None
    prior_precision: np.ndarray | None = None

    @property
    def n_candidates(self) -> int:
        return self.J.shape[0]

    @property
    def n_unknowns(self) -> int:
        return self.J.shape[2]

    @property
    def block_size(self) -> int:
        """Rows (equations) a candidate contributes: 6 for a pose, 3 per measured point."""
        return self.J.shape[1]

    @property
    def n_points(self) -> int:
        """Points whose position the prediction is about: the tool point of a pose, or the k
        measured reflectors."""
        return 1 if self.measured == "pose" else self.block_size // 3

    def position_rows(self, index=None) -> np.ndarray:
        """The position rows of J, (m, n_points, 3, p) m per unit of each unknown."""
        J = self.J if index is None else self.J[np.asarray(index, dtype=np.int64)]
        if self.measured == "pose":
            return J[:, None, :3, :]
        return J.reshape(len(J), self.n_points, 3, self.n_unknowns)

    def subset(self, index) -> "Information":
        """The candidates ``index`` alone (same column scale)."""
        index = np.asarray(index, dtype=np.int64)
        return Information(self.names, self.units, self.J[index], self.noise_cov[index], self.blocks[index],
                           self.scale, self.measured, self.prior_precision)

    def information(self, index) -> np.ndarray:
        """Scaled information matrix (p, p) of the poses ``index`` (repeats count twice)."""
        B = self.blocks[np.asarray(index, dtype=np.int64)].reshape(-1, self.n_unknowns)
        return B.T @ B


def reflector_pose_noise(robot, q, noise_m: float = TRACKER_NOISE_M) -> np.ndarray:
    """Covariance (n, 6, 6) of Δz = (δt at E's origin [m], δφ in F_I [rad]) of the pose that
    Kabsch derives from the three reflectors, each coordinate with noise ``noise_m`` (m)."""
    T = forward(robot, q)
    R = T[:, :3, :3]
    r = np.asarray(robot.reflector_positions_in_E, dtype=float) @ np.swapaxes(R, 1, 2)  # (n, k, 3) in F_I
    n, k = r.shape[:2]
    # displacement of reflector k under the twist: δt + δφ × r_k = δt − [r_k]× δφ
    A = np.zeros((n, k, 3, 6))
    A[:, :, :, :3] = np.eye(3)
    sk = np.zeros((n, k, 3, 3))
    sk[..., 0, 1], sk[..., 0, 2] = -r[..., 2], r[..., 1]
    sk[..., 1, 0], sk[..., 1, 2] = r[..., 2], -r[..., 0]
    sk[..., 2, 0], sk[..., 2, 1] = -r[..., 1], r[..., 0]
    A[:, :, :, 3:] = -sk
    A = A.reshape(n, 3 * k, 6)
    info = np.swapaxes(A, 1, 2) @ A / noise_m**2
    return np.linalg.inv(info)


def unknowns_jacobian(robot, q, effects=(), context=None, base=None):
    """``∂Δz/∂x`` (n, 6, p) at the identification's start point (x = 0), with the unknowns'
    names and units: exactly the rows `calibrate`'s solver builds (CalibrationModel). base:
    the geometric base parameters (default: those of 6-D poses)."""
    from campaign.identify.solver import CalibrationModel

    q = np.asarray(q, dtype=float)
    es = EffectSet(tuple(make_effect(e, robot) if isinstance(e, str) else e for e in effects))
    for e in es.effects:
        missing = [k for k in e.context_keys if k != "time_s" and k not in (context or {})]
        if missing:
            raise ConfigError(f"effect '{e.name}' depends on '{missing[0]}', which is known only when measuring: "
                              "the plan cannot weigh it (leave it out of --for-effects)")
    ctx = effect_context(context or {}, (context or {}).get("time_s", np.zeros(len(q))))
    # the solver's own Jacobian, evaluated without fitting (its _jacobian reads these two)
    probe = CalibrationModel(robot=robot, effects=es.effects)
    probe.effect_set_ = es
    probe.base_ = base_parameters(robot) if base is None else base
    theta = es.initial_params()
    T0 = model_pose(robot, q, None, es, theta, ctx)
    J = probe._jacobian(q, probe.base_.expand(np.zeros(probe.base_.n_base)), theta, ctx, T0)
    names = probe.base_.names + es.param_names
    units = probe.base_.units + es.param_units
    return J, names, units


def measures_points(robot) -> bool:
    """Whether a campaign of ``robot`` measures reflector positions only (robot.yaml names one
    or two reflectors) rather than 6-D poses (three or more, by Kabsch)."""
    return 1 <= len(robot.reflectors) <= 2


def position_only_jacobian(robot, q, effects=(), context=None):
    """The positions of the robot's k (1 or 2) reflectors against the unknowns of position-only
    data: (n, 3k, p) m per unit of each unknown (rows x, y, z of each reflector in F_I), with the
    unknowns' names and units.

    The model is `calibrate`'s for one-reflector data: the robot whose tool point is the first
    reflector (:meth:`RobotModel.with_tool_point`), its position-only base parameters (of all k
    reflectors' positions) and the effects' parameters. A reflector at ``d`` (F_I) from the tool
    point moves by ``δt + δφ × d`` under the model's pose error (δt, δφ)."""
    P = np.asarray(robot.reflector_positions_in_E, dtype=float)
    tool, offsets, base = _points_model(robot)
    J6, names, units = unknowns_jacobian(tool, q, effects, context, base=base)
    if len(P) == 1:
        return np.ascontiguousarray(J6[:, :3, :]), names, units
    d = offsets @ np.swapaxes(forward(tool, q)[:, :3, :3], 1, 2)  # (n, k, 3) in F_I
    J = point_rows(J6, d)
    return J.reshape(len(q), 3 * len(P), -1), names, units


def _points_model(robot):
    """Position-only data's model: (the robot whose tool point is the first reflector, the
    reflectors' offsets from it in the tool frame (k, 3) m, its position-only base parameters)."""
    P = np.asarray(robot.reflector_positions_in_E, dtype=float)
    tool = robot.with_tool_point(P[0])
    offsets = P - P[0]  # from the tool point, in the (unturned) tool frame
    base = base_parameters(tool, position_only=True) if len(P) == 1 else \
        base_parameters(tool, position_only=True, points=offsets)
    return tool, offsets, base


def information_model(robot, q, *, effects=(), noise_m: float = TRACKER_NOISE_M, context=None,
                      noise_cov=None, priors: bool = False) -> Information:
    """The :class:`Information` of candidate joint vectors q (m, N) rad.

    A robot with three reflectors or more: 6-D poses, noise_cov (m, 6, 6) the covariance of each
    measured Δz, default: the reflectors, each coordinate with σ = ``noise_m`` (m), fitted by
    Kabsch (:func:`reflector_pose_noise`). One or two reflectors: their positions
    (:func:`position_only_jacobian`), each coordinate with σ = ``noise_m`` (noise_cov (m, 3k, 3k)).
    priors: attach the unknowns' prior precision (the tolerances, campaign.model.priors), which
    the design then starts from (Bayesian D-optimality: information plus prior precision).
    """
    q = np.asarray(q, dtype=float)
    if measures_points(robot):
        J, names, units = position_only_jacobian(robot, q, effects, context)
        measured = "points"
        cov = np.broadcast_to(noise_m**2 * np.eye(J.shape[1]), (len(q),) + (J.shape[1],) * 2).copy() \
            if noise_cov is None else np.asarray(noise_cov, dtype=float)
    else:
        J, names, units = unknowns_jacobian(robot, q, effects, context)
        measured = "pose"
        cov = reflector_pose_noise(robot, q, noise_m) if noise_cov is None else np.asarray(noise_cov, dtype=float)
    L = np.linalg.cholesky(np.linalg.inv(cov))  # Λ = L Lᵀ
    B = np.swapaxes(L, 1, 2) @ J
    scale = np.sqrt(np.mean(np.sum(B**2, axis=1), axis=0))
    dead = scale <= 1e-12 * max(scale.max(), 1e-300)
    if dead.any():
        name = names[int(np.flatnonzero(dead)[0])]
        raise ConfigError(f"no candidate pose informs '{name}': it cannot be planned for")
    B = B / scale
    prior = _prior_precision(robot, effects, measured) if priors else None
    for a in (J, cov, B, scale) + (() if prior is None else (prior,)):
        a.setflags(write=False)
    return Information(tuple(names), tuple(units), J, cov, B, scale, measured, prior)


def _prior_precision(robot, effects, measured) -> np.ndarray:
    """The unknowns' prior precision (p, p) for ``information_model``: the base parameters of
    the data's model (6-D poses, or positions of the reflectors) and the effects' parameters."""
    from campaign.model.priors import make_prior, unknowns_precision

    model, base = (robot, base_parameters(robot)) if measured == "pose" else _points_model(robot)[::2]
    es = tuple(make_effect(e, model) if isinstance(e, str) else e for e in effects)
    return unknowns_precision(base, make_prior(model, es))


def log_det(info: Information, index) -> float:
    """log det of the scaled information of the poses ``index`` (no ridge), directly."""
    sign, val = np.linalg.slogdet(info.information(index))
    return float(val) if sign > 0 else -np.inf


def _logdet_spd(K):
    """log det of a batch of symmetric positive definite matrices (…, k, k)."""
    Lc = np.linalg.cholesky(K)
    return 2.0 * np.sum(np.log(np.diagonal(Lc, axis1=-2, axis2=-1)), axis=-1)


class Design:
    """The growing design: M⁻¹ (with the ridge) and Gⱼ = Bⱼ M⁻¹ Bⱼᵀ (b×b) for every candidate,
    b the rows of a candidate's block (6 for a pose, 3 per measured point)."""

    def __init__(self, info: Information, criterion: str, weight=None):
        self.B = info.blocks
        self.b = info.blocks.shape[1]
        p = info.n_unknowns
        self.M = RIDGE * np.eye(p)
        if info.prior_precision is not None:  # Bayesian D-optimality: the prior's precision, scaled
            self.M = self.M + info.prior_precision / np.outer(info.scale, info.scale)
        self.Minv = np.eye(p) / RIDGE
        # refreshes as M reaches full rank and becomes well conditioned: the updates from the
        # ridge's 1/RIDGE scale down to O(1) lose digits, which a fresh M⁻¹ restores
        self.full_rank_at = int(np.ceil(p / self.b))
        self.count = np.zeros(info.n_candidates, dtype=np.int64)
        self.criterion = criterion
        # A: W = I; I: W = mean over candidates of the position rows' JᵀJ, in scaled parameters
        self.W_half = None if weight is None else np.linalg.cholesky(weight + 1e-12 * np.trace(weight) / p * np.eye(p))
        self.updates = 0
        self.refresh()

    def refresh(self):
        self.Minv = np.linalg.inv(self.M)
        self.Minv = 0.5 * (self.Minv + self.Minv.T)
        BM = self.B @ self.Minv  # (m, b, p)
        self.G = BM @ np.swapaxes(self.B, 1, 2)
        self.updates = 0

    def _update(self, j, sign):
        """M += sign · Bⱼᵀ Bⱼ (sign ±1), updating M⁻¹ and every G (rank b, Woodbury)."""
        Bj = self.B[j]
        self.M = self.M + sign * (Bj.T @ Bj)
        u = self.Minv @ Bj.T  # (p, b)
        K = np.eye(self.b) + sign * (Bj @ u)
        Kinv = np.linalg.inv(K)
        self.Minv = self.Minv - sign * (u @ Kinv @ u.T)
        self.Minv = 0.5 * (self.Minv + self.Minv.T)
        C = self.B @ u  # (m, b, b) = Bᵢ M⁻¹ Bⱼᵀ
        self.G = self.G - sign * (C @ Kinv @ np.swapaxes(C, 1, 2))
        self.updates += 1
        n = int(self.count.sum()) + int(sign)
        if self.updates >= REFRESH_EVERY or n in (self.full_rank_at, 2 * self.full_rank_at, 4 * self.full_rank_at):
            self.refresh()

    def add(self, j):
        self._update(j, +1.0)
        self.count[j] += 1

    def remove(self, j):
        self._update(j, -1.0)
        self.count[j] -= 1

    def gains(self, index=None):
        """Improvement of the criterion from adding each candidate (larger is better)."""
        G = self.G if index is None else self.G[index]
        Ib = np.eye(self.b)
        if self.criterion == "D":
            return _logdet_spd(Ib + G)
        H = self._H(index)
        return np.trace(np.linalg.solve(Ib + G, H), axis1=1, axis2=2)

    def losses(self, index):
        """Worsening of the criterion from removing each pose of ``index`` (smaller is better)."""
        G = self.G[index]
        K = np.eye(self.b) - G
        if self.criterion == "D":
            ev = np.linalg.eigvalsh(0.5 * (K + np.swapaxes(K, 1, 2)))
            return -np.sum(np.log(np.clip(ev, 1e-300, None)), axis=1)
        H = self._H(index)
        return np.trace(np.linalg.solve(K, H), axis1=1, axis2=2)

    def _H(self, index):
        """Bⱼ M⁻¹ W M⁻¹ Bⱼᵀ (…, b, b)."""
        P = self.Minv if self.W_half is None else self.Minv @ self.W_half
        B = self.B if index is None else self.B[index]
        BP = B @ P
        return BP @ np.swapaxes(BP, 1, 2)

    def criterion_value(self):
        """log det M (D) or tr W M⁻¹ (A, I), ridge included."""
        if self.criterion == "D":
            return float(np.linalg.slogdet(self.M)[1])
        P = self.Minv if self.W_half is None else self.W_half.T @ self.Minv @ self.W_half
        return float(np.trace(P))


def position_weight(info: Information) -> np.ndarray:
    """Mean over the candidates (and their measured points) of the position rows' JᵀJ in scaled
    parameters (p, p): the I-criterion's weight, tr(W M⁻¹) = mean variance of the predicted
    position of the tool point (or of the measured reflectors)."""
    Jt = info.position_rows().reshape(-1, 3, info.n_unknowns) * info.scale
    return np.einsum("mri,mrj->ij", Jt, Jt) / len(Jt)


@dataclass(frozen=True)
class Selection:
    """Chosen candidates (indices into the candidate array) in the order they were chosen,
    the criterion and its value (log det of the scaled information for D), and timings (s)."""

    index: np.ndarray
    criterion: str
    log_det: float
    exchanges: int
    time_s: float


def select(info: Information, n: int | None = None, *, criterion: str = "D", exchange: bool = True,
           cost_s=None, budget_s: float | None = None, travel_s=None, start=None,
           max_exchanges: int | None = None) -> Selection:
    """Choose ``n`` candidates greedily, then improve them by DETMAX exchanges.

    cost_s: (m,) seconds each candidate costs besides the motion to it (settle + tracker);
    travel_s: optional callable ``travel_s(j) -> (m,)`` seconds from candidate j to every
    candidate, so a candidate's motion cost is its time from the nearest chosen pose (from
    ``start``: (m,) seconds from the robot's start). With costs, each step maximises gain per
    second, and ``budget_s`` (instead of n) stops when the estimated time is spent.
    """
    import time

    t0 = time.perf_counter()
    if criterion not in CRITERIA:
        raise ConfigError(f"criterion must be one of {', '.join(CRITERIA)}, got {criterion!r}")
    m = info.n_candidates
    if n is None and budget_s is None:
        raise ConfigError("select: give a number of poses or a budget")
    if n is not None and not 1 <= n <= m:
        raise ConfigError(f"cannot select {n} of {m} suitable poses")
    weight = position_weight(info) if criterion == "I" else None
    d = Design(info, criterion, weight)
    fixed = None if cost_s is None else np.broadcast_to(np.asarray(cost_s, dtype=float), (m,))
    nearest = None
    if travel_s is not None:
        nearest = np.zeros(m) if start is None else np.asarray(start, dtype=float).copy()
    chosen = []
    spent = 0.0
    free = np.ones(m, dtype=bool)
    limit = m if n is None else n
    while len(chosen) < limit:
        g = d.gains()
        score = g.copy()
        cost = None
        if fixed is not None:
            cost = fixed + (nearest if nearest is not None else 0.0)
            score = g / np.maximum(cost, 1e-9)
        score[~free] = -np.inf
        j = int(np.argmax(score))
        if not np.isfinite(score[j]):
            break
        if budget_s is not None and cost is not None and spent + cost[j] > budget_s:
            break
        if cost is not None:
            spent += float(cost[j])
        d.add(j)
        free[j] = False
        chosen.append(j)
        if nearest is not None:
            nearest = np.minimum(nearest, travel_s(j)) if len(chosen) > 1 or start is not None else travel_s(j)
    n_ex = 0
    if exchange and len(chosen) and fixed is None:
        chosen, n_ex = _detmax(d, chosen, free, max_exchanges)
    idx = np.array(chosen, dtype=np.int64)
    return Selection(idx, criterion, log_det(info, idx), n_ex, time.perf_counter() - t0)


def _detmax(d: Design, chosen, free, max_exchanges=None):
    """Mitchell's DETMAX with excursions of one: add the best candidate, remove the least
    useful pose; stop when the pose removed is the one just added."""
    chosen = list(chosen)
    limit = max_exchanges if max_exchanges is not None else 4 * len(chosen) + 20
    n_ex = 0
    for _ in range(limit):
        g = d.gains()
        g[~free] = -np.inf
        j = int(np.argmax(g))
        if not np.isfinite(g[j]):
            break
        d.add(j)
        members = np.array(chosen + [j])
        loss = d.losses(members)
        k = int(np.argmin(loss))
        i = int(members[k])
        if i == j or g[j] - loss[k] <= 1e-10 * max(abs(g[j]), 1.0):
            d.remove(j)
            break
        d.remove(i)
        chosen.remove(i)
        chosen.append(j)
        free[j] = False
        free[i] = True
        n_ex += 1
    return chosen, n_ex


# -- predicted accuracy ----------------------------------------------------------------------------
def estimator_covariance(info: Information, index) -> np.ndarray:
    """Covariance (p, p) of the unknowns (in their own units) estimated from the poses
    ``index`` by `calibrate`'s solver: rows weighted by one σ per block (position,
    orientation; position-only data: one σ for all) from the noise, so the covariance is the
    sandwich H⁻¹ S H⁻¹."""
    index = np.asarray(index, dtype=np.int64)
    J = info.J[index]
    S6 = info.noise_cov[index]
    if info.measured == "pose":
        var_p = np.mean(np.trace(S6[:, :3, :3], axis1=1, axis2=2)) / 3.0
        var_o = np.mean(np.trace(S6[:, 3:, 3:], axis1=1, axis2=2)) / 3.0
        w = np.array([1 / var_p] * 3 + [1 / var_o] * 3)
    else:
        w = np.full(info.block_size, info.block_size / np.mean(np.trace(S6, axis1=1, axis2=2)))
    WJ = J * w[None, :, None]
    H = np.einsum("nri,nrj->ij", J, WJ)
    S = np.einsum("nri,nrs,nsj->ij", WJ, S6, WJ)
    Hinv = np.linalg.pinv(H)
    return Hinv @ S @ Hinv


def expected_norm(C, n_samples: int = NORM_SAMPLES, seed: int = 0) -> np.ndarray:
    """E‖x‖ for x ~ N(0, Cₖ), each Cₖ (k, 3, 3) symmetric PSD; fixed normal samples."""
    C = np.asarray(C, dtype=float)
    lam, V = np.linalg.eigh(0.5 * (C + np.swapaxes(C, -1, -2)))
    root = V * np.sqrt(np.clip(lam, 0, None))[:, None, :]
    z = np.random.default_rng(seed).standard_normal((n_samples, C.shape[-1]))
    out = np.empty(len(root))
    for s in range(0, len(root), NORM_CHUNK):  # bounds the (chunk, samples, 3) draws' memory
        out[s:s + NORM_CHUNK] = np.mean(np.linalg.norm(np.einsum("kij,sj->ksi", root[s:s + NORM_CHUNK], z),
                                                       axis=-1), axis=1)
    return out


@dataclass(frozen=True)
class Prediction:
    """Predicted accuracy of a design over the evaluation poses (mm, mrad): the model against
    the truth, and held-out (the model's error plus the measurement's noise), mean and RMS. For
    position-only data the positions are those of the measured reflector(s) and the orientation
    fields are None (nothing measures an orientation)."""

    model_position_mm: float
    model_position_rms_mm: float
    model_orientation_mrad: float | None
    heldout_position_mm: float
    heldout_orientation_mrad: float | None
    noise_position_mm: float

    def as_dict(self) -> dict:
        return {k: None if v is None else float(v) for k, v in self.__dict__.items()}


def predicted_model_position_mm(info: Information, index, evaluate=None, *, max_poses: int = 2000,
                                n_samples: int = 64) -> float:
    """A quick :attr:`Prediction.model_position_mm` (for searching sizes): evaluated on at most
    ``max_poses`` of the evaluation poses (a fixed spread subset) with fewer normal samples."""
    ev = np.arange(info.n_candidates) if evaluate is None else np.asarray(evaluate, dtype=np.int64)
    if len(ev) > max_poses:
        ev = ev[np.linspace(0, len(ev) - 1, max_poses).round().astype(np.int64)]
    cov = estimator_covariance(info, index)
    Jt = info.position_rows(ev).reshape(-1, 3, info.n_unknowns)
    return 1e3 * float(np.mean(expected_norm(Jt @ cov @ np.swapaxes(Jt, 1, 2), n_samples)))


def predict_accuracy(info: Information, index, evaluate=None) -> Prediction:
    """What a campaign on the poses ``index`` will achieve, averaged over the candidates
    ``evaluate`` (default: all): expected mean errors from :func:`estimator_covariance`."""
    cov = estimator_covariance(info, index)
    ev = np.arange(info.n_candidates) if evaluate is None else np.asarray(evaluate, dtype=np.int64)
    J = info.J[ev]
    C = J @ cov @ np.swapaxes(J, 1, 2)  # (k, r, r) model error at each evaluation pose
    N = info.noise_cov[ev]
    if info.measured == "points":  # each measured point's 3×3 diagonal block
        k = info.n_points
        blocks = [np.s_[:, 3 * i:3 * i + 3, 3 * i:3 * i + 3] for i in range(k)]
        Cp = np.concatenate([C[b] for b in blocks])
        Np = np.concatenate([N[b] for b in blocks])
        return Prediction(
            model_position_mm=1e3 * float(np.mean(expected_norm(Cp))),
            model_position_rms_mm=1e3 * float(np.sqrt(np.mean(np.trace(Cp, axis1=1, axis2=2)))),
            model_orientation_mrad=None,
            heldout_position_mm=1e3 * float(np.mean(expected_norm(Cp + Np))),
            heldout_orientation_mrad=None,
            noise_position_mm=1e3 * float(np.mean(expected_norm(Np))),
        )
    Cp, Co = C[:, :3, :3], C[:, 3:, 3:]
    return Prediction(
        model_position_mm=1e3 * float(np.mean(expected_norm(Cp))),
        model_position_rms_mm=1e3 * float(np.sqrt(np.mean(np.trace(Cp, axis1=1, axis2=2)))),
        model_orientation_mrad=1e3 * float(np.mean(expected_norm(Co))),
        heldout_position_mm=1e3 * float(np.mean(expected_norm(Cp + N[:, :3, :3]))),
        heldout_orientation_mrad=1e3 * float(np.mean(expected_norm(Co + N[:, 3:, 3:]))),
        noise_position_mm=1e3 * float(np.mean(expected_norm(N[:, :3, :3]))),
    )


def evaluation_sample(info: Information, index, *, rel: float = PREDICTION_REL_HALF_WIDTH,
                      pilot: int = PREDICTION_PILOT, seed: int = PREDICTION_SEED):
    """The poses (indices into ``info``'s candidates, ascending) over which the prediction of the
    design ``index`` is averaged, and what they are (a dict for summary.json).

    A random sample (fixed seed) of size ``n = (1.96 · cv / rel)²``, cv the largest coefficient
    of variation of the per-pose expected model errors (position; orientation when measured)
    on a pilot sample of ``pilot`` poses: the sample's mean is then within ±``rel`` of the
    mean over every candidate at 95 % confidence. All candidates when there are no more than
    the sample would take."""
    m = info.n_candidates
    everything = {"poses": int(m), "of": int(m), "relative_half_width": 0.0, "confidence": 1.0}
    if m <= pilot:
        return np.arange(m), everything
    perm = np.random.default_rng(seed).permutation(m)
    first = np.sort(perm[:pilot])
    J = info.J[first]
    C = J @ estimator_covariance(info, index) @ np.swapaxes(J, 1, 2)
    if info.measured == "pose":
        parts = [C[:, :3, :3], C[:, 3:, 3:]]
    else:
        parts = [np.concatenate([C[:, 3 * i:3 * i + 3, 3 * i:3 * i + 3] for i in range(info.n_points)])]
    cv = max(float(np.std(e) / max(np.mean(e), 1e-300)) for e in (expected_norm(P, 64) for P in parts))
    n = max(pilot, int(np.ceil((1.96 * cv / rel) ** 2)))
    if n >= m:
        return np.arange(m), everything
    return np.sort(perm[:n]), {"poses": int(n), "of": int(m), "relative_half_width": rel, "confidence": 0.95,
                               "pilot_coefficient_of_variation": cv, "seed": seed}


def sample_text(sample: dict) -> str:
    """What the prediction was averaged over, for summary.json and the printout."""
    among = sample.get("suitable", 0)
    if among > sample["of"]:  # the design chose among a pool of the suitable poses (campaign.plan.region)
        pool = f"{sample['of']:,} candidate poses drawn at random from the {among:,} suitable"
    else:
        pool = f"{sample['of']:,} suitable poses"
    if sample["poses"] >= sample["of"]:
        return f"all {pool}"
    return (f"a random sample of {sample['poses']:,} of the {pool} (mean within "
            f"±{100 * sample['relative_half_width']:g} % of all of them, 95 % confidence)")


def smallest_reaching(info: Information, target_mm: float, *, criterion: str = "D", evaluate=None,
                      max_n: int | None = None):
    """The smallest greedy design whose predicted model error against the truth (mean
    position, mm, over ``evaluate``) is at most ``target_mm``: (n, Selection, Prediction).

    Greedy designs are nested, so the size is found by bisection on one greedy order; the
    chosen size is then improved by exchanges."""
    m = info.n_candidates
    max_n = min(max_n or m, m)
    p_min = _min_poses(info) + 1  # one pose more than the unknowns need
    best = predict_accuracy(info, np.arange(m) if max_n == m else select(info, max_n, exchange=False).index,
                            evaluate)
    if best.model_position_mm > target_mm:
        raise ConfigError(f"--target-mm {target_mm:g}: even {max_n} poses are predicted to reach only "
                          f"{best.model_position_mm:.4f} mm")
    # greedy designs are nested: grow the size by doubling until it reaches the target, then bisect
    # within the last greedy order (its prefixes are the smaller greedy designs)
    n_hi = min(max(2 * p_min, 16), max_n)
    while True:
        order = select(info, n_hi, criterion=criterion, exchange=False).index
        if n_hi == max_n or predicted_model_position_mm(info, order, evaluate) <= target_mm:
            break
        n_hi = min(2 * n_hi, max_n)

    def pred(k):
        return predict_accuracy(info, order[:k], evaluate)

    lo, hi = min(p_min, len(order)), len(order)  # the quick prediction of hi reaches the target
    while lo < hi:
        mid = (lo + hi) // 2
        if predicted_model_position_mm(info, order[:mid], evaluate) <= target_mm:
            hi = mid
        else:
            lo = mid + 1
    # the full prediction decides: grow by 2 % steps while it misses (the quick one is a sample)
    while hi < len(order) and pred(hi).model_position_mm > target_mm:
        hi = min(len(order), hi + max(1, hi // 50))
    for _ in range(5):  # ... and shrinks while a smaller prefix still reaches the target
        if hi - 1 < p_min or pred(hi - 1).model_position_mm > target_mm:
            break
        hi -= 1
    sel = select(info, hi, criterion=criterion, exchange=True)
    p = predict_accuracy(info, sel.index, evaluate)
    if p.model_position_mm > target_mm:  # exchanges are for the criterion, not the target: keep greedy's
        sel = Selection(order[:hi], criterion, log_det(info, order[:hi]), 0, sel.time_s)
        p = pred(hi)
    return hi, sel, p


# -- the campaign: selected poses, validation poses, repeats ---------------------------------------
#: pose_id of the r-th repeat (r ≥ 1) of candidate p: p + r · REPEAT_ID_STRIDE (the store keys on
#: pose_id, so a repeat gets an id of its own; its joint vector is identical to p's)
REPEAT_ID_STRIDE = 1_000_000_000
#: seed of the random draw of validation poses (fixed: a re-plan draws the same ones)
VALIDATION_SEED = 20200101
VALIDATION_FRACTION = 0.2
MIN_VALIDATION = 30


def base_pose_id(pose_id) -> np.ndarray:
    """The candidate a pose id measures: repeats map back to their original."""
    return np.asarray(pose_id, dtype=np.int64) % REPEAT_ID_STRIDE


@dataclass(frozen=True)
class SelectionOptions:
    """What `campaign plan` is asked to choose. Exactly one of n / budget_h / target_mm.

    n: number of poses; budget_h: campaign hours (motion, settle, tracker; validation and
    repeats included); target_mm: predicted mean position error of the model against the
    truth over the suitable poses (mm); effects: effect names to plan for (besides the
    geometry); criterion: D, A or I; validation_fraction, min_validation: random validation
    poses added (a share of the chosen number, at least that many); repeat_poses,
    repeat_times: poses measured several times for the noise floor; noise_m: tracker σ (m) of the
    accuracy prediction (None: TRACKER_NOISE_M; `campaign plan` passes campaign.yaml's
    ``tracker: {noise_m}`` when the file states one).
    """

    n: int | None = None
    budget_h: float | None = None
    target_mm: float | None = None
    effects: tuple = ()
    criterion: str = "D"
    validation_fraction: float = VALIDATION_FRACTION
    min_validation: int = MIN_VALIDATION
    repeat_poses: int = REPEAT_POSES
    repeat_times: int = REPEAT_TIMES
    noise_m: float | None = None
    #: start the design from the unknowns' prior precision (Bayesian D-optimality, docs/priors.md)
    priors: bool = True

    def check(self):
        given = [v is not None for v in (self.n, self.budget_h, self.target_mm)]
        if sum(given) != 1:
            raise ConfigError("give exactly one of --select N, --budget HOURS, --target-mm X")
        if self.n is not None and self.n < 1:
            raise ConfigError(f"--select must be a positive number of poses, got {self.n}")
        if self.budget_h is not None and not self.budget_h > 0:
            raise ConfigError(f"--budget must be a positive number of hours, got {self.budget_h}")
        if self.target_mm is not None and not self.target_mm > 0:
            raise ConfigError(f"--target-mm must be positive, got {self.target_mm}")
        if self.criterion not in CRITERIA:
            raise ConfigError(f"--criterion must be one of {', '.join(CRITERIA)}, got {self.criterion!r}")
        if not 0 <= self.validation_fraction < 1:
            raise ConfigError(f"--validation must be a fraction in [0, 1), got {self.validation_fraction}")
        if self.min_validation < 0 or self.repeat_poses < 0 or self.repeat_times < 1:
            raise ConfigError("validation and repeat counts must be >= 0 (repeat times >= 1)")
        if self.repeat_times > 16:
            raise ConfigError(f"a pose can be measured at most 16 times, got {self.repeat_times}")
        if self.noise_m is not None and not 0 < self.noise_m < 0.01:
            raise ConfigError(f"tracker noise must be in (0, 0.01) m, got {self.noise_m!r}")
        return self


@dataclass(frozen=True)
class CampaignChoice:
    """The chosen campaign, as candidate grid indices: ``selected`` (the design, in the
    order chosen), ``validation`` (random, for the test set), ``repeated`` (selected poses
    measured ``repeat_times`` times); ``prediction`` for the selected poses; ``summary``."""

    selected: np.ndarray
    validation: np.ndarray
    repeated: np.ndarray
    repeat_times: int
    prediction: Prediction
    summary: dict

    @property
    def members(self) -> np.ndarray:
        """Grid indices to visit once each (selected + validation)."""
        return np.concatenate([self.selected, self.validation])

    def with_repeats(self, order) -> np.ndarray:
        """Tour order (pose ids) with the repeats' ids inserted back to back, as ISO 9283
        measures repeatability: a repeated pose p is measured again after each of the tour
        poses that follow it, ``p, a, p', b, p'', c, ...`` (the robot moves away to a nearby
        pose of the tour and back), so the copies of one pose lie a minute apart, not hours:
        their differences are the tracker's noise, not the drift (the driver's drift check
        monitors that). A pose too near the tour's end has its last repeats at the end."""
        order = np.asarray(order, dtype=np.int64)
        reps = set(int(p) for p in self.repeated)
        if self.repeat_times < 2 or not reps:
            return order
        out, pending = [], []  # pending: repeat ids still to measure, first in first out
        for pid in order:
            out.append(int(pid))
            if pending:
                out.append(pending.pop(0))
            if int(pid) in reps:
                pending += [int(pid) + r * REPEAT_ID_STRIDE for r in range(1, self.repeat_times)]
        out += pending
        return np.array(out, dtype=np.int64)


def repeats_in_tour(order) -> dict:
    """summary.json's ``tour.repeats_back_to_back``: how the toured order (pose ids) measures the
    repeated poses: per repeated pose its positions in the tour, and the largest number of tour
    steps between two successive measurements of one pose (2: one other pose in between)."""
    order = np.asarray(order, dtype=np.int64)
    base = base_pose_id(order)
    repeated = np.unique(base[order >= REPEAT_ID_STRIDE])
    where = {int(p): np.flatnonzero(base == p).tolist() for p in repeated}
    steps = [int(np.max(np.diff(w))) for w in where.values() if len(w) > 1]
    return {"poses": len(where), "measurements": {str(p): len(w) for p, w in where.items()},
            "tour_positions": {str(p): w for p, w in where.items()},
            "max_steps_between": max(steps) if steps else None,
            "text": "each repeated pose measured again after the next tour pose (p, a, p', b, p'', ...: moving away "
                    "and back, as ISO 9283 measures repeatability): the floor from their differences is the noise, "
                    "not the drift; every motion to and from a repeat is collision-checked with the rest of the "
                    "tour (stage 3's motion check and repair)"}


def _draw_validation(m, chosen, fraction, minimum, seed=VALIDATION_SEED):
    n_val = 0 if fraction == 0 and minimum == 0 else max(int(minimum), int(round(fraction * len(chosen))))
    rest = np.setdiff1d(np.arange(m), chosen)
    n_val = min(n_val, len(rest))
    rng = np.random.default_rng(seed)
    return np.sort(rng.choice(rest, n_val, replace=False)) if n_val else np.zeros(0, dtype=np.int64)


def check_select_size(robot, opts: SelectionOptions, *, n_probe: int = 64, seed: int = 0) -> None:
    """ConfigError when ``--select N`` asks for fewer poses than the unknowns need, checked on
    ``n_probe`` random joint vectors within the limits before the grid is filtered (the count of
    unknowns and equations per pose does not depend on which poses: the same line as
    :func:`choose_campaign` gives, in a fraction of a second instead of after the filters)."""
    if opts.n is None:
        return
    lo = np.maximum(np.asarray(robot.q_lower, dtype=float), -np.pi)
    hi = np.minimum(np.asarray(robot.q_upper, dtype=float), np.pi)
    q = lo + (hi - lo) * np.random.default_rng(seed).random((n_probe, len(lo)))
    info = information_model(robot, q, effects=opts.effects,
                             noise_m=TRACKER_NOISE_M if opts.noise_m is None else float(opts.noise_m))
    _require_poses(info, opts.n)


def _min_poses(info: Information) -> int:
    """The fewest poses whose equations are as many as ``info``'s unknowns."""
    return int(np.ceil(info.n_unknowns / info.block_size))


def _require_poses(info: Information, n: int) -> None:
    """ConfigError for ``--select n`` when n poses give fewer equations than ``info`` has unknowns."""
    p_min = _min_poses(info)
    if n < p_min:
        raise ConfigError(f"--select {n}: {info.n_unknowns} unknowns need at least {p_min} poses "
                          f"({info.block_size} equations each)")


def choose_campaign(robot, grid, suitable, opts: SelectionOptions, *, settle_s: float, tracker_s: float,
                    travel_from=None, start_s=None, tour_time=None, progress=None) -> CampaignChoice:
    """Choose the campaign among the ``suitable`` grid indices (what `plan --select`,
    ``--budget`` and ``--target-mm`` do).

    settle_s, tracker_s: seconds per pose (tracker time for the robot's reflectors);
    travel_from(k) -> (m,) s from suitable pose k to every suitable pose; start_s (m,) s from
    the robot's start; tour_time(grid indices) -> s of the ordered tour (for ``--budget``).
    """
    import time

    opts.check()
    say = progress or (lambda msg: None)
    t0 = time.perf_counter()
    suitable = np.asarray(suitable, dtype=np.int64)
    m = len(suitable)
    if m == 0:
        raise ConfigError("no suitable poses to select from")
    noise_m = TRACKER_NOISE_M if opts.noise_m is None else float(opts.noise_m)
    info = information_model(robot, grid.q(suitable), effects=opts.effects, noise_m=noise_m, priors=opts.priors)
    t_info = time.perf_counter() - t0
    say(f"information of {m:,} suitable poses about {info.n_unknowns} unknowns ({t_info:.1f} s)")
    per_pose_s = settle_s + tracker_s
    p_min = _min_poses(info)
    n_val = lambda n: 0 if n == 0 else max(opts.min_validation, int(round(opts.validation_fraction * n)))  # noqa: E731
    if opts.n is not None:
        _require_poses(info, opts.n)
        sel = select(info, opts.n, criterion=opts.criterion)
        mode = {"select": opts.n}
    elif opts.target_mm is not None:
        _, sel, _ = smallest_reaching(info, opts.target_mm, criterion=opts.criterion)
        mode = {"target_mm": opts.target_mm}
    else:
        budget_s = opts.budget_h * 3600.0
        extra_per = opts.repeat_poses * (opts.repeat_times - 1)
        sel, eff = None, budget_s
        for _ in range(5):
            # the budget's share for the design: validation and repeats cost their share too
            design_s = eff / (1.0 + opts.validation_fraction) - extra_per * per_pose_s
            s = select(info, None, criterion=opts.criterion, cost_s=per_pose_s, budget_s=max(design_s, 0.0),
                       travel_s=travel_from, start=start_s)
            if len(s.index) < p_min:
                break
            nv = n_val(len(s.index))
            total = (len(s.index) + nv + extra_per) * per_pose_s
            if tour_time is not None:
                total += tour_time(suitable[s.index])
            if total <= budget_s:
                sel = s if sel is None or len(s.index) > len(sel.index) else sel
                if total > 0.97 * budget_s:
                    break
            eff *= budget_s / max(total, 1e-9)
        if sel is None:
            raise ConfigError(f"--budget {opts.budget_h:g} h: too short for the {p_min} poses that "
                              f"{info.n_unknowns} unknowns need (at least {p_min * per_pose_s / 3600:.2f} h "
                              "without motion)")
        mode = {"budget_h": opts.budget_h}
    chosen = sel.index
    val = _draw_validation(m, chosen, opts.validation_fraction, opts.min_validation)
    n_rep = min(opts.repeat_poses, len(chosen)) if opts.repeat_times > 1 else 0
    # repeated poses: spread over the design's choice order (first, middle, last chosen...), each
    # measured back to back (CampaignChoice.with_repeats)
    rep = chosen[np.linspace(0, len(chosen) - 1, n_rep).round().astype(int)] if n_rep else np.zeros(0, np.int64)
    t1 = time.perf_counter()
    # the repeats' extra measurements are training data too
    train = np.concatenate([chosen, np.repeat(rep, max(opts.repeat_times - 1, 0))])
    ev, sample = evaluation_sample(info, train)
    pred = predict_accuracy(info, train, ev)
    t_pred = time.perf_counter() - t1
    summary = {
        **mode, "criterion": opts.criterion, "unknowns": list(info.names), "n_unknowns": info.n_unknowns,
        "effects": list(opts.effects), "tracker_noise_m": noise_m,
        "measured": _measured_summary(robot, info),
        "selected": int(len(chosen)), "validation": int(len(val)), "repeated_poses": int(n_rep),
        "repeat_times": int(opts.repeat_times) if n_rep else 1,
        "log_det_information": sel.log_det, "exchanges": sel.exchanges,
        "predicted": {**pred.as_dict(),
                      "evaluated_over": sample_text(sample) if info.measured == "pose" else
                      f"the measured reflector positions at {sample_text(sample)} (no orientation is measured)",
                      "sample": sample,
                      "note": "expected mean errors of the model calibrated on the selected poses: "
                              "model_* against the truth, heldout_* against measurements (model + tracker noise)"},
        "time_s": {"information": t_info, "selection": sel.time_s, "prediction": t_pred},
    }
    return CampaignChoice(suitable[chosen], suitable[val], suitable[rep], int(opts.repeat_times), pred, summary)


def _measured_summary(robot, info: Information) -> dict:
    """summary.json's ``selection.measured``: what each pose measures, the equations it gives."""
    names = [r.name for r in robot.reflectors]
    if info.measured == "pose":
        text = f"a 6-D pose from {len(names)} reflectors (Kabsch)"
    else:
        text = f"the position of {' and '.join(names)}: position only"
    return {"kind": info.measured, "reflectors": names, "equations_per_pose": info.block_size, "text": text}


def write_choice(out, choice: CampaignChoice | None, visited_ids) -> None:
    """RUN/plan/validation.csv (``pose_id`` of the validation poses in the tour) and
    RUN/plan/repeats.csv (``pose_id,repeat_of``: each repeat's id and the pose it repeats)."""
    from pathlib import Path

    from campaign.fileio import atomic_write

    out = Path(out)
    if choice is None:
        for name in ("validation.csv", "repeats.csv"):
            (out / name).unlink(missing_ok=True)
        return
    visited = set(int(p) for p in visited_ids)
    lines = ["pose_id"] + [str(int(p)) for p in choice.validation if int(p) in visited]
    atomic_write(out / "validation.csv", "\n".join(lines) + "\n")
    rl = ["pose_id,repeat_of"] + [f"{int(p)},{int(p) % REPEAT_ID_STRIDE}" for p in visited_ids
                                  if int(p) >= REPEAT_ID_STRIDE]
    atomic_write(out / "repeats.csv", "\n".join(rl) + "\n")

