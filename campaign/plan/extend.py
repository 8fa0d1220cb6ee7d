"""More poses for a run that is being measured (`campaign auto`): chosen among the suitable poses
of the run's grid that the plan does not hold yet, toured from the plan's last pose and checked
as `campaign plan` checks its tour, then appended to RUN/plan/poses.csv (and vias.csv), where
`campaign run` finds them as poses without a stored outcome.

Three ways to choose (each deterministic: the same measured data give the same poses):

* :func:`design_poses` — the same optimal design as the plan's selection
  (:mod:`campaign.plan.selection`, D-optimal, greedy), for the current model with its effects,
  continuing from the information of the poses already measured: the poses that teach the model
  most given what is known.
* :func:`spread_poses` — poses that fill the gaps of the measured ones over given inputs (joint
  angles, or the gravity load): farthest-point sampling in those inputs scaled to their range,
  so that a structure the model-free test found gets the evidence it needs.
* :func:`separating_poses` — where two effects that the measured poses cannot tell apart differ
  most (T-optimal design): each one's position signal less the best fit of the other (with a
  constant offset of every joint and of the tool) over the measured poses and those chosen before.
* :func:`remeasure_poses` — measured poses measured again now (repeat ids ``p + r·10⁹``): the
  oldest first, spread over the joints, so that a dependence on time shows as the same pose
  giving another answer later.
"""

from __future__ import annotations

import json
from dataclasses import dataclass
from functools import cached_property

import numpy as np

from campaign.errors import ConfigError, DataError
from campaign.fileio import atomic_write, atomic_write_json
from campaign.plan.selection import REPEAT_ID_STRIDE, base_pose_id

#: greedy additions between two checks of the predicted model error (:func:`design_poses`)
DESIGN_CHECK_EVERY = 4
#: a pose measured again later (:func:`remeasure_poses`) is commanded this much further on its last
#: joint per repeat (rad; 1 µrad moves the tool by a fraction of a µm, which the model accounts for,
#: as it takes the commanded joints): the noise floor pools repeats of identical joint vectors, and
#: two measurements hours apart would give it the drift between them, not the noise
REMEASURE_OFFSET_RAD = 1e-6
#: free suitable poses :func:`separating_poses` weighs at most (an even stride over them): a few
#: forward kinematics each
SEPARATE_CANDIDATES = 20000
#: central-difference step of an effect's parameters and of the joints, in their units
SIGNAL_STEP = 1e-6


@dataclass(frozen=True)
class PlanSpace:
    """What choosing more poses for a run needs: its robot (with the reflectors it measures), its
    cell, the grid the plan was made on and the suitable poses of that grid. Build it with
    :func:`plan_space`."""

    robot: object
    scene: object
    grid: object
    suitable: np.ndarray
    clearance_m: float
    motion_clearance_m: float
    motion_sample_deg: float
    seconds_per_pose: float
    #: choose among the poses one tour can visit (the plan's own ``reachable`` set), as the plan did
    reachable_only: bool = False

    @cached_property
    def reachable(self) -> np.ndarray:
        """(m,) bool over ``suitable``: the poses new ones are chosen among. With ``reachable_only``,
        those of the largest set that collision-free motions join (campaign.plan.region, as the
        plan chose among: the poses of its random pool inside it; a few seconds), else all. On a UR
        arm (joints ±2π) half the suitable poses lie behind a barrier of joints 2 and 3: chosen
        among every suitable pose, 27 to 30 of 30 poses a round were dropped as unreachable."""
        if not self.reachable_only:
            return np.ones(len(self.suitable), dtype=bool)
        from campaign.plan.region import reachable_region

        region = reachable_region(self.robot, self.checker, self.grid, self.suitable,
                                  np.deg2rad(self.motion_sample_deg), self.motion_clearance_m,
                                  pose_clearance=self.clearance_m)
        inside = np.zeros(len(self.suitable), dtype=bool)
        inside[region.pool[region.in_pool]] = True
        return inside

    @cached_property
    def checker(self):
        from campaign.plan.checks import ClearanceChecker

        return ClearanceChecker(self.robot, self.scene, self.clearance_m)

    @cached_property
    def times(self):
        from campaign.plan.timing import GridTimes

        return GridTimes(self.robot, self.grid)


