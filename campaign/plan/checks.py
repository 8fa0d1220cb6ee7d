"""Suitability of poses: tracker range, reflector cones, line of sight, clearance.

Vectorised tests that are conservative (they may reject a good pose, never accept a bad
one) decide most candidates; the clearance of every pose that passes them is then decided
with FCL. :class:`ExactChecker` computes the same criteria directly with FCL and no
shortcuts; the tests use it to re-check samples.
"""

from __future__ import annotations

import functools
import itertools

import numpy as np

from campaign.plan.geometry import (RobotSpheres, fcl_geometry, point_primitive_distance, robot_primitives, robot_spheres,
                                    to_world)

#: frames whose primitives may occlude the tracker's beams (the tool plate and flange lie
#: behind the reflectors' cones, so frames 6 and 7 cannot block a beam that passed the cone test)
OCCLUDING_FRAMES = (0, 1, 2, 3, 4, 5)


def reflector_geometry(robot, R_E, t_E):
    """Reflector centres (n, 3, 3) and nest axes (n, 3, 3) in F_I."""
    P = np.einsum("nij,rj->nri", R_E, robot.reflector_positions_in_E) + t_E[:, None, :]
    axes = np.array([r.axis_in_E for r in robot.reflectors])
    A = np.einsum("nij,rj->nri", R_E, axes)
    return P, A


def range_ok(scene, P):
    d = np.linalg.norm(P - scene.tracker_position, axis=-1)
    return np.all((d >= scene.min_range_m) & (d <= scene.max_range_m), axis=1)


def cone_ok(robot, scene, P, A):
    to_tracker = scene.tracker_position - P
    to_tracker /= np.linalg.norm(to_tracker, axis=-1, keepdims=True)
    cosang = np.sum(A * to_tracker, axis=-1)
    limits = np.cos([r.half_angle for r in robot.reflectors])
    return np.all(cosang >= limits, axis=1)


def _segment_hits_box(p0, p1, half):
    """Slab test: does the segment p0→p1 (…, 3) meet the box [-half, half] (3,)? (…,) bool."""
    d = p1 - p0
    with np.errstate(divide="ignore", invalid="ignore"):
        inv = 1.0 / d
        t1 = (-half - p0) * inv
        t2 = (half - p0) * inv
    tmin = np.where(np.isfinite(t1), np.minimum(t1, t2), -np.inf)
    tmax = np.where(np.isfinite(t2), np.maximum(t1, t2), np.inf)
    # a zero direction component: inside the slab for all t or never
    parallel = d == 0
    inside = np.abs(p0) <= half
    tmin = np.where(parallel, np.where(inside, -np.inf, np.inf), tmin)
    tmax = np.where(parallel, np.where(inside, np.inf, -np.inf), tmax)
    enter = np.max(tmin, axis=-1)
    leave = np.min(tmax, axis=-1)
    return (enter <= leave) & (leave >= 0.0) & (enter <= 1.0)


def _box_of(kind, size):
    return np.asarray(size, dtype=float) if kind == "box" else np.array([2 * size[0], 2 * size[0], size[1]])


def scene_line_of_sight_ok(scene, P):
    """No obstacle within the beam radius of any tracker→reflector segment. (n,) bool, conservative."""
    o = scene.tracker_position
    ok = np.ones(len(P), dtype=bool)
    for obs in scene.obstacles:
        half = 0.5 * _box_of(obs.kind, obs.size) + scene.beam_radius_m
        R, c = obs.T_I[:3, :3], obs.T_I[:3, 3]
        p0 = (P - c) @ R
        p1 = np.broadcast_to((o - c) @ R, p0.shape)
        ok &= ~np.any(_segment_hits_box(p0, p1, half), axis=1)
    return ok


