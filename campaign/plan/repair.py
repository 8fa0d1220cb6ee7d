"""Stage 3's repair: a straight joint motion between two poses of the tour that does not keep
the motion clearance is replaced by a path through via postures: two that lift the arm, else
one of a few structured paths (the wrist to a neutral posture first, the elbow before the
shoulder), else a path found by a seeded RRT-Connect search with a bounded budget and shortened
(campaign.plan.pathsearch; :class:`PathFinder`). When no path is found, the pose is dropped, and
the motion to the next pose, which then starts elsewhere, is checked (and repaired) again
(:func:`repair_tour`). Poses that no search reaches from the tour may be joined among
themselves (a UR10 on a pedestal: the ranges of joint 2 on either side of the posture that
points the upper arm into the pedestal): :func:`repair_largest` tours each such set in turn
and keeps the largest.

The lifted arm (:func:`lift_posture`) keeps joint 1 and the wrist (the last three joints) of
the pose it leaves or reaches and sets the arm's joints in between (joints 2..N-3; joint 2
alone for a chain of four joints or fewer) to the posture that holds the flange highest
against gravity, found among multiples of 45° within the joint limits (ties: the smallest
joint values) with joint 1 and the wrist at 0 (or their nearest limit). The COMAU: joints 2
and 3 at (0, -90°), the arm upright; a UR10: (-90°, 0); a Panda: joints 2..4 at (-45°, 0, -45°)."""

from __future__ import annotations

import functools
from dataclasses import dataclass

import numpy as np

from campaign.plan.geometry import joint_reach, nominal_frames_entry_first
from campaign.plan.tour import interior_samples, segment_sample_counts

#: the lifted arm's joints take multiples of this (rad)
LIFT_STEP = np.pi / 4
#: most postures searched for the lifted arm (more arm joints: a coarser search is not needed)
LIFT_MAX_CANDIDATES = 200_000
#: motion samples checked together (the sphere bounds of a mesh arm take about 10 kB a sample)
MOTION_CHUNK = 8192
#: motions whose samples are generated together (bounds the samples' memory on a long tour)
MOTION_BLOCK = 4096
#: every this-many-th sample of a motion is checked first (a collision usually shows there)
COARSE_STRIDE = 8


def check_segments(robot, checker, Q_from, Q_to, max_step, clearance, chunk=MOTION_CHUNK, *, stop_at_first=False,
                   ends_clearance=None):
    """(m,) bool: each straight joint-space motion Q_from[i]→Q_to[i] (m, N) clear by
    ``clearance`` (m) at every sample ≤ ``max_step`` (rad) of joint motion apart.

    ``ends_clearance``: None, or a clearance (m) that every end pose is known to keep for every
    checked pair (the suitable poses: the pose clearance). A pair is then not checked at the
    samples where the end poses bound it (:func:`ends_known_clear`): a pair of links that the
    motion does not move against each other, or a sample near enough to an end pose.

    The end poses themselves are not re-checked here (they passed the pose filter at the
    stricter pose clearance); all inner samples of all segments are generated at once and
    checked ``chunk`` at a time (FK, sphere bounds, FCL for what the bounds leave): every
    :data:`COARSE_STRIDE`-th sample of each segment first, then the others of the segments
    still clear (a colliding motion is usually found among the first, and costs no more).
    ``stop_at_first``: return as soon as one segment collides (its path is lost; the others
    are then left True, unchecked)."""
    ok = np.ones(len(Q_from), dtype=bool)
    if len(Q_from) == 0:
        return ok
    if len(Q_from) > MOTION_BLOCK:  # block by block: the same answers, bounded memory
        for s in range(0, len(Q_from), MOTION_BLOCK):
            ok[s : s + MOTION_BLOCK] = check_segments(robot, checker, Q_from[s : s + MOTION_BLOCK],
                                                      Q_to[s : s + MOTION_BLOCK], max_step, clearance, chunk,
                                                      stop_at_first=stop_at_first, ends_clearance=ends_clearance)
            if stop_at_first and not ok[s : s + MOTION_BLOCK].all():
                break
        return ok
    q, seg = interior_samples(Q_from, Q_to, max_step)
    within = np.arange(len(seg)) - np.searchsorted(seg, seg)  # sample number in its segment (seg ascends)
    coarse = within % COARSE_STRIDE == 0
    speeds = None
    if ends_clearance is not None and ends_clearance >= clearance:
        speeds = pair_speeds(robot, np.asarray(Q_to, dtype=float) - np.asarray(Q_from, dtype=float))
        steps = segment_sample_counts(Q_from, Q_to, max_step)
    for first in (True, False):
        todo = np.flatnonzero(coarse if first else ~coarse & ok[seg])
        for s in range(0, len(todo), chunk):
            idx = todo[s : s + chunk]
            R, t = nominal_frames_entry_first(robot, q[idx])
            known = None
            if speeds is not None:
                g = seg[idx]
                known = ends_known_clear(speeds, g, (within[idx] + 1) / steps[g], ends_clearance - clearance)
            good = checker.clear_entry_first(R, t, clearance, known)
            ok[seg[idx][~good]] = False
            if stop_at_first and not good.all():
                return ok
    return ok


