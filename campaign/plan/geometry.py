"""Collision geometry of the robot (from the URDF) and the scene, for FCL and for bounds.

The robot's geometry is every ``<collision>`` of every link of its URDF, carried by the chain
frame that link moves with (:attr:`campaign.model.robot.RobotModel.link_frames`): boxes,
cylinders, spheres, capsules (``<capsule radius length>``, axis z) and meshes (any format
trimesh reads: STL, DAE, OBJ, ...; ``scale`` applied; ``package://`` and relative paths
resolved as yourdfpy does). Geometry the planner cannot check (a mesh file that is missing or
unreadable, another element) is one ConfigError line naming the link and the file, never
dropped.

Two representations of the same shapes:

* FCL objects (python-fcl) for exact distances: the primitives themselves, a mesh as its
  triangles (a bounding-volume hierarchy);
* enclosing spheres for vectorised, conservative lower bounds: if the spheres are clear by
  d, the real geometry is clear by at least d. A box or cylinder is cut along its long axis
  into pieces, each inside one sphere; a mesh's surface is cut into cells of its oriented
  bounding box, each cell's triangles inside one sphere. Where a bound needs a shape's exact
  distance to a point, a mesh stands in for itself by its oriented bounding box (which
  contains it: the bound stays a lower bound).
"""

from __future__ import annotations

import functools
import os
import xml.etree.ElementTree as ET
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from campaign.errors import ConfigError
from campaign.model.rotations import urdf_rpy
from campaign.model.tool_side import resolve_mesh_path  # noqa: F401  (re-exported: the planner resolves its meshes)

#: kinds of collision geometry the planner checks (URDF elements of the same names)
SUPPORTED = ("box", "cylinder", "sphere", "capsule", "mesh")
#: a mesh's surface is cut into cubes of its oriented bounding box's smallest edge times this
#: (at least MESH_PIECE_MIN_M), one enclosing sphere per cube: smaller spheres decide more pairs
#: a point farther than this outside a convex hull's plane is outside the hull (the planes' round-off), m
HULL_PLANE_TOLERANCE_M = 1e-7
#: without FCL but cost more per bound
MESH_PIECE_FRACTION = 0.5
MESH_PIECE_MIN_M = 0.02
#: slabs of a mesh's triangles whose convex hulls bound it after its one hull (campaign.plan.checks)
MESH_HULL_PIECES = 4
#: a flat mesh (an edge of its bounding box below this, m) gets this thickness for its box bound
MESH_MIN_EXTENT_M = 1e-6