def plan_space(run) -> PlanSpace:
    """The :class:`PlanSpace` of a planned run (:class:`campaign.run.RunFolder`): the grid's cells
    from RUN/plan/summary.json (the grid the plan's pose ids index), the suitable poses by the
    plan's own filters (a second or two for the default cell)."""
    from campaign.plan.grid import Grid
    from campaign.plan.pipeline import suitable_poses

    summary_path = run.plan_dir / "summary.json"
    try:
        summary = json.loads(summary_path.read_text())
        cells = tuple(int(c) for c in summary["grid_cells"])
    except (OSError, ValueError, KeyError, TypeError):
        raise DataError(f"{summary_path}: missing or unreadable (plan the run with `campaign plan` first)") from None
    cfg = run.config
    robot = run.robot().with_default_reflectors()
    scene = run.scene()
    grid = Grid.for_robot(robot, cells)
    pc = cfg.plan
    suitable = suitable_poses(robot, scene, grid, pc.clearance_m)
    est = summary.get("estimated_campaign", {})
    per_pose = est.get("seconds_per_pose") or \
        (pc.settle_time_s + len(robot.reflectors) * pc.tracker_time_per_reflector_s)
    reachable = (summary.get("reachable") or {}).get("chosen_among") == "reachable"
    return PlanSpace(robot, scene, grid, suitable, pc.clearance_m, pc.motion_clearance_m, pc.motion_sample_deg,
                     float(per_pose), reachable)


def _free(space: PlanSpace, planned_ids) -> np.ndarray:
    """(m,) bool over ``space.suitable``: poses to choose among, those of its reachable set
    (:attr:`PlanSpace.reachable`) that ``planned_ids`` do not hold (in any repeat; pass the poses
    the plan dropped too, :func:`dropped_ids`, so that none is chosen again)."""
    return ~np.isin(space.suitable, base_pose_id(np.asarray(planned_ids, dtype=np.int64))) & space.reachable


DROPPED_HEADER = "pose_id,reason"


def dropped_ids(run) -> np.ndarray:
    """The pose ids RUN/plan/dropped.csv lists (the plan's own and those :func:`append_tour`
    dropped since): poses no collision-free motion reached, not to be chosen again."""
    path = run.plan_dir / "dropped.csv"
    if not path.is_file():
        return np.zeros(0, dtype=np.int64)
    out = []
    for ln in path.read_text().splitlines()[1:]:
        head = ln.split(",", 1)[0].strip()
        if head:
            try:
                out.append(int(float(head)))
            except ValueError:
                raise DataError(f"{path}: pose id {head!r} is not a number") from None
    return np.array(out, dtype=np.int64)


def design_poses(space: PlanSpace, measured_ids, planned_ids, effects, *, n_max: int, target_mm: float | None = None,
                 noise_m: float | None = None, n_min: int = 1):
    """Up to ``n_max`` new poses (grid indices, in the order chosen) by greedy D-optimal design
    for the geometry plus ``effects``, starting from the information of ``measured_ids`` (the
    training poses measured so far; repeats count again). With ``target_mm``: stop once the
    predicted mean position error of the model against the truth over the suitable poses is at
    most that (after at least ``n_min`` poses). Returns (grid indices, predicted model error mm
    before, after)."""
    from campaign.plan.selection import TRACKER_NOISE_M, Design, predicted_model_position_mm

    where = {int(g): i for i, g in enumerate(space.suitable)}
    train = np.array([where[int(b)] for b in base_pose_id(measured_ids) if int(b) in where], dtype=np.int64)
    info = _information(space, tuple(effects), TRACKER_NOISE_M if noise_m is None else noise_m)
    before = predicted_model_position_mm(info, train)
    d = Design(info, "D")
    for j in train:
        d.add(int(j))
    d.refresh()
    free = _free(space, planned_ids)
    chosen = []
    after = before
    while len(chosen) < n_max and free.any():
        g = d.gains()
        g[~free] = -np.inf
        j = int(np.argmax(g))
        d.add(j)
        free[j] = False
        chosen.append(j)
        if target_mm is not None and len(chosen) >= n_min and len(chosen) % DESIGN_CHECK_EVERY == 0:
            after = predicted_model_position_mm(info, np.concatenate([train, chosen]))
            if after <= target_mm:
                break
    if chosen:
        after = predicted_model_position_mm(info, np.concatenate([train, chosen]))
    return space.suitable[np.array(chosen, dtype=np.int64)], before, after