def pair_speeds(robot, dQ):
    """How fast the checked pairs can approach along straight joint motions dQ (m, N) (rad, m),
    in m per unit of the motion's parameter s ∈ [0, 1] (:func:`~campaign.plan.geometry.joint_reach`):
    ``(scene (N+2, m), self (N+2, N+2, m))``; a frame f against the fixed scene: the joints
    1..f move it; frames a < b against each other: only the joints a+1..b move b relative to a."""
    reach = joint_reach(robot)  # (N, K)
    N, K = reach.shape
    # cum[j, f]: the speed joints 1..j give to frame f's points, for each motion
    cum = np.zeros((N + 1, K, len(dQ)))
    np.cumsum(reach[:, :, None] * np.abs(np.asarray(dQ, dtype=float)).T[:, None, :], axis=0, out=cum[1:])
    joints_to = np.minimum(np.arange(K), N)  # joints that move frame f: 1..min(f, N)
    scene = cum[joints_to, np.arange(K)]  # (K, m)
    a, b = np.meshgrid(np.arange(K), np.arange(K), indexing="ij")
    lo, hi = np.minimum(a, b), np.maximum(a, b)
    pair = cum[joints_to[hi], hi] - cum[joints_to[lo], hi]  # (K, K, m), symmetric
    return scene, pair


def ends_known_clear(speeds, segment, s, margin):
    """Which frames' pairs the end poses prove clear at motion samples: ``(scene (N+2, M),
    self (N+2, N+2, M))`` bool for samples at parameter s (M,) ∈ (0, 1) of motions ``segment``
    (M,) (indices into :func:`pair_speeds`' motions), when every end pose keeps ``margin`` (m)
    more than the clearance checked: a pair's distance changes by at most its speed times the
    parameter's distance to the nearer end pose."""
    scene, pair = speeds
    u = np.minimum(s, 1.0 - s)
    return scene[:, segment] * u <= margin, pair[:, :, segment] * u <= margin


@dataclass(frozen=True)
class Repair:
    """keep: (n,) bool, which tour poses stay; vias: {pose_id: [q (N,) rad, ...]} postures passed
    before reaching that pose; dropped: [(pose_id, reason), ...] in the order they were dropped;
    searched: motions that needed the path search, search_checks: the steps it checked."""

    keep: np.ndarray
    vias: dict
    dropped: list
    searched: int = 0
    search_checks: int = 0


def arm_joints(n_joints: int) -> np.ndarray:
    """Indices (0-based) of the arm's joints that the lifted posture sets: 1 .. N-4 (joints
    2..N-3), at least joint 2; none for a single joint."""
    return np.arange(1, max(2, n_joints - 3)) if n_joints > 1 else np.zeros(0, dtype=int)


