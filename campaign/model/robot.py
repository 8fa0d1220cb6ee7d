"""The robot description: URDF + metadata, loaded once, never mutated.

:class:`RobotModel` reads a URDF with yourdfpy and its companion ``robot.yaml``, and
exposes the paper's chain (frames I, 0..6, E) as nominal rotations and translations,
the joint limits, the reflectors on the tool and a Pinocchio model of the same file
with gravity stated in F_I.
"""

from __future__ import annotations

import functools
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from campaign.errors import ConfigError

from campaign.paths import DEFAULT_ROBOT, ROBOT_MODELS  # noqa: F401  (re-exported)

#: Names of the eight transforms of eq. (5), in order.
TRANSFORM_NAMES = ("I0", "01", "12", "23", "34", "45", "56", "6E")


@dataclass(frozen=True)
class Reflector:
    """A spherically mounted reflector on the calibration tool.

    ``position_in_E`` in m, ``axis_in_E`` a unit vector (the nest's axis), ``half_angle``
    the acceptance half-angle in rad.
    """

    name: str
    kind: str
    position_in_E: tuple
    axis_in_E: tuple
    half_angle: float


def _read_only(a):
    a = np.array(a, dtype=float)
    a.setflags(write=False)
    return a


@dataclass(frozen=True, eq=False)
class RobotModel:
    """A serial 6R arm described by a URDF whose chain follows the paper's frames.

    Build it with :meth:`load`. Every array it returns is read-only.
    """

    name: str
    urdf_path: Path
    #: nominal rotations R̄ of the 8 transforms, (8, 3, 3)
    R_nominal: np.ndarray
    #: nominal translations t̄ of the 8 transforms in the parent frame, (8, 3), m
    t_nominal: np.ndarray
    #: joint limits, (6,) each, rad
    q_lower: np.ndarray
    q_upper: np.ndarray
    joint_names: tuple
    link_names: tuple
    gravity_in_I: np.ndarray
    max_velocity: np.ndarray
    max_acceleration: np.ndarray
    max_jerk: np.ndarray
    reflectors: tuple

    @classmethod
    def load(cls, name_or_path: str | Path = DEFAULT_ROBOT) -> "RobotModel":
        """Load a robot folder (name under ``robot_models/`` or a path) holding ``robot.yaml``."""
        folder = Path(name_or_path)
        if not folder.is_dir():
            folder = ROBOT_MODELS / str(name_or_path)
        meta_path = folder / "robot.yaml"
        if not meta_path.is_file():
            raise ConfigError(f"{meta_path}: robot description not found (expected robot.yaml beside a URDF)")
        return _load_cached(str(meta_path.resolve()))

    @functools.cached_property
    def urdf(self):
        """The yourdfpy ``URDF`` of this robot (loaded on first use)."""
        import yourdfpy

        return yourdfpy.URDF.load(str(self.urdf_path), load_meshes=False, build_scene_graph=True)

    @functools.cached_property
    def pinocchio_model(self):
        """A Pinocchio model of the same URDF, with ``gravity`` set from ``robot.yaml``."""
        import pinocchio as pin

        model = pin.buildModelFromUrdf(str(self.urdf_path))
        model.gravity.linear = np.array(self.gravity_in_I, dtype=float)
        return model

    @property
    def reflector_positions_in_E(self) -> np.ndarray:
        """(3, 3): row j is reflector j's centre in F_E, m."""
        return _read_only([r.position_in_E for r in self.reflectors])

    @property
    def q_mid(self) -> np.ndarray:
        return _read_only(0.5 * (self.q_lower + self.q_upper))

    def check_joints(self, q, *, field: str = "q", slack: float = 0.0) -> np.ndarray:
        """Validate joint vectors; return them as float64 (n, 6).

        Raises :class:`campaign.errors.DataError` naming the row, the joint, the value
        and the limit.
        """
        from campaign.errors import DataError

        q = np.asarray(q, dtype=float)
        if q.ndim == 1:
            q = q[None, :]
        if q.ndim != 2 or q.shape[1] != 6:
            raise DataError(f"{field}: expected shape (n, 6), got {q.shape}")
        bad = ~np.isfinite(q)
        if bad.any():
            i, j = np.argwhere(bad)[0]
            raise DataError(f"{field}: row {i}, q{j + 1} is {q[i, j]} (not a finite number)")
        lo = q < self.q_lower - slack
        hi = q > self.q_upper + slack
        if lo.any() or hi.any():
            i, j = np.argwhere(lo | hi)[0]
            lim = self.q_lower[j] if lo[i, j] else self.q_upper[j]
            raise DataError(
                f"{field}: row {i}, q{j + 1} = {q[i, j]:.6g} rad is outside the joint limit {lim:.6g} rad"
            )
        return q


