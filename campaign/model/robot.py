"""The robot description: a serial chain of a URDF (+ optional ``robot.yaml``), loaded once.

:meth:`RobotModel.load` accepts a name under ``campaign/data/robot_models/``, a path to a
URDF, or a path to a ``robot.yaml`` (or its folder) naming its URDF. The URDF is parsed once
with yourdfpy. The chain runs from the root link (or ``base_frame``) to ``tool_frame``
(default: walking down from the base while a link has exactly one child joint, the link
where the walk stops: a leaf or a branch; for the COMAU, link ``E``).

The chain is cut into N + 2 transforms, the paper's eq. (5) generalised:

    T_IE = T_base · A_1(q_1) · A_2(q_2) · ... · A_N(q_N) · T_tool

* ``T_base``: the fixed joints from the base to the parent link of moving joint 1;
* ``A_j``: the fixed joints between moving joint j-1 and j, then joint j's origin; its
  motion is ``Rz(q_j)`` (revolute, continuous) or a translation ``q_j`` along z
  (prismatic), in a *model frame* whose z is the joint's axis: if the URDF axis ``u`` is not
  ``+z``, the child link frame is rotated by a constant ``S_j`` with ``S_j z = u`` (so the
  model frame of joint j is ``link_j · S_j``), and ``S_j^T`` is folded into the next
  transform;
* ``T_tool``: the fixed joints from the last moving joint's child link to the tool frame.

Joints outside the chain (fingers, other branches) are locked at 0 or at ``robot.yaml``'s
``locked_joints``; a moving joint of the chain named there is locked too (folded as fixed).
Every array this module returns is read-only. SI units: m, rad, s.
"""

from __future__ import annotations

import functools
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from campaign.errors import ConfigError
from campaign.paths import DEFAULT_ROBOT, ROBOT_MODELS  # noqa: F401  (re-exported)

#: Names of the eight transforms of eq. (5) of the default 6R robot, in order.
TRANSFORM_NAMES = ("I0", "01", "12", "23", "34", "45", "56", "6E")

#: Default gravity in the base frame, m/s² (−z of the root).
DEFAULT_GRAVITY = (0.0, 0.0, -9.81)


@dataclass(frozen=True)
class Reflector:
    """A spherically mounted reflector on the calibration tool.

    ``position_in_E`` in m (tool frame), ``axis_in_E`` a unit vector (the nest's axis),
    ``half_angle`` the acceptance half-angle in rad.
    """

    name: str
    kind: str
    position_in_E: tuple
    axis_in_E: tuple
    half_angle: float


#: Reflectors assumed on the tool of a robot whose robot.yaml names none (planning, `campaign run`, the
#: simulated cell): a 5 cm triad in the tool frame (enough for a pose by Kabsch), every nest facing the
#: tool frame's +z with robot.yaml's default acceptance half-angle (30°).
DEFAULT_REFLECTOR_POSITIONS = ((0.05, 0.0, 0.0), (0.0, 0.05, 0.0), (0.0, 0.0, 0.05))
DEFAULT_HALF_ANGLE_DEG = 30.0
DEFAULT_REFLECTORS = tuple(Reflector(f"m{i + 1}", "smr", p, (0.0, 0.0, 1.0), float(np.deg2rad(DEFAULT_HALF_ANGLE_DEG)))
                           for i, p in enumerate(DEFAULT_REFLECTOR_POSITIONS))
#: the default triad of a robot whose tool frame carries a hand sits this far (m) beyond the
#: reflectors' spheres' clearance of the hand's farthest point along +z: a centimetre of bracket
DEFAULT_REFLECTOR_GAP_M = 0.01


def default_reflectors(lift_m: float = 0.0) -> tuple:
    """:data:`DEFAULT_REFLECTORS`, moved ``lift_m`` (m) along the tool frame's +z."""
    if lift_m == 0.0:
        return DEFAULT_REFLECTORS
    return tuple(Reflector(r.name, r.kind, (r.position_in_E[0], r.position_in_E[1], r.position_in_E[2] + float(lift_m)),
                           r.axis_in_E, r.half_angle) for r in DEFAULT_REFLECTORS)


def _read_only(a):
    a = np.array(a, dtype=float)
    a.setflags(write=False)
    return a


def transform_names(n_joints: int) -> tuple:
    """Names of the N + 2 transforms: ``I0``, ``01`` .. ``(N-1)N``, ``NE`` (``_`` between
    indices when N >= 10 so that names stay unambiguous)."""
    sep = "_" if n_joints >= 10 else ""
    return ("I0",) + tuple(f"{j - 1}{sep}{j}" for j in range(1, n_joints + 1)) + (f"{n_joints}E",)


def parameter_layout(joint_types) -> tuple:
    """(names, units) of the 6N + 12 error parameters for joints of these types.

    Per transform k, six consecutive entries. Base and tool: ``pL_k_x, pL_k_y, pL_k_z`` (m),
    ``pR_k_x, pR_k_y, pR_k_z`` (rad). Revolute joint j: ``pL_k_x, pL_k_y, pL_k_z``,
    ``pR_k_x, pR_k_y`` and the zero offset ``pq<j>`` (rad) — the paper's Table 2. Prismatic
    joint j: ``pL_k_x, pL_k_y`` (m, resolved in the joint's nominal frame, perpendicular to
    its axis), ``pR_k_z`` (rad, rotation about the axis, which a prismatic joint does not
    carry), ``pR_k_x, pR_k_y`` (rad) and the zero offset ``pd<j>`` (m): the translation along
    the axis is the zero offset, so it is not repeated.
    """
    n = len(joint_types)
    names, units = [], []
    for k, tname in enumerate(transform_names(n)):
        kind = joint_types[k - 1] if 1 <= k <= n else "fixed"
        if kind == "prismatic":
            nm = [f"pL_{tname}_x", f"pL_{tname}_y", f"pR_{tname}_z", f"pR_{tname}_x", f"pR_{tname}_y", f"pd{k}"]
            un = ["m", "m", "rad", "rad", "rad", "m"]
        else:
            nm = [f"pL_{tname}_x", f"pL_{tname}_y", f"pL_{tname}_z", f"pR_{tname}_x", f"pR_{tname}_y"]
            nm.append(f"pq{k}" if kind != "fixed" else f"pR_{tname}_z")
            un = ["m", "m", "m", "rad", "rad", "rad"]
        names += nm
        units += un
    return tuple(names), tuple(units)