@dataclass(frozen=True, eq=False)
class MeshShape:
    """A collision mesh in its primitive's frame (the mesh's oriented bounding box, centred):
    vertices (V, 3) m, faces (F, 3), the file it came from, and whether it is closed
    (watertight: then it has an inside, which FCL's triangle distance does not see)."""

    vertices: np.ndarray
    faces: np.ndarray
    path: Path
    watertight: bool

    @functools.cached_property
    def trimesh(self):
        import trimesh

        return trimesh.Trimesh(self.vertices, self.faces, process=False)

    @functools.cached_property
    def hull(self):
        """The convex hull's vertices (h, 3) m and triangles (g, 3), in the primitive's frame."""
        import trimesh

        h = trimesh.convex.convex_hull(self.vertices)
        return np.ascontiguousarray(h.vertices, dtype=float), np.ascontiguousarray(h.faces, dtype=np.int64)

    @functools.cached_property
    def hull_planes(self) -> tuple:
        """The convex hull as half-spaces n·x <= d: outward unit normals (g, 3) and offsets (g,) m."""
        v, f = self.hull
        n = np.cross(v[f[:, 1]] - v[f[:, 0]], v[f[:, 2]] - v[f[:, 0]])
        length = np.linalg.norm(n, axis=1)
        keep = length > 1e-12 * max(1.0, float(np.max(length, initial=0.0)))  # no slivers
        n, f = n[keep] / length[keep, None], f[keep]
        n *= np.where(np.einsum("gi,gi->g", n, v[f[:, 0]] - v.mean(axis=0)) < 0, -1.0, 1.0)[:, None]  # outward
        return n, np.einsum("gi,gi->g", n, v[f[:, 0]])

    @functools.cached_property
    def pieces(self) -> tuple:
        """Convex hulls ((h, 3) vertices, (g, 3) triangles) of :data:`MESH_HULL_PIECES` slabs of the
        mesh's triangles along its bounding box's longest edge (by centroid): together they
        contain its surface, hugging a long, bent link closer than its one hull."""
        import trimesh

        axis = int(np.argmax(np.ptp(self.vertices, axis=0)))
        tri = self.vertices[self.faces]  # (F, 3, 3)
        x = tri.mean(axis=1)[:, axis]
        edges = np.linspace(x.min(), x.max(), MESH_HULL_PIECES + 1)
        slab = np.clip(np.searchsorted(edges, x, side="right") - 1, 0, MESH_HULL_PIECES - 1)
        out = []
        for k in range(MESH_HULL_PIECES):
            pts = tri[slab == k].reshape(-1, 3)
            if len(pts) == 0:
                continue
            try:
                with np.errstate(all="ignore"):  # a flat slab's hull has no volume
                    h = trimesh.convex.convex_hull(pts)
                v, f = np.asarray(h.vertices, dtype=float), np.asarray(h.faces, dtype=np.int64)
                if len(f) == 0:
                    raise ValueError("flat")
            except Exception:  # a flat or degenerate slab: the whole hull contains it
                v, f = self.hull
            out.append((np.ascontiguousarray(v), np.ascontiguousarray(f)))
        return tuple(out)

    def contains(self, points) -> np.ndarray:
        """(n,) bool: points (n, 3) in the primitive's frame inside the closed mesh."""
        points = np.asarray(points, dtype=float).reshape(-1, 3)
        out = np.zeros(len(points), dtype=bool)
        if not self.watertight:
            return out
        normals, offsets = self.hull_planes
        maybe = np.all(points @ normals.T <= offsets + HULL_PLANE_TOLERANCE_M, axis=1)  # outside the hull: outside
        if maybe.any():
            out[maybe] = np.asarray(self.trimesh.contains(points[maybe]), dtype=bool)
        return out


@dataclass(frozen=True)
class Primitive:
    """One collision shape fixed in a chain frame (index of ``kinematics.frames``).

    kind and size: ``box`` (3 edges), ``cylinder`` (radius, length; axis z), ``sphere``
    (radius,), ``capsule`` (radius, length between the caps' centres; axis z), ``mesh``
    (the edges of its oriented bounding box; the triangles in ``mesh``). T (4, 4): pose of
    the shape's frame (a mesh: of its bounding box) in the chain frame. link: the URDF link."""

    frame: int
    kind: str
    size: tuple
    T: np.ndarray
    link: str = ""
    mesh: MeshShape | None = field(default=None, compare=False)


def check_plannable(robot) -> None:
    """One ConfigError line unless the planner can handle ``robot``: at least one reflector on
    the tool (robot.yaml's, or the default triad: ``robot.with_default_reflectors()``) and
    collision geometry it can check (:func:`robot_primitives`)."""
    if len(robot.reflectors) < 1:
        raise ConfigError(f"{robot.name}: no reflector on the tool (robot.yaml 'reflectors'); planning "
                          "needs at least one to check the tracker's line of sight and the nests' cones")
    robot_primitives(robot)


def _numbers(el, attr, n, where):
    text = el.get(attr)
    try:
        v = [float(x) for x in (text or "").split()]
    except ValueError:
        v = []
    if len(v) != n or not np.all(np.isfinite(v)):
        raise ConfigError(f"{where}: <{el.tag} {attr}=\"{text}\"> must be {n} number{'s' if n > 1 else ''}")
    return v


#: bump when what :func:`_load_mesh` stores changes (the on-disk cache's entries then miss)
MESH_CACHE_VERSION = 1


def cache_dir() -> Path:
    """Where derived geometry is cached across runs: ``$CAMPAIGN_CACHE_DIR``, else
    ``$XDG_CACHE_HOME/campaign``, else ``~/.cache/campaign``."""
    import os

    if os.environ.get("CAMPAIGN_CACHE_DIR"):
        return Path(os.environ["CAMPAIGN_CACHE_DIR"])
    return Path(os.environ.get("XDG_CACHE_HOME") or Path.home() / ".cache") / "campaign"