def reflector_noise_for_floor(robot, floor_mm) -> float | None:
    """The tracker noise σ (m per coordinate of each reflector centre) whose noise floor, carried
    through the rigid fit of ``robot``'s reflectors as campaign.measure.floor carries a stated
    noise, is ``floor_mm`` (a floor's E‖e‖ grows linearly with σ): what :func:`design_poses` takes
    as ``noise_m`` to predict on the run's own noise. None without a floor or for a floor of 0."""
    from campaign.measure.floor import floor_from_stated, mean_norm_mm
    from campaign.plan.selection import TRACKER_NOISE_M

    if floor_mm is None or not floor_mm > 0:
        return None
    P_E = getattr(robot, "reflector_positions_in_E", None)
    unit = floor_from_stated(TRACKER_NOISE_M, P_E).mean_position_mm if P_E is not None and len(P_E) >= 3 \
        else mean_norm_mm(np.full(3, TRACKER_NOISE_M))
    return TRACKER_NOISE_M * float(floor_mm) / unit


def _information(space: PlanSpace, effects, noise_m):
    """The plan's information model of the suitable poses for the geometry and ``effects``,
    leaving out the effects no pose informs (of time or a measured context, which a plan cannot
    set: the design weighs the rest)."""
    from campaign.plan.selection import information_model

    Q = space.grid.q(space.suitable)
    try:
        return information_model(space.robot, Q, effects=effects, noise_m=noise_m)
    except ConfigError:
        if not effects:
            raise
    kept = []
    for e in effects:
        try:
            information_model(space.robot, Q[:64], effects=(e,), noise_m=noise_m)
            kept.append(e)
        except ConfigError:
            continue
    return information_model(space.robot, Q, effects=tuple(kept), noise_m=noise_m)


def load_features(robot, q) -> np.ndarray:
    """The gravity load of joint vectors q (n, N): the joints' gravity torques and the size of the
    overturning moment (n, N + 1), N·m."""
    from campaign.effects.gravity import gravity_torques, overturning_moment

    return np.concatenate([gravity_torques(robot, q), np.linalg.norm(overturning_moment(robot, q), axis=1)[:, None]],
                          axis=1)


def spread_poses(space: PlanSpace, measured_ids, planned_ids, inputs, n: int) -> np.ndarray:
    """``n`` new poses (grid indices) that fill the largest gaps the measured poses leave over
    ``inputs`` (names ``q1..qN``, and ``gravity load``): farthest-point sampling, each input
    scaled by its range over the suitable poses, distances to the measured poses and the poses
    chosen before."""
    robot, grid = space.robot, space.grid
    free = _free(space, planned_ids)
    if not free.any() or n <= 0:
        return np.zeros(0, dtype=np.int64)
    Q = grid.q(space.suitable)
    cols = []
    for name in inputs:
        if name.startswith("q") and name[1:].isdigit() and 1 <= int(name[1:]) <= robot.n_joints:
            cols.append(Q[:, int(name[1:]) - 1][:, None])
        elif name == "gravity load":
            cols.append(load_features(robot, Q))
    if not cols:  # no input the poses choose (time, a context column): spread over every joint
        cols = [Q]
    F = np.concatenate(cols, axis=1)
    span = np.ptp(F, axis=0)
    F = (F - F.min(axis=0)) / np.where(span > 0, span, 1.0)
    where = {int(g): i for i, g in enumerate(space.suitable)}
    known = [where[int(b)] for b in base_pose_id(measured_ids) if int(b) in where]
    gap = np.full(len(F), np.inf)
    for s in range(0, len(known), 256):
        block = F[known[s:s + 256]]
        gap = np.minimum(gap, np.min(np.linalg.norm(F[:, None, :] - block[None], axis=2), axis=1))
    chosen = []
    for _ in range(min(n, int(free.sum()))):
        score = np.where(free, gap, -np.inf)
        j = int(np.argmax(score))
        chosen.append(j)
        free[j] = False
        gap = np.minimum(gap, np.linalg.norm(F - F[j], axis=1))
    return space.suitable[np.array(chosen, dtype=np.int64)]


