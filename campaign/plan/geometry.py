"""Collision geometry of the robot (from the URDF) and the scene, for FCL and for bounds.

Two representations of the same primitives:

* FCL objects (python-fcl) for exact distances;
* enclosing spheres (each box or cylinder cut along its long axis into pieces, each piece
  inside one sphere) for vectorised, conservative lower bounds: if the spheres are clear by
  d, the real geometry is clear by at least d.
"""

from __future__ import annotations

import functools
import xml.etree.ElementTree as ET
from dataclasses import dataclass

import numpy as np

from campaign.model.rotations import urdf_rpy

#: frame index of each URDF link in campaign.model.kinematics.frames (0 = F_0, ..., 7 = F_E)
LINK_FRAME = {"link0": 0, "link1": 1, "link2": 2, "link3": 3, "link4": 4, "link5": 5, "link6": 6, "E": 7}


@dataclass(frozen=True)
class Primitive:
    """A box (size = 3 edges) or cylinder (size = radius, height; axis z) fixed in a frame."""

    frame: int
    kind: str
    size: tuple
    T: np.ndarray  # pose in its frame (4, 4)


def check_plannable(robot) -> None:
    """One ConfigError line unless the planner can handle ``robot``: today six revolute joints
    whose links carry the paper's names (link0..link6, E), at least three reflectors on the tool,
    and collision geometry of boxes and cylinders only (issue 12, item 9 is not done)."""
    from campaign.errors import ConfigError

    names = tuple(robot.link_names[1:])
    if robot.n_joints != 6 or any(t != "revolute" for t in robot.joint_types) or set(names) != set(LINK_FRAME):
        raise ConfigError(f"plan: {robot.name} ({robot.n_joints} joints, links {', '.join(names)}): planning "
                          "supports only 6R arms whose chain links are named link0..link6, E (as the COMAU's) for "
                          "now; measure another robot with your own tooling and `campaign import` the CSV")
    if len(robot.reflectors) < 3:
        raise ConfigError(f"plan: {robot.name}: robot.yaml names {len(robot.reflectors)} reflectors; planning needs "
                          "three on the tool")
    robot_primitives(robot)


def robot_primitives(robot) -> tuple:
    """The URDF's collision primitives of links link0..link6 and E (boxes and cylinders; any
    other collision geometry of those links is one ConfigError line, never dropped)."""
    root = ET.parse(robot.urdf_path).getroot()
    out = []
    for link in root.findall("link"):
        name = link.get("name")
        if name not in LINK_FRAME:
            continue
        for col in link.findall("collision"):
            T = np.eye(4)
            origin = col.find("origin")
            if origin is not None:
                T[:3, 3] = [float(v) for v in origin.get("xyz", "0 0 0").split()]
                T[:3, :3] = urdf_rpy(*[float(v) for v in origin.get("rpy", "0 0 0").split()])
            geom = col.find("geometry")
            box, cyl = geom.find("box"), geom.find("cylinder")
            if box is not None:
                out.append(Primitive(LINK_FRAME[name], "box", tuple(float(v) for v in box.get("size").split()), T))
            elif cyl is not None:
                out.append(Primitive(LINK_FRAME[name], "cylinder",
                                     (float(cyl.get("radius")), float(cyl.get("length"))), T))
            else:
                from campaign.errors import ConfigError

                kinds = ", ".join(f"<{g.tag}>" for g in geom) if geom is not None else "none"
                raise ConfigError(f"{robot.urdf_path}: link '{name}': collision geometry {kinds} is not supported by "
                                  "the planner (boxes and cylinders only)")
    return tuple(out)


def fcl_geometry(kind, size):
    import fcl

    if kind == "box":
        return fcl.Box(*size)
    if kind == "cylinder":
        return fcl.Cylinder(size[0], size[1])
    raise ValueError(kind)


def enclosing_spheres(kind, size, T, max_aspect: float = 1.0):
    """Spheres (centres in the primitive's frame (k, 3), radii (k,)) enclosing the primitive.

    A box is cut into near-cubes whose side is about its smallest edge (times ``max_aspect``),
    each inside the sphere through its corners; a cylinder into slices no taller than
    ``max_aspect`` times its radius, each inside the sphere through its rim.
    """
    if kind == "box":
        ext = np.asarray(size, dtype=float)
        side = max_aspect * ext.min()
        k = np.maximum(1, np.ceil(ext / side - 1e-9)).astype(int)
        piece = ext / k
        r = 0.5 * np.linalg.norm(piece)
        axes = [(np.arange(k[a]) + 0.5) * piece[a] - 0.5 * ext[a] for a in range(3)]
        c = np.stack(np.meshgrid(*axes, indexing="ij"), axis=-1).reshape(-1, 3)
    else:
        radius, height = size
        k = max(1, int(np.ceil(height / (radius * max_aspect))))
        h = height / k
        r = np.hypot(radius, h / 2)
        c = np.zeros((k, 3))
        c[:, 2] = (np.arange(k) + 0.5) * h - 0.5 * height
    centres = c @ T[:3, :3].T + T[:3, 3]
    return centres, np.full(len(centres), r)


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