def robot_line_of_sight_ok(robot, scene, P, R, t):
    """No robot link (frames 0-5) within the beam radius of a beam. R, t: frames (n, 8, ...). Conservative."""
    o = scene.tracker_position
    ok = np.ones(len(P), dtype=bool)
    for prim in robot_primitives(robot):
        if prim.frame not in OCCLUDING_FRAMES:
            continue
        half = 0.5 * _box_of(prim.kind, prim.size) + scene.beam_radius_m
        Rw = R[:, prim.frame] @ prim.T[:3, :3]  # (n, 3, 3)
        cw = np.einsum("nij,j->ni", R[:, prim.frame], prim.T[:3, 3]) + t[:, prim.frame]
        p0 = np.einsum("nri,nij->nrj", P - cw[:, None, :], Rw)
        p1 = np.einsum("ni,nij->nj", o - cw, Rw)[:, None, :].repeat(3, axis=1)
        ok &= ~np.any(_segment_hits_box(p0, p1, half), axis=1)
    return ok


class ClearanceChecker:
    """Minimum distance robot–scene and between non-adjacent links, with FCL.

    Pairs: every moving link's primitives against every obstacle, and primitives of frames
    i, j with |i − j| ≥ 2 (adjacent links touch by design), less the pairs found closer than
    the clearance in every one of a random sample of configurations (as a set-up assistant
    disables "always in contact" pairs); those are listed in ``disabled_pairs``.
    """

    def __init__(self, robot, scene, clearance_m):
        import fcl

        self.robot, self.scene, self.clearance = robot, scene, float(clearance_m)
        self.prims = robot_primitives(robot)
        self.spheres: RobotSpheres = robot_spheres(robot)
        self.robot_objs = [fcl.CollisionObject(fcl_geometry(p.kind, p.size), fcl.Transform()) for p in self.prims]
        self.scene_objs = []
        for obs in scene.obstacles:
            self.scene_objs.append(fcl.CollisionObject(fcl_geometry(obs.kind, obs.size),
                                                       fcl.Transform(obs.T_I[:3, :3], obs.T_I[:3, 3])))
        self.scene_pairs = [(i, j) for i, p in enumerate(self.prims) if p.frame >= 1 for j in range(len(self.scene_objs))]
        self._sphere_centre = [self.spheres.centre[self.spheres.primitive == i] for i in range(len(self.prims))]
        self._sphere_radius = [self.spheres.radius[self.spheres.primitive == i] for i in range(len(self.prims))]
        # per obstacle: the columns of its pairs in scene_pairs, and their robot primitives
        self._scene_pair_columns = [np.array([m for m, (i, o) in enumerate(self.scene_pairs) if o == j], dtype=int)
                                    for j in range(len(self.scene_objs))]
        self._scene_pair_prims = [np.array([i for i, o in self.scene_pairs if o == j], dtype=int)
                                  for j in range(len(self.scene_objs))]
        cand = [(i, j) for i, j in itertools.combinations(range(len(self.prims)), 2)
                if abs(self.prims[i].frame - self.prims[j].frame) >= 2]
        self.self_pairs, self.disabled_pairs = self._prune_always_near(cand)
        self._self_pair_index = np.array(self.self_pairs, dtype=int).reshape(-1, 2).T

    def _prune_always_near(self, pairs, n=300, seed=0):
        from campaign.model.kinematics import frames

        rng = np.random.default_rng(seed)
        q = rng.uniform(self.robot.q_lower, self.robot.q_upper, size=(n, 6))
        R, t = frames(self.robot, q)
        near = np.zeros(len(pairs), dtype=int)
        for k in range(n):
            self._place(R[k], t[k])
            for m, (i, j) in enumerate(pairs):
                near[m] += self._dist(self.robot_objs[i], self.robot_objs[j]) < self.clearance
        keep = [p for p, c in zip(pairs, near) if c < n]
        dropped = [(self.prims[i].frame, self.prims[j].frame) for (i, j), c in zip(pairs, near) if c == n]
        return keep, dropped

    def _place(self, R, t, which=None):
        """Put the robot's FCL objects (all, or the primitive indices ``which``) at a pose."""
        import fcl

        for i in range(len(self.prims)) if which is None else which:
            p = self.prims[i]
            self.robot_objs[i].setTransform(fcl.Transform(R[p.frame] @ p.T[:3, :3], R[p.frame] @ p.T[:3, 3] + t[p.frame]))

    @staticmethod
    def _dist(a, b):
        import fcl

        res = fcl.DistanceResult()
        return fcl.distance(a, b, fcl.DistanceRequest(), res)

    def pair_distances(self, R, t) -> tuple:
        """Exact FCL distances (m) of every checked pair for one pose (frames R (8,3,3), t (8,3)):
        ``(robot-scene (len(scene_pairs),), robot-robot (len(self_pairs),))``."""
        self._place(R, t)
        d_scene = np.array([self._dist(self.robot_objs[i], self.scene_objs[j]) for i, j in self.scene_pairs])
        d_self = np.array([self._dist(self.robot_objs[i], self.robot_objs[j]) for i, j in self.self_pairs])
        return d_scene, d_self

    def exact_min_distance(self, R, t) -> float:
        """Exact FCL minimum distance over all checked pairs for one pose (frames R (8,3,3), t (8,3))."""
        d_scene, d_self = self.pair_distances(R, t)
        return float(min(d_scene.min(initial=np.inf), d_self.min(initial=np.inf)))

    def undecided_pairs(self, R, t, clearance):
        """Which pairs the sphere bounds cannot clear, for poses with frames given entry-first:
        R (8, 3, 3, n), t (8, 3, n) (see :func:`~campaign.plan.geometry.nominal_frames_entry_first`).

        Returns ``(need_scene (len(scene_pairs), n), need_self (len(self_pairs), n))``, bool:
        True where the lower bound on that pair's distance is below ``clearance`` (m); False
        means the pair is certainly farther apart than ``clearance``. Two levels: one sphere
        per primitive for every pose; then, only where that could not decide, each primitive's
        sphere set against the other side's exact shape. Every sphere contains its piece of
        the primitive, so a sphere's centre distance to the other shape less its radius is a
        lower bound on that piece's distance."""
        c = float(clearance)
        n = R.shape[-1]
        S = self.spheres
        # coarse level: one sphere per primitive, for every pose; centres (3, P, n)
        Cw = np.stack([sum(R[f, :, j] * cc[j] for j in range(3)) + t[f] for f, cc in zip(S.coarse_frame, S.coarse_centre)],
                      axis=1)
        need_scene = np.zeros((len(self.scene_pairs), n), dtype=bool)
        for j, obs in enumerate(self.scene.obstacles):
            prims = self._scene_pair_prims[j]
            d = point_primitive_distance(Cw[:, prims], obs.kind, obs.size, obs.T_I[:3, :3], obs.T_I[:3, 3])
            need_scene[self._scene_pair_columns[j]] = d - S.coarse_radius[prims, None] < c
        I, J = self._self_pair_index
        diff = Cw[:, I] - Cw[:, J]
        d = np.sqrt(diff[0] * diff[0] + diff[1] * diff[1] + diff[2] * diff[2])
        need_self = d - (S.coarse_radius[I] + S.coarse_radius[J])[:, None] < c
        # fine level, only for the poses (columns) that the coarse level could not decide
        for m, (i, j) in enumerate(self.scene_pairs):
            cols = np.flatnonzero(need_scene[m])
            if len(cols) == 0:
                continue
            f, obs = self.prims[i].frame, self.scene.obstacles[j]
            W = to_world(R[f][..., cols], t[f][:, cols], self._sphere_centre[i])
            d = point_primitive_distance(W, obs.kind, obs.size, obs.T_I[:3, :3], obs.T_I[:3, 3])
            need_scene[m, cols] = np.min(d - self._sphere_radius[i][:, None], axis=0) < c
        for m, (i, j) in enumerate(self.self_pairs):
            cols = np.flatnonzero(need_self[m])
            # i's spheres against j's shape, then j's spheres against i's shape where still undecided
            for a, b in ((i, j), (j, i)):
                if len(cols) == 0:
                    break
                lb = self._spheres_to_primitive(R, t, cols, a, b)
                need_self[m, cols[lb >= c]] = False
                cols = cols[lb < c]
        return need_scene, need_self

    def _spheres_to_primitive(self, R, t, cols, a, b):
        """Lower bound (len(cols),) on the distance (m) between robot primitives a and b at the
        poses ``cols`` of entry-first frames R (8, 3, 3, n), t (8, 3, n): a's enclosing spheres
        against b's exact shape."""
        fa, pb = self.prims[a].frame, self.prims[b]
        W = to_world(R[fa][..., cols], t[fa][:, cols], self._sphere_centre[a])
        Rf, tf = R[pb.frame][..., cols], t[pb.frame][:, cols]
        Rb = np.stack([np.stack([sum(Rf[i, l] * pb.T[l, k] for l in range(3)) for k in range(3)]) for i in range(3)])
        cb = to_world(Rf, tf, pb.T[None, :3, 3])[:, 0]
        d = point_primitive_distance(W, pb.kind, pb.size, Rb, cb)
        return np.min(d - self._sphere_radius[a][:, None], axis=0)

    def clear(self, R, t, clearance=None) -> np.ndarray:
        """(n,) bool: every checked pair farther apart than the clearance (m; default: the
        checker's). Frames R (n, 8, 3, 3), t (n, 8, 3). Sphere bounds first, FCL for the rest."""
        R, t = np.asarray(R), np.asarray(t)
        return self.clear_entry_first(np.ascontiguousarray(np.moveaxis(R, 0, -1)),
                                      np.ascontiguousarray(np.moveaxis(t, 0, -1)), clearance)

    def clear_entry_first(self, R, t, clearance=None) -> np.ndarray:
        """:meth:`clear` for frames given entry-first: R (8, 3, 3, n), t (8, 3, n)."""
        c = self.clearance if clearance is None else float(clearance)
        n = R.shape[-1]
        need_scene, need_self = self.undecided_pairs(R, t, c)
        need_scene, need_self = need_scene.T, need_self.T
        ok = np.ones(n, dtype=bool)
        todo = np.flatnonzero(need_scene.any(axis=1) | need_self.any(axis=1))
        scene_pairs = np.array(self.scene_pairs).reshape(-1, 2)
        self_pairs = np.array(self.self_pairs).reshape(-1, 2)
        for k in todo:
            ms, mo = np.flatnonzero(need_scene[k]), np.flatnonzero(need_self[k])
            which = set(scene_pairs[ms, 0]) | set(self_pairs[mo, 0]) | set(self_pairs[mo, 1])
            self._place(R[..., k], t[..., k], which)
            for i, j in scene_pairs[ms]:
                if self._dist(self.robot_objs[i], self.scene_objs[j]) < c:
                    ok[k] = False
                    break
            if not ok[k]:
                continue
            for i, j in self_pairs[mo]:
                if self._dist(self.robot_objs[i], self.robot_objs[j]) < c:
                    ok[k] = False
                    break
        return ok