@dataclass(frozen=True, eq=False)
class RobotModel:
    """A serial chain of N moving joints described by a URDF.

    Build it with :meth:`load`. Every array it holds is read-only.
    """

    name: str
    urdf_path: Path
    #: nominal rotations R̄ of the N + 2 transforms, (N + 2, 3, 3)
    R_nominal: np.ndarray
    #: nominal translations t̄ of the N + 2 transforms in the parent model frame, (N + 2, 3), m
    t_nominal: np.ndarray
    #: joint limits, (N,) each, rad or m (continuous joints: ±pi for sampling, not checked)
    q_lower: np.ndarray
    q_upper: np.ndarray
    joint_names: tuple
    #: the base frame's name, then the link after each of the N + 2 transforms
    link_names: tuple
    #: gravity in the base frame F_I, (3,) m/s²
    gravity_in_I: np.ndarray
    max_velocity: np.ndarray
    max_acceleration: np.ndarray
    max_jerk: np.ndarray
    reflectors: tuple
    #: "revolute", "continuous" or "prismatic" per moving joint
    joint_types: tuple = ()
    #: S_j (N, 3, 3): model frame of joint j = URDF child link frame · S_j
    axis_alignment: np.ndarray = None
    #: URDF joint names folded into each of the N + 2 transforms, in order
    transform_joints: tuple = ()
    #: tool and base frame (URDF link names)
    tool_frame: str = "E"
    base_frame: str = "I"
    #: values (rad or m) of the locked URDF joints, by name
    locked_joints: dict = field(default_factory=dict)
    #: controller convention q_model = A q_controller + b: A (N, N), b (N,)
    controller_matrix: np.ndarray = None
    controller_offset: np.ndarray = None
    #: what `load` was given (stored in RUN/campaign.yaml)
    spec: str = DEFAULT_ROBOT
    #: the robot.yaml read, if any
    meta_path: Path | None = None
    #: pose of F_I (the base frame) in the URDF's root link, (4, 4), with locked joints applied
    T_root_base: np.ndarray = None
    #: the tool mounting folded into the tool transform (:meth:`with_tool_transform`): the
    #: measured frame in the URDF's tool frame, (4, 4), or None
    tool_mounting: np.ndarray = None
    #: the measured point folded into the tool transform (:meth:`with_tool_point`): (3,) m in the
    #: URDF's tool frame, or None (the URDF export names it as a frame of its own)
    tool_point: np.ndarray = None

    # -- loading ------------------------------------------------------------------------
    @classmethod
    def load(cls, spec: str | Path = DEFAULT_ROBOT, *, tool_frame: str | None = None,
             base_frame: str | None = None) -> "RobotModel":
        """Load a robot: a name under ``robot_models/``, a URDF path, a robot.yaml path or its folder.

        ``tool_frame`` / ``base_frame`` (URDF link names) override robot.yaml's and the defaults.
        Any problem is one :class:`ConfigError` line naming the file and the element.
        """
        named = _named_example(spec)
        if named is not None:
            spec, tool_frame, base_frame = named[0], tool_frame or named[1], base_frame or named[2]
        urdf, meta = _resolve(spec)
        # files edited in place are read again (the cache key holds their modification times)
        files = [urdf] if urdf else [meta, *sorted(meta.parent.glob("*.urdf"))]
        stamp = tuple(f.stat().st_mtime_ns for f in files)
        return _load_cached(str(urdf) if urdf else None, str(meta) if meta else None,
                            tool_frame or None, base_frame or None, str(spec), stamp)

    # -- derived views --------------------------------------------------------------------
    @property
    def n_joints(self) -> int:
        """N, the number of moving joints of the chain."""
        return len(self.joint_names)

    @functools.cached_property
    def param_names(self) -> tuple:
        """Names of the 6N + 12 geometric error parameters (COMAU: Table 2's 48)."""
        return parameter_layout(self.joint_types)[0]

    @functools.cached_property
    def param_units(self) -> tuple:
        """SI unit ("m" or "rad") of each error parameter."""
        return parameter_layout(self.joint_types)[1]

    @property
    def n_params(self) -> int:
        return 6 * self.n_joints + 12

    @property
    def transform_names(self) -> tuple:
        return transform_names(self.n_joints)

    @property
    def joint_offset_index(self) -> tuple:
        """Index of each moving joint's zero offset (pq<j> or pd<j>) in ``p_e``."""
        return tuple(6 * k + 5 for k in range(1, self.n_joints + 1))

    @property
    def joint_frame_index(self) -> tuple:
        """For each moving joint j, the index along frames()'s axis 1 of the frame right after
        joint j's motion (COMAU: (1, .., 6))."""
        return tuple(range(1, self.n_joints + 1))

    @property
    def prismatic(self) -> np.ndarray:
        """(N,) bool: which joints are prismatic."""
        return np.array([t == "prismatic" for t in self.joint_types], dtype=bool)

    @property
    def gravity_in_root(self) -> np.ndarray:
        """Gravity in the chain's base frame F_I, (3,) m/s² (COMAU: (0, 9.81, 0))."""
        return self.gravity_in_I

    @property
    def joint_units(self) -> tuple:
        """"rad" or "m" per moving joint."""
        return tuple("m" if t == "prismatic" else "rad" for t in self.joint_types)

    @functools.cached_property
    def urdf(self):
        """The yourdfpy ``URDF`` of this robot with its scene graph (loaded on first use)."""
        return _load_yourdfpy(self.urdf_path, build_scene_graph=True)

    @functools.cached_property
    def pinocchio_model(self):
        """A Pinocchio model of the chain's moving joints (others locked), gravity in its world.

        The world of the model is the URDF's root; ``gravity`` is ``gravity_in_I`` rotated into
        it. Its configuration for joint vectors ``q`` (n, N) is :meth:`pinocchio_q`.
        """
        import pinocchio as pin

        model = pin.buildModelFromUrdf(str(self.urdf_path))
        keep = set(self.joint_names)
        lock_ids, q_ref = [], pin.neutral(model)
        for jid in range(1, model.njoints):
            jname = model.names[jid]
            if jname in keep:
                continue
            lock_ids.append(jid)
            value = float(self.locked_joints.get(jname, 0.0))
            idx, nq = model.joints[jid].idx_q, model.joints[jid].nq
            if nq == 1:
                q_ref[idx] = value
            elif nq == 2:
                q_ref[idx:idx + 2] = (np.cos(value), np.sin(value))
        if lock_ids:
            model = pin.buildReducedModel(model, lock_ids, q_ref)
        names = [model.names[j] for j in range(1, model.njoints)]
        if names != list(self.joint_names):
            raise ConfigError(f"{self.urdf_path}: Pinocchio orders the chain's joints {names}, "
                              f"expected {list(self.joint_names)}")
        R = np.asarray(self.T_root_base)[:3, :3] if self.T_root_base is not None else np.eye(3)
        model.gravity.linear = R @ np.asarray(self.gravity_in_I, dtype=float)
        return model

    def pinocchio_q(self, q) -> np.ndarray:
        """Pinocchio configurations (n, nq) for joint vectors q (n, N) (continuous joints: cos, sin)."""
        q = np.asarray(q, dtype=float).reshape(-1, self.n_joints)
        if "continuous" not in self.joint_types:
            return q
        cols = []
        for j, t in enumerate(self.joint_types):
            cols += [np.cos(q[:, j]), np.sin(q[:, j])] if t == "continuous" else [q[:, j]]
        return np.stack(cols, axis=1)

    @property
    def reflector_positions_in_E(self) -> np.ndarray:
        """(k, 3): row j is reflector j's centre in the tool frame, m."""
        return _read_only(np.reshape([r.position_in_E for r in self.reflectors], (-1, 3)))

    @property
    def q_mid(self) -> np.ndarray:
        return _read_only(0.5 * (self.q_lower + self.q_upper))

    def with_tool_point(self, point_in_tool) -> "RobotModel":
        """The same robot whose tool frame is moved (not turned) to ``point_in_tool`` (3,), m:
        the model of one-reflector data measured at a reflector off the tool frame's origin."""
        import dataclasses

        p = np.asarray(point_in_tool, dtype=float).reshape(3)
        if not np.any(p):
            return self
        t = np.array(self.t_nominal)
        t[-1] = t[-1] + self.R_nominal[-1] @ p
        before = np.zeros(3) if self.tool_point is None else self.tool_point
        return dataclasses.replace(self, t_nominal=_read_only(t), name=self.name, tool_point=_read_only(before + p))

    def with_tool_transform(self, T_tool_measured) -> "RobotModel":
        """The same robot whose tool frame is the measured frame ``T_tool_measured`` (4, 4) in the
        URDF's tool frame (moved and turned): the model of 6-D or raw-reflector data measured on a
        tool mounting (a marker plate, a flange) the URDF does not describe. The mounting is kept
        in :attr:`tool_mounting` (composed with any earlier one), for the URDF export."""
        import dataclasses

        X = np.asarray(T_tool_measured, dtype=float).reshape(4, 4)
        if np.allclose(X, np.eye(4), rtol=0, atol=0):
            return self
        t, R = np.array(self.t_nominal), np.array(self.R_nominal)
        t[-1] = t[-1] + R[-1] @ X[:3, 3]
        R[-1] = R[-1] @ X[:3, :3]
        before = np.eye(4) if self.tool_mounting is None else self.tool_mounting
        return dataclasses.replace(self, t_nominal=_read_only(t), R_nominal=_read_only(R), name=self.name,
                                   tool_mounting=_read_only(before @ X))

    def with_default_reflectors(self) -> "RobotModel":
        """This robot, or, when robot.yaml names no reflector, the same robot carrying
        :data:`DEFAULT_REFLECTORS` (what `plan`, `run` and the simulated cell measure), moved
        along the tool frame's +z beyond what the tool frame carries (a hand and its fingers,
        campaign.model.tool_side; by the reflector's radius and DEFAULT_REFLECTOR_GAP_M more),
        not inside it. Cached: the same object on every call."""
        if self.reflectors:
            return self
        cached = self.__dict__.get("_with_default_reflectors")
        if cached is None:
            import dataclasses

            cached = dataclasses.replace(self, reflectors=default_reflectors(self.default_reflector_lift_m))
            self.__dict__["_with_default_reflectors"] = cached
        return cached

    @functools.cached_property
    def default_reflector_lift_m(self) -> float:
        """How far (m) the default triad sits along the tool frame's +z: 0 for a bare flange,
        else beyond the collision geometry the tool frame carries (a hand, its fingers)."""
        from campaign.model.tool_side import tool_side_reach_m
        from campaign.tolerances import REFLECTOR_RADIUS_M

        reach = tool_side_reach_m(self)
        return 0.0 if reach <= 0.0 else reach + REFLECTOR_RADIUS_M + DEFAULT_REFLECTOR_GAP_M

    @functools.cached_property
    def link_frames(self) -> dict:
        """Where every link of the URDF sits on the chain: ``{link: (k, T)}`` with k the index of
        the frame of :func:`campaign.model.kinematics.frames` it moves with (0: the base side,
        j = 1..N: after joint j, N + 1: the tool frame and what hangs from it) and T (4, 4) its
        pose in that frame (joints outside the chain at their locked values). A link is carried
        by the nearest chain frame above it in the tree; links above the base frame (the base
        is not the root) stand still with frame 0."""
        N = self.n_joints
        joints = {j.child: j for j in self.urdf.robot.joints}
        chain = {}
        for k, name in enumerate(self.link_names[1:]):  # frames 0 .. N + 1
            if name in chain:
                continue  # a tool frame that is the last joint's own link moves with that joint
            T = np.eye(4)
            if 1 <= k <= N:  # model frame k = link · S_k
                T[:3, :3] = np.asarray(self.axis_alignment[k - 1]).T
            chain[name] = (k, T)
        T0 = _as_T(self.R_nominal[0], self.t_nominal[0])  # frame 0 in F_I
        if self.base_frame not in chain:
            chain[self.base_frame] = (0, np.linalg.inv(T0))

        def locked(j):
            return _origin(j) @ _motion(j, self.locked_joints.get(j.name, 0.0))

        out = {}
        for link in self.urdf.link_map:
            T, cur = np.eye(4), link
            while cur not in chain and cur in joints:  # up to the nearest chain link
                T = locked(joints[cur]) @ T
                cur = joints[cur].parent
            if cur in chain:
                k, Tc = chain[cur]
                out[link] = (k, Tc @ T)
            else:  # above the base: T is the link's pose in the root
                out[link] = (0, np.linalg.inv(T0) @ np.linalg.inv(np.asarray(self.T_root_base)) @ T)
        for k, T in out.values():
            T.setflags(write=False)
        return out

    def to_model_q(self, q_controller) -> np.ndarray:
        """q_model = A q_controller + b, (n, N) (robot.yaml's ``controller`` convention)."""
        q = np.asarray(q_controller, dtype=float)
        if self.controller_matrix is None:
            return q
        return q @ self.controller_matrix.T + self.controller_offset

    def to_controller_q(self, q_model) -> np.ndarray:
        """Inverse of :meth:`to_model_q`, (n, N)."""
        q = np.asarray(q_model, dtype=float)
        if self.controller_matrix is None:
            return q
        return np.linalg.solve(self.controller_matrix, (q - self.controller_offset).T).T

    def check_joints(self, q, *, field: str = "q", slack=0.0, pose_ids=None, lines=None,
                     slack_source: str | None = None) -> np.ndarray:
        """Validate joint vectors; return them as float64 (n, N).

        Raises :class:`campaign.errors.DataError` naming the robot, the row (its ``pose_ids``
        entry, its file line from ``lines``, else its 1-based row number), the joint, the value
        and the limit (continuous joints have none). slack: scalar or (N,), rad or m;
        slack_source: where it comes from, when the message should say the slack in force.
        """
        from campaign.errors import DataError

        q = np.asarray(q, dtype=float)
        if q.ndim == 1:
            q = q[None, :]
        N = self.n_joints
        if q.ndim != 2 or q.shape[1] != N:
            raise DataError(f"{field}: expected shape (n, {N}) for {self.name} ({N} joints), got {q.shape}")
        bad = ~np.isfinite(q)
        if bad.any():
            i, j = np.argwhere(bad)[0]
            raise DataError(f"{field}: {_row_label(i, pose_ids, lines)}, q{j + 1} is {q[i, j]} (not a finite number)")
        limited = np.array([t != "continuous" for t in self.joint_types], dtype=bool)
        lo = (q < self.q_lower - slack) & limited
        hi = (q > self.q_upper + slack) & limited
        if lo.any() or hi.any():
            i, j = np.argwhere(lo | hi)[0]
            lim = self.q_lower[j] if lo[i, j] else self.q_upper[j]
            u = self.joint_units[j]
            where = _row_label(i, pose_ids, lines)
            said = "" if slack_source is None else \
                f" (limit slack in force: {limit_slack_text(self, np.broadcast_to(slack, (N,))[j], j)}, {slack_source})"
            from campaign.tolerances import FAR_PAST_LIMIT_M, FAR_PAST_LIMIT_RAD

            excess = (lim - q[i, j]) if lo[i, j] else (q[i, j] - lim)
            if slack_source is not None and excess > (FAR_PAST_LIMIT_M if self.prismatic[j] else FAR_PAST_LIMIT_RAD):
                past = f"{excess * 1e3:.3g} mm" if self.prismatic[j] else f"{np.degrees(excess):.3g} deg"
                said = (f" ({past} past it: no reading slightly past a limit, but joints of another robot, unit or "
                        f"joint convention: the file is read as {self.name}'s, in the controller's convention of its "
                        "robot.yaml; --angle-unit)")
            raise DataError(f"{field}: {where}, q{j + 1} = {q[i, j]:.6g} {u} is outside the joint limit "
                            f"{lim:.6g} {u} of {self.name}{said}")
        return q

    def describe(self) -> str:
        """One line per transform: its URDF joints and type."""
        lines = [f"{self.name}: {self.n_joints} moving joints from '{self.base_frame}' to '{self.tool_frame}' "
                 f"({self.urdf_path}); {self.n_params} error parameters; gravity "
                 f"{np.round(self.gravity_in_I, 4).tolist()} m/s² in '{self.base_frame}'"]
        for k, tname in enumerate(self.transform_names):
            kind = self.joint_types[k - 1] if 1 <= k <= self.n_joints else "fixed"
            lines.append(f"  T_{tname:<6} {kind:<10} {', '.join(self.transform_joints[k]) or '(identity)'}")
        return "\n".join(lines)


