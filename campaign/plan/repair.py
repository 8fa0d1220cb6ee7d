"""Stage 3's repair: a straight joint motion between two poses of the tour that does not keep
the motion clearance is replaced by a path through two via postures that lift the arm; when
that path collides too, the pose is dropped, and the motion to the next pose, which then starts
elsewhere, is checked (and repaired) again (:func:`repair_tour`).

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

from campaign.model.kinematics import frames
from campaign.plan.geometry import nominal_frames_entry_first
from campaign.plan.tour import interior_samples

#: the lifted arm's joints take multiples of this (rad)
LIFT_STEP = np.pi / 4
#: most postures searched for the lifted arm (more arm joints: a coarser search is not needed)
LIFT_MAX_CANDIDATES = 200_000
#: motion samples checked together (bounds memory at about 2 kB a sample)
MOTION_CHUNK = 32_768
#: every this-many-th sample of a motion is checked first (a collision usually shows there)
COARSE_STRIDE = 8


def check_segments(robot, checker, Q_from, Q_to, max_step, clearance, chunk=MOTION_CHUNK, *, stop_at_first=False):
    """(m,) bool: each straight joint-space motion Q_from[i]→Q_to[i] (m, N) clear by
    ``clearance`` (m) at every sample ≤ ``max_step`` (rad) of joint motion apart.

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
    q, seg = interior_samples(Q_from, Q_to, max_step)
    within = np.arange(len(seg)) - np.searchsorted(seg, seg)  # sample number in its segment (seg ascends)
    coarse = within % COARSE_STRIDE == 0
    for first in (True, False):
        todo = np.flatnonzero(coarse if first else ~coarse & ok[seg])
        for s in range(0, len(todo), chunk):
            idx = todo[s : s + chunk]
            R, t = nominal_frames_entry_first(robot, q[idx])
            good = checker.clear_entry_first(R, t, clearance)
            ok[seg[idx][~good]] = False
            if stop_at_first and not good.all():
                return ok
    return ok


@dataclass(frozen=True)
class Repair:
    """keep: (n,) bool, which tour poses stay; vias: {pose_id: [q (N,) rad, ...]} postures passed
    before reaching that pose; dropped: [(pose_id, reason), ...] in the order they were dropped."""

    keep: np.ndarray
    vias: dict
    dropped: list


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


def _via_path(robot, a, b):
    """[a, lifted a, lifted b, b]: joint 1 and the wrist kept, the arm raised (:func:`lift_posture`).
    A joint whose limits span more than a turn takes the lifted angle a whole number of turns
    away where that lies nearest to its values at a and b (no needless full turn)."""
    arm, lift = arm_joints(robot.n_joints), lift_posture(robot).copy()
    for i, j in enumerate(arm):
        if robot.joint_types[j] != "prismatic":
            turns = np.arange(np.ceil((robot.q_lower[j] - lift[i]) / (2 * np.pi) - 1e-12),
                              np.floor((robot.q_upper[j] - lift[i]) / (2 * np.pi) + 1e-12) + 1)
            if len(turns) > 1:
                c = lift[i] + 2 * np.pi * turns
                lift[i] = c[np.argmin(np.abs(a[j] - c) + np.abs(b[j] - c))]
    v1, v2 = np.array(a, dtype=float), np.array(b, dtype=float)
    v1[arm] = lift
    v2[arm] = lift
    return np.array([a, v1, v2, b])


def repair_tour(robot, checker, order, Q, ok, max_step, clearance) -> Repair:
    """Repair the tour ``order`` (n,) pose ids with joint vectors Q (n, N) rad, whose motions
    ``ok`` (n - 1,) bool say which straight motions keep ``clearance`` (m) at samples
    ``max_step`` (rad) apart (:func:`check_segments`).

    One pass along the tour: each pose is reached from the last pose kept before it, by the
    straight motion when it keeps the clearance (known from ``ok`` when that previous pose is
    the tour's own, checked afresh after a drop), else through the lifted arm (:func:`_via_path`:
    the via postures and every motion of the path checked), else the pose is dropped. Every
    motion of the repaired tour is thereby checked."""
    vias, dropped = {}, []
    keep = np.ones(len(order), dtype=bool)
    prev = 0
    for k in range(1, len(order)):
        if prev == k - 1 and ok[k - 1]:
            prev = k
            continue
        if prev != k - 1 and check_segments(robot, checker, Q[prev][None], Q[k][None], max_step, clearance)[0]:
            prev = k
            continue
        path = _via_path(robot, Q[prev], Q[k])
        if checker.clear(*frames(robot, path[1:3]), clearance).all() and \
                check_segments(robot, checker, path[:-1], path[1:], max_step, clearance, stop_at_first=True).all():
            vias[int(order[k])] = [path[1], path[2]]
            prev = k
        else:
            keep[k] = False
            dropped.append((int(order[k]), "no collision-free motion from the previous pose, even via a lifted arm"
                            if prev == k - 1 else "no collision-free motion after re-ordering, even via a lifted arm"))
    return Repair(keep, vias, dropped)


def tour_path(order, Q, vias) -> np.ndarray:
    """(m, N) rad: the tour's joint vectors with each pose's via postures before it."""
    path = [Q[0]] if len(Q) else []
    for i in range(1, len(order)):
        path.extend(vias.get(int(order[i]), []))
        path.append(Q[i])
    return np.array(path).reshape(-1, Q.shape[1] if Q.ndim == 2 else 6)
