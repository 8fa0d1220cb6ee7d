"""The MuJoCo twin: a robot cell whose physics is MuJoCo's, not ours (``--cell mujoco``).

The controller and the tracker of this module are cell adapters (docs/cell.md) sharing one
:class:`Twin`, built by MuJoCo's compiler from the run's URDF and scene
(:mod:`campaign.cell.mjcf`):

* the robot as it really is: the nominal chain plus hidden manufacturing errors (joint origin
  offsets and tilts of the paper's Table 4 size, drawn from a seed as the simulated cell's,
  :func:`campaign.sim.truth.make_truth`), written to ``RUN/cell/truth.yaml`` only;
* joints held by position servos of finite stiffness and damping, so that the arm sags under
  its own weight as MuJoCo's dynamics make it, and the encoders (the motor side) read the
  commanded angles;
* ``move(q)`` follows Ruckig's time-optimal, jerk-limited profile from the last command to q
  (as `plan` times it) as the servos' targets, step by step, then waits until every joint is
  at rest (speed below ``settle_velocity_rad_s`` for ``settle_steps`` steps in a row); every
  step counts MuJoCo's contacts between the robot and the scene and between non-adjacent
  links: a contact stops the motion, puts the arm back where the motion began (an operator
  would jog it back) and fails the pose with ``RobotFault("collision in the twin: ...")``;
* the tracker reads the reflector sites in its frame with Gaussian noise and loses a beam when
  the reflector is out of range, outside its nest's cone, or MuJoCo's ray from the tracker to
  it hits any geom before the reflector's own sphere (``nest_radius_m``);
* the simulated time is the campaign clock (``clock()``): the motions' steps, and the tracker's
  time per target (``plan.tracker_time_per_reflector_s``).

``RUN/cell/twin.json`` (written atomically after every motion) counts the motions, steps and
contacts of this session: ``{"contacts", "max_penetration_m", "motions", "steps", ...}``, and
keeps every session of the run (``sessions``, earlier ones first, and their sums ``totals``).

Options (``--options FILE.yaml``), SI units; the ``controller:`` section sets up the world:
``seed`` (default: ``sim.seed``), ``stiffness_nm_rad`` (one number or one per joint, N·m/rad or
N/m; default 1e5: a few tenths of a millimetre of sag at the COMAU's tool), ``damping_ratio``
(0.7; the damping of joint j is 2·ζ·sqrt(kp_j·(M_jj + armature_j)) with M at the middle of the
limits) or ``damping_nms_rad`` (per joint), ``armature_kgm2`` (0.1), ``timestep_s`` (1e-3,
made smaller when a servo's natural frequency needs it), ``settle_velocity_rad_s`` (1e-5),
``settle_steps`` (20), ``max_settle_s`` (10), ``start_q`` (the arm's rest pose before the
first move; default: the first target, where the operator put it). The ``tracker:`` section:
``noise_m`` (default ``sim.noise_m``), ``resolution_m`` (1e-6), ``nest_radius_m`` (0.0191, a
1.5" reflector), ``search_radius_m`` (0.05: a reflector farther than this from the driver's aim is
not found), ``position_m`` and ``rotation_cardan_deg`` (its pose in the scene's frame;
default the scene's).
"""

from __future__ import annotations

import json
import threading
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from campaign.cell import RobotFault, context, request_id
from campaign.config import check_int, check_number, load_config
from campaign.errors import ConfigError
from campaign.measure.protocol import SETUP_TARGETS
from campaign.measure.reflectors import transform_points
from campaign.tolerances import REFLECTOR_RADIUS_M

#: key of the twin in the cell's shared dict
SHARED_KEY = "campaign.cell.mujoco_twin"
#: distances of the base-frame set-up points from F_I's origin along x and y (m), as the simulated cell's
SETUP_SPACING_M = 0.3
#: the set-up points in F_I (m): on the base plate, measured before the campaign (no ray cast)
SETUP_POINTS_I = {"setup_origin": np.zeros(3), "setup_x": np.array([SETUP_SPACING_M, 0.0, 0.0]),
                  "setup_y": np.array([0.0, SETUP_SPACING_M, 0.0])}