class ExactChecker:
    """The suitability criteria computed directly with FCL, one pose at a time (for tests)."""

    def __init__(self, robot, scene, clearance_m):
        import fcl

        self.robot, self.scene = robot, scene
        self.clearance = ClearanceChecker(robot, scene, clearance_m)
        self._fcl = fcl

    def line_of_sight_clear(self, R, t, P) -> bool:
        """FCL distance from each beam (a capsule of the beam radius) to the scene and links 0-5 > 0."""
        fcl = self._fcl
        o = self.scene.tracker_position
        self.clearance._place(R, t)
        others = list(self.clearance.scene_objs) + [obj for obj, p in zip(self.clearance.robot_objs, self.clearance.prims)
                                                   if p.frame in OCCLUDING_FRAMES]
        for p in P:
            axis = o - p
            length = np.linalg.norm(axis)
            z = axis / length
            x = np.cross(z, [1.0, 0, 0]) if abs(z[0]) < 0.9 else np.cross(z, [0, 1.0, 0])
            x /= np.linalg.norm(x)
            Rb = np.stack([x, np.cross(z, x), z], axis=1)
            beam = fcl.CollisionObject(fcl.Capsule(self.scene.beam_radius_m, length),
                                       fcl.Transform(Rb, p + 0.5 * axis))
            for obj in others:
                res = fcl.DistanceResult()
                if fcl.distance(beam, obj, fcl.DistanceRequest(), res) <= 0.0:
                    return False
        return True
