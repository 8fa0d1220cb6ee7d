"""Stage 3's last resort for a colliding motion: a collision-free joint-space path between two
poses, searched by bidirectional RRT-Connect (Kuffner and LaValle, ICRA 2000) and shortened.

Two trees grow from the two poses within the joint limits; each step adds a posture at most
:data:`STEP` from the tree's nearest posture toward a random one, and the other tree then
reaches for it step by step until it is reached or a step collides. A posture is accepted when
it keeps the motion clearance, a step when every sample of its straight motion does (at the
plan's sample spacing: :func:`campaign.plan.repair.check_segments`). The search is seeded and
bounded: at most ``budget`` checked steps per motion. The path found (tree postures from one
pose to the other) is then shortened greedily: from each kept posture, the farthest later one
that the straight motion reaches clear. Distances are in joint coordinates (rad, or m for a
prismatic joint), the largest joint motion, as the motion check's sample spacing.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

#: largest joint motion of one tree step (rad): a check costs about as much for 115 samples (at
#: the default 1° spacing) as for 30, and long steps reach across a UR10's ±360° joints in fewer
STEP = 2.0
#: checked steps per motion before the search gives up (the pose is then dropped): about 1 s.
#: The COMAU under a ceiling that the upright arm hits (tests/test_plan_search.py) needed up to
#: about 200; 100 left a third of its poses unreached
BUDGET = 400
#: the random postures are drawn within this much (rad) beyond the two poses' values of a
#: revolute joint, within its limits: every posture of a joint lies within half a turn either
#: side of any value, so only needless extra turns are left out
MARGIN_RAD = np.pi


@dataclass(frozen=True)
class Search:
    """path: (m, N) postures from the start to the goal (both included), or None when the budget
    ran out; checks: the steps checked."""

    path: np.ndarray | None
    checks: int


def sampling_box(robot, a, b):
    """(lower (N,), upper (N,)) of the random postures for a path a → b: a revolute joint within
    :data:`MARGIN_RAD` of the range its two values span, a prismatic joint anywhere; both
    within the joint limits."""
    lo, hi = np.asarray(robot.q_lower, dtype=float), np.asarray(robot.q_upper, dtype=float)
    revolute = np.array([t != "prismatic" for t in robot.joint_types], dtype=bool)
    lo_s = np.where(revolute, np.maximum(lo, np.minimum(a, b) - MARGIN_RAD), lo)
    hi_s = np.where(revolute, np.minimum(hi, np.maximum(a, b) + MARGIN_RAD), hi)
    return lo_s, hi_s


class _Tree:
    """Postures (n, N) grown from a root, each with its parent's index (-1 for the root)."""

    def __init__(self, root, capacity):
        self.q = np.empty((capacity, len(root)))
        self.parent = np.empty(capacity, dtype=np.int64)
        self.q[0], self.parent[0], self.n = root, -1, 1

    def nearest(self, q) -> int:
        d = self.q[: self.n] - q
        return int(np.argmin(np.einsum("ij,ij->i", d, d)))

    def add(self, q, parent) -> int:
        self.q[self.n], self.parent[self.n] = q, parent
        self.n += 1
        return self.n - 1

    def branch(self, i):
        """Postures from node i back to the root."""
        out = []
        while i >= 0:
            out.append(self.q[i])
            i = self.parent[i]
        return out


def rrt_connect(a, b, step_clear, rng, lower, upper, *, step=STEP, budget=BUDGET) -> Search:
    """A path a → b (N,) whose every straight step ``step_clear(q_from (N,), q_to (N,)) -> bool``
    accepts (the posture q_to included), random postures from ``rng`` uniform in [lower, upper];
    at most ``budget`` calls of ``step_clear``."""
    a, b = np.asarray(a, dtype=float), np.asarray(b, dtype=float)
    start = _Tree(a, budget + 2)
    trees = [start, _Tree(b, budget + 2)]
    checks = 0

    def toward(q_from, q_to):
        d = q_to - q_from
        span = np.max(np.abs(d))
        return (q_to, True) if span <= step else (q_from + (step / span) * d, False)

    while checks < budget:
        grow, other = trees
        target = rng.uniform(lower, upper)
        i = grow.nearest(target)
        q_new, _ = toward(grow.q[i], target)
        checks += 1
        if step_clear(grow.q[i], q_new):
            new = grow.add(q_new, i)
            j = other.nearest(q_new)  # the other tree reaches for it
            while checks < budget:
                q_next, arrived = toward(other.q[j], q_new)
                checks += 1
                if not step_clear(other.q[j], q_next):
                    break
                if arrived:
                    half_a, half_b = grow.branch(new), other.branch(j)
                    path = half_a[::-1] + half_b if grow is start else half_b[::-1] + half_a
                    return Search(np.array(path), checks)
                j = other.add(q_next, j)
        trees.reverse()
    return Search(None, checks)


def shortcut(path, segments_clear):
    """Fewer postures on ``path`` (m, N) whose consecutive straight motions are clear: from each
    kept posture, on to the farthest later one that ``segments_clear(Q_from (k, N), Q_to (k, N))
    -> (k,) bool`` accepts (all candidates checked in one call; the next posture always is).
    Returns (postures (m', N), calls)."""
    keep, i, calls = [0], 0, 0
    while i < len(path) - 1:
        later = np.arange(len(path) - 1, i + 1, -1)  # farthest first, the next one left out
        nxt = i + 1
        if len(later):
            ok = segments_clear(np.repeat(path[i][None], len(later), axis=0), path[later])
            calls += 1
            if ok.any():
                nxt = int(later[np.argmax(ok)])
        keep.append(nxt)
        i = nxt
    return path[keep], calls