#: servo stiffness (N·m/rad or N/m): joint compliance 1e-5 rad/(N·m); the COMAU's tool sags by 0.1 to
#: 0.6 mm over the default short campaign
DEFAULT_STIFFNESS = 1.0e5
DEFAULT_DAMPING_RATIO = 0.7
#: reflected rotor inertia (kg·m²): a 1e-5 kg·m² rotor through a 100:1 gear
DEFAULT_ARMATURE = 0.1
DEFAULT_TIMESTEP_S = 1e-3
#: a servo's natural frequency times the step stays below this (semi-implicit Euler is stable below 2)
MAX_OMEGA_DT = 1.0
#: random configurations in which a pair of chain frames must always touch to be excluded from contacts
EXCLUDE_SAMPLES = 100
#: radius of a 1.5" spherically mounted reflector (m): the beam ends at its surface (as the plan's)
DEFAULT_NEST_RADIUS_M = REFLECTOR_RADIUS_M
DEFAULT_RESOLUTION_M = 1e-6
#: how far from where it is aimed (m) the tracker finds a reflector (its search spiral)
DEFAULT_SEARCH_RADIUS_M = 0.05


def _number(value, where, **limits) -> float:
    """check_number, also of a number YAML read as text (it reads ``1e5`` so, ``1.0e5`` as a number)."""
    if isinstance(value, str):
        try:
            value = float(value)
        except ValueError:
            pass
    return check_number(value, where, **limits)


def _per_joint(value, n, where, *, low=0.0, low_open=True) -> np.ndarray:
    if isinstance(value, (list, tuple)):
        if len(value) != n:
            raise ConfigError(f"{where}: must be one number or {n} (one per joint), got {len(value)}")
        return np.array([_number(v, f"{where}[{i}]", low=low, low_open=low_open) for i, v in enumerate(value)])
    return np.full(n, _number(value, where, low=low, low_open=low_open))


@dataclass(frozen=True)
class TwinOptions:
    """The world's settings (the ``controller:`` options), validated. SI units."""

    seed: int = 0
    stiffness: tuple = ()
    damping: tuple | None = None
    damping_ratio: float = DEFAULT_DAMPING_RATIO
    armature: tuple = ()
    timestep_s: float = DEFAULT_TIMESTEP_S
    settle_velocity_rad_s: float = 1e-5
    settle_steps: int = 20
    max_settle_s: float = 10.0
    start_q: tuple | None = None

    KEYS = ("seed", "stiffness_nm_rad", "damping_nms_rad", "damping_ratio", "armature_kgm2", "timestep_s",
            "settle_velocity_rad_s", "settle_steps", "max_settle_s", "start_q")

    @classmethod
    def parse(cls, options: dict, n_joints: int, default_seed: int = 0, where: str = "controller options"):
        o = dict(options or {})
        extra = sorted(set(o) - set(cls.KEYS))
        if extra:
            raise ConfigError(f"{where}: unknown option {extra[0]!r} of the MuJoCo twin "
                              f"(allowed: {', '.join(cls.KEYS)})")
        w = lambda k: f"{where}: {k}"  # noqa: E731
        kw = {"seed": check_int(o.get("seed", default_seed), w("seed"), low=0, high=2**63 - 1),
              "stiffness": tuple(_per_joint(o.get("stiffness_nm_rad", DEFAULT_STIFFNESS), n_joints,
                                            w("stiffness_nm_rad"))),
              "armature": tuple(_per_joint(o.get("armature_kgm2", DEFAULT_ARMATURE), n_joints, w("armature_kgm2"),
                                           low_open=False))}
        if "damping_nms_rad" in o:
            kw["damping"] = tuple(_per_joint(o["damping_nms_rad"], n_joints, w("damping_nms_rad")))
        for key, low in (("damping_ratio", 0.0), ("timestep_s", 0.0), ("settle_velocity_rad_s", 0.0),
                         ("max_settle_s", 0.0)):
            if key in o:
                kw[key] = _number(o[key], w(key), low=low, low_open=True)
        if "settle_steps" in o:
            kw["settle_steps"] = check_int(o["settle_steps"], w("settle_steps"), low=1, high=10**6)
        if o.get("start_q") is not None:
            kw["start_q"] = tuple(_per_joint(o["start_q"], n_joints, w("start_q"), low=None))
        return cls(**kw)