def separating_poses(space: PlanSpace, measured_ids, planned_ids, first: str, second: str, n: int) -> np.ndarray:
    """``n`` new poses (grid indices) that separate effects ``first`` and ``second`` (specs), which
    the measured poses cannot tell apart: the T-optimal design of model discrimination (Atkinson &
    Fedorov 1975), both ways. At each pose, one effect's position signal (at its typical parameters)
    less the least-squares fit of the other, with a constant offset of every joint and of the tool
    (what the geometry takes), fitted on the measured poses and those chosen before; the pose with
    the largest misfit (the two ways' sum, each over its largest) is chosen next."""
    from campaign.effects.base import make_effect

    where = {int(g): i for i, g in enumerate(space.suitable)}
    known = np.array([where[int(b)] for b in base_pose_id(measured_ids) if int(b) in where], dtype=np.int64)
    free = np.flatnonzero(_free(space, planned_ids))
    cand = free[:: max(1, len(free) // SEPARATE_CANDIDATES)]
    if n <= 0 or not len(cand):
        return np.zeros(0, dtype=np.int64)
    rows = np.concatenate([known, cand])
    robot = space.robot
    q = space.grid.q(space.suitable[rows])
    effects = [make_effect(s, robot) for s in (first, second)]
    offsets = _signal_columns(robot, q, None)  # (r, 3, N + 3): each joint's offset, the tool's translation
    cols = [_signal_columns(robot, q, e) for e in effects]
    signal = [c @ _typical(e) for c, e in zip(cols, effects)]
    fit = list(range(len(known)))
    chosen = []
    for _ in range(min(n, len(cand))):
        score = np.zeros(len(rows))
        for a, b in ((0, 1), (1, 0)):  # each effect's signal against the other's best fit
            A = np.concatenate([cols[a], offsets], axis=2)
            c = np.linalg.lstsq(A[fit].reshape(-1, A.shape[2]), signal[b][fit].reshape(-1), rcond=None)[0] \
                if fit else np.zeros(A.shape[2])
            miss = np.linalg.norm(signal[b] - A @ c, axis=1)
            score += miss / max(miss[len(known):].max(), 1e-300)
        score[: len(known)] = -np.inf
        score[chosen] = -np.inf
        i = int(np.argmax(score))
        chosen.append(i)
        fit.append(i)
    return space.suitable[rows[np.array(chosen, dtype=np.int64)]]


def _typical(effect) -> np.ndarray:
    """An effect's typical parameters (its ``typical_params`` when it has one, else ones)."""
    typical = getattr(effect, "typical_params", None)
    return np.asarray(typical(0) if typical is not None else np.ones(effect.n_params), dtype=float)


def _signal_columns(robot, q, effect) -> np.ndarray:
    """(n, 3, k): the tool origin's motion per unit of each of ``effect``'s k parameters at poses q
    (central differences, SIGNAL_STEP), or with ``effect`` None per unit offset of each joint and
    per unit translation of the tool (N + 3 columns)."""
    from campaign.effects.base import EffectSet, model_pose
    from campaign.model.kinematics import forward

    if effect is None:
        cols = [(forward(robot, q + d)[:, :3, 3] - forward(robot, q - d)[:, :3, 3]) / (2 * SIGNAL_STEP)
                for d in SIGNAL_STEP * np.eye(q.shape[1])]
        cols += [np.broadcast_to(e, (len(q), 3)) for e in np.eye(3)]
        return np.stack(cols, axis=2)
    es = EffectSet((effect,))
    h = SIGNAL_STEP * np.eye(effect.n_params)
    return np.stack([(model_pose(robot, q, None, es, d, {})[:, :3, 3] - model_pose(robot, q, None, es, -d, {})[:, :3, 3])
                     / (2 * SIGNAL_STEP) for d in h], axis=2)


def remeasure_poses(space: PlanSpace, measured_ids, times_s, n: int) -> np.ndarray:
    """``n`` repeat ids (``p + r·10⁹``, r the next free repeat of p) of measured poses: among the
    oldest half of the measured poses, those spread farthest apart over the joints. Append them
    with ``append_tour(..., offset_repeats=True)`` (REMEASURE_OFFSET_RAD)."""
    measured_ids = np.asarray(measured_ids, dtype=np.int64)
    times_s = np.asarray(times_s, dtype=float)
    base = base_pose_id(measured_ids)
    first = {}
    for pid, b, t in sorted(zip(measured_ids, base, times_s), key=lambda r: (r[2], r[0])):
        first.setdefault(int(b), float(t))
    oldest = sorted(first, key=lambda b: (first[b], b))[: max(n, len(first) // 2)]
    Q = space.grid.q(np.array(oldest, dtype=np.int64))
    span = np.ptp(space.grid.q(space.suitable), axis=0)
    F = Q / np.where(span > 0, span, 1.0)
    chosen, gap = [0], np.linalg.norm(F - F[0], axis=1)
    while len(chosen) < min(n, len(oldest)):
        j = int(np.argmax(np.where(np.isin(np.arange(len(F)), chosen), -np.inf, gap)))
        chosen.append(j)
        gap = np.minimum(gap, np.linalg.norm(F - F[j], axis=1))
    repeats = {}
    for pid in measured_ids:
        b = int(pid % REPEAT_ID_STRIDE)
        repeats[b] = max(repeats.get(b, 0), int(pid // REPEAT_ID_STRIDE))
    return np.array([oldest[j] + (repeats.get(oldest[j], 0) + 1) * REPEAT_ID_STRIDE for j in chosen], dtype=np.int64)


@dataclass(frozen=True)
class Extension:
    """Poses appended to a plan: ``added`` pose ids in visiting order, ``dropped`` [(pose_id,
    reason)] (no collision-free motion), ``via_poses`` inserted, ``motion_s`` of the new tour."""

    added: tuple
    dropped: tuple
    via_poses: int
    motion_s: float


def append_tour(run, space: PlanSpace, pose_ids, *, offset_repeats: bool = False) -> Extension:
    """Append ``pose_ids`` (grid indices, or repeat ids) to the run's plan: ordered into a short
    tour from the plan's last pose (front-of-wall and behind-wall groups, as `campaign plan`),
    every motion checked at the plan's motion clearance and repaired through via postures or
    the pose dropped (campaign.plan.repair), then written to RUN/plan/vias.csv and poses.csv
    (atomically, vias first), the poses dropped with their reasons to RUN/plan/dropped.csv. Ids
    the plan holds or dropped already are skipped, so a call repeated after an interruption
    appends nothing twice and tries no dropped pose again. ``offset_repeats``: repeat ids r are commanded
    r·REMEASURE_OFFSET_RAD further on the last joint (:func:`remeasure_poses`)."""
    from campaign.measure.driver import read_plan
    from campaign.plan.pipeline import _order_tour
    from campaign.plan.repair import check_segments, repair_tour, tour_path
    from campaign.plan.timing import path_time

    ids, Q, _ = read_plan(run.path)
    tried = set(ids.tolist()) | set(dropped_ids(run).tolist())
    pose_ids = np.array([int(p) for p in pose_ids if int(p) not in tried], dtype=np.int64)
    if len(pose_ids) == 0:
        return Extension((), (), 0, 0.0)
    grid, robot = space.grid, space.robot
    by_base = {}
    for p in pose_ids:
        by_base.setdefault(int(p % REPEAT_ID_STRIDE), []).append(int(p))
    home = grid.cell_indices(np.array([int(ids[-1] % REPEAT_ID_STRIDE)]))[0]
    members = np.array(sorted(by_base), dtype=np.int64)
    ordered_base = _order_tour(robot, space.scene, grid, space.times, home, members)
    order = np.array([p for b in ordered_base for p in by_base[int(b)]], dtype=np.int64)
    seq = np.concatenate([[ids[-1]], order])
    Qs = np.concatenate([Q[-1:], grid.q(base_pose_id(order))])
    max_step = np.deg2rad(space.motion_sample_deg)
    mc = space.motion_clearance_m
    ok = check_segments(robot, space.checker, Qs[:-1], Qs[1:], max_step, mc)
    repair = repair_tour(robot, space.checker, seq, Qs, ok, max_step, mc)
    kept = repair.keep.copy()
    kept[0] = False  # the plan's last pose: toured already
    new_ids, new_Q = seq[kept], Qs[kept].copy()
    if offset_repeats:
        new_Q[:, -1] += (new_ids // REPEAT_ID_STRIDE) * REMEASURE_OFFSET_RAD
    vias = {p: v for p, v in repair.vias.items() if p in set(new_ids.tolist())}
    _append_dropped(run.plan_dir, repair.dropped)
    _append_rows(run.plan_dir, new_ids, new_Q, vias)
    _drift_monitor_again(run, space)
    path = tour_path(seq[repair.keep], Qs[repair.keep], repair.vias)
    return Extension(tuple(int(p) for p in new_ids), tuple(repair.dropped), int(sum(len(v) for v in vias.values())),
                     float(path_time(robot, path)) if len(path) > 1 else 0.0)


def _drift_monitor_again(run, space: PlanSpace) -> None:
    """RUN/plan/summary.json's ``drift_monitor`` over the plan with its appended poses. The driver
    re-measures the reference pose every ``drift_check_interval(every, len(plan))`` stored poses,
    moving there directly, and skips only the checks the plan found not clear: the plan's length
    changed the interval, and the motions from an appended pose to the reference pose and on are
    new, so they are checked here as `campaign plan` checks its own (on the MuJoCo twin an unchecked
    return from an appended Panda pose put the hand 0.5 mm into the cabinet)."""
    from campaign.measure.driver import read_plan
    from campaign.plan.pipeline import _drift_monitor

    path = run.plan_dir / "summary.json"
    try:
        summary = json.loads(path.read_text())
    except (OSError, ValueError):
        return  # plan_space read it a moment ago; a plan without one has no monitor to keep
    ids, Q, _ = read_plan(run.path)
    summary["drift_monitor"] = _drift_monitor(space.robot, space.checker, ids, Q, run.config.run.drift_check_every,
                                              np.deg2rad(space.motion_sample_deg), space.motion_clearance_m,
                                              pose_clearance=space.clearance_m)
    atomic_write_json(path, summary)


def _append_dropped(plan_dir, dropped) -> None:
    """Add (pose_id, reason) rows to dropped.csv (the plan's format), each pose once."""
    if not dropped:
        return
    path = plan_dir / "dropped.csv"
    lines = path.read_text().splitlines() if path.is_file() else [DROPPED_HEADER]
    have = {ln.split(",", 1)[0].strip() for ln in lines[1:]}
    lines += [f"{int(p)},{r}" for p, r in dropped if str(int(p)) not in have]
    atomic_write(path, "\n".join(lines) + "\n")


def _append_rows(plan_dir, ids, Q, vias) -> None:
    """Add rows to vias.csv (those of ``ids`` replaced) and then to poses.csv."""
    def row(pid, q):
        return f"{int(pid)}," + ",".join(repr(float(v)) for v in q)

    new = set(int(p) for p in ids)
    vpath = plan_dir / "vias.csv"
    N = Q.shape[1]
    header = "before_pose_id," + ",".join(f"q{j + 1}" for j in range(N))
    lines = vpath.read_text().splitlines() if vpath.is_file() else [header]
    lines = [lines[0]] + [ln for ln in lines[1:] if ln.strip() and int(float(ln.split(",")[0])) not in new]
    lines += [row(p, v) for p in ids for v in vias.get(int(p), [])]
    atomic_write(vpath, "\n".join(lines) + "\n")
    ppath = plan_dir / "poses.csv"
    text = ppath.read_text()
    if not text.endswith("\n"):
        text += "\n"
    atomic_write(ppath, text + "".join(row(p, q) + "\n" for p, q in zip(ids, Q)))
