"""The hidden truth of a simulated cell: geometric errors, physical effects, tracker noise.

Nothing that `plan`, `calibrate` or `diagnose` imports may import this module: the
truth's values live only here and in the simulator's own file (``truth.yaml``).

:class:`TruthRobot` produces what a laser tracker would see: noisy reflector centres in
F_L, from which :func:`synthesize` derives measured poses exactly as a real campaign does
(T_LI from the base-frame set-up points, then Kabsch on the three reflectors).
"""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
import yaml

from campaign.effects.base import EffectSet, effect_context, is_file_spec, make_effect, model_pose, split_joints
from campaign.measure.data import MeasuredPoses
from campaign.measure.reflectors import frame_from_setup_points, pose_from_reflectors, transform_points
from campaign.model.base_params import base_parameters
from campaign.model.robot import DEFAULT_REFLECTOR_POSITIONS, RobotModel
from campaign.model.rotations import cardan_xyz

#: The paper's Table 4: identified base parameters of its COMAU Racer5-0.80 (m or rad),
#: in the order of Table 3. Used as the magnitude of the hidden geometric errors.
TABLE4_BASE = np.array([
    7.752e-4, 2.343e-3, -2.720e-3, -2.567e-4, 6.334e-5, 1.676e-3, 5.611e-4, 8.479e-4, -3.293e-4, 8.669e-5,
    -7.575e-4, -6.430e-4, -2.026e-5, -1.524e-3, -1.639e-3, 8.150e-4, -1.054e-4, 3.050e-3, -2.759e-3, 1.279e-2,
    -8.877e-4, 2.778e-3, -5.821e-5, -1.393e-4, -2.455e-4, 2.380e-4, -1.934e-2, 7.956e-3, 2.588e-4, 1.134e-3,
])

#: Leica LTD800: 1 µm resolution; ±25 µm accuracy. σ per coordinate of a reflector centre.
TRACKER_NOISE_M = 10e-6
TRACKER_RESOLUTION_M = 1e-6


#: Reflectors assumed on the tool of a robot whose robot.yaml names fewer than three, m in the
#: tool frame (a 5 cm triad: enough for a pose from Kabsch; the model's DEFAULT_REFLECTORS).
DEFAULT_TOOL_TRIAD = np.array(DEFAULT_REFLECTOR_POSITIONS)


def tool_points(robot: RobotModel) -> np.ndarray:
    """The reflector centres the simulated tracker sees, (k, 3) m in the tool frame."""
    P = robot.reflector_positions_in_E
    return P if len(P) >= 3 else DEFAULT_TOOL_TRIAD


def default_T_LI() -> np.ndarray:
    """A plausible pose of F_I in the tracker frame: tracker 3 m in front of the robot."""
    T = np.eye(4)
    T[:3, :3] = cardan_xyz(0.02, -0.6, 0.01)
    T[:3, 3] = (0.4, -0.3, 3.0)
    return T