@functools.lru_cache(maxsize=8)
def lift_posture(robot) -> np.ndarray:
    """Values (len(arm_joints),) rad (m for a prismatic joint) of the arm's joints in the via
    posture: the flange (the origin of frame N) highest against the robot's gravity."""
    import itertools

    N = robot.n_joints
    arm = arm_joints(N)
    if len(arm) == 0:
        return np.zeros(0)
    lo, hi = np.asarray(robot.q_lower), np.asarray(robot.q_upper)
    axes = []
    for j in arm:
        if robot.joint_types[j] == "prismatic":
            axes.append(np.linspace(lo[j], hi[j], 5))
        else:
            v = np.arange(np.ceil(lo[j] / LIFT_STEP - 1e-9), np.floor(hi[j] / LIFT_STEP + 1e-9) + 1) * LIFT_STEP
            axes.append(v if len(v) else np.array([0.5 * (lo[j] + hi[j])]))
    while np.prod([len(a) for a in axes], dtype=float) > LIFT_MAX_CANDIDATES:
        axes = [a[::2] for a in axes]
    combos = np.array(list(itertools.product(*axes)), dtype=float)
    q = np.tile(np.clip(0.0, lo, hi), (len(combos), 1))
    q[:, arm] = combos
    _, t = nominal_frames_entry_first(robot, q)
    g = np.asarray(robot.gravity_in_I, dtype=float)
    height = -(np.asarray(g) / np.linalg.norm(g)) @ t[N] if np.linalg.norm(g) > 0 else t[N][2]
    best = np.flatnonzero(height >= height.max() - 1e-9)
    pick = best[np.argmin(np.sum(combos[best] ** 2, axis=1))]
    return combos[pick] + 0.0  # no -0.0


def wrist_joints(n_joints: int) -> np.ndarray:
    """Indices (0-based) of the joints after the arm's (:func:`arm_joints`): the wrist, the last
    three joints of a chain of six or more."""
    arm = arm_joints(n_joints)
    return np.arange(arm[-1] + 1 if len(arm) else 1, n_joints)


def _nearest_turn(robot, joints, values, a, b):
    """``values`` (len(joints),) for the joints ``joints``, each a whole number of turns away where
    it lies nearest to the joint's values at a and b, within its limits (a prismatic joint, or
    one whose limits span less than a turn, as given)."""
    values = np.array(values, dtype=float)
    for i, j in enumerate(joints):
        if robot.joint_types[j] != "prismatic":
            turns = np.arange(np.ceil((robot.q_lower[j] - values[i]) / (2 * np.pi) - 1e-12),
                              np.floor((robot.q_upper[j] - values[i]) / (2 * np.pi) + 1e-12) + 1)
            if len(turns) > 1:
                c = values[i] + 2 * np.pi * turns
                values[i] = c[np.argmin(np.abs(a[j] - c) + np.abs(b[j] - c))]
    return values


def _via_path(robot, a, b):
    """[a, lifted a, lifted b, b]: joint 1 and the wrist kept, the arm raised (:func:`lift_posture`).
    A joint whose limits span more than a turn takes the lifted angle a whole number of turns
    away where that lies nearest to its values at a and b (no needless full turn)."""
    arm = arm_joints(robot.n_joints)
    lift = _nearest_turn(robot, arm, lift_posture(robot), a, b)
    v1, v2 = np.array(a, dtype=float), np.array(b, dtype=float)
    v1[arm] = lift
    v2[arm] = lift
    return np.array([a, v1, v2, b])


#: the wrist's values in :func:`neutral_wrist` are multiples of this (rad)
WRIST_STEP = np.pi / 2
#: clearances (m) the neutral wrist is sought at, the largest first
WRIST_CLEARANCES_M = (0.2, 0.1, 0.05, 0.0)