@functools.lru_cache(maxsize=64)
def _load_mesh(path: str, scale: tuple, stamp: int):
    """(vertices (V, 3) in the mesh's oriented bounding box's frame, centred, scaled; faces (F, 3);
    watertight; the box's edges (3,); the transform (4, 4) from the mesh file's frame to the box's)
    of a mesh file. Kept in :func:`cache_dir` by the hash of the file's bytes and the scale
    (numpy's .npz, no pickle): trimesh's parsing and bounding box cost a mesh arm most of a second
    per plan. A cache that cannot be read or written is passed by."""
    import hashlib

    data = Path(path).read_bytes()
    key = hashlib.sha256(data + repr((tuple(float(x) for x in scale), MESH_CACHE_VERSION)).encode()).hexdigest()[:32]
    cached = cache_dir() / "meshes" / f"{key}.npz"
    try:
        with np.load(cached, allow_pickle=False) as z:
            return z["vertices"], z["faces"], bool(z["watertight"]), z["extents"], z["to_box"]
    except (OSError, KeyError, ValueError):
        pass
    import trimesh

    mesh = trimesh.load(path, force="mesh")
    v = np.asarray(mesh.vertices, dtype=float) * np.asarray(scale, dtype=float)
    f = np.asarray(mesh.faces, dtype=np.int64)
    watertight = bool(mesh.is_watertight)
    if len(f) == 0 or not np.all(np.isfinite(v)):
        return v, f, watertight, None, None
    to_box, extents = trimesh.bounds.oriented_bounds(v)  # mesh frame -> box frame (centred)
    v_box = v @ to_box[:3, :3].T + to_box[:3, 3]
    extents = np.asarray(extents, dtype=float)
    try:
        cached.parent.mkdir(parents=True, exist_ok=True)
        tmp = cached.with_name(f"{cached.stem}.{os.getpid()}.tmp.npz")
        np.savez(tmp, vertices=v_box, faces=f, watertight=watertight, extents=extents, to_box=to_box)
        tmp.replace(cached)
    except OSError:
        pass
    return v_box, f, watertight, extents, to_box


def _mesh_primitive(el, T, frame, link, urdf_path, where):
    """A Primitive for a ``<mesh>`` element at pose T (4, 4) of the chain frame."""
    filename = el.get("filename")
    if not filename:
        raise ConfigError(f"{where}: <mesh> without a filename")
    scale = (1.0, 1.0, 1.0)
    if el.get("scale") is not None:
        s = el.get("scale").split()
        scale = tuple(_numbers(el, "scale", 1, where) * 3) if len(s) == 1 else tuple(_numbers(el, "scale", 3, where))
    path = resolve_mesh_path(filename, urdf_path)
    if not path.is_file():
        raise ConfigError(f"{where}: collision mesh '{filename}' not found (looked for {path}); the planner "
                          "cannot check geometry it cannot load")
    try:
        v_box, f, watertight, extents, to_obb = _load_mesh(str(path.resolve()), scale, path.stat().st_mtime_ns)
    except Exception as exc:  # trimesh raises many kinds
        raise ConfigError(f"{where}: collision mesh {path} is not a readable mesh "
                          f"({str(exc).splitlines()[0] if str(exc) else exc.__class__.__name__})") from None
    if to_obb is None:
        raise ConfigError(f"{where}: collision mesh {path} is not a readable mesh (no triangles in it)")
    v_box, f = v_box.copy(), f.copy()
    extents = np.maximum(np.asarray(extents, dtype=float), MESH_MIN_EXTENT_M)
    shape = MeshShape(v_box, f, path, watertight)
    for a in (v_box, f):
        a.setflags(write=False)
    return Primitive(frame, "mesh", tuple(float(e) for e in extents), T @ np.linalg.inv(to_obb), link, shape)