def limit_slack_text(robot, slack, j: int) -> str:
    """``0.5 deg`` or ``0.2 mm``: how far past joint j's limit readings are accepted (``slack``,
    rad or m, JOINT_LIMIT_SLACK's round-off allowance included and not shown), as --limit-slack
    takes it; ``none`` for round-off alone."""
    from campaign.tolerances import JOINT_LIMIT_SLACK

    extra = max(float(slack) - JOINT_LIMIT_SLACK, 0.0)
    if extra <= JOINT_LIMIT_SLACK:
        return "none"
    return f"{extra * 1e3:.6g} mm" if robot.prismatic[j] else f"{np.degrees(extra):.6g} deg"


def _row_label(i: int, pose_ids=None, lines=None) -> str:
    """``pose_id 17``, ``line 5`` (a file's, 1-based) or ``row 3`` (1-based) for row index i."""
    if pose_ids is not None:
        return f"pose_id {int(pose_ids[i])}"
    if lines is not None:
        return f"line {int(lines[i])}"
    return f"row {i + 1}"


# -- resolution of the spec ----------------------------------------------------------------
def names_example_robot(spec) -> bool:
    """Whether ``spec`` names one of example-robot-data's robots: a name of the catalog that no
    file, robot.yaml folder or embedded model of that name hides (a folder without a robot.yaml,
    such as the run folder `campaign plan --run ur3 --robot ur3` made, does not hide it)."""
    from campaign.model import catalog

    text = str(spec)
    here = Path(text)
    if "/" in text or here.is_file() or (here / "robot.yaml").is_file() or (ROBOT_MODELS / text).is_dir():
        return False
    return catalog.lookup(text) is not None


