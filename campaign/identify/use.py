"""Using a calibration: `campaign predict` and `campaign compensate`.

A run's calibration folder holds everything needed to evaluate the calibrated robot again:
``params.yaml`` (the 6N + 12 geometric parameters and the effects' parameters, plain YAML) and,
when the ANN was trained, ``ann_nominal.pt`` / ``ann_geometric.pt`` (tensors only, loaded with
``weights_only``; N joint inputs, 6 outputs, or 3 for position-only data: then the network
corrects the measured point's position only). :class:`CalibratedRobot` reads them back and evaluates any stage of
``metrics.json``'s ``order``: ``nominal``, ``geometric``, ``geometric+<effect>...``, ``ann``
(nominal + network) or ``<model>+ann``.

*Predict* gives the pose of E in F_I for joint coordinates. *Compensate* inverts it: for the
pose a program expects from nominal joint commands q_nom (T* = FK_nominal(q_nom)), it finds
commands q with model(q) = T* by Newton iteration on the full model (network included), the
Jacobian taken by central differences, so whatever the stage contains is inverted exactly.
"""

from __future__ import annotations

import json
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from campaign.effects.base import EffectSet, make_effect, model_pose
from campaign.errors import ConfigError, DataError
from campaign.fileio import atomic_open, read_yaml_mapping
from campaign.measure.csvio import read_numeric_table
from campaign.model.ik import solve_pose
from campaign.model.kinematics import forward
from campaign.model.robot import RobotModel
from campaign.model.rotations import matrix_to_rotvec
from campaign.tolerances import JOINT_LIMIT_SLACK

JOINT_COLUMNS = ("q1", "q2", "q3", "q4", "q5", "q6")  # the default 6-joint robot's


def joint_columns(n_joints: int) -> tuple:
    """``q1..qN``."""
    return tuple(f"q{j}" for j in range(1, n_joints + 1))
POSE_COLUMNS = ("x", "y", "z", "rx", "ry", "rz")
#: networks by the prior model they were trained after ("nominal" or the identified model)
ANN_FILES = {"nominal": "ann_nominal.pt", "model": "ann_geometric.pt"}


@dataclass(frozen=True)
class _Model:
    """One identified model block of params.yaml: p_e (48,) and the effects with their values."""

    stage: str
    p_e: np.ndarray
    effects: EffectSet = field(default_factory=EffectSet)
    theta: np.ndarray = field(default_factory=lambda: np.zeros(0))


def _block(robot, block: dict, source: Path, where: str) -> _Model:
    try:
        names = list(block["p_e_names"])
        p_e = np.asarray(block["p_e"], dtype=float)
        effects = block.get("effects") or {}
        if names != list(robot.param_names) or p_e.shape != (robot.n_params,) or not np.all(np.isfinite(p_e)):
            raise DataError(f"{source}: {where}p_e must be the {robot.n_params} finite values named as "
                            f"robot.param_names of {robot.name}")
        made, theta = [], []
        for name, spec in effects.items():
            eff = make_effect((spec.get("spec") if isinstance(spec, dict) else None) or name, robot)
            values = [float(p["value"]) for p in spec["parameters"]]
            if [p["name"] for p in spec["parameters"]] != list(eff.param_names):
                raise DataError(f"{source}: {where}effects.{name}: parameters do not match the effect's "
                                f"({', '.join(eff.param_names)})")
            made.append(eff)
            theta.extend(values)
    except (KeyError, TypeError, ValueError) as exc:
        raise DataError(f"{source}: {where}malformed ({exc.__class__.__name__}: {exc})") from None
    stage = "+".join(["geometric", *(e.name for e in made)])
    return _Model(stage, p_e, EffectSet(tuple(made)), np.asarray(theta, dtype=float))


