"""Suitability of poses: tracker range, reflector cones, line of sight, clearance.

Vectorised tests that are conservative (they may reject a good pose, never accept a bad
one) decide most candidates; the clearance of every pose that passes them is then decided
with FCL. :class:`ExactChecker` computes the same criteria directly with FCL and no
shortcuts; the tests use it to re-check samples.
"""

from __future__ import annotations

import itertools
import json
import math

import numpy as np

from campaign.plan.geometry import (RobotSpheres, fcl_geometry, frame_spheres, hull_geometry,
                                    point_primitive_distance, robot_primitives, robot_spheres, to_world)
from campaign.tolerances import REFLECTOR_RADIUS_M


def occludes(robot, prim) -> bool:
    """Whether a robot primitive may occlude the tracker's beams: every link, the last one and
    what hangs from the tool frame (a hand, its fingers) too, checked against the beam from the
    reflector's sphere on (:func:`beam_starts`): the tool right around a nest lies within it."""
    return True


def beam_starts(scene, P):
    """Where each beam leaves its reflector: the point of the reflector's sphere
    (tolerances.REFLECTOR_RADIUS_M) towards the tracker, (n, k, 3) for centres P (n, k, 3)."""
    to = scene.tracker_position - P
    return P + REFLECTOR_RADIUS_M * to / np.linalg.norm(to, axis=-1, keepdims=True)


def reflector_geometry(robot, R_E, t_E):
    """Reflector centres (n, k, 3) and nest axes (n, k, 3) in F_I for tool frames R_E (n, 3, 3), t_E (n, 3)."""
    P = np.einsum("nij,rj->nri", R_E, robot.reflector_positions_in_E) + t_E[:, None, :]
    axes = np.array([r.axis_in_E for r in robot.reflectors])
    A = np.einsum("nij,rj->nri", R_E, axes)
    return P, A


def range_ok(scene, P):
    d = np.linalg.norm(P - scene.tracker_position, axis=-1)
    return np.all((d >= scene.min_range_m) & (d <= scene.max_range_m), axis=1)


def cone_ok(robot, scene, P, A, margin_rad: float = 0.0):
    """(n,) bool: every reflector's beam to the tracker within its nest's half-angle less
    ``margin_rad``; P, A (n, k, 3) reflector centres and nest axes in the cell."""
    to_tracker = scene.tracker_position - P
    to_tracker /= np.linalg.norm(to_tracker, axis=-1, keepdims=True)
    cosang = np.sum(A * to_tracker, axis=-1)
    limits = np.cos(np.maximum(np.array([r.half_angle for r in robot.reflectors]) - margin_rad, 0.0))
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
    """Edges (3,) of a box about the shape's centre, in its frame, that contains it."""
    if kind in ("box", "mesh"):
        return np.asarray(size, dtype=float)
    if kind == "sphere":
        return np.full(3, 2.0 * size[0])
    if kind == "capsule":
        return np.array([2 * size[0], 2 * size[0], size[1] + 2 * size[0]])
    return np.array([2 * size[0], 2 * size[0], size[1]])


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


def robot_beam_hits(robot, scene, P, R, t):
    """The beams each robot link (:func:`occludes`) may block, by its bounding box widened by the
    beam radius: yields (primitive index, (n, k) bool, the beams' ends (reflector, tracker) in the
    primitive's frame (n, k, 3) each). P (n, k, 3) reflector centres; R, t: frames (n, N+2, ...).
    Conservative: a beam it does not flag is clear of that link. The beams start at the
    reflectors' spheres (:func:`beam_starts`)."""
    o = scene.tracker_position
    P = beam_starts(scene, P)
    for i, prim in enumerate(robot_primitives(robot)):
        if not occludes(robot, prim):
            continue
        half = 0.5 * _box_of(prim.kind, prim.size) + scene.beam_radius_m
        Rw = R[:, prim.frame] @ prim.T[:3, :3]  # (n, 3, 3)
        cw = np.einsum("nij,j->ni", R[:, prim.frame], prim.T[:3, 3]) + t[:, prim.frame]
        p0 = np.einsum("nri,nij->nrj", P - cw[:, None, :], Rw)
        p1 = np.einsum("ni,nij->nj", o - cw, Rw)[:, None, :].repeat(P.shape[1], axis=1)
        yield i, _segment_hits_box(p0, p1, half), p0, p1


def robot_line_of_sight_ok(robot, scene, P, R, t):
    """No robot link (:func:`occludes`) within the beam radius of a beam, by the links' bounding
    boxes (:func:`robot_beam_hits`). P (n, k, 3) reflector centres; R, t: frames (n, N+2, ...).
    Conservative: :meth:`ClearanceChecker.beams_clear` decides what it rejects on the shapes."""
    ok = np.ones(len(P), dtype=bool)
    for _, hits, _, _ in robot_beam_hits(robot, scene, P, R, t):
        ok &= ~np.any(hits, axis=1)
    return ok