@dataclass(frozen=True)
class TruthRobot:
    """A robot as it really is. Angles in rad, lengths in m."""

    robot: RobotModel
    p_e: np.ndarray
    T_LI: np.ndarray = field(default_factory=default_T_LI)
    noise_m: float = TRACKER_NOISE_M
    resolution_m: float = TRACKER_RESOLUTION_M
    effects: EffectSet = EffectSet()
    theta: np.ndarray = field(default_factory=lambda: np.zeros(0))

    def pose(self, q, context=None) -> np.ndarray:
        """True pose of F_E in F_I, (n, 4, 4)."""
        return model_pose(self.robot, q, self.p_e, self.effects, self.theta, context)

    def pose_in_measured_frame(self, q, T_LI_measured, context=None) -> np.ndarray:
        """True pose of F_E in the frame I' that the set-up points defined, (n, 4, 4).

        A set-up error makes I' differ slightly from I; the base parameters absorb it, so
        recovered parameters are to be compared with the truth seen in I'.
        """
        from campaign.measure.reflectors import invert

        return invert(T_LI_measured) @ self.T_LI @ self.pose(q, context)

    def pose_of(self, poses) -> np.ndarray:
        """True poses of measured poses (MeasuredPoses) in their own set-up frame, (n, 4, 4)."""
        return self.pose_in_measured_frame(poses.q, poses.T_LI, effect_context(poses.context, poses.time_s))

    def expected_base_params(self, T_LI_measured, n_poses: int = 500, seed: int = 0) -> np.ndarray:
        """The base parameters that reproduce this truth's geometry in frame I' exactly
        (a noise-free fit; only for evaluating a pipeline after it has answered)."""
        from campaign.identify.solver import CalibrationModel

        q = random_joint_poses(self.robot, n_poses, seed)
        T = self.pose_in_measured_frame(q, T_LI_measured)
        model = CalibrationModel(robot=self.robot, estimate_noise=False).fit(q, T)
        return model.base_params_

    def reflectors_in_L(self, q, rng, context=None) -> np.ndarray:
        """Noisy reflector centres in F_L as the tracker reports them, (n, k, 3), m."""
        T_LE = self.T_LI @ self.pose(q, context)
        P_E = tool_points(self.robot)
        P = transform_points(T_LE, np.broadcast_to(P_E, (len(T_LE),) + P_E.shape))
        return self._measure_points(P, rng)

    def setup_points_in_L(self, rng, spacing_m: float = 0.3, repeats: int = 10) -> np.ndarray:
        """The base-frame set-up points (origin, on x, on y of F_I) in F_L, averaged over repeats, (3, 3)."""
        P_I = np.array([[0.0, 0.0, 0.0], [spacing_m, 0.0, 0.0], [0.0, spacing_m, 0.0]])
        P_L = transform_points(self.T_LI, P_I)
        return np.mean([self._measure_points(P_L, rng) for _ in range(repeats)], axis=0)

    def _measure_points(self, P, rng):
        P = P + rng.normal(0.0, self.noise_m, size=P.shape) if self.noise_m > 0 else P.copy()
        if self.resolution_m > 0:
            P = np.round(P / self.resolution_m) * self.resolution_m
        return P

    def to_yaml(self) -> str:
        doc = {
            "robot": self.robot.name,
            "p_e": [float(v) for v in self.p_e],
            "T_LI": [[float(v) for v in row] for row in self.T_LI],
            "noise_m": float(self.noise_m),
            "resolution_m": float(self.resolution_m),
            # a user's effect file or a joint list by its spec (path/file.py:Class, name:2,3), so that
            # read_truth finds it again
            "effects": {(e.spec if is_file_spec(split_joints(getattr(e, "spec", ""))[0]) or split_joints(e.spec)[1]
                         else e.name): [float(v) for v in th]
                        for e, th in zip(self.effects.effects, self.effects.split(self.theta))},
        }
        return yaml.safe_dump(doc, sort_keys=False)


def make_truth(robot: RobotModel | None = None, *, seed: int | None = 0, scale: float = 1.0,
               noise_m: float = TRACKER_NOISE_M, resolution_m: float = TRACKER_RESOLUTION_M,
               effects: dict | None = None, T_LI=None, position_only: bool = False) -> TruthRobot:
    """A truth robot with geometric errors of the size of the paper's Table 4.

    ``seed=None`` takes Table 4 itself; a seed draws each base parameter as Table 4's
    magnitude times a random sign and a factor in [0.5, 1.5]. The errors are placed on the
    base parameters (``p_e = expand(p_b)``), so the geometric model can represent them
    exactly. ``effects``: name -> parameter vector of hidden physical effects.
    ``position_only``: place them on the base set of position measurements (what one-reflector
    data can identify), so that such data, too, can represent the truth exactly.
    """
    robot = robot or RobotModel.load()
    base = base_parameters(robot, position_only=position_only)
    if seed is None:
        p_b = TABLE4_BASE.copy()
    else:
        rng = np.random.default_rng(seed)
        p_b = np.abs(TABLE4_BASE) * rng.choice([-1.0, 1.0], size=30) * rng.uniform(0.5, 1.5, size=30)
    if base.n_base != len(p_b):
        p_b = np.resize(p_b, base.n_base)
    p_e = base.expand(scale * p_b)
    effs = []
    thetas = []
    for name, th in (effects or {}).items():
        e = make_effect(name, robot)
        th = np.asarray(th, dtype=float)
        if th.shape != (e.n_params,):
            raise ValueError(f"effect {name}: expected {e.n_params} parameters, got {th.shape}")
        effs.append(e)
        thetas.append(th)
    return TruthRobot(robot, p_e, default_T_LI() if T_LI is None else np.asarray(T_LI, dtype=float),
                      noise_m, resolution_m, EffectSet(tuple(effs)),
                      np.concatenate(thetas) if thetas else np.zeros(0))