class CalibratedRobot:
    """The calibrated robot of a run, read back from ``RUN/calibration``.

    stage: a stage of metrics.json's ``order`` (None: the last one, the current model).
    """

    def __init__(self, run_dir, stage: str | None = None, robot: RobotModel | None = None):
        from campaign.identify.calibrate import CALIBRATION_DIR
        from campaign.run import RunFolder
        from campaign.versioned import calibration_folder

        self.run_dir = Path(run_dir)
        # the current calibration, resolved once: every file below is of that one calibration
        folder = calibration_folder(self.run_dir).current() or self.run_dir / CALIBRATION_DIR
        metrics_path, params_path = folder / "metrics.json", folder / "params.yaml"
        for path in (metrics_path, params_path):
            if not path.is_file():
                raise DataError(f"{path}: not found; run `campaign calibrate {self.run_dir}` first")
        try:
            order = list(json.loads(metrics_path.read_text())["order"])
        except (json.JSONDecodeError, KeyError, TypeError) as exc:
            raise DataError(f"{metrics_path}: malformed ({exc.__class__.__name__})") from None
        params = read_yaml_mapping(params_path, DataError)
        self.robot = robot or RunFolder(self.run_dir).robot()
        self.robot = measured_frame(self.robot, params, params_path)
        if params.get("robot") not in (None, self.robot.name):
            raise DataError(f"{params_path}: calibrated for robot {params.get('robot')!r}, "
                            f"the run's robot is {self.robot.name!r}")
        self.stage = order[-1] if stage is None else stage
        if self.stage not in order:
            raise ConfigError(f"--stage: '{self.stage}' is not a stage of {metrics_path} ({', '.join(order)})")

        main = _block(self.robot, params, params_path, "")
        geo = _block(self.robot, params["geometric_only"], params_path, "geometric_only.") \
            if "geometric_only" in params else main
        models = {"nominal": _Model("nominal", np.zeros(self.robot.n_params)), "geometric": geo, main.stage: main}
        prior, net_file = self.stage, None
        if self.stage == "ann":
            prior, net_file = "nominal", ANN_FILES["nominal"]
        elif self.stage.endswith("+ann"):
            prior, net_file = self.stage[: -len("+ann")], ANN_FILES["model"]
        if prior not in models:
            raise DataError(f"{params_path}: holds no parameters for stage '{prior}' "
                            f"(it holds {', '.join(models)}); re-run calibrate")
        trained = params.get("ann_stages") or {}
        if net_file is not None and trained.get(self.stage) != net_file:
            raise DataError(f"{folder}: the network of stage '{self.stage}' was not trained by the last "
                            f"calibrate; re-run `campaign calibrate {self.run_dir} --ann`")
        self.model = models[prior]
        from campaign.identify.domain import read_domain

        #: domain.json (campaign.identify.domain.StoredDomain), None for a calibration made before it
        self.stored_domain = read_domain(folder, params.get("calibration_id"), self.robot)
        self.network = None
        if net_file is not None:
            from campaign.ann import ResidualNetwork

            self.network = ResidualNetwork.load(folder / net_file)
            if self.network.n_inputs_ != self.robot.n_joints:
                raise DataError(f"{folder / net_file}: the network takes {self.network.n_inputs_} joint values, "
                                f"the run's robot {self.robot.name} has {self.robot.n_joints} joints; "
                                f"re-run calibrate")

    @property
    def context_keys(self) -> tuple:
        return tuple(k for e in self.model.effects.effects for k in e.context_keys)

    def predict(self, q, context=None) -> np.ndarray:
        """Calibrated pose of E in F_I, (n, 4, 4), for joint coordinates q (n, N) rad."""
        q = np.asarray(q, dtype=float).reshape(-1, self.robot.n_joints)
        self.model.effects.check_context(context or {}, len(q))
        T = model_pose(self.robot, q, self.model.p_e, self.model.effects, self.model.theta, context or {})
        if self.network is not None:
            from campaign.ann import compensate_pose

            T = compensate_pose(T, self.network.predict(q))
        return T

    def in_domain(self, q):
        """(n,) bool: inside the calibrated domain (None without domain.json)."""
        if self.stored_domain is None:
            return None
        return self.stored_domain.domain.contains(np.asarray(q, dtype=float).reshape(-1, self.robot.n_joints))

    @property
    def network_members(self) -> int:
        """Members of the stage's network (0: no network; 1: a single network; K: a fold ensemble)."""
        if self.network is None:
            return 0
        return int(self.network.weights_.shape[0]) if self.network.weights_.ndim == 2 else 1

    def sigma_mm(self, q, context=None):
        """(n,) mm: the model's 1-σ position uncertainty at the tool point, √trace of its 3×3 covariance:
        the physical model's (campaign.identify.uncertainty) and, for a network stage trained as a fold
        ensemble, the spread of its cross-validation members' position corrections (their covariance
        added: the members differ by the data each was trained on). None without domain.json, or for a
        stage with neither (``nominal``; ``ann`` with a single network, whose uncertainty is not
        estimated)."""
        if self.stored_domain is None:
            return None
        q = np.asarray(q, dtype=float).reshape(-1, self.robot.n_joints)
        unc = self.stored_domain.uncertainty.get(self.model.stage)
        if unc is not None and unc.names != tuple(self.robot.param_names) + tuple(self.model.effects.param_names):
            raise DataError(f"domain.json: the uncertainty of stage '{self.model.stage}' is not of its parameters "
                            f"(params.yaml's); re-run calibrate")
        var = None if unc is None else \
            (1e3 * unc.sigma_m(self.robot, self.model.effects, self.model.p_e, self.model.theta, q, context)) ** 2
        if self.network_members > 1:
            members = self.network.predict_members(q)[:, :, :3]  # (K, n, 3) m
            spread = 1e6 * np.sum(np.var(members, axis=0, ddof=1), axis=1)
            var = spread if var is None else var + spread
        return None if var is None else np.sqrt(var)

    def compensate(self, T_target, q_start, context=None, *, tol_m: float = 1e-9, tol_rad: float = 1e-8,
                   max_iter: int = 50, step_rad: float = 1e-6, max_step_rad: float = 0.1):
        """Joint commands q (n, N) with predict(q) = T_target, iterated from q_start.

        Levenberg-Marquardt per pose (a Newton step where the Jacobian is well conditioned,
        damped near a singularity, steps of at most ``max_step_rad``), the Jacobian of the
        whole stage by central differences. Returns (q, residual (n, 6) =
        pose_error(predict(q), T_target) in m and rad, converged (n,) bool). A pose whose
        target the calibrated model cannot reach (beside a singularity, e.g. the elbow nearly
        folded) ends unconverged, with its remaining residual.
        """
        T_target = np.asarray(T_target, dtype=float).reshape(-1, 4, 4)
        q, r, ok = self._solve(T_target, np.array(q_start, dtype=float).reshape(-1, self.robot.n_joints), context,
                               tol_m, tol_rad, max_iter, step_rad, max_step_rad)
        return q, r, ok

    def _solve(self, T_target, q, context, tol_m, tol_rad, max_iter, step_rad, max_step_rad):
        return solve_pose(lambda qq, idx: self.predict(qq, _rows(context, idx)), T_target, q, tol_m=tol_m,
                          tol_rad=tol_rad, max_iter=max_iter, step_rad=step_rad, max_step_rad=max_step_rad)