def neutral_wrist(robot, checker) -> np.ndarray:
    """Values (len(wrist_joints),) rad (m for a prismatic joint) of the wrist's joints, with the arm
    lifted (:func:`lift_posture`) and joint 1 at 0 (or its nearest limit): among multiples of 90°
    within the limits and half a turn of 0 (a prismatic joint: its middle), the one nearest 0 (sum
    of squares; ties: the first in joint order) that keeps the largest of
    :data:`WRIST_CLEARANCES_M` from the cell and the rest of the robot."""
    import itertools

    N = robot.n_joints
    arm, wrist = arm_joints(N), wrist_joints(N)
    if len(wrist) == 0:
        return np.zeros(0)
    lo, hi = np.asarray(robot.q_lower), np.asarray(robot.q_upper)
    axes = []
    for j in wrist:
        v = np.arange(np.ceil(max(lo[j], -np.pi) / WRIST_STEP - 1e-9),
                      np.floor(min(hi[j], np.pi) / WRIST_STEP + 1e-9) + 1) * WRIST_STEP
        axes.append(v if robot.joint_types[j] != "prismatic" and len(v) else np.array([0.5 * (lo[j] + hi[j])]))
    combos = np.array(list(itertools.product(*axes)), dtype=float)
    combos = combos[np.argsort(np.sum(combos ** 2, axis=1), kind="stable")]
    q = np.tile(np.clip(0.0, lo, hi), (len(combos), 1))
    q[:, arm] = lift_posture(robot)
    q[:, wrist] = combos
    R, t = nominal_frames_entry_first(robot, q)
    for c in WRIST_CLEARANCES_M:
        ok = checker.clear_entry_first(R, t, c)
        if ok.any():
            return combos[int(np.argmax(ok))] + 0.0
    return combos[0] + 0.0


def _structured_paths(robot, a, b, wrist_values):
    """Via paths a → b tried after the lifted arm (:func:`_via_path`), each (k, N) from a to b
    (repeated postures left out): the wrist to its neutral values (:func:`neutral_wrist`) first,
    then the arm lifted, joint 1 turned, and back in the reverse order; the elbow (the arm's last
    joint) lifted before the shoulder; both."""
    arm, wrist = arm_joints(robot.n_joints), wrist_joints(robot.n_joints)
    lift = _nearest_turn(robot, arm, lift_posture(robot), a, b)
    W = _nearest_turn(robot, wrist, wrist_values, a, b)

    def at(q, joints, values):
        q = np.array(q, dtype=float)
        q[joints] = values
        return q

    aW, bW = at(a, wrist, W), at(b, wrist, W)
    elbow, e = arm[-1:], lift[-1:]
    paths = [[a, aW, at(aW, arm, lift), at(bW, arm, lift), bW, b],
             [a, at(a, elbow, e), at(a, arm, lift), at(b, arm, lift), at(b, elbow, e), b],
             [a, aW, at(aW, elbow, e), at(aW, arm, lift), at(bW, arm, lift), at(bW, elbow, e), bW, b]]
    out = []
    for p in paths:
        p = np.array(p)
        keep = np.ones(len(p), dtype=bool)
        keep[1:] = np.any(p[1:] != p[:-1], axis=1)
        out.append(p[keep])
    return out


class PathFinder:
    """Collision-free motions a → b for one robot in one cell: the straight motion, the lifted
    arm (:func:`_via_path`), the structured via paths (:func:`_structured_paths`), then a seeded
    RRT-Connect search (campaign.plan.pathsearch) shortened by shortcuts. Every posture passed
    keeps ``clearance`` (m) and every straight motion between them does at samples ``max_step``
    (rad) apart (:func:`check_segments`). Scratch state (the neutral wrist, counters) lives here,
    not on the robot or the checker."""

    def __init__(self, robot, checker, max_step, clearance, *, budget=None):
        from campaign.plan import pathsearch

        self.robot, self.checker, self.max_step, self.clearance = robot, checker, max_step, clearance
        self.budget = pathsearch.BUDGET if budget is None else int(budget)
        self._wrist = None
        self.searched = 0  # motions that needed the search
        self.search_checks = 0  # steps and shortcuts it checked

    def postures_clear(self, Q) -> np.ndarray:
        """(k,) bool: each posture Q (k, N) keeps the clearance."""
        return self.checker.clear_entry_first(*nominal_frames_entry_first(self.robot, Q), self.clearance)

    def path_clear(self, path) -> bool:
        """Whether a path (k, N) is clear: its inner postures and every straight motion along it."""
        return bool(self.postures_clear(path[1:-1]).all()) and bool(
            check_segments(self.robot, self.checker, path[:-1], path[1:], self.max_step, self.clearance,
                           stop_at_first=True).all())

    def vias(self, a, b, seed, *, search=True):
        """The via postures (list of (N,)) of a clear path a → b other than the straight motion
        (not checked here), or None. ``seed``: the search's random seed (a sequence of ints);
        ``search``: False to try the structured paths only."""
        path = _via_path(self.robot, a, b)
        if self.path_clear(path):
            return [path[1], path[2]]
        if self._wrist is None:
            self._wrist = neutral_wrist(self.robot, self.checker)
        for path in _structured_paths(self.robot, a, b, self._wrist):
            if self.path_clear(path):
                return list(path[1:-1])
        return self.search(a, b, seed) if search else None

    def search(self, a, b, seed):
        """RRT-Connect (campaign.plan.pathsearch) from a to b, shortened; its via postures or None."""
        from campaign.plan import pathsearch

        robot, checker = self.robot, self.checker

        def step_clear(q_from, q_to):
            return bool(self.postures_clear(q_to[None])[0]) and bool(
                check_segments(robot, checker, q_from[None], q_to[None], self.max_step, self.clearance)[0])

        def segments_clear(Q_from, Q_to):
            return check_segments(robot, checker, Q_from, Q_to, self.max_step, self.clearance)

        self.searched += 1
        found = pathsearch.rrt_connect(a, b, step_clear, np.random.default_rng(seed),
                                       *pathsearch.sampling_box(robot, a, b), budget=self.budget)
        self.search_checks += found.checks
        if found.path is None:
            return None
        path, calls = pathsearch.shortcut(found.path, segments_clear)
        self.search_checks += calls
        return list(path[1:-1])