@functools.lru_cache(maxsize=8)
def robot_primitives(robot) -> tuple:
    """Every link's collision geometry, in URDF order: a tuple of :class:`Primitive` in the
    chain frames (``robot.link_frames``). Geometry the planner cannot check is one
    ConfigError line naming the URDF, the link and the element or file."""
    urdf = robot.urdf_path
    try:
        root = ET.parse(urdf).getroot()
    except (OSError, ET.ParseError) as exc:
        raise ConfigError(f"{urdf}: cannot read the URDF ({exc})") from None
    frames = robot.link_frames
    out = []
    for link in root.findall("link"):
        name = link.get("name")
        if name not in frames:
            continue
        frame, T_fl = frames[name]
        identity = np.array_equal(T_fl, np.eye(4))
        for col in link.findall("collision"):
            where = f"{urdf}: link '{name}'"
            T = np.eye(4)
            origin = col.find("origin")
            if origin is not None:
                T[:3, 3] = _numbers(origin, "xyz", 3, where) if origin.get("xyz") is not None else 0.0
                T[:3, :3] = urdf_rpy(*(_numbers(origin, "rpy", 3, where) if origin.get("rpy") is not None else (0, 0, 0)))
            if not identity:
                T = T_fl @ T
            geom = col.find("geometry")
            shapes = list(geom) if geom is not None else []
            if len(shapes) != 1 or shapes[0].tag not in SUPPORTED:
                kinds = ", ".join(f"<{g.tag}>" for g in shapes) or "none"
                raise ConfigError(f"{where}: collision geometry {kinds} is not supported by the planner "
                                  f"(one of {', '.join(SUPPORTED)} per <collision>)")
            g = shapes[0]
            if g.tag == "box":
                size = tuple(_numbers(g, "size", 3, where))
            elif g.tag in ("cylinder", "capsule"):
                size = (_numbers(g, "radius", 1, where)[0], _numbers(g, "length", 1, where)[0])
            elif g.tag == "sphere":
                size = (_numbers(g, "radius", 1, where)[0],)
            else:
                out.append(_mesh_primitive(g, T, frame, name, urdf, where))
                continue
            if min(size) < 0 or size[0] <= 0 or (g.tag != "capsule" and min(size) <= 0):
                raise ConfigError(f"{where}: <{g.tag}> sizes must be positive, got {list(size)}")
            out.append(Primitive(frame, g.tag, size, T, name))
    return tuple(out)


def fcl_geometry(kind, size, mesh: MeshShape | None = None):
    """The FCL shape of a primitive (a mesh: its triangles, in its bounding box's frame)."""
    import fcl

    if kind == "box":
        return fcl.Box(*size)
    if kind == "cylinder":
        return fcl.Cylinder(size[0], size[1])
    if kind == "sphere":
        return fcl.Sphere(size[0])
    if kind == "capsule":
        return fcl.Capsule(size[0], size[1])
    if kind == "mesh":
        m = fcl.BVHModel()
        m.beginModel(len(mesh.vertices), len(mesh.faces))
        m.addSubModel(np.ascontiguousarray(mesh.vertices), np.ascontiguousarray(mesh.faces, dtype=np.int32))
        m.endModel()
        return m
    raise ValueError(kind)


def hull_geometry(mesh: MeshShape, piece: int | None = None):
    """The FCL convex hull of a mesh (in its bounding box's frame): a solid containing the mesh,
    so its distance to any shape is at most the mesh's (GJK: far cheaper than the triangles).
    piece: the hull of that piece of the mesh instead (:attr:`MeshShape.pieces`)."""
    import fcl

    v, f = mesh.hull if piece is None else mesh.pieces[piece]
    return fcl.Convex(v, len(f), np.hstack([np.full((len(f), 1), 3), f]).ravel())


def _mesh_spheres(mesh: MeshShape, size):
    """Spheres (centres (k, 3), radii (k,), in the mesh's box frame) that together contain its
    surface: the triangles, split until no edge is longer than half a piece, grouped by the
    cube of side ``piece`` of the bounding box that holds their centroid; each group's sphere
    holds every vertex of its triangles, so (being convex) the triangles themselves."""
    import trimesh

    ext = np.asarray(size, dtype=float)
    piece = max(MESH_PIECE_FRACTION * ext.min(), MESH_PIECE_MIN_M)
    try:
        v, f = trimesh.remesh.subdivide_to_size(mesh.vertices, mesh.faces, max_edge=piece / 2, max_iter=30)
    except ValueError:  # would need more than max_iter rounds: keep the triangles as they are
        v, f = np.asarray(mesh.vertices), np.asarray(mesh.faces)
    dims = np.maximum(1, np.ceil(ext / piece - 1e-9)).astype(int)
    cell = np.clip(np.floor((v[f].mean(axis=1) + 0.5 * ext) / piece).astype(int), 0, dims - 1)
    key = np.ravel_multi_index(cell.T, dims)
    order = np.argsort(key, kind="stable")
    bounds = np.flatnonzero(np.diff(key[order])) + 1
    centres, radii = [], []
    for group in np.split(order, bounds):
        pts = v[f[group]].reshape(-1, 3)
        c = 0.5 * (pts.min(axis=0) + pts.max(axis=0))
        centres.append(c)
        radii.append(np.sqrt(np.max(np.sum((pts - c) ** 2, axis=1))))
    return np.array(centres), np.array(radii)