def calibrated_geometry(run_dir) -> tuple:
    """(robot, p_e (6N + 12,)) of a calibrated run: the geometric-only identification."""
    from campaign.identify.calibrate import CALIBRATION_DIR, load_robot_for_run

    from campaign.versioned import calibration_folder

    params_path = (calibration_folder(run_dir).current() or Path(run_dir) / CALIBRATION_DIR) / "params.yaml"
    if not params_path.is_file():
        raise DataError(f"{params_path}: not found; run `campaign calibrate {run_dir}` first")
    params = read_yaml_mapping(params_path, DataError)
    robot = measured_frame(load_robot_for_run(run_dir), params, params_path)
    block = params.get("geometric_only", params)
    return robot, _block(robot, {"p_e_names": block.get("p_e_names"), "p_e": block.get("p_e")}, params_path,
                         "geometric_only." if "geometric_only" in params else "").p_e


def export_notes(run_dir, robot: RobotModel) -> list:
    """What the exported URDF of a calibrated run is and leaves out, one sentence each (written
    as a comment into the URDF and said by `campaign export --urdf`): the joint convention its
    joints are in, the gravity of its root frame (a URDF cannot state it; Pinocchio assumes -z),
    and what of the current model it does not hold (the effects, the network)."""
    from campaign.versioned import calibration_folder

    folder = calibration_folder(run_dir).current() or Path(run_dir) / "calibration"
    params = read_yaml_mapping(folder / "params.yaml", DataError)
    notes = []
    if robot.controller_matrix is None:
        notes.append("joints: the URDF's own convention, which is the controller's (robot.yaml names no "
                     "controller convention)")
    else:
        from campaign.measure.plausibility import controller_yaml

        notes.append("joints: the URDF's (model) convention, not the controller's: q_model = coupling * q_controller + "
                     f"offset, robot.yaml's {controller_yaml(robot, np.eye(robot.n_joints), np.zeros(robot.n_joints))}")
    if robot.tool_point is not None:
        from campaign.model.export import measured_point_link

        mm = ", ".join(f"{v * 1e3:.1f}" for v in robot.tool_point)
        notes.append(f"the measured point: frame '{measured_point_link(robot)}' ({mm}) mm in '{robot.tool_frame}', "
                     "where `campaign predict` gives the calibrated poses (one-reflector data)")
    from campaign.model.robot import EXPORTED_GRAVITY

    g = ", ".join(f"{v:.6g}" for v in robot.gravity_in_I)
    notes.append(EXPORTED_GRAVITY.format(base=robot.base_frame, g=g) + " (a URDF cannot state it: give it to Pinocchio "
                 "or a simulator, whose default is (0, 0, -9.81); campaign reads it back from this line)")
    effects = list((params.get("effects") or {}))
    left = [f"the effects {', '.join(effects)} (identified with the geometry; the URDF holds the geometric-only "
            "identification)"] if effects else []
    if params.get("ann_stages"):
        left.append("the neural compensator")
    if left:
        notes.append(f"left out: {' and '.join(left)}; `campaign predict` and `campaign compensate` apply them")
    return notes