def _names_embedded(spec) -> bool:
    """Whether ``spec`` names an embedded model (campaign/data/robot_models/<name>) that no file or
    robot.yaml folder of that name in the current directory hides (a bare folder does not)."""
    text = str(spec)
    here = Path(text)
    return ("/" not in text and (ROBOT_MODELS / text).is_dir() and not here.is_file()
            and not (here / "robot.yaml").is_file())


def robot_spec(given) -> str:
    """The one reading of ``--robot`` for every command: a robot's name stays a name (a folder
    of that name without a robot.yaml in the current directory, such as a run folder, does not
    hide it); a URDF, a robot.yaml or its folder becomes an absolute path (a run's campaign.yaml
    records it so)."""
    text = str(given)
    if not Path(text).exists() or names_example_robot(text) or _names_embedded(text):
        return text
    return str(Path(text).resolve())


def _named_example(spec):
    """(URDF path, tool frame, base frame) when ``spec`` names one of example-robot-data's robots
    (:func:`names_example_robot`); None otherwise."""
    from campaign.model import catalog

    if not names_example_robot(spec):
        return None
    known = catalog.lookup(str(spec))
    path = catalog.urdf_of(known)
    if path is None or not path.is_file():
        raise ConfigError(f"robot '{spec}' is one of example-robot-data's robots, which is not installed "
                          "(pip install example-robot-data)")
    return path, known.tool_frame, known.base_frame