class Twin:
    """The MuJoCo world of one cell: the truth robot in its scene, its servos, its clock.

    robot: the RobotModel with the reflectors the run measures; scene: the Scene placed in the
    robot's F_I; opts: :class:`TwinOptions`; run_dir: where ``cell/truth.yaml`` and
    ``cell/twin.json`` go (None: nowhere); start_clock_s: the campaign clock to start from (s).
    ``move``, ``set_joints`` and the tracker's ``measure`` hold the twin's lock (the controller
    and the tracker are served by two threads).
    """

    def __init__(self, robot, scene, opts: TwinOptions, *, run_dir=None, start_clock_s: float = 0.0, config=None):
        import mujoco

        from campaign.cell.mjcf import build_mjcf
        from campaign.model.export import calibrated_transforms
        from campaign.sim.truth import make_truth

        self.robot, self.scene, self.opts = robot, scene, opts
        #: the cell's CampaignConfig (its plan's tracker time per target, its sim's noise) or None
        self.config = config
        N = robot.n_joints
        self.p_e = make_truth(robot, seed=opts.seed, noise_m=0.0).p_e
        self.chain_T = np.array(calibrated_transforms(robot, self.p_e))
        self.kp = np.array(opts.stiffness, dtype=float)
        self.armature = np.array(opts.armature, dtype=float)

        def compile_model(kv, timestep, exclude=()):
            xml = build_mjcf(robot, self.chain_T, scene.obstacles, kp=self.kp, kv=kv, armature=self.armature,
                             timestep_s=timestep, exclude=exclude)
            try:
                return mujoco.MjModel.from_xml_string(xml)
            except ValueError as exc:
                raise ConfigError(f"{robot.urdf_path}: MuJoCo cannot compile the twin "
                                  f"({str(exc).splitlines()[0]})") from None

        # the inertia each servo drives (its diagonal of the mass matrix, middle of the limits, plus
        # the armature) sets the damping of the ratio asked for and the step that integrates it
        probe = compile_model(np.zeros(N), opts.timestep_s)
        inertia = self._joint_inertia(probe, robot.q_mid)
        omega = np.sqrt(self.kp / inertia)
        self.kv = (np.array(opts.damping, dtype=float) if opts.damping is not None
                   else 2.0 * opts.damping_ratio * np.sqrt(self.kp * inertia))
        self.timestep_s = float(min(opts.timestep_s, MAX_OMEGA_DT / omega.max()))
        self.excluded_pairs = self._always_touching(probe, robot)
        self.model = compile_model(self.kv, self.timestep_s, self.excluded_pairs)
        self.data = mujoco.MjData(self.model)
        m = self.model
        self._site = {r.name: mujoco.mj_name2id(m, mujoco.mjtObj.mjOBJ_SITE, f"reflector:{r.name}")
                      for r in robot.reflectors}
        self._site_E = mujoco.mj_name2id(m, mujoco.mjtObj.mjOBJ_SITE, "E")
        self._axis_E = {r.name: np.asarray(r.axis_in_E, dtype=float) for r in robot.reflectors}
        #: acceptance half-angle of each reflector's nest, rad
        self.half_angle = {r.name: float(r.half_angle) for r in robot.reflectors}
        self.q_cmd = None  # the last commanded joint vector (the motor side), None before the first move
        self.clock_s = float(start_clock_s)
        self.lock = threading.RLock()
        self.stats = {"contacts": 0, "max_penetration_m": 0.0, "motions": 0, "steps": 0, "collisions": 0,
                      "contact_pairs": [], "excluded_pairs": [list(p) for p in self.excluded_pairs],
                      "lost_beams": {},
                      "timestep_s": self.timestep_s, "simulated_s": 0.0}
        self.run_dir = Path(run_dir) if run_dir is not None else None
        self.earlier_sessions = self._earlier_sessions()
        self.tracker_truth = None
        self.write_truth()
        self.write_stats()

    # -- set-up ---------------------------------------------------------------------------------
    @staticmethod
    def _joint_inertia(model, q) -> np.ndarray:
        import mujoco

        d = mujoco.MjData(model)
        d.qpos[:] = q
        mujoco.mj_forward(model, d)
        diag = np.empty(model.nv)
        for j, e in enumerate(np.eye(model.nv)):
            col = np.empty(model.nv)
            mujoco.mj_mulM(model, d, col, e)
            diag[j] = col[j]
        return diag  # includes the armature

    @staticmethod
    def _always_touching(model, robot) -> tuple:
        """Pairs (i, j) of chain frames in contact in every one of EXCLUDE_SAMPLES random
        configurations (parts that touch by design, as a set-up assistant disables them)."""
        import mujoco

        from campaign.cell.mjcf import body_name
        from campaign.sim.truth import random_joint_poses

        d = mujoco.MjData(model)
        N = robot.n_joints
        body_frame = {mujoco.mj_name2id(model, mujoco.mjtObj.mjOBJ_BODY, body_name(k, N)): k for k in range(N + 2)}
        always = None
        for q in random_joint_poses(robot, EXCLUDE_SAMPLES, seed=1, margin=0.0):
            d.qpos[:] = q
            mujoco.mj_kinematics(model, d)
            mujoco.mj_collision(model, d)
            seen = set()
            for c in d.contact[:d.ncon]:
                a = body_frame.get(int(model.geom_bodyid[c.geom1]))
                b = body_frame.get(int(model.geom_bodyid[c.geom2]))
                if a is not None and b is not None:
                    seen.add((min(a, b), max(a, b)))
            always = seen if always is None else always & seen
            if not always:
                return ()
        return tuple(sorted(always or ()))

    def truth_doc(self) -> dict:
        o = self.opts
        doc = {"robot": self.robot.name, "seed": o.seed, "p_e": [float(v) for v in self.p_e],
               "chain_transforms": [[[float(v) for v in row] for row in T] for T in self.chain_T],
               "servo": {"stiffness": [float(v) for v in self.kp], "damping": [float(v) for v in self.kv],
                         "armature": [float(v) for v in self.armature]},
               "timestep_s": self.timestep_s, "gravity_m_s2": [float(v) for v in self.robot.gravity_in_I]}
        if self.tracker_truth is not None:
            doc["tracker"] = self.tracker_truth
        return doc

    def write_truth(self):
        if self.run_dir is None:
            return
        import yaml

        from campaign.fileio import atomic_write

        atomic_write(self.run_dir / "cell" / "truth.yaml", yaml.safe_dump(self.truth_doc(), sort_keys=False))

    def _earlier_sessions(self) -> list:
        """The sessions an earlier twin of this run wrote to ``cell/twin.json`` (each its stats)."""
        if self.run_dir is None:
            return []
        try:
            doc = json.loads((self.run_dir / "cell" / "twin.json").read_text())
        except (OSError, ValueError):
            return []
        if not isinstance(doc, dict):
            return []
        if isinstance(doc.get("sessions"), list):
            return [d for d in doc["sessions"] if isinstance(d, dict)]
        return [doc]  # written before the file kept its sessions

    def write_stats(self):
        """``cell/twin.json``: this session's counts at the top level (as they always were), every
        session's (earlier ones first) under ``sessions``, and their sums under ``totals``."""
        if self.run_dir is None:
            return
        from campaign.fileio import atomic_write

        sessions = self.earlier_sessions + [self.stats]
        totals = {k: sum(int(d.get(k, 0)) for d in sessions) for k in ("contacts", "motions", "steps", "collisions")}
        lost = {}
        for d in sessions:
            for why, n in (d.get("lost_beams") or {}).items():
                lost[why] = lost.get(why, 0) + int(n)
        totals.update(lost_beams=lost, simulated_s=sum(float(d.get("simulated_s", 0.0)) for d in sessions),
                      max_penetration_m=max(float(d.get("max_penetration_m", 0.0)) for d in sessions))
        doc = {**self.stats, "sessions": sessions, "totals": totals}
        atomic_write(self.run_dir / "cell" / "twin.json", json.dumps(doc, indent=2) + "\n")

    # -- the controller's side ------------------------------------------------------------------
    def move(self, q) -> None:
        """Drive the arm to the joint vector q (N,) (rad | m) along Ruckig's profile and wait until
        it is at rest; RobotFault on a contact or when it does not settle."""
        import mujoco

        from campaign.cell.mjcf import servo_command
        from campaign.plan.timing import ruckig_trajectory

        q = np.asarray(q, dtype=float).reshape(self.robot.n_joints)
        m, d = self.model, self.data
        with self.lock:
            placed = self.q_cmd is None
            if placed:  # the arm stands at rest where the operator put it
                start = np.array(self.opts.start_q if self.opts.start_q is not None else q)
                d.qpos[:] = start
                d.qvel[:] = 0.0
                d.ctrl[:] = start
                self.q_cmd = start
            q_from = self.q_cmd.copy()
            saved = (d.qpos.copy(), d.qvel.copy())
            dt = m.opt.timestep
            duration, traj = ruckig_trajectory(self.robot, q_from, q)
            n_motion = int(np.ceil(duration / dt - 1e-9))
            steps = 0
            try:
                for k in range(n_motion):
                    p, v, _ = traj.at_time(k * dt)
                    d.ctrl[:] = servo_command(p, v, self.kp, self.kv)
                    mujoco.mj_step(m, d)
                    steps += 1
                    if d.ncon:
                        self._collision()
                d.ctrl[:] = q
                calm, limit = 0, int(np.ceil(self.opts.max_settle_s / dt))
                thr = self.opts.settle_velocity_rad_s
                while calm < self.opts.settle_steps:
                    mujoco.mj_step(m, d)
                    steps += 1
                    if d.ncon:
                        self._collision()
                    calm = calm + 1 if np.max(np.abs(d.qvel)) < thr else 0
                    if steps - n_motion > limit:
                        raise RobotFault(f"the twin's arm did not settle within {self.opts.max_settle_s} s "
                                         f"(joint speeds up to {np.max(np.abs(d.qvel)):.3g} rad/s)")
            except RobotFault:
                d.qpos[:], d.qvel[:] = saved[0], saved[1]
                d.ctrl[:] = q_from
                mujoco.mj_kinematics(m, d)
                if placed:  # not a pose to go back to: the operator places the arm again at the next move
                    self.q_cmd = None
                raise
            finally:
                self.stats["motions"] += 1
                self.stats["steps"] += steps
                self.clock_s += steps * dt
                self.stats["simulated_s"] += steps * dt
                self.write_stats()
            self.q_cmd = q.copy()
            mujoco.mj_kinematics(m, d)

    def _collision(self):
        """Count the contacts of this step; raise RobotFault naming the deepest pair."""
        import mujoco

        m, d = self.model, self.data
        con = d.contact[:d.ncon]
        depth = -np.asarray(con.dist, dtype=float)
        k = int(np.argmax(depth))
        names = sorted(mujoco.mj_id2name(m, mujoco.mjtObj.mjOBJ_GEOM, int(g)) for g in (con.geom1[k], con.geom2[k]))
        self.stats["contacts"] += int(d.ncon)
        self.stats["collisions"] += 1
        self.stats["max_penetration_m"] = max(self.stats["max_penetration_m"], float(max(depth.max(), 0.0)))
        pair = " and ".join(names)
        if pair not in self.stats["contact_pairs"]:
            self.stats["contact_pairs"].append(pair)
        raise RobotFault(f"collision in the twin: {pair} ({max(depth[k], 0.0) * 1e3:.2f} mm deep)")

    def joint_positions(self) -> np.ndarray:
        """The link side: the joint angles the arm is really at (N,), rad | m."""
        return self.data.qpos.copy()

    # -- the tracker's side ---------------------------------------------------------------------
    def reflectors_in_I(self) -> dict:
        """{name: (centre (3,) m, nest axis (3,) unit)} in F_I at the arm's current state."""
        d = self.data
        out = {}
        for name, sid in self._site.items():
            R = d.site_xmat[sid].reshape(3, 3)
            out[name] = (d.site_xpos[sid].copy(), R @ self._axis_E[name])
        return out

    def tool_pose(self) -> np.ndarray:
        """Pose of the tool frame E in F_I at the arm's current state, (4, 4)."""
        T = np.eye(4)
        T[:3, :3] = self.data.site_xmat[self._site_E].reshape(3, 3)
        T[:3, 3] = self.data.site_xpos[self._site_E]
        return T

    def set_joints(self, q):
        """Place the arm at the link-side joint vector q (N,) at rest, without dynamics (tests,
        inspection): the kinematics of the truth."""
        import mujoco

        with self.lock:
            self.data.qpos[:] = q
            self.data.qvel[:] = 0.0
            mujoco.mj_kinematics(self.model, self.data)

    def first_hit(self, origin, target) -> tuple:
        """(distance m, geom name) of the first geom MuJoCo's ray from ``origin`` towards
        ``target`` (F_I, m) meets, or (inf, None)."""
        import mujoco

        origin = np.asarray(origin, dtype=float)
        vec = np.asarray(target, dtype=float) - origin
        vec = vec / np.linalg.norm(vec)
        gid = np.array([-1], dtype=np.int32)
        dist = mujoco.mj_ray(self.model, self.data, origin, vec, None, 1, -1, gid)
        if dist < 0 or gid[0] < 0:
            return float("inf"), None
        return float(dist), mujoco.mj_id2name(self.model, mujoco.mjtObj.mjOBJ_GEOM, int(gid[0]))

    def close(self):
        with self.lock:
            self.write_stats()