def measured_frame(robot: RobotModel, params: dict, params_path, *, point: bool = True) -> RobotModel:
    """The run's robot whose tool frame is where the calibrated data were measured (params.yaml):
    a one-reflector measured point (``point``), a tool mounting of 6-D or raw-reflector data."""
    from campaign.identify.calibrate import mounting_from_json

    if point and params.get("measured_point_in_tool_m") is not None:  # one-reflector data: the model's tool point
        robot = robot.with_tool_point(params["measured_point_in_tool_m"])
    if params.get("tool_mounting_in_tool") is not None:
        robot = robot.with_tool_transform(mounting_from_json(params["tool_mounting_in_tool"], params_path))
    return robot


def _rows(context, idx):
    return {k: np.asarray(v)[idx] for k, v in (context or {}).items()}


def joint_scale(robot: RobotModel, angle_unit: str = "rad") -> np.ndarray:
    """(N,) factors from the CSV's joint unit to SI: pi/180 for revolute joints in degrees, else 1."""
    if angle_unit not in ("rad", "deg"):
        raise ConfigError(f"--angle-unit must be rad or deg, not {angle_unit!r}")
    return np.where(robot.prismatic | (angle_unit == "rad"), 1.0, np.pi / 180.0)


def read_joint_csv(path, robot: RobotModel, context_keys=(), angle_unit: str = "rad", columns=None,
                   slack=None, slack_source: str | None = None, run_dir=None) -> tuple:
    """Joint coordinates (and the context columns an effect needs) from a CSV.

    Header: ``q1..qN`` (rad, or deg with ``angle_unit``; m for prismatic joints; in the
    controller's convention, converted by robot.yaml's ``controller``), optionally ``pose_id``
    and any context columns (``time_s``, ``temperature_c``, ...); the columns neither the joints,
    ``pose_id`` nor ``context_keys`` are not checked (a measured file's empty reflector cells, a
    text label). columns: the file's own
    names (``--columns`` text or {column in the file: name used}; default robot.yaml's
    ``columns:``), as `import` reads them; a mapped measurement column may be absent. Without
    ``columns``, a ``run_dir``'s import's mapping (its ``--columns``, recorded) comes before
    robot.yaml's, and of these mappings only the joints' columns must be in the file. slack:
    (N,) rad or m, how far past the URDF's limits readings are accepted (default: round-off,
    JOINT_LIMIT_SLACK; :func:`run_joint_slack` gives a run's), said as from ``slack_source``.
    Returns (pose_id (n,), q (n, N) model, rad and m, context dict).
    """
    from campaign.measure.csvio import missing_columns, not_joint_name
    from campaign.measure.importer import column_mapping

    cols = joint_columns(robot.n_joints)
    scale = joint_scale(robot, angle_unit)
    used = {*cols, "pose_id", *context_keys}
    given = bool(columns)
    if not given and run_dir is not None:
        from campaign.measure.importer import recorded_columns

        columns = recorded_columns(run_dir) or None
    header, col, lines = read_numeric_table(path, (), rename=column_mapping(robot, columns), expected=",".join(cols),
                                            rename_optional=not_joint_name if given else (lambda h: h not in cols),
                                            unused=lambda h: h not in used)
    missing = [c for c in cols if c not in col]
    if missing:
        raise missing_columns(path, missing, header, robot.name)
    missing = [k for k in context_keys if k not in col]
    if missing:
        raise DataError(f"{path}: the calibrated model needs the column(s) {', '.join(missing)} "
                        f"(context of its effects)")
    extra = [h for h in header if h.startswith("q") and h[1:].isdigit() and h not in cols]
    if extra:
        from campaign.measure.csvio import joint_count_error

        raise joint_count_error(path, robot.n_joints + len(extra), robot.n_joints, robot.name)
    from campaign.measure.csvio import check_joint_units

    written = np.stack([col[c] for c in cols], axis=1)
    check_joint_units(path, written * scale, written, lines, robot, angle_unit == "deg")
    q = robot.to_model_q(written * scale)
    robot.check_joints(q, field=f"{path}" + (" (read in deg)" if angle_unit == "deg" else ""),
                       slack=JOINT_LIMIT_SLACK if slack is None else slack, lines=lines, slack_source=slack_source)
    pose_id = col["pose_id"].astype(np.int64) if "pose_id" in col else np.arange(len(q), dtype=np.int64)
    context = {k: col[k] for k in header if k not in cols and k != "pose_id"}
    return pose_id, q, context