def _resolve(spec) -> tuple:
    """(urdf path or None, robot.yaml path or None) for what `load` was given."""
    p = Path(spec)
    if p.is_dir() and not _names_embedded(spec):
        meta = p / "robot.yaml"
        if not meta.is_file():
            raise ConfigError(f"{meta}: robot description not found (expected robot.yaml beside a URDF)")
        return None, meta.resolve()
    if p.is_file():
        if p.suffix.lower() in (".yaml", ".yml"):
            return None, p.resolve()
        return p.resolve(), None
    named = ROBOT_MODELS / str(spec)
    if "/" not in str(spec) and named.is_dir():
        return _resolve(named)
    import difflib

    from campaign.model import catalog

    names = [known.name for known, _ in catalog.known_robots()]
    close = difflib.get_close_matches(str(spec).lower(), names, 1, 0.6)
    raise ConfigError(f"robot '{spec}': neither a URDF file, a robot.yaml (or its folder), nor a known name"
                      + (f" (did you mean {close[0]}?)" if close else "")
                      + f"; known names: {', '.join(names)} (`campaign robots` says which are installed)")


def _xml_diagnosis(urdf_path: Path) -> str:
    """Which element of a URDF yourdfpy could not read (only used to word an error)."""
    import xml.etree.ElementTree as ET

    try:
        root = ET.parse(urdf_path).getroot()
    except ET.ParseError as exc:
        return f"not valid XML ({exc})"
    for kind in ("joint", "link"):
        for el in root.iter(kind):
            for sub in el.iter():
                for attr, val in sub.attrib.items():
                    if attr in ("xyz", "rpy", "lower", "upper", "velocity", "effort", "value", "radius",
                                "length", "size", "ixx", "iyy", "izz", "ixy", "ixz", "iyz", "multiplier", "offset"):
                        try:
                            [float(v) for v in val.split()]
                        except ValueError:
                            return f"{kind} '{el.get('name')}': <{sub.tag} {attr}=\"{val}\"> is not numeric"
    return ""


def _without_geometry(urdf_path: Path):
    """The URDF's XML with every <visual> and <collision> removed (a file-like object), or None
    when it cannot be read: the chain needs no geometry, and yourdfpy refuses geometry it does
    not know (``<capsule>``, ...) that the planner checks or names itself."""
    import io
    import xml.etree.ElementTree as ET

    try:
        tree = ET.parse(urdf_path)
    except (OSError, ET.ParseError):
        return None
    for link in tree.getroot().iter("link"):
        for el in list(link):
            if el.tag in ("visual", "collision"):
                link.remove(el)
    return io.BytesIO(ET.tostring(tree.getroot()))


def _load_yourdfpy(urdf_path: Path, build_scene_graph: bool = False):
    """yourdfpy's URDF (no meshes loaded); on geometry it cannot parse, the URDF without geometry."""
    import yourdfpy

    kw = dict(load_meshes=False, build_scene_graph=build_scene_graph, build_collision_scene_graph=False)
    try:
        return yourdfpy.URDF.load(str(urdf_path), **kw)
    except ValueError as exc:
        bare = _without_geometry(urdf_path) if str(exc).startswith("Unknown tag") else None
        if bare is None:
            raise
        return yourdfpy.URDF.load(bare, **kw)


def _moving_depth(joint, children: dict, locked: dict) -> int:
    """The most moving joints (neither fixed nor locked) on a path from ``joint`` down to a leaf."""
    below = max((_moving_depth(j, children, locked) for j in children[joint.child]), default=0)
    return below + (joint.type != "fixed" and joint.name not in locked)


def _tool_choices(link: str, children: dict, locked: dict) -> list:
    """Tool frames a branch starting at ``link`` offers: where the default walk down it stops (a
    leaf, or a link whose branches are fixed or one joint long), then the leaves below that;
    branches with chains of their own below are followed each."""
    while len(children[link]) == 1:
        link = children[link][0].child
    if any(_moving_depth(j, children, locked) >= 2 for j in children[link]):  # a hand with fingers, or more arms
        return [link, *(e for j in children[link] for e in _tool_choices(j.child, children, locked))]
    out, stack = [link], [j.child for j in reversed(children[link])]
    while stack:  # the leaves below, depth first, in the URDF's order
        cur = stack.pop()
        if not children[cur]:
            out.append(cur)
        stack.extend(j.child for j in reversed(children[cur]))
    return out


def _not_xml(path: Path, exc) -> ConfigError:
    """The one line for a file that is not well-formed XML (an ``xml.etree`` ParseError): the
    file, the line and the column (yourdfpy would print its parser's lines, then read what it
    could recover)."""
    line, column = exc.position
    why = str(exc).split(": line")[0]
    return ConfigError(f"{path}: not valid XML (line {line}, column {column + 1}: {why})")


def _parse_urdf(urdf_path: Path):
    import xml.etree.ElementTree as ET

    from campaign.model.urdf_chain import NotReadHere, read_chain

    not_read = None
    try:  # the chain alone, without importing yourdfpy and trimesh (half a second)
        return read_chain(urdf_path)
    except ET.ParseError as exc:
        raise _not_xml(urdf_path, exc) from None
    except NotReadHere as exc:  # a file it does not take: yourdfpy reads it, or words what is wrong as before
        if str(exc).startswith("root element"):  # yourdfpy would read some other XML as a robot of one link
            raise ConfigError(f"{urdf_path}: {exc}: not a URDF") from None
        not_read = exc
    except Exception:
        pass
    try:
        return _load_yourdfpy(urdf_path)
    except Exception as exc:  # yourdfpy raises plain exceptions; word them as one line
        where = _xml_diagnosis(urdf_path) or (str(not_read) if not_read is not None else str(exc).splitlines()[0])
        raise ConfigError(f"{urdf_path}: cannot read the URDF: {where}") from None


def _origin(joint) -> np.ndarray:
    return np.array(joint.origin, dtype=float) if joint.origin is not None else np.eye(4)


def _rot(axis, angle) -> np.ndarray:
    from campaign.model.rotations import rotvec_to_matrix

    return rotvec_to_matrix(np.asarray(axis, dtype=float) * angle)


def _motion(joint, value: float) -> np.ndarray:
    """URDF joint motion (4, 4) at ``value`` (for locked joints)."""
    M = np.eye(4)
    if joint.type in ("revolute", "continuous"):
        M[:3, :3] = _rot(_unit_axis(joint), value)
    elif joint.type == "prismatic":
        M[:3, 3] = _unit_axis(joint) * value
    return M