def _cell_config(ctx):
    """The cell's CampaignConfig: the served run's, its campaign.yaml, or the embedded default."""
    if ctx.config is not None:
        return ctx.config
    if ctx.run_dir is not None and (Path(ctx.run_dir) / "campaign.yaml").is_file():
        return load_config(Path(ctx.run_dir) / "campaign.yaml")
    return load_config(None)


def shared_twin(robot, options=None) -> Twin:
    """The cell's one Twin (built on first use, from the ``controller:`` options)."""
    from campaign.plan.scene import load_scene

    ctx = context()
    shared = ctx.shared
    twin = shared.get(SHARED_KEY)
    if twin is not None:
        if options:
            raise ConfigError("the MuJoCo twin was built before the controller's options were read "
                              "(build the controller first)")
        return twin
    cfg = _cell_config(ctx)
    robot = robot.with_default_reflectors()
    opts = TwinOptions.parse(options or {}, robot.n_joints, default_seed=cfg.sim.seed)
    scene = load_scene(cfg.scene_path).placed(robot)
    twin = Twin(robot, scene, opts, run_dir=ctx.run_dir, start_clock_s=ctx.start_clock_s, config=cfg)
    shared[SHARED_KEY] = twin
    if twin.run_dir is not None:  # `campaign serve` prints what the cell announces in its ready line
        shared.setdefault("announce", {})["truth"] = str(twin.run_dir / "cell" / "truth.yaml")
    return twin


