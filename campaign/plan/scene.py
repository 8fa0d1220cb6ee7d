"""The cell: obstacles, the wall, the tracker, where the robot stands. Loaded from YAML,
validated, immutable.

Every error names the file and the field. Positions are in the cell's frame, m: the frame
the file is written in. ``down`` says which way gravity points in it (default ``[0, 1, 0]``:
the default cell's frame is the COMAU's F_I, y vertical, up = -y). ``robot_base`` places the
robot's base frame F_I in the cell (``position_m``, ``rotation_cardan_deg``); by default the
base stands at the cell's origin, turned by the smallest rotation that takes the robot's
gravity (robot.yaml's, default −z of the URDF's root) onto ``down`` — the identity for the
COMAU in the default cell, so its cell frame is its F_I. :meth:`Scene.placed` gives the cell
in a robot's F_I, where every check of the plan works.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np
import yaml

from campaign.errors import ConfigError
from campaign.model.rotations import cardan_xyz

_TOP_KEYS = {"name", "obstacles", "tracker", "wall", "down", "robot_base"}
_BASE_KEYS = {"position_m", "rotation_cardan_deg"}
#: gravity in the default cell's frame (the COMAU's F_I: up is -y)
DEFAULT_DOWN = (0.0, 1.0, 0.0)
_TRACKER_KEYS = {"position_m", "rotation_cardan_deg", "min_range_m", "max_range_m", "beam_radius_m"}
_WALL_KEYS = {"obstacle", "normal_in_I", "offset_m"}


@dataclass(frozen=True)
class Obstacle:
    """A box (``size`` = (x, y, z) edge lengths) or a cylinder (``size`` = (radius, height))
    whose axis is z of its frame; ``T_I`` is its pose in F_I (4, 4)."""

    name: str
    kind: str
    size: tuple
    T_I: np.ndarray


@dataclass(frozen=True)
class Scene:
    """A cell. As loaded, positions are in the cell's frame; :meth:`placed` expresses them in a
    robot's base frame F_I (``T_cell_I`` then holds where that robot stands)."""

    path: Path
    name: str
    obstacles: tuple
    #: pose of the tracker frame F_L in F_I (4, 4)
    T_IL: np.ndarray
    min_range_m: float
    max_range_m: float
    beam_radius_m: float
    wall_name: str
    wall_normal: np.ndarray
    wall_offset_m: float
    #: gravity's direction in the cell's frame (3,), unit
    down: np.ndarray = None
    #: the file's robot_base: position (3,) m and rotation (3, 3) or None (from gravity), or None
    robot_base: tuple | None = None
    #: pose of the robot's base frame F_I in the cell's frame (4, 4): identity until placed
    T_cell_I: np.ndarray = None
    #: the robot this scene is placed for (None: in the cell's frame)
    placed_for: str | None = None

    def base_pose(self, robot) -> np.ndarray:
        """Pose (4, 4) of ``robot``'s base frame F_I in the cell's frame: the file's
        ``robot_base``, its rotation by default the smallest one taking the robot's gravity onto
        ``down``."""
        position, rotation = self.robot_base if self.robot_base is not None else (np.zeros(3), None)
        T = np.eye(4)
        if rotation is None:
            g = np.asarray(robot.gravity_in_I, dtype=float)
            norm = np.linalg.norm(g)
            rotation = np.eye(3) if norm == 0 else rotation_between(g / norm, self.down)
        T[:3, :3] = rotation
        T[:3, 3] = position
        return T

    def placed(self, robot) -> "Scene":
        """This cell in ``robot``'s base frame F_I (positions, tracker pose, wall plane), with
        ``T_cell_I`` = :meth:`base_pose`. The scene itself when the robot stands at the cell's
        origin unturned (the default COMAU in the default cell)."""
        import dataclasses

        if self.placed_for is not None:
            raise ValueError(f"{self.path}: already placed for {self.placed_for}")
        T = self.base_pose(robot)
        if np.array_equal(T, np.eye(4)):
            return dataclasses.replace(self, placed_for=robot.name)
        T_I_cell = np.eye(4)
        T_I_cell[:3, :3] = T[:3, :3].T
        T_I_cell[:3, 3] = -T[:3, :3].T @ T[:3, 3]
        obstacles = tuple(dataclasses.replace(o, T_I=_frozen(T_I_cell @ o.T_I)) for o in self.obstacles)
        normal = T_I_cell[:3, :3] @ self.wall_normal
        # the plane n·x_cell = offset, with x_cell = R x_I + p
        offset = self.wall_offset_m - float(self.wall_normal @ T[:3, 3])
        return dataclasses.replace(self, obstacles=obstacles, T_IL=_frozen(T_I_cell @ self.T_IL),
                                   wall_normal=_frozen(normal), wall_offset_m=offset, T_cell_I=_frozen(T),
                                   placed_for=robot.name)

    @property
    def T_LI(self) -> np.ndarray:
        from campaign.measure.reflectors import invert

        return invert(self.T_IL)

    @property
    def tracker_position(self) -> np.ndarray:
        return self.T_IL[:3, 3]

    def side_of_wall(self, points) -> np.ndarray:
        """True where points (n, 3) lie in front of the wall (the tracker's side)."""
        return np.asarray(points) @ self.wall_normal > self.wall_offset_m