def _unit_axis(joint) -> np.ndarray:
    a = np.array(joint.axis if joint.axis is not None else (1.0, 0.0, 0.0), dtype=float)
    n = np.linalg.norm(a)
    if not np.isfinite(n) or n < 1e-9:
        raise ConfigError(f"joint '{joint.name}': axis {a.tolist()} is not a direction")
    return a / n


def axis_alignment(u) -> np.ndarray:
    """A rotation S (3, 3) with ``S @ z = u``: identity for +z, Rx(pi) for −z, else the
    smallest rotation taking z to u."""
    u = np.asarray(u, dtype=float)
    z = np.array([0.0, 0.0, 1.0])
    if np.allclose(u, z, atol=1e-12):
        return np.eye(3)
    if np.allclose(u, -z, atol=1e-12):
        return np.diag([1.0, -1.0, -1.0])
    c = np.cross(z, u)
    angle = np.arctan2(np.linalg.norm(c), z @ u)
    S = _rot(c / np.linalg.norm(c), angle)
    # snap round-off (e.g. cos(pi/2) = 6e-17) so that axis-aligned joints stay exact
    S[np.abs(S) < 1e-15] = 0.0
    return S


def _as_T(R=None, t=None) -> np.ndarray:
    T = np.eye(4)
    if R is not None:
        T[:3, :3] = R
    if t is not None:
        T[:3, 3] = t
    return T