@functools.lru_cache(maxsize=4)
def robot_spheres(robot) -> RobotSpheres:
    frames, centres, radii, prims = [], [], [], []
    cc, cr, cf = [], [], []
    for i, p in enumerate(robot_primitives(robot)):
        c, r = enclosing_spheres(p.kind, p.size, p.T)
        frames += [p.frame] * len(r)
        centres.append(c)
        radii.append(r)
        prims += [i] * len(r)
        cc.append(p.T[:3, 3])
        cr.append(0.5 * np.linalg.norm(p.size) if p.kind == "box" else np.hypot(p.size[0], p.size[1] / 2))
        cf.append(p.frame)
    return RobotSpheres(np.array(frames), np.concatenate(centres), np.concatenate(radii), np.array(prims),
                        np.array(cc), np.array(cr), np.array(cf))


def nominal_frames_entry_first(robot, q):
    """Frames 0..7 of the nominal model for joint vectors q (n, 6), rad, entry-first:
    R (8, 3, 3, n), t (8, 3, n), m, so that each matrix entry over all poses is contiguous.

    The same frames as :func:`campaign.model.kinematics.frames` with no error parameters
    (R_k = R̄_k Rz(q_k), t_k = t̄_k), computed on one (n,) array per matrix entry instead of
    stacks of 3×3 products; several times faster for the motion re-check's many samples.
    """
    q = np.asarray(q, dtype=float).reshape(-1, 6)
    n = len(q)
    R_out = np.empty((8, 3, 3, n))
    t_out = np.empty((8, 3, n))
    R = [[1.0 if i == j else 0.0 for j in range(3)] for i in range(3)]  # entries: scalars or (n,) arrays
    t = [0.0, 0.0, 0.0]
    for k in range(8):
        tn, Rn = robot.t_nominal[k], robot.R_nominal[k]
        t = [t[i] + R[i][0] * tn[0] + R[i][1] * tn[1] + R[i][2] * tn[2] for i in range(3)]
        A = [[R[i][0] * Rn[0, j] + R[i][1] * Rn[1, j] + R[i][2] * Rn[2, j] for j in range(3)] for i in range(3)]
        if 1 <= k <= 6:
            c, s = np.cos(q[:, k - 1]), np.sin(q[:, k - 1])
            A = [[a[0] * c + a[1] * s, a[1] * c - a[0] * s, a[2]] for a in A]  # (R R̄_k) Rz(q_k)
        R = A
        for i in range(3):
            t_out[k, i] = t[i]
            for j in range(3):
                R_out[k, i, j] = R[i][j]
    return R_out, t_out


def nominal_frames(robot, q):
    """:func:`nominal_frames_entry_first` in the layout of ``kinematics.frames``: R (n, 8, 3, 3), t (n, 8, 3)."""
    R, t = nominal_frames_entry_first(robot, q)
    return np.moveaxis(R, -1, 0), np.moveaxis(t, -1, 0)


def to_world(R, t, local):
    """Points fixed in a frame, in F_I, entry-first: R (3, 3, n), t (3, n), local (s, 3) → (3, s, n), m."""
    return np.stack([local @ R[i] + t[i] for i in range(3)])


def world_spheres(spheres: RobotSpheres, R, t):
    """Sphere centres in F_I for poses with frame rotations R (n, 8, 3, 3), origins t (n, 8, 3): (n, S, 3)."""
    Rf = R[:, spheres.frame]  # (n, S, 3, 3)
    return np.einsum("nsij,sj->nsi", Rf, spheres.centre) + t[:, spheres.frame]


def local_point_distance(local, kind, size):
    """Distance (…) from points given coordinate-first in a primitive's own frame (3, …) to
    that box or cylinder (0 inside), m. ``size``: box edges, or (radius, height), axis z."""
    if kind == "box":
        d = [np.maximum(np.abs(local[k]) - 0.5 * size[k], 0.0) for k in range(3)]
        return np.sqrt(d[0] * d[0] + d[1] * d[1] + d[2] * d[2])
    radius, height = size
    dr = np.maximum(np.sqrt(local[0] * local[0] + local[1] * local[1]) - radius, 0.0)
    dz = np.maximum(np.abs(local[2]) - 0.5 * height, 0.0)
    return np.sqrt(dr * dr + dz * dz)


def point_primitive_distance(points, kind, size, R, c):
    """Distance (…, n) from points (3, …, n) in F_I to a box or cylinder with orientation
    R (3, 3, n) or (3, 3) and centre c (3, n) or (3,) in F_I, entry-first, m."""
    if R.ndim == 2:  # a fixed primitive: broadcast its pose
        shape = (3,) + (1,) * (points.ndim - 1)
        d = points - c.reshape(shape)
        local = [d[0] * R[0, k] + d[1] * R[1, k] + d[2] * R[2, k] for k in range(3)]
    else:
        d = points - c[:, None, :] if points.ndim == 3 else points - c
        local = [d[0] * R[0, k] + d[1] * R[1, k] + d[2] * R[2, k] for k in range(3)]
    return local_point_distance(local, kind, size)