def _frozen(a) -> np.ndarray:
    a = np.array(a, dtype=float)
    a.setflags(write=False)
    return a


def rotation_between(u, v) -> np.ndarray:
    """The smallest rotation (3, 3) taking unit vector u onto unit vector v (identity when they
    are equal; half a turn about an axis perpendicular to u when they are opposite)."""
    u, v = np.asarray(u, dtype=float), np.asarray(v, dtype=float)
    if np.allclose(u, v, atol=1e-12):
        return np.eye(3)
    from campaign.model.rotations import rotvec_to_matrix

    axis = np.cross(u, v)
    s = np.linalg.norm(axis)
    if s < 1e-12:  # opposite: any perpendicular axis, the one along the least aligned coordinate axis
        e = np.eye(3)[int(np.argmin(np.abs(u)))]
        axis = np.cross(u, e)
        return rotvec_to_matrix(np.pi * axis / np.linalg.norm(axis))
    return rotvec_to_matrix(axis / s * np.arctan2(s, float(u @ v)))


def _vec(value, n, where):
    try:
        v = np.asarray(value, dtype=float)
    except (TypeError, ValueError):
        raise ConfigError(f"{where}: expected {n} numbers, got {value!r}") from None
    if v.shape != (n,) or not np.all(np.isfinite(v)):
        raise ConfigError(f"{where}: expected {n} finite numbers, got {value!r}")
    return v


def _positive(value, where):
    try:
        v = float(value)
    except (TypeError, ValueError):
        raise ConfigError(f"{where}: expected a number, got {value!r}") from None
    if not np.isfinite(v) or v <= 0:
        raise ConfigError(f"{where}: must be positive, got {value!r}")
    return v


def _unknown(d, allowed, where):
    extra = sorted(set(d) - set(allowed))
    if extra:
        raise ConfigError(f"{where}: unknown key '{extra[0]}' (allowed: {', '.join(sorted(allowed))})")


def _missing(d, required, where):
    for key in required:
        if key not in d:
            raise ConfigError(f"{where}: missing field '{key}'")