@functools.lru_cache(maxsize=16)
def _load_cached(urdf_str, meta_str, tool_frame, base_frame, spec, stamp=()) -> RobotModel:
    from campaign.fileio import read_yaml_mapping

    meta_file = Path(meta_str) if meta_str else None
    meta = read_yaml_mapping(meta_file) if meta_file else {}
    where = str(meta_file) if meta_file else None
    if meta_file is not None:
        if "chain" in meta and not set(GRAVITY_FIELDS) & set(meta):
            # the explicit paper-chain format states its gravity (F_I need not have z up)
            raise ConfigError(f"{meta_file}: missing field 'gravity_m_s2' (or 'gravity_in_I_m_s2'): a robot.yaml "
                              "with 'chain' states its gravity")
        if "urdf" in meta:
            urdf_path = meta_file.parent / str(meta["urdf"])
            if not urdf_path.is_file():
                raise ConfigError(f"{meta_file}: field 'urdf' names {urdf_path}, which does not exist")
        else:
            found = sorted(meta_file.parent.glob("*.urdf"))
            if len(found) != 1:
                raise ConfigError(f"{meta_file}: missing field 'urdf' (and {len(found)} .urdf files beside it)")
            urdf_path = found[0]
    else:
        urdf_path = Path(urdf_str)
    urdf_path = urdf_path.resolve()
    src = where or str(urdf_path)

    u = _parse_urdf(urdf_path)
    joints = {j.name: j for j in u.robot.joints}
    links = {lk.name for lk in u.robot.links}
    child_of = {}  # link -> joint whose child it is
    children = {lk: [] for lk in links}
    for j in u.robot.joints:
        for end in (j.parent, j.child):
            if end not in links:
                raise ConfigError(f"{urdf_path}: joint '{j.name}' names link '{end}', which the URDF does not define")
        if j.child in child_of:
            raise ConfigError(f"{urdf_path}: link '{j.child}' is the child of two joints "
                              f"('{child_of[j.child].name}', '{j.name}'): not a tree")
        child_of[j.child] = j
        children[j.parent].append(j)
        if j.type not in ("fixed", "revolute", "continuous", "prismatic"):
            raise ConfigError(f"{urdf_path}: joint '{j.name}' has type '{j.type}' (a serial chain takes revolute, "
                              "continuous, prismatic and fixed joints)")
    roots = sorted(links - set(child_of))
    if len(roots) != 1:
        raise ConfigError(f"{urdf_path}: expected one root link, found {len(roots)} ({', '.join(roots[:5])})")
    root = roots[0]

    def text_field(key, given):
        v = given if given is not None else meta.get(key)
        if v is not None and not isinstance(v, str):
            raise ConfigError(f"{src}: field '{key}' must be a link name, got {v!r}")
        return v

    base = text_field("base_frame", base_frame) or root
    if base not in links:
        raise ConfigError(f"{src}: {_frame_field('base', base_frame)} '{base}' is not a link of {urdf_path.name}")
    locked_in = meta.get("locked_joints") or {}
    if not isinstance(locked_in, dict):
        raise ConfigError(f"{src}: field 'locked_joints' must map joint names to values (rad or m)")
    locked = {}
    for jn, v in locked_in.items():
        if jn not in joints:
            raise ConfigError(f"{src}: locked_joints names '{jn}', which is not a joint of {urdf_path.name}")
        try:
            locked[jn] = float(v)
        except (TypeError, ValueError):
            locked[jn] = float("nan")
        if not np.isfinite(locked[jn]):
            raise ConfigError(f"{src}: field 'locked_joints.{jn}' must be a finite number (rad or m), got {v!r}")
    tool = text_field("tool_frame", tool_frame)
    if tool is None:
        tool = base
        while len(children[tool]) == 1:
            tool = children[tool][0].child
        # a branch with a chain of its own (an arm, a head) below: which end is the tool cannot be
        # guessed; fixed branches (reflectors, sensors) and one-joint ones (a gripper's fingers) end it
        if any(_moving_depth(j, children, locked) >= 2 for j in children[tool]):
            ends = list(dict.fromkeys(e for j in children[tool] for e in _tool_choices(j.child, children, locked)))

            def joints_to(link):  # moving joints from the branch down to ``link``: the arms' ends first
                n = 0
                while link != tool:
                    n += child_of[link].type != "fixed" and child_of[link].name not in locked
                    link = child_of[link].parent
                return n

            ends.sort(key=lambda e: (len(children[e]) == 0, -joints_to(e)))  # a hand before its fingers
            shown = ", ".join(ends[:12]) + (f", ... ({len(ends)} in all)" if len(ends) > 12 else "")
            raise ConfigError(f"{src}: the tree branches at '{tool}' into {len(children[tool])} branches: name the "
                              f"tool frame with --tool-frame or tool_frame in robot.yaml (the branches end at "
                              f"{shown})")
    if tool not in links:
        raise ConfigError(f"{src}: {_frame_field('tool', tool_frame)} '{tool}' is not a link of {urdf_path.name}")

    # the path from the tool up to the base
    path, cur = [], tool
    while cur != base:
        if cur not in child_of:
            raise ConfigError(f"{src}: tool frame '{tool}' is not below base frame '{base}' in {urdf_path.name} "
                              "(no serial path between them)")
        path.append(child_of[cur])
        cur = child_of[cur].parent
    path.reverse()
    moving = [j for j in path if j.type != "fixed" and j.name not in locked]
    if not moving:
        if tool == base:  # nothing below the base moves
            raise ConfigError(f"{src}: no moving joint below '{base}' in {urdf_path.name} ({len(links)} links, "
                              f"{len(joints)} joints, none of them revolute, continuous or prismatic below it)")
        raise ConfigError(f"{src}: no moving joint between '{base}' and '{tool}'")
    for j in moving:
        if j.mimic is not None:
            raise ConfigError(f"{urdf_path}: joint '{j.name}' mimics '{j.mimic.joint}': a mimic joint cannot be "
                              "part of the calibrated chain (lock it in robot.yaml's locked_joints)")
    if "chain" in meta:
        listed = list(meta["chain"] or [])
        if listed != [j.name for j in path]:
            raise ConfigError(f"{meta_file}: field 'chain' lists {listed}, the URDF's chain from '{base}' to "
                              f"'{tool}' is {[j.name for j in path]}")

    def fixed_T(j):
        T = _origin(j)
        if j.type != "fixed":  # a locked moving joint
            T = T @ _motion(j, locked.get(j.name, 0.0))
        return T

    # cut the path into N + 2 transforms (model frames: z along each moving joint's axis)
    N = len(moving)
    moving_names = {j.name for j in moving}
    Ts, tj = [], []
    acc, names = np.eye(4), []
    S_prev = np.eye(3)
    S_all, types, lower, upper, vel = [], [], [], [], []
    for j in path:
        if j.name not in moving_names:
            acc = acc @ fixed_T(j)
            names.append(j.name)
            continue
        if not Ts:  # the base transform: everything before joint 1
            Ts.append(acc)
            tj.append(tuple(names))
            acc, names = np.eye(4), []
        S = axis_alignment(_unit_axis(j))
        Ts.append(_as_T(S_prev.T) @ acc @ _origin(j) @ _as_T(S))
        tj.append(tuple(names + [j.name]))
        acc, names, S_prev = np.eye(4), [], S
        S_all.append(S)
        types.append(j.type)
        lim = j.limit
        if j.type == "continuous":
            lo, hi = -np.pi, np.pi
        else:
            if lim is None or lim.lower is None or lim.upper is None:
                raise ConfigError(f"{urdf_path}: joint '{j.name}' ({j.type}) has no <limit lower upper>")
            lo, hi = float(lim.lower), float(lim.upper)
            if not lo < hi:
                raise ConfigError(f"{urdf_path}: joint '{j.name}': limit lower {lo} is not below upper {hi}")
        lower.append(lo)
        upper.append(hi)
        vel.append(float(lim.velocity) if lim is not None and lim.velocity else np.nan)
    Ts.append(_as_T(S_prev.T) @ acc)  # the tool transform
    tj.append(tuple(names))
    tj = tuple(tj)
    link_after = [base, moving[0].parent] + [j.child for j in moving] + [tool]

    # pose of the base frame in the URDF root (locked joints applied), for gravity in Pinocchio
    T_rb, cur = np.eye(4), base
    while cur != root:
        j = child_of[cur]
        T_rb = fixed_T(j) @ T_rb
        cur = j.parent

    # -- robot.yaml's extras ---------------------------------------------------------------
    g = _gravity_field(meta, src, base)
    if not any(k in meta for k in GRAVITY_FIELDS):  # a URDF written by `campaign export --urdf` states its own
        g = exported_gravity(urdf_path, base, g)

    def vecN(keys, default, what):
        for key in keys:
            if key in meta:
                if not _is_numeric_list(meta[key], N):
                    raise ConfigError(f"{src}: field '{key}' must be {N} numbers ({what})")
                v = np.asarray(meta[key], dtype=float)
                if np.any(v <= 0):
                    raise ConfigError(f"{src}: field '{key}' must be {N} positive numbers")
                return v
        return np.asarray(default, dtype=float)

    v_def = np.where(np.isfinite(vel) & (np.asarray(vel) > 0), vel, 1.0)
    max_vel = vecN(("max_velocity_rad_s", "max_velocity"), v_def, "per joint, rad/s or m/s")
    max_acc = vecN(("max_acceleration_rad_s2", "max_acceleration"), 2.5 * max_vel, "rad/s² or m/s²")
    max_jerk = vecN(("max_jerk_rad_s3", "max_jerk"), 10.0 * max_acc, "rad/s³ or m/s³")

    reflectors = _reflectors(meta, src, tool, children, fixed_T)

    A = b = None
    ctrl = meta.get("controller")
    if ctrl is not None:
        if not isinstance(ctrl, dict) or set(ctrl) - {"sign", "offset", "coupling"}:
            raise ConfigError(f"{src}: field 'controller' takes 'sign', 'offset' and 'coupling' "
                              "(q_model = coupling·diag(sign)·q_controller + offset)")
        A = np.eye(N)
        if "coupling" in ctrl:
            c = ctrl["coupling"]
            if not (isinstance(c, list) and len(c) == N and all(_is_numeric_list(r, N) for r in c)):
                raise ConfigError(f"{src}: field 'controller.coupling' must be a {N}x{N} matrix of numbers")
            A = np.asarray(c, dtype=float)
        if "sign" in ctrl:
            if not _is_numeric_list(ctrl["sign"], N) or not set(map(float, ctrl["sign"])) <= {1.0, -1.0}:
                raise ConfigError(f"{src}: field 'controller.sign' must be {N} values of 1 or -1")
            A = A @ np.diag(np.asarray(ctrl["sign"], dtype=float))
        b = np.zeros(N)
        if "offset" in ctrl:
            if not _is_numeric_list(ctrl["offset"], N):
                raise ConfigError(f"{src}: field 'controller.offset' must be {N} numbers (rad or m)")
            b = np.asarray(ctrl["offset"], dtype=float)
        if abs(np.linalg.det(A)) < 1e-9:
            raise ConfigError(f"{src}: field 'controller.coupling' is a singular matrix")
        A, b = _read_only(A), _read_only(b)

    name = str(meta.get("name", meta_file.parent.name if meta_file else u.robot.name or urdf_path.stem))
    return RobotModel(
        name=name,
        urdf_path=urdf_path,
        R_nominal=_read_only(np.stack([T[:3, :3] for T in Ts])),
        t_nominal=_read_only(np.stack([T[:3, 3] for T in Ts])),
        q_lower=_read_only(lower),
        q_upper=_read_only(upper),
        joint_names=tuple(j.name for j in moving),
        link_names=tuple(link_after),
        gravity_in_I=_read_only(g),
        max_velocity=_read_only(max_vel),
        max_acceleration=_read_only(max_acc),
        max_jerk=_read_only(max_jerk),
        reflectors=tuple(reflectors),
        joint_types=tuple(types),
        axis_alignment=_read_only(np.stack(S_all)),
        transform_joints=tj,
        tool_frame=tool,
        base_frame=base,
        locked_joints=dict(locked),
        controller_matrix=A,
        controller_offset=b,
        spec=spec,
        meta_path=meta_file,
        T_root_base=_read_only(T_rb),
    )