class Controller:
    """The twin's robot controller (cell adapter): ``move(q)`` drives the MuJoCo arm."""

    joint_convention = "model"

    def __init__(self, robot, options):
        self.twin = shared_twin(robot, options)

    def move(self, q):
        self.twin.move(q)

    def joints(self):
        """The motor side: the commanded joint vector, as a real controller's encoders read it."""
        return tuple(float(v) for v in self.twin.q_cmd)

    def clock(self) -> float:
        return self.twin.clock_s

    def close(self):
        self.twin.close()


@dataclass(frozen=True)
class TrackerOptions:
    """The ``tracker:`` options, validated. SI units."""

    noise_m: float
    resolution_m: float = DEFAULT_RESOLUTION_M
    nest_radius_m: float = DEFAULT_NEST_RADIUS_M
    search_radius_m: float = DEFAULT_SEARCH_RADIUS_M
    position_m: tuple | None = None
    rotation_cardan_deg: tuple | None = None

    KEYS = ("noise_m", "resolution_m", "nest_radius_m", "search_radius_m", "position_m", "rotation_cardan_deg")

    @classmethod
    def parse(cls, options: dict, default_noise_m: float, where: str = "tracker options"):
        o = dict(options or {})
        extra = sorted(set(o) - set(cls.KEYS))
        if extra:
            raise ConfigError(f"{where}: unknown option {extra[0]!r} of the MuJoCo twin's tracker "
                              f"(allowed: {', '.join(cls.KEYS)})")
        kw = {"noise_m": _number(o.get("noise_m", default_noise_m), f"{where}: noise_m", low=0.0, high=1.0)}
        for key in ("resolution_m", "nest_radius_m", "search_radius_m"):
            if key in o:
                kw[key] = _number(o[key], f"{where}: {key}", low=0.0, high=1.0)
        for key in ("position_m", "rotation_cardan_deg"):
            if key in o:
                v = o[key]
                if not isinstance(v, (list, tuple)) or len(v) != 3:
                    raise ConfigError(f"{where}: {key} must be 3 numbers, got {v!r}")
                kw[key] = tuple(_number(x, f"{where}: {key}[{i}]") for i, x in enumerate(v))
        return cls(**kw)