@functools.lru_cache(maxsize=8)
def _load_cached(meta_path: str) -> RobotModel:
    from campaign.fileio import read_yaml_mapping
    from campaign.model.rotations import urdf_rpy

    meta_file = Path(meta_path)
    meta = read_yaml_mapping(meta_file)
    required = ("urdf", "chain", "gravity_in_I_m_s2", "reflectors", "max_velocity_rad_s",
                "max_acceleration_rad_s2", "max_jerk_rad_s3")
    for key in required:
        if key not in meta:
            raise ConfigError(f"{meta_file}: missing field '{key}'")
    urdf_path = meta_file.parent / meta["urdf"]
    if not urdf_path.is_file():
        raise ConfigError(f"{meta_file}: field 'urdf' names {urdf_path}, which does not exist")

    import xml.etree.ElementTree as ET

    try:
        root = ET.parse(urdf_path).getroot()
    except ET.ParseError as exc:
        raise ConfigError(f"{urdf_path}: not valid XML ({exc})") from None
    joints = {j.get("name"): j for j in root.findall("joint")}
    chain = list(meta["chain"])
    if len(chain) != 8:
        raise ConfigError(f"{meta_file}: field 'chain' must list 8 joints (I0, joint1..joint6, 6E), got {len(chain)}")
    R_nom, t_nom, lower, upper, jnames, links = [], [], [], [], [], []
    for k, jname in enumerate(chain):
        if jname not in joints:
            raise ConfigError(f"{meta_file}: chain joint '{jname}' is not in {urdf_path.name}")
        j = joints[jname]
        origin = j.find("origin")
        xyz = [float(v) for v in (origin.get("xyz", "0 0 0") if origin is not None else "0 0 0").split()]
        rpy = [float(v) for v in (origin.get("rpy", "0 0 0") if origin is not None else "0 0 0").split()]
        R_nom.append(urdf_rpy(*rpy))
        t_nom.append(xyz)
        jtype = j.get("type")
        moving = 1 <= k <= 6
        if moving != (jtype in ("revolute", "continuous")):
            raise ConfigError(f"{urdf_path}: joint '{jname}' has type '{jtype}', "
                              f"expected {'revolute' if moving else 'fixed'} at chain position {k}")
        if moving:
            axis = j.find("axis")
            ax = [float(v) for v in axis.get("xyz").split()] if axis is not None else [1.0, 0, 0]
            if not np.allclose(ax, [0, 0, 1]):
                raise ConfigError(f"{urdf_path}: joint '{jname}' axis is {ax}; the paper's chain needs z (0 0 1)")
            lim = j.find("limit")
            if lim is None:
                raise ConfigError(f"{urdf_path}: joint '{jname}' has no <limit>")
            lower.append(float(lim.get("lower")))
            upper.append(float(lim.get("upper")))
            jnames.append(jname)
        links.append(j.find("child").get("link"))

    link_of_joint = {j.get("name"): j.find("child").get("link") for j in joints.values()}
    parent_of_link = {j.find("child").get("link"): (j.find("parent").get("link"), j) for j in joints.values()}
    reflectors = []
    for r in meta["reflectors"]:
        for key in ("name", "link", "axis_in_E", "half_angle_deg"):
            if key not in r:
                raise ConfigError(f"{meta_file}: a reflector lacks field '{key}'")
        if r["link"] not in parent_of_link or parent_of_link[r["link"]][0] != "E":
            raise ConfigError(f"{meta_file}: reflector '{r['name']}' link '{r['link']}' is not a child of link E")
        origin = parent_of_link[r["link"]][1].find("origin")
        pos = tuple(float(v) for v in origin.get("xyz").split())
        axis = np.asarray(r["axis_in_E"], dtype=float)
        axis = axis / np.linalg.norm(axis)
        reflectors.append(Reflector(r["name"], r.get("kind", "smr"), pos, tuple(axis),
                                    float(np.deg2rad(r["half_angle_deg"]))))
    if len(reflectors) != 3:
        raise ConfigError(f"{meta_file}: the calibration tool needs exactly 3 reflectors, got {len(reflectors)}")
    if links[-1] != "E":
        raise ConfigError(f"{urdf_path}: the chain must end in a link named 'E', ends in '{links[-1]}'")
    del link_of_joint

    def vec6(key):
        v = np.asarray(meta[key], dtype=float)
        if v.shape != (6,) or np.any(v <= 0):
            raise ConfigError(f"{meta_file}: field '{key}' must be 6 positive numbers")
        return _read_only(v)

    return RobotModel(
        name=str(meta.get("name", meta_file.parent.name)),
        urdf_path=urdf_path,
        R_nominal=_read_only(np.stack(R_nom)),
        t_nominal=_read_only(t_nom),
        q_lower=_read_only(lower),
        q_upper=_read_only(upper),
        joint_names=tuple(jnames),
        link_names=tuple(["I"] + links),
        gravity_in_I=_read_only(meta["gravity_in_I_m_s2"]),
        max_velocity=vec6("max_velocity_rad_s"),
        max_acceleration=vec6("max_acceleration_rad_s2"),
        max_jerk=vec6("max_jerk_rad_s3"),
        reflectors=tuple(reflectors),
    )