#: unreached poses nearest in joint space (largest joint difference) that a pose is tried against
#: before the path search (:func:`_joined`)
JOIN_TRIES = 3


def _joined(finder, Q, unreached, k, ends_clearance=None):
    """The first of the :data:`JOIN_TRIES` poses ``unreached`` (indices into Q) nearest to pose k
    that the straight motion, the lifted arm or a structured path joins to it, or None
    (``ends_clearance``: as :func:`check_segments`', which the poses of Q keep)."""
    if len(unreached) == 0:
        return None
    near = unreached[np.argsort(np.max(np.abs(Q[unreached] - Q[k]), axis=1), kind="stable")[:JOIN_TRIES]]
    straight = check_segments(finder.robot, finder.checker, Q[near], np.repeat(Q[k][None], len(near), axis=0),
                              finder.max_step, finder.clearance, ends_clearance=ends_clearance)
    if straight.any():
        return int(near[np.argmax(straight)])
    for x in near:
        if finder.vias(Q[x], Q[k], None, search=False) is not None:
            return int(x)
    return None


def repair_tour(robot, checker, order, Q, ok, max_step, clearance, *, budget=None, ends_clearance=None) -> Repair:
    """Repair the tour ``order`` (n,) pose ids with joint vectors Q (n, N) rad, whose motions
    ``ok`` (n - 1,) bool say which straight motions keep ``clearance`` (m) at samples
    ``max_step`` (rad) apart (:func:`check_segments`).

    One pass along the tour: each pose is reached from the last pose kept before it, by the
    straight motion when it keeps the clearance (known from ``ok`` when that previous pose is
    the tour's own, checked afresh after a drop; ``ends_clearance``: as :func:`check_segments`',
    a clearance that every pose of Q keeps), else through via postures (:class:`PathFinder`:
    the lifted arm, structured vias, a path search of at most ``budget`` checked steps, default
    campaign.plan.pathsearch.BUDGET, seeded by the two pose ids), else the pose is dropped. A
    pose that a clear path without search joins to a pose dropped before is dropped without a
    search (a path to it would reach that pose too): the straight motion from the pose before
    it in the tour, when that one was dropped (tried first), else one of :func:`_joined`'s
    (tried after the lifted arm and the structured paths). Every motion of the repaired tour is
    thereby checked."""
    finder = PathFinder(robot, checker, max_step, clearance, budget=budget)
    vias, dropped = {}, []
    keep = np.ones(len(order), dtype=bool)
    unreached = np.zeros(len(order), dtype=bool)  # dropped: not reached from the tour (search or join)
    prev = 0
    for k in range(1, len(order)):
        if prev == k - 1 and ok[k - 1]:
            prev = k
            continue
        # a clear path from a pose that no search reached: a path here would reach it too
        found, joined = None, k - 1 if unreached[k - 1] and ok[k - 1] else None
        if joined is None and prev != k - 1 and \
                check_segments(robot, checker, Q[prev][None], Q[k][None], max_step, clearance,
                               ends_clearance=ends_clearance)[0]:
            prev = k
            continue
        seed = (int(order[prev]), int(order[k]))
        if joined is None:
            found = finder.vias(Q[prev], Q[k], seed, search=False)
        if found is None and joined is None:
            joined = _joined(finder, Q, np.flatnonzero(unreached[:k]), k, ends_clearance)
            if joined is None:
                found = finder.search(Q[prev], Q[k], seed)
        if found is not None:
            vias[int(order[k])] = found
            prev = k
            continue
        keep[k], unreached[k] = False, True
        if joined is not None:
            reason = (f"no collision-free motion from the tour: a clear path joins it to pose {int(order[joined])}, "
                      "which it did not reach either")
        else:
            reason = (("no collision-free motion from the previous pose" if prev == k - 1 else
                       "no collision-free motion after re-ordering")
                      + f", even via a lifted arm or after a path search of {finder.budget} checked steps")
        dropped.append((int(order[k]), reason))
    return Repair(keep, vias, dropped, finder.searched, finder.search_checks)