def enclosing_spheres(kind, size, T, max_aspect: float = 1.0, mesh: MeshShape | None = None):
    """Spheres (centres in the primitive's frame (k, 3), radii (k,)) enclosing the primitive.

    A box is cut into near-cubes whose side is about its smallest edge (times ``max_aspect``),
    each inside the sphere through its corners; a cylinder into slices no taller than
    ``max_aspect`` times its radius, each inside the sphere through its rim; a capsule likewise,
    each slice inside the sphere of its radius plus half the slice; a sphere is itself; a
    mesh's surface as :func:`_mesh_spheres`.
    """
    if kind == "box":
        ext = np.asarray(size, dtype=float)
        side = max_aspect * ext.min()
        k = np.maximum(1, np.ceil(ext / side - 1e-9)).astype(int)
        piece = ext / k
        r = 0.5 * np.linalg.norm(piece)
        axes = [(np.arange(k[a]) + 0.5) * piece[a] - 0.5 * ext[a] for a in range(3)]
        c = np.stack(np.meshgrid(*axes, indexing="ij"), axis=-1).reshape(-1, 3)
    elif kind == "sphere":
        c, r = np.zeros((1, 3)), size[0]
    elif kind == "mesh":
        c, r = _mesh_spheres(mesh, size)
    else:
        radius, height = size
        k = max(1, int(np.ceil(height / (radius * max_aspect))))
        h = height / k
        r = radius + h / 2 if kind == "capsule" else np.hypot(radius, h / 2)
        c = np.zeros((k, 3))
        c[:, 2] = (np.arange(k) + 0.5) * h - 0.5 * height
    centres = c @ T[:3, :3].T + T[:3, 3]
    return centres, np.broadcast_to(np.asarray(r, dtype=float), (len(centres),)).copy()


def bounding_radius(p: Primitive) -> float:
    """Radius of one sphere about the primitive's centre that encloses it, m (the coarse level)."""
    if p.kind == "box":
        return 0.5 * np.linalg.norm(p.size)
    if p.kind == "cylinder":
        return np.hypot(p.size[0], p.size[1] / 2)
    if p.kind == "sphere":
        return p.size[0]
    if p.kind == "capsule":
        return p.size[0] + p.size[1] / 2
    return float(np.sqrt(np.max(np.sum(p.mesh.vertices ** 2, axis=1))))


@dataclass(frozen=True)
class RobotSpheres:
    frame: np.ndarray  # (S,) frame index
    centre: np.ndarray  # (S, 3) in the frame
    radius: np.ndarray  # (S,)
    primitive: np.ndarray  # (S,) index into robot_primitives
    #: one sphere per primitive (centre in its frame (P, 3), radius (P,), frame (P,)): the coarse level
    coarse_centre: np.ndarray = None
    coarse_radius: np.ndarray = None
    coarse_frame: np.ndarray = None


@functools.lru_cache(maxsize=8)
def robot_spheres(robot) -> RobotSpheres:
    frames, centres, radii, prims = [], [], [], []
    cc, cr, cf = [], [], []
    for i, p in enumerate(robot_primitives(robot)):
        c, r = enclosing_spheres(p.kind, p.size, p.T, mesh=p.mesh)
        frames += [p.frame] * len(r)
        centres.append(c)
        radii.append(r)
        prims += [i] * len(r)
        cc.append(p.T[:3, 3])
        cr.append(bounding_radius(p))
        cf.append(p.frame)
    if not cc:
        z = np.zeros(0)
        return RobotSpheres(z.astype(int), np.zeros((0, 3)), z, z.astype(int), np.zeros((0, 3)), z, z.astype(int))
    return RobotSpheres(np.array(frames), np.concatenate(centres), np.concatenate(radii), np.array(prims),
                        np.array(cc), np.array(cr), np.array(cf))


def frame_spheres(spheres: RobotSpheres, n_frames: int):
    """One sphere per frame enclosing the coarse spheres of every primitive on it: centres
    (n_frames, 3) m in their frames, radii (n_frames,) m; a frame without primitives has radius
    -inf (no pair involves it)."""
    centre, radius = np.zeros((n_frames, 3)), np.full(n_frames, -np.inf)
    for f in np.unique(spheres.coarse_frame):
        on = spheres.coarse_frame == f
        c, r = spheres.coarse_centre[on], spheres.coarse_radius[on]
        centre[f] = 0.5 * (np.min(c - r[:, None], axis=0) + np.max(c + r[:, None], axis=0))
        radius[f] = np.max(np.linalg.norm(c - centre[f], axis=1) + r)
    return centre, radius