class Tracker:
    """The twin's laser tracker (cell adapter): reflector sites seen from the tracker's pose."""

    def __init__(self, robot, options):
        from campaign.model.rotations import cardan_xyz

        self.twin = tw = shared_twin(robot)
        self.opts = TrackerOptions.parse(options, tw.config.sim.noise_m)
        scene = tw.scene
        T_IL = np.array(scene.T_IL)
        if self.opts.position_m is not None or self.opts.rotation_cardan_deg is not None:
            T_cell_L = np.array(scene.T_cell_I) @ T_IL  # the scene's tracker pose, in the cell's frame
            if self.opts.position_m is not None:
                T_cell_L[:3, 3] = self.opts.position_m
            if self.opts.rotation_cardan_deg is not None:
                T_cell_L[:3, :3] = cardan_xyz(*np.deg2rad(self.opts.rotation_cardan_deg))
            T_IL = np.linalg.solve(np.array(scene.T_cell_I), T_cell_L)
        self.T_IL = T_IL
        self.T_LI = np.linalg.inv(T_IL)
        self.tracker_s = float(tw.config.plan.tracker_time_per_reflector_s)
        self._count = 0
        tw.tracker_truth = {"T_LI": [[float(v) for v in row] for row in self.T_LI], "noise_m": self.opts.noise_m,
                            "resolution_m": self.opts.resolution_m, "nest_radius_m": self.opts.nest_radius_m}
        tw.write_truth()

    def lost(self, name, p, axis) -> str | None:
        """Why the beam to reflector ``name`` at p (3,) with nest axis (3,) in F_I is lost, or None."""
        o = self.T_IL[:3, 3]
        to_tracker = o - p
        dist = float(np.linalg.norm(to_tracker))
        sc = self.twin.scene
        if not sc.min_range_m <= dist <= sc.max_range_m:
            return "out of range"
        if axis @ to_tracker < np.cos(self.twin.half_angle[name]) * dist:
            return "outside the nest's cone"
        hit, geom = self.twin.first_hit(o, p)
        if hit < dist - self.opts.nest_radius_m:
            return f"beam blocked by {geom}"
        return None

    def measure(self, aims):
        tw = self.twin
        with tw.lock:
            rid = request_id()
            self._count += 1
            rng = np.random.default_rng([tw.opts.seed, 99, rid if rid is not None else self._count])
            seen = tw.reflectors_in_I()
            out = {}
            for name, aim in aims.items():
                why = None
                if name in seen:
                    p, axis = seen[name]
                    why = self.lost(name, p, axis)
                elif name in SETUP_POINTS_I:
                    p = SETUP_POINTS_I[name]
                else:
                    raise ValueError(f"unknown target {name!r} (the twin's reflectors: {', '.join(seen)}; "
                                     f"set-up points: {', '.join(SETUP_TARGETS)})")
                x = transform_points(self.T_LI, np.asarray(p, dtype=float)[None])[0]
                if why is None and aim is not None and np.linalg.norm(np.asarray(aim, dtype=float) - x) > \
                        self.opts.search_radius_m:
                    why = "aimed beyond the search radius"
                if why:
                    lost = tw.stats["lost_beams"]
                    lost[why] = lost.get(why, 0) + 1
                    out[name] = "out_of_range" if why == "out of range" else None
                    continue
                if self.opts.noise_m > 0:
                    x = x + rng.normal(0.0, self.opts.noise_m, 3)
                    if self.opts.resolution_m > 0:
                        x = np.round(x / self.opts.resolution_m) * self.opts.resolution_m
                out[name] = tuple(float(v) for v in x)
            tw.clock_s += self.tracker_s * len(aims)
            if any(v is None or isinstance(v, str) for v in out.values()):
                tw.write_stats()
            return out

    def clock(self) -> float:
        return self.twin.clock_s

    def close(self):
        self.twin.close()