#: passes of :func:`repair_largest`: sets of poses joined among themselves that are each toured
#: in turn (a UR10 on a pedestal: three, one for each range of joint 2 between the postures that
#: point the upper arm into the pedestal)
MAX_PASSES = 3


def repair_largest(robot, checker, order, Q, ok, max_step, clearance, *, budget=None,
                   ends_clearance=None) -> Repair:
    """:func:`repair_tour`, then again over the poses it dropped (in tour order, from the first of
    them), up to :data:`MAX_PASSES` passes while the poses left could outnumber the most kept:
    the pass that keeps the most poses is the tour (ties: the earlier pass). No motion joins a
    pose that another pass kept to this tour's poses (the search from the tour did not reach it),
    so it is dropped with that reason. Arguments as :func:`repair_tour`; the Repair is over
    ``order``."""
    rest, passes = np.arange(len(order)), []
    for _ in range(MAX_PASSES):
        sub_ok = ok if len(passes) == 0 else check_segments(robot, checker, Q[rest[:-1]], Q[rest[1:]], max_step,
                                                            clearance, ends_clearance=ends_clearance)
        passes.append((rest, repair_tour(robot, checker, order[rest], Q[rest], sub_ok, max_step, clearance,
                                         budget=budget, ends_clearance=ends_clearance)))
        most = max(int(r.keep.sum()) for _, r in passes)
        rest = rest[~passes[-1][1].keep]
        if len(rest) <= most:
            break
    best = max(range(len(passes)), key=lambda i: (int(passes[i][1].keep.sum()), -i))
    rows, repair = passes[best]
    keep = np.zeros(len(order), dtype=bool)
    keep[rows[repair.keep]] = True
    reason = {p: r for p, r in repair.dropped}
    for i, (rows_i, r) in enumerate(passes):
        if i != best:
            n_i = int(r.keep.sum())
            for p in order[rows_i[r.keep]]:
                reason[int(p)] = (f"no collision-free motion to the tour: it lies among {n_i} poses joined among "
                                  f"themselves that no path search reached from the tour's {int(keep.sum())}")
    dropped = [(int(p), reason[int(p)]) for p in order[~keep]]
    return Repair(keep, repair.vias, dropped, sum(r.searched for _, r in passes),
                  sum(r.search_checks for _, r in passes))


def tour_path(order, Q, vias) -> np.ndarray:
    """(m, N) rad: the tour's joint vectors with each pose's via postures before it."""
    path = [Q[0]] if len(Q) else []
    for i in range(1, len(order)):
        path.extend(vias.get(int(order[i]), []))
        path.append(Q[i])
    return np.array(path).reshape(-1, Q.shape[1] if Q.ndim == 2 else 6)