def nominal_frames_entry_first(robot, q):
    """Frames 0..N+1 of the nominal model for joint vectors q (n, N), rad or m, entry-first:
    R (N+2, 3, 3, n), t (N+2, 3, n), m, so that each matrix entry over all poses is contiguous.

    The same frames as :func:`campaign.model.kinematics.frames` with no error parameters
    (R_k = R̄_k Rz(q_k), t_k = t̄_k; a prismatic joint: R_k = R̄_k, t_k = t̄_k + R̄_k e_z q_k),
    computed on one (n,) array per matrix entry instead of stacks of 3×3 products; several
    times faster for the motion re-check's many samples.
    """
    N = robot.n_joints
    q = np.asarray(q, dtype=float).reshape(-1, N)
    n = len(q)
    K = N + 2
    R_out = np.empty((K, 3, 3, n))
    t_out = np.empty((K, 3, n))
    R = [[1.0 if i == j else 0.0 for j in range(3)] for i in range(3)]  # entries: scalars or (n,) arrays
    t = [0.0, 0.0, 0.0]
    prismatic = robot.prismatic
    for k in range(K):
        tn, Rn = robot.t_nominal[k], robot.R_nominal[k]
        t = [t[i] + R[i][0] * tn[0] + R[i][1] * tn[1] + R[i][2] * tn[2] for i in range(3)]
        A = [[R[i][0] * Rn[0, j] + R[i][1] * Rn[1, j] + R[i][2] * Rn[2, j] for j in range(3)] for i in range(3)]
        if 1 <= k <= N and prismatic[k - 1]:
            d = q[:, k - 1]
            t = [t[i] + A[i][2] * d for i in range(3)]  # along the joint's axis, z of (R R̄_k)
        elif 1 <= k <= N:
            c, s = np.cos(q[:, k - 1]), np.sin(q[:, k - 1])
            A = [[a[0] * c + a[1] * s, a[1] * c - a[0] * s, a[2]] for a in A]  # (R R̄_k) Rz(q_k)
        R = A
        for i in range(3):
            t_out[k, i] = t[i]
            for j in range(3):
                R_out[k, i, j] = R[i][j]
    return R_out, t_out


def nominal_frames(robot, q):
    """:func:`nominal_frames_entry_first` in the layout of ``kinematics.frames``: R (n, N+2, 3, 3), t (n, N+2, 3)."""
    R, t = nominal_frames_entry_first(robot, q)
    return np.moveaxis(R, -1, 0), np.moveaxis(t, -1, 0)


def to_world(R, t, local):
    """Points fixed in a frame, in F_I, entry-first: R (3, 3, n), t (3, n), local (s, 3) → (3, s, n), m."""
    return np.stack([local @ R[i] + t[i] for i in range(3)])


def world_spheres(spheres: RobotSpheres, R, t):
    """Sphere centres in F_I for poses with frame rotations R (n, N+2, 3, 3), origins t (n, N+2, 3): (n, S, 3)."""
    Rf = R[:, spheres.frame]  # (n, S, 3, 3)
    return np.einsum("nsij,sj->nsi", Rf, spheres.centre) + t[:, spheres.frame]


def local_point_distance(local, kind, size):
    """Distance (…) from points given coordinate-first in a primitive's own frame (3, …) to
    that shape (0 inside), m. ``size`` as :class:`Primitive`'s; a mesh: to its bounding box (a
    lower bound of the distance to the mesh)."""
    if kind in ("box", "mesh"):
        d = [np.maximum(np.abs(local[k]) - 0.5 * size[k], 0.0) for k in range(3)]
        return np.sqrt(d[0] * d[0] + d[1] * d[1] + d[2] * d[2])
    if kind == "sphere":
        return np.maximum(np.sqrt(local[0] * local[0] + local[1] * local[1] + local[2] * local[2]) - size[0], 0.0)
    radius, height = size
    dz = np.maximum(np.abs(local[2]) - 0.5 * height, 0.0)
    if kind == "capsule":
        return np.maximum(np.sqrt(local[0] * local[0] + local[1] * local[1] + dz * dz) - radius, 0.0)
    dr = np.maximum(np.sqrt(local[0] * local[0] + local[1] * local[1]) - radius, 0.0)
    return np.sqrt(dr * dr + dz * dz)