#: mean displacement (m) of the tool point that a hidden effect without a declared scale gets
#: (a few tenths of a millimetre: well above the tracker's noise, small against the geometry's errors)
DEFAULT_EFFECT_DISPLACEMENT_M = 3e-4


def hidden_effect_params(effect, seed: int = 0, params=None) -> np.ndarray:
    """The hidden parameter vector (SI, the effect's order) of ``effect`` in a simulated truth:
    ``params`` when campaign.yaml states them (``{effect: SPEC, params: [...]}``), else the
    effect's ``typical_params(seed)``, else normal draws at the scale it declares
    (``typical_scale``: one number or one per parameter, SI), else normal draws scaled so that
    the effect moves the tool point by DEFAULT_EFFECT_DISPLACEMENT_M on average over random
    poses (each parameter's share by its own effect at the tool)."""
    from campaign.errors import ConfigError

    if params is not None:
        params = np.asarray(params, dtype=float)
        if params.shape != (effect.n_params,):
            raise ConfigError(f"sim.hidden_effects: effect '{effect.spec}' has {effect.n_params} parameters "
                              f"({', '.join(effect.param_names)}), the entry states {params.size}")
        return params
    if hasattr(effect, "typical_params"):
        return np.asarray(effect.typical_params(seed), dtype=float).reshape(effect.n_params)
    rng = np.random.default_rng([int(seed), 4099])
    draw = rng.standard_normal(effect.n_params)
    scale = getattr(effect, "typical_scale", None)
    if scale is not None:
        return draw * np.broadcast_to(np.asarray(scale, dtype=float), (effect.n_params,))
    return draw * _unit_displacement_scale(effect, rng)


def _unit_displacement_scale(effect, rng, n_poses: int = 64, step: float = 1e-6) -> np.ndarray:
    """(p,) scale per parameter: ``step`` times the ratio of DEFAULT_EFFECT_DISPLACEMENT_M to the
    mean tool displacement a parameter of ``step`` causes over random poses, over √p. A parameter
    that leaves the tool point where it is (a turn about the tool's own origin) is scaled by what
    the reflectors see; one that moves neither is a ConfigError asking for its ``params``."""
    from campaign.errors import ConfigError
    from campaign.tolerances import SIM_UNMOVED_RTOL

    robot = effect.robot
    q = random_joint_poses(robot, n_poses, seed=int(rng.integers(1 << 31)))
    es = EffectSet((effect,))
    context = effect_context({k: np.full(n_poses, 20.0) for k in effect.context_keys},
                             np.linspace(0.0, 3600.0, n_poses))
    theta0 = effect.initial_params()
    T0 = model_pose(robot, q, None, es, theta0, context)
    points = tool_points(robot)
    out = np.empty(effect.n_params)
    for i in range(effect.n_params):
        th = theta0.copy()
        th[i] += step
        T = model_pose(robot, q, None, es, th, context)
        moved = np.mean(np.linalg.norm(T[:, :3, 3] - T0[:, :3, 3], axis=1))
        seen = np.mean(np.linalg.norm(transform_points(T, points) - transform_points(T0, points), axis=-1))
        if not moved > SIM_UNMOVED_RTOL * seen:
            moved = seen
        if not moved > 0:
            at = ", ".join(f"{k} = 20" for k in effect.context_keys if k != "time_s")
            raise ConfigError(f"sim.hidden_effects: effect '{effect.spec}': its parameter {effect.param_names[i]} "
                              f"moves neither the tool point nor its reflectors on {n_poses} random poses"
                              f"{' at ' + at if at else ''}, so no typical size can be drawn: state its params "
                              "({effect: ..., params: [...]})")
        out[i] = step * DEFAULT_EFFECT_DISPLACEMENT_M / moved
    return out / np.sqrt(max(effect.n_params, 1))