def load_scene(path) -> Scene:
    """Read and validate a scene YAML file."""
    path = Path(path)
    try:
        doc = yaml.safe_load(path.read_text())
    except OSError as exc:
        raise ConfigError(f"{path}: cannot read the scene ({exc.strerror})") from None
    except yaml.YAMLError as exc:
        raise ConfigError(f"{path}: not valid YAML ({str(exc).splitlines()[0]})") from None
    if not isinstance(doc, dict):
        raise ConfigError(f"{path}: expected a mapping at the top level")
    _unknown(doc, _TOP_KEYS, str(path))
    _missing(doc, ("obstacles", "tracker", "wall"), str(path))
    obstacles = []
    if not isinstance(doc["obstacles"], list) or not doc["obstacles"]:
        raise ConfigError(f"{path}: obstacles: expected a non-empty list")
    names = set()
    for i, o in enumerate(doc["obstacles"]):
        where = f"{path}: obstacles[{i}]"
        if not isinstance(o, dict):
            raise ConfigError(f"{where}: expected a mapping")
        _unknown(o, {"name", "box", "cylinder", "mesh"}, where)
        _missing(o, ("name",), where)
        name = str(o["name"])
        where = f"{path}: obstacle '{name}'"
        if name in names:
            raise ConfigError(f"{where}: duplicate name")
        names.add(name)
        shapes = [k for k in ("box", "cylinder", "mesh") if k in o]
        if len(shapes) != 1:
            raise ConfigError(f"{where}: give exactly one of box, cylinder, mesh")
        kind = shapes[0]
        spec = o[kind]
        if not isinstance(spec, dict):
            raise ConfigError(f"{where}.{kind}: expected a mapping")
        T = np.eye(4)
        if kind == "box":
            _unknown(spec, {"center_m", "size_m", "rotation_cardan_deg"}, f"{where}.box")
            _missing(spec, ("center_m", "size_m"), f"{where}.box")
            T[:3, 3] = _vec(spec["center_m"], 3, f"{where}.box.center_m")
            size = _vec(spec["size_m"], 3, f"{where}.box.size_m")
            if np.any(size <= 0):
                raise ConfigError(f"{where}.box.size_m: sizes must be positive")
            if "rotation_cardan_deg" in spec:
                T[:3, :3] = cardan_xyz(*np.deg2rad(_vec(spec["rotation_cardan_deg"], 3, f"{where}.box.rotation_cardan_deg")))
            obstacles.append(Obstacle(name, "box", tuple(size), T))
        elif kind == "cylinder":
            _unknown(spec, {"center_m", "radius_m", "height_m", "axis"}, f"{where}.cylinder")
            _missing(spec, ("center_m", "radius_m", "height_m"), f"{where}.cylinder")
            T[:3, 3] = _vec(spec["center_m"], 3, f"{where}.cylinder.center_m")
            axis = str(spec.get("axis", "z"))
            if axis not in ("x", "y", "z"):
                raise ConfigError(f"{where}.cylinder.axis: must be x, y or z, not {axis!r}")
            # FCL's cylinder axis is z: rotate z onto the requested axis
            T[:3, :3] = {"x": cardan_xyz(0, np.pi / 2, 0), "y": cardan_xyz(-np.pi / 2, 0, 0), "z": np.eye(3)}[axis]
            obstacles.append(Obstacle(name, "cylinder", (_positive(spec["radius_m"], f"{where}.cylinder.radius_m"),
                                                         _positive(spec["height_m"], f"{where}.cylinder.height_m")), T))
        else:
            _unknown(spec, {"file", "center_m"}, f"{where}.mesh")
            _missing(spec, ("file",), f"{where}.mesh")
            mesh_path = (path.parent / str(spec["file"])).resolve()
            if not mesh_path.is_file():
                raise ConfigError(f"{where}.mesh.file: {mesh_path} does not exist")
            import trimesh

            try:
                mesh = trimesh.load(str(mesh_path), force="mesh")
            except Exception as exc:  # trimesh raises many kinds
                raise ConfigError(f"{where}.mesh.file: {mesh_path} is not a readable mesh ({exc})") from None
            if "center_m" in spec:
                T[:3, 3] = _vec(spec["center_m"], 3, f"{where}.mesh.center_m")
            # conservative: the mesh's oriented bounding box stands for it
            obb = mesh.bounding_box_oriented
            T = T @ np.asarray(obb.primitive.transform)
            obstacles.append(Obstacle(name, "box", tuple(np.asarray(obb.primitive.extents, dtype=float)), T))

    tr = doc["tracker"]
    if not isinstance(tr, dict):
        raise ConfigError(f"{path}: tracker: expected a mapping")
    _unknown(tr, _TRACKER_KEYS, f"{path}: tracker")
    _missing(tr, ("position_m", "rotation_cardan_deg", "min_range_m", "max_range_m"), f"{path}: tracker")
    T_IL = np.eye(4)
    T_IL[:3, 3] = _vec(tr["position_m"], 3, f"{path}: tracker.position_m")
    T_IL[:3, :3] = cardan_xyz(*np.deg2rad(_vec(tr["rotation_cardan_deg"], 3, f"{path}: tracker.rotation_cardan_deg")))
    rmin = _positive(tr["min_range_m"], f"{path}: tracker.min_range_m")
    rmax = _positive(tr["max_range_m"], f"{path}: tracker.max_range_m")
    if rmax <= rmin:
        raise ConfigError(f"{path}: tracker.max_range_m must exceed min_range_m")
    beam = _positive(tr.get("beam_radius_m", 0.004), f"{path}: tracker.beam_radius_m")

    wall = doc["wall"]
    if not isinstance(wall, dict):
        raise ConfigError(f"{path}: wall: expected a mapping")
    _unknown(wall, _WALL_KEYS, f"{path}: wall")
    _missing(wall, ("obstacle", "normal_in_I", "offset_m"), f"{path}: wall")
    if wall["obstacle"] not in names:
        raise ConfigError(f"{path}: wall.obstacle: no obstacle named '{wall['obstacle']}'")
    normal = _vec(wall["normal_in_I"], 3, f"{path}: wall.normal_in_I")
    if np.linalg.norm(normal) < 1e-9:
        raise ConfigError(f"{path}: wall.normal_in_I must not be zero")
    down = _vec(doc.get("down", DEFAULT_DOWN), 3, f"{path}: down")
    if np.linalg.norm(down) < 1e-9:
        raise ConfigError(f"{path}: down must not be zero (gravity's direction in the cell's frame)")
    base = None
    if doc.get("robot_base") is not None:
        rb = doc["robot_base"]
        if not isinstance(rb, dict):
            raise ConfigError(f"{path}: robot_base: expected a mapping (position_m, rotation_cardan_deg)")
        _unknown(rb, _BASE_KEYS, f"{path}: robot_base")
        position = _vec(rb.get("position_m", [0, 0, 0]), 3, f"{path}: robot_base.position_m")
        rotation = None
        if "rotation_cardan_deg" in rb:
            rotation = cardan_xyz(*np.deg2rad(_vec(rb["rotation_cardan_deg"], 3,
                                                   f"{path}: robot_base.rotation_cardan_deg")))
        base = (position, rotation)
    for a in (T_IL,):
        a.setflags(write=False)
    return Scene(path, str(doc.get("name", path.stem)), tuple(obstacles), T_IL, rmin, rmax, beam,
                 str(wall["obstacle"]), normal / np.linalg.norm(normal), float(wall["offset_m"]),
                 _frozen(down / np.linalg.norm(down)), base, _frozen(np.eye(4)))