#: robot.yaml's gravity, m/s² in F_I: the documented field and its alias
GRAVITY_FIELDS = ("gravity_m_s2", "gravity_in_I_m_s2")


def _gravity_field(meta, src, base) -> np.ndarray:
    """Gravity (3,) m/s² from robot.yaml (DEFAULT_GRAVITY when not stated); ConfigError naming
    the field as the file spells it."""
    given = [k for k in GRAVITY_FIELDS if k in meta]
    for key in given:
        v = meta[key]
        if not _is_numeric_list(v, 3):
            raise ConfigError(f"{src}: field '{key}' must be 3 finite numbers (m/s² in '{base}'), got {v!r}")
        if np.linalg.norm(np.asarray(v, dtype=float)) < 1e-6:
            raise ConfigError(f"{src}: field '{key}' must not be zero (m/s² in '{base}')")
    if len(given) == 2 and not np.allclose(np.asarray(meta[given[0]], dtype=float),
                                          np.asarray(meta[given[1]], dtype=float), rtol=0, atol=1e-12):
        raise ConfigError(f"{src}: fields '{given[0]}' and '{given[1]}' are the same field and disagree; give one")
    return np.asarray(meta[given[0]] if given else DEFAULT_GRAVITY, dtype=float)


#: how `campaign export --urdf` states the gravity in its header comment (read back by :func:`exported_gravity`)
EXPORTED_GRAVITY = "gravity in the base frame '{base}': ({g}) m/s^2"


def exported_gravity(urdf_path, base: str, default) -> np.ndarray:
    """The gravity (3,) m/s² that the header comment of a URDF written by `campaign export --urdf`
    states for the base frame ``base`` (:data:`EXPORTED_GRAVITY`), else ``default``: a URDF cannot
    state gravity, and the exported COMAU's is +y, not the -z a bare URDF gets."""
    import re

    try:
        with open(urdf_path, encoding="utf-8", errors="replace") as fh:
            head = fh.read(4000)
    except OSError:
        return default
    pattern = re.escape(EXPORTED_GRAVITY.format(base=base, g="@")).replace("@", r"([^)]*)")
    m = re.search(pattern, head)
    if m is None or "<!--" not in head[:m.start()]:
        return default
    try:
        g = np.array([float(v) for v in m.group(1).split(",")])
    except ValueError:
        return default
    return g if g.shape == (3,) and np.all(np.isfinite(g)) and np.linalg.norm(g) > 1e-6 else default


def _frame_field(which: str, given) -> str:
    """How a message names the base or tool frame: robot.yaml's field, or the value the caller gave."""
    return f"{which} frame" if given is not None else f"field '{which}_frame':"


def _is_numeric_list(v, n) -> bool:
    if not isinstance(v, (list, tuple)) or len(v) != n:
        return False
    try:
        return all(np.isfinite(float(x)) for x in v)
    except (TypeError, ValueError):
        return False


def _reflectors(meta, src, tool, children, fixed_T) -> list:
    """Reflectors on the tool: ``position_m`` in the tool frame, or a ``link`` below the tool."""
    out = []
    items = meta.get("reflectors") or []
    if not isinstance(items, list):
        raise ConfigError(f"{src}: field 'reflectors' must be a list")
    below = {}  # link -> pose in the tool frame, for links hanging from the tool by fixed joints
    stack = [(tool, np.eye(4))]
    while stack:
        lk, T = stack.pop()
        below[lk] = T
        for j in children.get(lk, []):
            if j.type == "fixed":
                stack.append((j.child, T @ fixed_T(j)))
    for i, r in enumerate(items):
        if not isinstance(r, dict):
            raise ConfigError(f"{src}: field 'reflectors[{i}]' must be a mapping (name, position_m or link, ...)")
        name = str(r.get("name", f"m{i + 1}"))
        if "position_m" in r:
            if not _is_numeric_list(r["position_m"], 3):
                raise ConfigError(f"{src}: field 'reflectors[{i}].position_m' must be 3 finite numbers "
                                  f"(m, tool frame), got {r['position_m']!r}")
            pos = tuple(float(v) for v in r["position_m"])
        elif "link" in r:
            if r["link"] not in below or r["link"] == tool:
                raise ConfigError(f"{src}: field 'reflectors[{i}].link': '{r['link']}' is not a link hanging from "
                                  f"the tool frame '{tool}' by fixed joints")
            pos = tuple(float(v) for v in below[r["link"]][:3, 3])
        else:
            raise ConfigError(f"{src}: field 'reflectors[{i}]' ({name}) needs 'position_m' (tool frame, m) or 'link'")
        axis_key = "axis_in_E" if "axis_in_E" in r else "axis"
        axis = r.get(axis_key, [0, 0, 1])
        if not _is_numeric_list(axis, 3) or np.linalg.norm(np.asarray(axis, dtype=float)) < 1e-9:
            raise ConfigError(f"{src}: field 'reflectors[{i}].{axis_key}' must be 3 finite numbers, not all zero, "
                              f"got {axis!r}")
        axis = np.asarray(axis, dtype=float)
        axis = axis / np.linalg.norm(axis)
        half = r.get("half_angle_deg", 30.0)
        try:
            half = float(half)
        except (TypeError, ValueError):
            half = float("nan")
        if not 0 < half <= 90:
            raise ConfigError(f"{src}: field 'reflectors[{i}].half_angle_deg' must be a number in (0, 90], "
                              f"got {r.get('half_angle_deg')!r}")
        out.append(Reflector(name, str(r.get("kind", "smr")), pos, tuple(axis), float(np.deg2rad(half))))
    return out