def radians_read_as_degrees(q, robot: RobotModel, angle_unit: str) -> str | None:
    """What to say when joints read in degrees (``angle_unit`` "deg") look like radians: every
    revolute reading of RADIANS_AS_DEGREES_MIN_ROWS rows or more within ±2π as written (degrees
    of a program turn some joint farther), q (n, N) model, rad and m; None otherwise."""
    from campaign.tolerances import RADIANS_AS_DEGREES_MIN_ROWS, RADIANS_MAX_ABS

    revolute = ~np.asarray(robot.prismatic, dtype=bool)
    if angle_unit != "deg" or not revolute.any() or len(q) < RADIANS_AS_DEGREES_MIN_ROWS:
        return None
    written = np.degrees(robot.to_controller_q(q)[:, revolute])
    if np.abs(written).max() > RADIANS_MAX_ABS:
        return None
    return (f"every revolute joint of its {len(q)} rows reads within ±2π ({np.abs(written).max():.3g} at most), "
            "read in degrees (--angle-unit deg): radians? without --angle-unit they are read in rad")


def run_joint_slack(run_dir, robot: RobotModel, given_deg_or_mm: float | None = None) -> tuple:
    """(slack (N,) rad or m, its source in words) for joint readings given to a calibrated run:
    what its import accepted past the URDF's limits (``--limit-slack`` recorded), or
    ``given_deg_or_mm`` (deg for revolute joints, mm for prismatic ones) when that is more."""
    from campaign.measure.importer import joint_slack

    run_slack = joint_slack(run_dir, robot)
    source = "as the run's import accepted"
    if given_deg_or_mm is None:
        return run_slack, source + "; --limit-slack DEG_OR_MM to accept more"
    if not np.isfinite(given_deg_or_mm) or given_deg_or_mm < 0:
        raise ConfigError(f"--limit-slack must be a number >= 0 (deg or mm), got {given_deg_or_mm!r}")
    given = JOINT_LIMIT_SLACK + np.where(robot.prismatic, given_deg_or_mm * 1e-3, np.radians(given_deg_or_mm))
    return np.maximum(run_slack, given), "--limit-slack or the run's import, the larger"


def write_table(path, header, rows) -> None:
    """Write a numeric CSV atomically (``path`` None: standard output)."""
    import csv
    import sys

    if path is None:
        w = csv.writer(sys.stdout, lineterminator="\n")
        w.writerow(header)
        w.writerows(rows)
        return
    with atomic_open(path, "w", newline="") as fh:
        w = csv.writer(fh)
        w.writerow(header)
        w.writerows(rows)


DOMAIN_COLUMNS = ("in_domain", "sigma_mm")


def domain_columns(calibrated: CalibratedRobot, q, context=None):
    """(in_domain (n,) bool or None, sigma_mm (n,) or None, cells (n,) of [in_domain, sigma_mm] as
    written: 1/0 and mm, empty where unknown)."""
    inside = calibrated.in_domain(q)
    sigma = calibrated.sigma_mm(q, context)
    cells = [["" if inside is None else int(inside[k]), "" if sigma is None else f"{sigma[k]:.4g}"]
             for k in range(len(q))]
    return inside, sigma, cells