def point_primitive_distance(points, kind, size, R, c):
    """Distance (…, n) from points (3, …, n) in F_I to a primitive's shape with orientation
    R (3, 3, n) or (3, 3) and centre c (3, n) or (3,) in F_I, entry-first, m."""
    if R.ndim == 2:  # a fixed primitive: broadcast its pose
        shape = (3,) + (1,) * (points.ndim - 1)
        d = points - c.reshape(shape)
        local = [d[0] * R[0, k] + d[1] * R[1, k] + d[2] * R[2, k] for k in range(3)]
    else:
        d = points - c[:, None, :] if points.ndim == 3 else points - c
        local = [d[0] * R[0, k] + d[1] * R[1, k] + d[2] * R[2, k] for k in range(3)]
    return local_point_distance(local, kind, size)


@functools.lru_cache(maxsize=8)
def joint_reach(robot) -> np.ndarray:
    """(N, N+2) m: an upper bound, over every configuration within the joint limits, on the
    distance from joint k's axis to any point of the collision shapes on frame f (0 where frame
    f does not move with joint k, or carries no shape); for a prismatic joint k, 1 where frame f
    moves with it. So a point of frame f moves at most ``sum_k |dq_k| reach[k, f]`` (m) along a
    straight joint motion dq (N,) (rad, m): the frames' chain of offsets from joint k's frame to
    f (a prismatic joint in between adds its largest extension; of the first offset, in frame k,
    only its part across joint k's axis) plus the farthest point of f's enclosing spheres from its
    origin; for the shapes that joint k turns rigidly (frame k, and
    frame N+1 with joint N), their enclosing spheres' farthest point from the axis
    (:func:`motion_displacement`)."""
    N, K = robot.n_joints, robot.n_joints + 2
    S = robot_spheres(robot)
    rho = np.full(K, -np.inf)  # farthest shape point of each frame from its origin, m
    for f in np.unique(S.frame):
        on = S.frame == f
        rho[f] = np.max(np.linalg.norm(S.centre[on], axis=1) + S.radius[on])
    t_bar = np.asarray(robot.t_nominal, dtype=float)  # t̄_l: frame l-1 to l
    extension = np.zeros(K)  # a prismatic joint's largest extension adds to its frame's offset
    extension[1 : N + 1] = np.where(robot.prismatic, np.maximum(np.abs(robot.q_lower), np.abs(robot.q_upper)), 0.0)
    step = np.linalg.norm(t_bar, axis=1) + extension
    # the first offset beyond joint k, in frame k: only its part across the axis (z) moves
    across = np.hypot(t_bar[:, 0], t_bar[:, 1]) + extension
    reach = np.zeros((N, K))
    for k in range(1, N + 1):  # joint k turns frames k..N+1 about an axis through frame k's origin
        for f in range(k, K):
            if np.isfinite(rho[f]):
                reach[k - 1, f] = 1.0 if robot.prismatic[k - 1] else \
                    (across[k + 1] + step[k + 2 : f + 1].sum() if f > k else 0.0) + rho[f]
    # the shapes joint k turns with no joint between (frame k; frame N+1 with joint N): their
    # distance from the axis itself (the z axis of frame k), a wrist's roll moves the hand little
    for k, f in [(k, k) for k in range(1, N + 1)] + [(N, N + 1)]:
        on = S.frame == f
        if robot.prismatic[k - 1] or not on.any():
            continue
        c = S.centre[on]
        if f == N + 1:  # in frame N
            c = c @ np.asarray(robot.R_nominal[N + 1], dtype=float).T + np.asarray(robot.t_nominal[N + 1], dtype=float)
        reach[k - 1, f] = np.max(np.hypot(c[:, 0], c[:, 1]) + S.radius[on])
    return reach


def motion_displacement(robot, dQ) -> np.ndarray:
    """(N+2, m) m: how far any point of each frame's collision shapes moves (at most) along each
    straight joint motion dQ (m, N) (rad, m; :func:`joint_reach`)."""
    return joint_reach(robot).T @ np.abs(np.asarray(dQ, dtype=float)).T