def random_joint_poses(robot: RobotModel, n: int, seed: int = 0, margin: float = 0.05) -> np.ndarray:
    """n joint vectors uniformly inside the joint limits (shrunk by ``margin`` rad, or by
    ``margin`` x 10 % of the range for a prismatic joint), (n, N)."""
    rng = np.random.default_rng(seed)
    span = robot.q_upper - robot.q_lower
    m = np.where(robot.prismatic, np.minimum(0.1 * span, margin), margin)
    return rng.uniform(robot.q_lower + m, robot.q_upper - m, size=(n, robot.n_joints))


def synthesize(truth: TruthRobot, q, *, seed: int = 0, time_s=None, context=None) -> MeasuredPoses:
    """Measured poses as a campaign would produce them from this truth.

    The tracker measures the set-up points (-> T_LI) and the three reflectors of each
    pose (-> Kabsch -> T_IE); joint values are the commanded ones.
    """
    rng = np.random.default_rng(seed)
    q = np.asarray(q, dtype=float)
    n = len(q)
    context = {k: np.asarray(v, dtype=float) for k, v in (context or {}).items()}
    t = np.arange(n, dtype=float) * 20.0 if time_s is None else np.asarray(time_s, dtype=float)
    T_LI_measured = frame_from_setup_points(*truth.setup_points_in_L(rng))
    P_L = truth.reflectors_in_L(q, rng, effect_context(context, t))
    T_IE, _ = pose_from_reflectors(T_LI_measured, tool_points(truth.robot), P_L)
    return MeasuredPoses(np.arange(1, n + 1, dtype=np.int64), t, q, T_IE, context, T_LI_measured)


def write_truth(truth: TruthRobot, path) -> None:
    from campaign.fileio import atomic_write

    atomic_write(path, truth.to_yaml())


def synthetic_campaign(robot: RobotModel, n_poses: int, *, seed: int = 0, noise_m: float = TRACKER_NOISE_M,
                       hidden=(), position_only: bool = False) -> tuple:
    """(MeasuredPoses, TruthRobot): ``n_poses`` random poses measured on a truth drawn from
    ``seed`` with the named physical effects hidden at their typical magnitude (`campaign synth`)."""
    from campaign.errors import ConfigError

    if isinstance(n_poses, bool) or not isinstance(n_poses, int) or n_poses < 1:
        raise ConfigError(f"--poses must be a positive integer, got {n_poses!r}")
    if not 0 <= noise_m < 1:
        raise ConfigError(f"--noise-um must be a finite number >= 0 below 1e6, got {noise_m * 1e6!r}")
    effects = {}
    for name in hidden:
        e = make_effect(name, robot)
        effects[name] = e.typical_params(seed) if hasattr(e, "typical_params") else e.initial_params()
    truth = make_truth(robot, seed=seed, noise_m=noise_m, effects=effects, position_only=position_only)
    q = random_joint_poses(robot, n_poses, seed=seed + 1)
    context = {}
    for e in truth.effects.effects:
        if hasattr(e, "synthetic_context"):
            context.update(e.synthetic_context(len(q), seed))
    return synthesize(truth, q, seed=seed + 2, context=context), truth