#: FCL's GJK distance between a convex hull and another shape can exceed the true distance (python-fcl
#: 0.7, measured at random UR10 and Panda postures: by up to 1.4 % of it, 1.2 mm at 0.86 m): a hull
#: clears a pair only when its distance less this share and this margin still reaches the clearance
HULL_SLACK_REL = 0.05
HULL_SLACK_M = 5e-4
#: most (pair, pose) entries of the primitive-sphere level computed at once (about 60 B each)
SPHERE_LEVEL_ENTRIES = 1 << 19
#: most exact verdicts a checker remembers (:meth:`ClearanceChecker.clear_entry_first`; about 200 B each)
MEMO_SIZE = 1_000_000


class ClearanceChecker:
    """Minimum distance robot–scene and between non-adjacent links, with FCL.

    Pairs: every moving link's primitives against every obstacle, and primitives of frames
    i, j with |i − j| ≥ 2 (adjacent links touch by design), less the pairs found closer than
    the clearance in every one of a random sample of configurations (as a set-up assistant
    disables "always in contact" pairs); those are listed in ``disabled_pairs``.

    A mesh is its triangles to FCL, which measures between surfaces: a shape wholly inside a
    closed (watertight) mesh would seem apart from it, so a pair that FCL finds clear is
    taken as touching (distance 0) when a point of one shape lies inside the other's mesh.

    Before a mesh's triangles, its convex hull (a solid that contains the mesh, so its distance
    is a lower bound of the mesh's, containment included) decides a pair in one GJK step: a
    pair whose hulls are at least the clearance apart is clear; only the others are measured
    on the triangles (:meth:`_clear_scene`, :meth:`_clear_self`).
    """

    def __init__(self, robot, scene, clearance_m):
        import fcl

        self.robot, self.scene, self.clearance = robot, scene, float(clearance_m)
        self.prims = robot_primitives(robot)
        self.spheres: RobotSpheres = robot_spheres(robot)
        self.robot_objs = [fcl.CollisionObject(fcl_geometry(p.kind, p.size, p.mesh), fcl.Transform()) for p in self.prims]
        # the convex hull of a mesh (the primitive itself otherwise): a lower bound in one GJK step
        self.hull_objs = [fcl.CollisionObject(hull_geometry(p.mesh), fcl.Transform()) if p.mesh is not None else obj
                          for p, obj in zip(self.prims, self.robot_objs)]
        # then the hulls of its pieces (a mesh), which hug a long or bent link closer
        self.piece_objs = [[fcl.CollisionObject(hull_geometry(p.mesh, k), fcl.Transform())
                            for k in range(len(p.mesh.pieces))] if p.mesh is not None else [obj]
                           for p, obj in zip(self.prims, self.robot_objs)]
        self._closed = [p.mesh is not None and p.mesh.watertight for p in self.prims]
        self._world = [None] * len(self.prims)  # (R, t) of each primitive as last placed, for the inside test
        self.scene_objs = []
        for obs in scene.obstacles:
            self.scene_objs.append(fcl.CollisionObject(fcl_geometry(obs.kind, obs.size),
                                                       fcl.Transform(obs.T_I[:3, :3], obs.T_I[:3, 3])))
        self.scene_pairs = [(i, j) for i, p in enumerate(self.prims) if p.frame >= 1 for j in range(len(self.scene_objs))]
        self._scene_pair_frame = np.array([self.prims[i].frame for i, _ in self.scene_pairs], dtype=int)
        self._frame_centre, self._frame_radius = frame_spheres(self.spheres, robot.n_joints + 2)
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
        # exact verdicts by the pose of the frames a pair depends on: a link's pose in the cell (a
        # scene pair), the two links' relative pose (a pair of links). Poses of the grid share
        # them where the joints beyond those links alone differ (the wrist's cells, motions of the wrist)
        self._memo = {}
        self._inside_cells = {}  # (primitive, cell edge, cell) -> inside its closed mesh (:meth:`_inside`)

    def _prune_always_near(self, pairs, n=300, seed=0):
        """(pairs kept, frame pairs of those closer than the clearance at every one of ``n``
        random configurations). A sample where the sphere bounds already clear a pair shows it
        is not always near without FCL; FCL decides the rest, sample by sample."""
        from campaign.plan.geometry import nominal_frames_entry_first

        cached = _pairs_cache_file(self.robot, self.prims, pairs, n, seed, self.clearance)
        try:
            always = json.loads(cached.read_text())["always"]
            if len(always) != len(pairs) or not all(isinstance(a, bool) for a in always):
                raise ValueError
        except (OSError, ValueError, KeyError, TypeError):
            rng = np.random.default_rng(seed)
            q = rng.uniform(self.robot.q_lower, self.robot.q_upper, size=(n, self.robot.n_joints))
            Re, te = nominal_frames_entry_first(self.robot, q)
            index = np.array(pairs, dtype=int).reshape(-1, 2).T
            need = self._self_undecided(Re, te, index, self.clearance, self._coarse_world(Re, te))
            always = []
            for m, (i, j) in enumerate(pairs):
                near = bool(need[m].all())
                for k in range(n) if near else ():
                    self._place(Re[..., k], te[..., k], (i, j))
                    if self._clear_self(i, j, self.clearance):
                        near = False
                        break
                always.append(near)
            _write_cache(cached, json.dumps({"always": always}))
        keep = [p for p, a in zip(pairs, always) if not a]
        dropped = [(self.prims[i].frame, self.prims[j].frame) for (i, j), a in zip(pairs, always) if a]
        return keep, dropped

    def _place(self, R, t, which=None):
        """Put the robot's FCL objects (all, or the primitive indices ``which``) at a pose:
        frames R (N+2, 3, 3), t (N+2, 3)."""
        import fcl

        for i in range(len(self.prims)) if which is None else which:
            p = self.prims[i]
            Rw, tw = R[p.frame] @ p.T[:3, :3], R[p.frame] @ p.T[:3, 3] + t[p.frame]
            tf = fcl.Transform(Rw, tw)
            self.robot_objs[i].setTransform(tf)
            if self.hull_objs[i] is not self.robot_objs[i]:
                self.hull_objs[i].setTransform(tf)
                for obj in self.piece_objs[i]:
                    obj.setTransform(tf)
            self._world[i] = (Rw, tw)

    @staticmethod
    def _dist(a, b):
        import fcl

        res = fcl.DistanceResult()
        return fcl.distance(a, b, fcl.DistanceRequest(), res)

    def _inside(self, i, point, apart=0.0) -> bool:
        """Whether a point (3,) in F_I lies inside robot primitive i's closed mesh (as placed).
        ``apart``: a distance (m) the point is known to keep from the mesh's surface; then the
        answer is the centre's of the point's cell of a grid of edge ``apart / 2`` in the mesh's
        frame (the segment to it, shorter than ``apart``, cannot cross the surface), remembered
        per cell: the points of nearby poses share it."""
        Rw, tw = self._world[i]
        local = (np.asarray(point) - tw) @ Rw
        if np.any(np.abs(local) > 0.5 * np.asarray(self.prims[i].size)):
            return False
        if apart <= 0:
            return bool(self.prims[i].mesh.contains(local[None])[0])
        edge = 0.5 * apart
        cell = np.floor(local / edge)
        key = (i, edge, cell.tobytes())
        v = self._inside_cells.get(key)
        if v is None:
            if len(self._inside_cells) > MEMO_SIZE:
                self._inside_cells.clear()
            v = self._inside_cells[key] = bool(self.prims[i].mesh.contains(((cell + 0.5) * edge)[None])[0])
        return v

    def _point_of(self, i):
        """A point (3,) in F_I of robot primitive i as placed (a mesh: a vertex; else its centre)."""
        Rw, tw = self._world[i]
        p = self.prims[i]
        return Rw @ p.mesh.vertices[0] + tw if p.mesh is not None else tw

    def _dist_scene(self, i, j) -> float:
        """FCL distance (m) of robot primitive i (placed) to obstacle j; 0 for an obstacle inside a closed mesh."""
        d = self._dist(self.robot_objs[i], self.scene_objs[j])
        if d > 0 and self._closed[i] and self._inside(i, self.scene.obstacles[j].T_I[:3, 3]):
            return 0.0
        return d

    def _dist_self(self, i, j) -> float:
        """FCL distance (m) of robot primitives i and j (placed); 0 for one inside the other's closed mesh."""
        d = self._dist(self.robot_objs[i], self.robot_objs[j])
        if d > 0 and ((self._closed[i] and self._inside(i, self._point_of(j)))
                      or (self._closed[j] and self._inside(j, self._point_of(i)))):
            return 0.0
        return d

    def _clear_scene(self, i, j, c) -> bool:
        """Whether robot primitive i (placed) is at least ``c`` (m) from obstacle j: the hull
        first, the triangles (:meth:`_dist_scene`) only when the hull is nearer than c."""
        if self.hull_objs[i] is not self.robot_objs[i]:
            if _hull_clear(self._dist(self.hull_objs[i], self.scene_objs[j]), c):
                return True
            if all(_hull_clear(self._dist(piece, self.scene_objs[j]), c) for piece in self.piece_objs[i]):
                # the surface is at least c away; an obstacle inside the closed mesh still touches it
                return not (self._closed[i] and self._inside(i, self.scene.obstacles[j].T_I[:3, 3], c))
        return self._dist_scene(i, j) >= c

    def _clear_self(self, i, j, c) -> bool:
        """Whether robot primitives i and j (placed) are at least ``c`` (m) apart: hulls first."""
        a, b = self.hull_objs[i], self.hull_objs[j]
        if a is not self.robot_objs[i] or b is not self.robot_objs[j]:
            if _hull_clear(self._dist(a, b), c):
                return True
            if all(_hull_clear(self._dist(x, y), c) for x in self.piece_objs[i] for y in self.piece_objs[j]):
                # the surfaces are at least c apart; one inside the other's closed mesh still touches it
                return not ((self._closed[i] and self._inside(i, self._point_of(j), c))
                            or (self._closed[j] and self._inside(j, self._point_of(i), c)))
        return self._dist_self(i, j) >= c

    def beams_clear(self, R, t, P) -> np.ndarray:
        """(n,) bool: every beam of each pose clear of the robot's links (:func:`occludes`) on
        their shapes: the bounding boxes (:func:`robot_beam_hits`) flag what may block, FCL
        decides it (a mesh's convex hull first, then its triangles; a beam starting inside a
        mesh crosses its surface). For the poses :func:`robot_line_of_sight_ok` rejects, whose
        bounding boxes stop a beam the link itself may leave free (a small arm: the wrist's box
        holds the reflectors, its mesh does not). R, t: frames (n, N+2, ...); P (n, k, 3)."""
        return np.array([b is None for b in self.beam_blockers(R, t, P)], dtype=bool)

    def beam_blockers(self, R, t, P) -> list:
        """Per pose, the first (primitive index, reflector index) whose beam the primitive's shape
        blocks, or None (see :meth:`beams_clear`)."""
        import fcl

        o, radius = self.scene.tracker_position, self.scene.beam_radius_m
        flagged = {}  # pose -> [(primitive, reflector)] whose box, spheres and hull may stop the beam
        S = beam_starts(self.scene, P)  # the beams leave the reflectors' spheres
        for i, hits, p0, p1 in robot_beam_hits(self.robot, self.scene, P, R, t):
            k, r = np.nonzero(hits)
            if len(k) == 0:
                continue
            near = ~self._spheres_clear_beams(i, R[k], t[k], S[k, r], o, radius)
            if self.prims[i].mesh is not None and near.any():
                near[near] = segments_meet_hull(self.prims[i].mesh, p0[k[near], r[near]], p1[k[near], r[near]], radius)
            for kk, rr in zip(k[near], r[near]):
                flagged.setdefault(int(kk), []).append((i, int(rr)))
        out = [None] * len(P)
        for k, pairs in flagged.items():
            beams = {}
            self._place(R[k], t[k], sorted({i for i, _ in pairs}))
            for i, r in pairs:
                beam = beams.get(r) or beams.setdefault(r, _beam_object(fcl, S[k, r], o, radius))
                if fcl.collide(beam, self.robot_objs[i], fcl.CollisionRequest(), fcl.CollisionResult()) > 0:
                    out[k] = (i, r)
                    break
        return out

    def _spheres_clear_beams(self, i, R, t, p, o, radius) -> np.ndarray:
        """(m,) bool: the beam from p[m] (3,) to the tracker o (3,), ``radius`` wide, misses every
        sphere enclosing robot primitive i (so the primitive too) with frames R (m, N+2, 3, 3), t (m, N+2, 3)."""
        f = self.prims[i].frame
        C = np.einsum("mij,sj->msi", R[:, f], self._sphere_centre[i]) + t[:, f][:, None, :]  # (m, S, 3)
        d = o - p
        u = np.clip(np.einsum("msi,mi->ms", C - p[:, None, :], d) / np.einsum("mi,mi->m", d, d)[:, None], 0.0, 1.0)
        gap = np.linalg.norm(C - p[:, None, :] - u[..., None] * d[:, None, :], axis=-1)
        return np.all(gap > self._sphere_radius[i] + radius, axis=1)

    def pair_distances(self, R, t) -> tuple:
        """Exact FCL distances (m) of every checked pair for one pose (frames R (N+2,3,3), t (N+2,3)):
        ``(robot-scene (len(scene_pairs),), robot-robot (len(self_pairs),))``."""
        self._place(R, t)
        d_scene = np.array([self._dist_scene(i, j) for i, j in self.scene_pairs])
        d_self = np.array([self._dist_self(i, j) for i, j in self.self_pairs])
        return d_scene, d_self

    def exact_min_distance(self, R, t) -> float:
        """Exact FCL minimum distance over all checked pairs for one pose (frames R (N+2,3,3), t (N+2,3))."""
        d_scene, d_self = self.pair_distances(R, t)
        return float(min(d_scene.min(initial=np.inf), d_self.min(initial=np.inf)))

    def _coarse_world(self, R, t):
        """Centres (3, P, n) in F_I of the one-sphere-per-primitive level, frames entry-first."""
        S = self.spheres
        if len(S.coarse_frame) == 0:
            return np.zeros((3, 0, R.shape[-1]))
        return np.stack([sum(R[f, :, j] * cc[j] for j in range(3)) + t[f]
                         for f, cc in zip(S.coarse_frame, S.coarse_centre)], axis=1)

    def _self_undecided(self, R, t, index, c, Cw, known_self=None):
        """(len(pairs), n) bool for the primitive pairs ``index`` (2, m): True where the sphere
        bounds cannot show the pair farther apart than ``c`` (m); see :meth:`undecided_pairs`
        (``known_self``: the frame pairs known clear, skipped).
        Levels: one sphere per frame around its primitives (the pairs of two frames are decided
        together: a gripper of 41 meshes against the body); where that fails, each primitive's
        sphere against the other frame's sphere, then against the other primitive's sphere; each
        primitive's sphere set against the other's shape where that fails too."""
        S = self.spheres
        I, J = index
        n = R.shape[-1]
        need_self = np.zeros((len(I), n), dtype=bool)
        if len(I) == 0:
            return need_self
        fI, fJ = S.coarse_frame[I], S.coarse_frame[J]
        frame_pairs, group = np.unique(np.stack([fI, fJ], axis=1).reshape(-1, 2), axis=0, return_inverse=True)
        def gap(A, B):  # centre distances of (3, ...) arrays
            diff = A - B
            return np.sqrt(diff[0] * diff[0] + diff[1] * diff[1] + diff[2] * diff[2])

        centre = {f: sum(R[f, :, j] * self._frame_centre[f, j] for j in range(3)) + t[f]
                  for f in np.unique(frame_pairs)}  # each frame's sphere centre (3, n) in F_I
        for g, (a, b) in enumerate(frame_pairs):
            poses = slice(None) if known_self is None else np.flatnonzero(~known_self[a, b])  # not known clear
            ca, cb = centre[a][:, poses], centre[b][:, poses]
            near_frames = np.flatnonzero(gap(ca, cb) - (self._frame_radius[a] + self._frame_radius[b]) < c)
            if len(near_frames) == 0:
                continue
            ca, cb = ca[:, near_frames], cb[:, near_frames]
            cols = near_frames if known_self is None else poses[near_frames]
            members = np.flatnonzero(group.reshape(-1) == g)
            Ia, Jb = I[members], J[members]  # the pairs' primitives on frames a and b
            ua, in_a = np.unique(Ia, return_inverse=True)
            ub, in_b = np.unique(Jb, return_inverse=True)
            block = max(1, SPHERE_LEVEL_ENTRIES // len(members))  # bounded memory for many pairs and poses
            for s in range(0, len(cols), block):
                cs, ls = cols[s : s + block], slice(s, s + block)  # poses, and their columns of ca, cb
                # each primitive against the other frame's sphere: a pair is near only if both are
                near_a = gap(Cw[:, ua[:, None], cs], cb[:, None, ls]) - S.coarse_radius[ua][:, None] < c + self._frame_radius[b]
                near_b = gap(Cw[:, ub[:, None], cs], ca[:, None, ls]) - S.coarse_radius[ub][:, None] < c + self._frame_radius[a]
                m, k = np.nonzero(near_a[in_a.reshape(-1)] & near_b[in_b.reshape(-1)])
                d = gap(Cw[:, Ia[m], cs[k]], Cw[:, Jb[m], cs[k]])
                near = d - (S.coarse_radius[Ia[m]] + S.coarse_radius[Jb[m]]) < c
                need_self[members[m[near]], cs[k[near]]] = True
        for m in np.flatnonzero(need_self.any(axis=1)):
            i, j = I[m], J[m]
            cols = np.flatnonzero(need_self[m])
            # i's spheres against j's shape, then j's spheres against i's shape where still undecided
            for a, b in ((i, j), (j, i)):
                if len(cols) == 0:
                    break
                lb = self._spheres_to_primitive(R, t, cols, a, b)
                need_self[m, cols[lb >= c]] = False
                cols = cols[lb < c]
        return need_self

    def undecided_pairs(self, R, t, clearance, known_clear=None):
        """Which pairs the sphere bounds cannot clear, for poses with frames given entry-first:
        R (N+2, 3, 3, n), t (N+2, 3, n) (see :func:`~campaign.plan.geometry.nominal_frames_entry_first`).
        ``known_clear``: None, or ``(scene (N+2, n), self (N+2, N+2, n))`` bool, the frames whose
        pairs with the scene, and the pairs of frames, already known to be at least ``clearance``
        apart at each pose (:func:`campaign.plan.repair.check_segments`: the motion's end poses
        bound them); their pairs are not undecided.

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
        Cw = self._coarse_world(R, t)
        need_scene = np.zeros((len(self.scene_pairs), n), dtype=bool)
        for j, obs in enumerate(self.scene.obstacles):
            prims = self._scene_pair_prims[j]
            if known_clear is None:
                d = point_primitive_distance(Cw[:, prims], obs.kind, obs.size, obs.T_I[:3, :3], obs.T_I[:3, 3])
                need_scene[self._scene_pair_columns[j]] = d - S.coarse_radius[prims, None] < c
                continue
            r, k = np.nonzero(~known_clear[0][self.spheres.coarse_frame[prims]])  # only where not known clear
            d = point_primitive_distance(Cw[:, prims[r], k], obs.kind, obs.size, obs.T_I[:3, :3], obs.T_I[:3, 3])
            need_scene[self._scene_pair_columns[j][r], k] = d - S.coarse_radius[prims[r]] < c
        # fine level, only for the poses (columns) that the coarse level could not decide
        for m in np.flatnonzero(need_scene.any(axis=1)):
            i, j = self.scene_pairs[m]
            cols = np.flatnonzero(need_scene[m])
            f, obs = self.prims[i].frame, self.scene.obstacles[j]
            W = to_world(R[f][..., cols], t[f][:, cols], self._sphere_centre[i])
            d = point_primitive_distance(W, obs.kind, obs.size, obs.T_I[:3, :3], obs.T_I[:3, 3])
            need_scene[m, cols] = np.min(d - self._sphere_radius[i][:, None], axis=0) < c
        need_self = self._self_undecided(R, t, self._self_pair_index, c, Cw,
                                         None if known_clear is None else known_clear[1])
        return need_scene, need_self

    def _spheres_to_primitive(self, R, t, cols, a, b):
        """Lower bound (len(cols),) on the distance (m) between robot primitives a and b at the
        poses ``cols`` of entry-first frames R (N+2, 3, 3, n), t (N+2, 3, n): a's enclosing spheres
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
        checker's). Frames R (n, N+2, 3, 3), t (n, N+2, 3). Sphere bounds first, FCL for the rest."""
        R, t = np.asarray(R), np.asarray(t)
        return self.clear_entry_first(np.ascontiguousarray(np.moveaxis(R, 0, -1)),
                                      np.ascontiguousarray(np.moveaxis(t, 0, -1)), clearance)

    def clear_entry_first(self, R, t, clearance=None, known_clear=None) -> np.ndarray:
        """:meth:`clear` for frames given entry-first: R (N+2, 3, 3, n), t (N+2, 3, n);
        ``known_clear``: the pairs already known clear (:meth:`undecided_pairs`)."""
        c = self.clearance if clearance is None else float(clearance)
        n = R.shape[-1]
        need_scene, need_self = self.undecided_pairs(R, t, c, known_clear)
        need_scene, need_self = need_scene.T, need_self.T
        ok = np.ones(n, dtype=bool)
        todo = np.flatnonzero(need_scene.any(axis=1) | need_self.any(axis=1))
        if len(todo) == 0:
            return ok
        scene_pairs = np.array(self.scene_pairs).reshape(-1, 2)
        self_pairs = np.array(self.self_pairs).reshape(-1, 2)
        memo = self._memo
        if len(memo) > MEMO_SIZE:
            memo.clear()
        keys = _PoseKeys(R[..., todo], t[..., todo])
        rows_s, cols_s = np.nonzero(need_scene[todo])
        rows_o, cols_o = np.nonzero(need_self[todo])
        cut_s = np.searchsorted(rows_s, np.arange(len(todo) + 1))
        cut_o = np.searchsorted(rows_o, np.arange(len(todo) + 1))
        for row, k in enumerate(todo):
            Rk, tk = R[..., k], t[..., k]
            placed = set()
            for i, j in scene_pairs[cols_s[cut_s[row]:cut_s[row + 1]]]:
                key = (0, i, j, c, keys.frame(self.prims[i].frame, row))
                v = memo.get(key)
                if v is None:
                    if i not in placed:
                        self._place(Rk, tk, (i,))
                        placed.add(i)
                    v = memo[key] = self._clear_scene(i, j, c)
                if not v:
                    ok[k] = False
                    break
            if not ok[k]:
                continue
            for i, j in self_pairs[cols_o[cut_o[row]:cut_o[row + 1]]]:
                key = (1, i, j, c, keys.relative(self.prims[i].frame, self.prims[j].frame, row))
                v = memo.get(key)
                if v is None:
                    new = [x for x in (i, j) if x not in placed]
                    if new:
                        self._place(Rk, tk, new)
                        placed.update(new)
                    v = memo[key] = self._clear_self(i, j, c)
                if not v:
                    ok[k] = False
                    break
        return ok


#: when the links' bounding boxes leave fewer suitable poses than this, the beams they stop are
#: decided on the links' shapes (:meth:`ClearanceChecker.beams_clear`: several seconds for a big
#: arm's tens of thousands of poses, so only when the boxes leave too few to choose a campaign
#: among: a small arm whose wrist's box holds the reflectors)
EXACT_SIGHT_BELOW = 2000
#: poses of the last filter's rejects examined to say why no pose is suitable (:func:`why_no_pose`)
WHY_SAMPLE = 40


def why_no_pose(robot, scene, grid, checker, removed, hidden, near, seed=0) -> str:
    """Why no candidate of ``grid`` is suitable, and what to change, in one sentence: from the
    last filter that removed any (``removed``: counts by filter, in order); for a link hiding
    the reflectors (``hidden``: grid indices) or poses too near (``near``), the link or pair
    found most often on a random sample of :data:`WHY_SAMPLE` of them."""
    from campaign.model.kinematics import frames

    last = [f for f, n in removed.items() if n > 0][-1]
    tool = f"the tool frame '{robot.tool_frame}'"
    if last == "tracker_range":
        return (f"every reflector lies outside the tracker's range ({scene.min_range_m:g}-{scene.max_range_m:g} m) "
                "in every pose: move the tracker within reach (the scene's tracker.position_m)")
    if last == "reflector_cone":
        deg = ", ".join(sorted({f"{np.degrees(r.half_angle):g}°" for r in robot.reflectors}))
        return (f"no pose turns every reflector's nest to within its half-angle ({deg}) of the tracker: check the "
                f"reflectors' axes (robot.yaml; without reflectors there, +z of {tool}) and the tracker's place")
    if last == "line_of_sight_scene":
        return "every beam to the tracker crosses an obstacle of the scene: move the tracker or the obstacles"
    rng = np.random.default_rng(seed)
    rows = hidden if last == "line_of_sight_robot" else near
    sample = np.sort(rng.choice(rows, min(WHY_SAMPLE, len(rows)), replace=False))
    R, t = frames(robot, grid.q(sample))
    found = {}
    if last == "line_of_sight_robot":
        E = robot.n_joints + 1
        P, _ = reflector_geometry(robot, R[:, E], t[:, E])
        for b in checker.beam_blockers(R, t, P):
            if b is not None:
                found[b] = found.get(b, 0) + 1
        (i, r), n = max(found.items(), key=lambda kv: kv[1]) if found else ((0, 0), 0)
        ref = robot.reflectors[r]
        where = ", ".join(f"{v:g}" for v in np.round(ref.position_in_E, 4))
        own = checker.prims[i].frame >= robot.n_joints  # the last link, or a hand / fingers beyond the tool frame
        what = "the robot itself hides" if own else "a link of the robot hides"
        link = f"its {'hand ' if checker.prims[i].frame > robot.n_joints else ''}link '{checker.prims[i].link}'"
        return (f"{what} a reflector in each of the {len(hidden):,} poses the tracker could see "
                f"(in {n} of {len(sample)} sampled: {link} hides reflector {ref.name} at "
                f"({where}) m in {tool}): the reflectors sit "
                + ("inside or behind the robot's own tool side; " if own else "too near the arm; ")
                + "name a tool frame at the tip of the tool (--tool-frame) or the reflectors where they are mounted "
                  "(robot.yaml reflectors, docs/robot_yaml.md)")
    names = [o.name for o in scene.obstacles]
    for k in range(len(sample)):
        d_scene, d_self = checker.pair_distances(R[k], t[k])
        pairs = {("obstacle", checker.prims[i].link, names[j]) for (i, j), d in zip(checker.scene_pairs, d_scene)
                 if d < checker.clearance}
        pairs |= {("link", checker.prims[i].link, checker.prims[j].link)
                  for (i, j), d in zip(checker.self_pairs, d_self) if d < checker.clearance}
        for p in pairs:
            found[p] = found.get(p, 0) + 1
    (kind, a, b), n = max(found.items(), key=lambda kv: kv[1])
    change = ("place the robot elsewhere in the cell (--base-frame, the scene's robot_base) or move the obstacle"
              if kind == "obstacle" else "a smaller plan.clearance_m, or a collision model that is not padded")
    return (f"each of the {len(near):,} poses the tracker sees is nearer than plan.clearance_m = {checker.clearance:g} m "
            f"to the cell or to the robot itself (in {n} of {len(sample)} sampled: link '{a}' to {kind} '{b}'): {change}")


#: beams checked against a hull's planes at once (bounds the (beams, planes) arrays)
HULL_BEAM_CHUNK = 2048


def segments_meet_hull(mesh, a, b, radius) -> np.ndarray:
    """(m,) bool: whether the segment a[m]→b[m] (m, 3), in the mesh's frame, meets its convex hull
    widened by ``radius`` (m): each hull plane moved out by the radius, the segment clipped by
    every half-space (Liang-Barsky). The widened planes hold the hull's points within the radius,
    so False proves a capsule of that radius about the segment clear of the mesh."""
    normals, offsets = mesh.hull_planes
    out = np.zeros(len(a), dtype=bool)
    for s in range(0, len(a), HULL_BEAM_CHUNK):
        p, d = a[s : s + HULL_BEAM_CHUNK], b[s : s + HULL_BEAM_CHUNK] - a[s : s + HULL_BEAM_CHUNK]
        room = offsets + radius - p @ normals.T  # (m, F): how far inside each plane the start lies
        rate = d @ normals.T  # its change along the segment
        with np.errstate(divide="ignore", invalid="ignore"):
            at = room / rate
        enter = np.max(np.where(rate < 0, at, -np.inf), axis=1, initial=0.0)
        leave = np.min(np.where(rate > 0, at, np.inf), axis=1, initial=1.0)
        parallel_out = np.any((rate == 0) & (room < 0), axis=1)
        out[s : s + HULL_BEAM_CHUNK] = (enter <= leave) & ~parallel_out
    return out


def _beam_object(fcl, p, o, radius):
    """The beam from reflector centre p (3,) to the tracker o (3,) as an FCL capsule of ``radius`` (m)."""
    to = o - p
    d = math.sqrt(to[0] * to[0] + to[1] * to[1] + to[2] * to[2])
    z0, z1, z2 = to[0] / d, to[1] / d, to[2] / d
    # x ⟂ z: z × e_x, or z × e_y when z is near e_x; y = z × x (scalars: numpy's cross is slow for one vector)
    x0, x1, x2 = (0.0, z2, -z1) if abs(z0) < 0.9 else (-z2, 0.0, z0)
    n = math.sqrt(x0 * x0 + x1 * x1 + x2 * x2)
    x0, x1, x2 = x0 / n, x1 / n, x2 / n
    y0, y1, y2 = z1 * x2 - z2 * x1, z2 * x0 - z0 * x2, z0 * x1 - z1 * x0
    frame = np.array([[x0, y0, z0], [x1, y1, z1], [x2, y2, z2]])
    return fcl.CollisionObject(fcl.Capsule(radius, d), fcl.Transform(frame, p + 0.5 * to))


def _hull_clear(d, c) -> bool:
    """Whether a hull distance d (m) from FCL proves the clearance c (m) despite GJK's error."""
    return d * (1.0 - HULL_SLACK_REL) - HULL_SLACK_M >= c


def _pairs_cache_file(robot, prims, pairs, n, seed, clearance):
    """Where :meth:`ClearanceChecker._prune_always_near`'s answer for this robot's geometry is kept
    (campaign.plan.geometry.cache_dir): keyed by the hash of everything it depends on (the chain's
    nominal frames and limits, every collision shape with its mesh, the pairs, the sample, the clearance)."""
    import hashlib

    from campaign.plan.geometry import cache_dir

    h = hashlib.sha256(repr((1, pairs, n, seed, float(clearance))).encode())
    for a in (robot.q_lower, robot.q_upper, robot.R_nominal, robot.t_nominal):
        h.update(np.ascontiguousarray(a, dtype=float).tobytes())
    for p in prims:
        h.update(repr((p.frame, p.kind, tuple(p.size))).encode() + np.ascontiguousarray(p.T).tobytes())
        if p.mesh is not None:
            h.update(np.ascontiguousarray(p.mesh.vertices).tobytes() + np.ascontiguousarray(p.mesh.faces).tobytes())
    return cache_dir() / "pairs" / f"{h.hexdigest()[:32]}.json"


def _write_cache(path, text):
    """Write a cache entry atomically; a cache that cannot be written is passed by."""
    import os

    try:
        path.parent.mkdir(parents=True, exist_ok=True)
        tmp = path.with_name(f"{path.name}.{os.getpid()}.tmp")
        tmp.write_text(text)
        tmp.replace(path)
    except OSError:
        pass


class _PoseKeys:
    """Hashable keys (bytes) of frame poses, equal for poses equal to 1e-10, computed for all
    poses at once per frame (a frame's pose in F_I) or frame pair (their relative pose) when
    first asked: frames entry-first R (K, 3, 3, n), t (K, 3, n)."""

    def __init__(self, R, t):
        self.R, self.t = R, t
        self._frame, self._relative = {}, {}

    @staticmethod
    def _rows(R, t):
        return np.ascontiguousarray(np.round(np.concatenate([R.reshape(9, -1), t]), 10).T)

    def frame(self, f, row) -> bytes:
        if f not in self._frame:
            self._frame[f] = self._rows(self.R[f], self.t[f])
        return self._frame[f][row].tobytes()

    def relative(self, fi, fj, row) -> bytes:
        if (fi, fj) not in self._relative:
            Ri, Rj = self.R[fi], self.R[fj]
            Rrel = np.einsum("jin,jkn->ikn", Ri, Rj)  # Riᵀ Rj
            trel = np.einsum("jin,jn->in", Ri, self.t[fj] - self.t[fi])  # Riᵀ (tj - ti)
            self._relative[(fi, fj)] = self._rows(Rrel, trel)
        return self._relative[(fi, fj)][row].tobytes()


class ExactChecker:
    """The suitability criteria computed directly with FCL, one pose at a time (for tests)."""

    def __init__(self, robot, scene, clearance_m):
        import fcl

        self.robot, self.scene = robot, scene
        self.clearance = ClearanceChecker(robot, scene, clearance_m)
        self._fcl = fcl

    def line_of_sight_clear(self, R, t, P) -> bool:
        """FCL distance from each beam (a capsule of the beam radius) to the scene, and from each
        beam leaving its reflector's sphere (:func:`beam_starts`) to the occluding links, > 0."""
        fcl = self._fcl
        o = self.scene.tracker_position
        self.clearance._place(R, t)
        links = [obj for obj, p in zip(self.clearance.robot_objs, self.clearance.prims) if occludes(self.robot, p)]
        for p, start in zip(P, beam_starts(self.scene, np.asarray(P)[None])[0]):
            for beam, others in ((_beam_object(fcl, p, o, self.scene.beam_radius_m), self.clearance.scene_objs),
                                 (_beam_object(fcl, start, o, self.scene.beam_radius_m), links)):
                for obj in others:
                    res = fcl.DistanceResult()
                    if fcl.distance(beam, obj, fcl.DistanceRequest(), res) <= 0.0:
                        return False
        return True