def predict_rows(calibrated: CalibratedRobot, pose_id, q, context, angle_unit: str = "rad"):
    """Rows ``pose_id,q1..qN,x,y,z,rx,ry,rz,in_domain,sigma_mm`` (m, rad; q in ``angle_unit``;
    in_domain 1/0, sigma_mm in mm) of the calibrated poses. Returns (header, rows, in_domain,
    sigma_mm) (the last two None without domain.json)."""
    T = calibrated.predict(q, context)
    rv = matrix_to_rotvec(T[:, :3, :3])
    header = ["pose_id", *joint_columns(calibrated.robot.n_joints), *POSE_COLUMNS, *DOMAIN_COLUMNS]
    q_out = calibrated.robot.to_controller_q(q) / joint_scale(calibrated.robot, angle_unit)
    inside, sigma, cells = domain_columns(calibrated, q, context)
    rows = [[int(i), *(repr(float(v)) for v in qq), *(repr(float(v)) for v in T[k, :3, 3]),
             *(repr(float(v)) for v in rv[k]), *cells[k]] for k, (i, qq) in enumerate(zip(pose_id, q_out))]
    return header, rows, inside, sigma


def compensate_rows(calibrated: CalibratedRobot, pose_id, q_nominal, context, angle_unit: str = "rad"):
    """Rows of corrected joint commands for the poses the nominal model gives at q_nominal.

    Columns: ``pose_id, q1..qN`` (corrected, rad or ``angle_unit``), ``dq1..dqN`` (correction, same unit),
    ``residual_position_mm, residual_orientation_mrad`` (model at the corrected q vs target),
    ``converged``, ``within_limits`` (0/1), ``in_domain`` (0/1, of the corrected command), ``sigma_mm``
    (mm, there). Returns (header, rows, converged, within_limits, in_domain, sigma_mm, the corrected
    commands q (n, N) rad).
    """
    robot = calibrated.robot
    T_target = forward(robot, q_nominal)
    q, r, ok = calibrated.compensate(T_target, q_nominal, context)
    inside = np.all((q >= robot.q_lower) & (q <= robot.q_upper), axis=1)
    scale = joint_scale(robot, angle_unit)
    q_ctrl, q_nominal_ctrl = robot.to_controller_q(q) / scale, robot.to_controller_q(q_nominal) / scale
    cols = joint_columns(robot.n_joints)
    header = ["pose_id", *cols, *(f"d{c}" for c in cols),
              "residual_position_mm", "residual_orientation_mrad", "converged", "within_limits", *DOMAIN_COLUMNS]
    in_dom, sigma, cells = domain_columns(calibrated, q, context)
    rows = []
    for k in range(len(q)):
        rows.append([int(pose_id[k]), *(repr(float(v)) for v in q_ctrl[k]),
                     *(repr(float(v)) for v in q_ctrl[k] - q_nominal_ctrl[k]),
                     f"{np.linalg.norm(r[k, :3]) * 1e3:.3e}", f"{np.linalg.norm(r[k, 3:]) * 1e3:.3e}",
                     int(ok[k]), int(inside[k]), *cells[k]])
    return header, rows, ok, inside, in_dom, sigma, q


def export_domain_columns(run_dir, poses) -> tuple:
    """({"in_domain": cells, "sigma_mm": cells}, one summary line) for `export --csv` of a run's
    measured poses under its current calibration; no columns (and a line saying why) when the run has
    no calibration or one without domain.json: the CSV stays one that `import` reads back."""
    from campaign.errors import CampaignError
    from campaign.identify.domain import domain_summary

    try:
        calibrated = CalibratedRobot(run_dir)
        calibrated.model.effects.check_context(_effect_context(poses), len(poses))
    except CampaignError as exc:
        return {}, f"no in_domain, sigma_mm columns: {exc}"
    inside, sigma, cells = domain_columns(calibrated, poses.q, _effect_context(poses))
    if inside is None:  # not "left empty": the export has no such columns then
        return {}, "no in_domain, sigma_mm columns: no calibrated domain (a calibration from before domain.json); " \
                   "re-run calibrate"
    if sigma is None:
        return {}, "no in_domain, sigma_mm columns: " + domain_summary(inside, sigma, "poses")
    return {c: [row[i] for row in cells] for i, c in enumerate(DOMAIN_COLUMNS)}, domain_summary(inside, sigma, "poses")


def _effect_context(poses) -> dict:
    from campaign.effects.base import effect_context

    return effect_context(poses.context, poses.time_s)