def random_tracker_pose(seed: int) -> np.ndarray:
    """T_LI (4, 4) of a tracker at an unknown pose 2-3 m from the base: its origin at a random
    direction and distance in F_I, its axes turned at random (the pose F_I has in F_L)."""
    from campaign.measure.reflectors import invert

    rng = np.random.default_rng(seed + 7919)
    d = rng.uniform(2.0, 3.0)
    u = rng.normal(size=3)
    u /= np.linalg.norm(u)
    T_IL = np.eye(4)
    T_IL[:3, :3] = cardan_xyz(*rng.uniform(-np.pi, np.pi, 3))
    T_IL[:3, 3] = d * u
    return invert(T_IL)


def synthesize_kind(truth: TruthRobot, q, *, kind: str = "pose", frame: str = "robot", seed: int = 0,
                    context=None, miss_rate: float = 0.0) -> MeasuredPoses:
    """Measured data of one kind as a tracker would give it, in the robot's frame (through the
    set-up points, as :func:`synthesize`) or in the tracker's own frame (``frame="tracker"``).

    kind: "pose" (6-D from the reflector set by Kabsch), "point" (one reflector: the tool
    frame's origin, or the robot's single reflector), "markers" (raw reflector centres; each
    missed with probability ``miss_rate``).
    """
    from campaign.measure.reflectors import fit_markers, invert

    rng = np.random.default_rng(seed)
    q = np.asarray(q, dtype=float)
    n = len(q)
    context = {k: np.asarray(v, dtype=float) for k, v in (context or {}).items()}
    t = np.arange(n, dtype=float) * 20.0
    if frame == "robot":
        T_LI_measured = frame_from_setup_points(*truth.setup_points_in_L(rng))
        to_data = invert(T_LI_measured)
    else:
        T_LI_measured, to_data = None, np.eye(4)
    T_LE = truth.T_LI @ truth.pose(q, effect_context(context, t))
    if kind == "point":
        P_E = truth.robot.reflector_positions_in_E if len(truth.robot.reflectors) == 1 else np.zeros((1, 3))
    elif kind == "markers" and len(truth.robot.reflectors) == 2:  # a two-reflector tool: its two
        P_E = truth.robot.reflector_positions_in_E
    else:
        P_E = tool_points(truth.robot)
    P_L = truth._measure_points(transform_points(T_LE, np.broadcast_to(P_E, (n,) + P_E.shape)), rng)
    P = transform_points(to_data, P_L)
    xyz, rv, markers = np.full((n, 3), np.nan), np.full((n, 3), np.nan), None
    if kind == "point":
        xyz = P[:, 0]
    else:
        if kind == "markers" and miss_rate > 0:
            P = P.copy()
            P[rng.uniform(size=P.shape[:2]) < miss_rate] = np.nan
            markers = P
        T, _ = fit_markers(P_E, P)
        ok = np.isfinite(T[:, 0, 0])
        xyz = T[:, :3, 3]
        from campaign.model.rotations import matrix_to_rotvec

        rv[ok] = matrix_to_rotvec(T[ok, :3, :3])
        if kind == "markers" and markers is None:
            markers = P
    return MeasuredPoses.from_vectors(np.arange(1, n + 1, dtype=np.int64), t, q, xyz, rv, context, kind=kind,
                                      frame=frame, markers=markers, T_LI=T_LI_measured,
                                      marker_positions=P_E if kind == "markers" else None)


def read_truth(path, robot: RobotModel | None = None) -> TruthRobot:
    """Load a truth file written by :func:`write_truth` (for evaluation after the fact)."""
    doc = yaml.safe_load(Path(path).read_text())
    robot = robot or RobotModel.load()
    effs, thetas = [], []
    for name, th in (doc.get("effects") or {}).items():
        effs.append(make_effect(name, robot))
        thetas.append(np.asarray(th, dtype=float))
    return TruthRobot(robot, np.asarray(doc["p_e"], dtype=float), np.asarray(doc["T_LI"], dtype=float),
                      float(doc["noise_m"]), float(doc["resolution_m"]), EffectSet(tuple(effs)),
                      np.concatenate(thetas) if thetas else np.zeros(0))
