"""`campaign import` as a library call: a measured-pose CSV into a run folder."""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

from campaign.errors import ConfigError, DataError, Implausible
from campaign.paths import DEFAULT_ROBOT
from campaign.run import RunFolder, load_robot, same_robot


@dataclass(frozen=True)
class ImportResult:
    """What `import` stored: the pose count, the plausibility warnings (also stored in the log's
    ``source`` meta, where `calibrate` finds them) and the joint readings accepted past the
    URDF's limits (a sentence, or None)."""

    n_poses: int
    warnings: tuple = ()
    past_limits: str | None = None
    robot: str = ""
    numbered: str | None = None  # a file without pose_id: the sentence saying its rows were numbered

    def __int__(self):
        return self.n_poses


def import_run(csv_path, run_dir, *, robot: str | None = None, tool_frame: str | None = None,
               base_frame: str | None = None, options=None, markers_file=None, progress=None,
               strict: bool = False) -> ImportResult:
    """Import ``csv_path`` into ``run_dir``; returns an :class:`ImportResult`.

    robot: name, URDF or robot.yaml (None: the robot the run records, else the default).
    A run that records another robot is refused; a folder without campaign.yaml gets one
    recording the robot. The CSV is validated whole (streaming, bounded memory) before the
    folder is touched, then streamed into the log. options: campaign.measure.csvio.ImportOptions
    (units, frame); markers_file: YAML with the raw reflectors' nominal positions.
    progress: callable receiving the fraction done (0..1). The data are checked against the
    nominal model (campaign.measure.plausibility.check_data); strict: any warning refuses the
    import (:class:`campaign.errors.Implausible`, the warnings in ``.warnings``), nothing written.
    robot.yaml's ``columns:`` maps the file's column names when ``options.columns`` is empty.
    """
    from dataclasses import replace

    from campaign.measure.csvio import ImportOptions, iter_measured_chunks, read_markers_file
    from campaign.measure.store import write_imported
    from campaign.model.robot import robot_spec

    run = RunFolder(run_dir)
    if run.has_config:
        cfg = run.config
        if (robot, tool_frame, base_frame) != (None, None, None):
            asked = load_robot(robot or cfg.robot_spec, tool_frame=tool_frame or cfg.tool_frame,
                               base_frame=base_frame or cfg.base_frame)
            if not same_robot(asked, run.robot()):
                raise ConfigError(f"{run.config_path} records robot {cfg.robot!r}"
                                  f"{_frames(cfg.tool_frame, cfg.base_frame)}, not the one asked for; "
                                  "import into a new run folder for another robot or frame")
        spec, tool_frame, base_frame = cfg.robot_spec, cfg.tool_frame, cfg.base_frame
    else:
        spec = robot_spec(robot) if robot is not None else DEFAULT_ROBOT
    model = load_robot(spec, tool_frame=tool_frame, base_frame=base_frame)
    if run.measurements_path.exists():  # checked again under the lock by write_imported
        raise DataError(f"{run.path}: already holds {run.measurements_path.name}; import into a new run folder")
    options = options or ImportOptions()
    if markers_file is not None:
        options = replace(options, markers=read_markers_file(markers_file))
    options = replace(options, columns=column_mapping(model, options.columns))
    reading = iter_measured_chunks(csv_path, model, options, progress=progress)
    match = None
    if not reading.layout.has_pose_id and run.poses_csv.is_file():  # the plan's ids, by the rows' joints
        ids, match = plan_pose_ids(reading.chunks, run, model)
        options = replace(options, pose_ids=ids)
        reading = replace(iter_measured_chunks(csv_path, model, options, progress=progress), plan_match=match)
    warnings = import_warnings(csv_path, model, options, run.path)
    if strict and warnings:
        raise Implausible(f"{csv_path}: {len(warnings)} plausibility warning(s) with --strict "
                          f"({', '.join(w.code for w in warnings)}): nothing imported", warnings)
    past = None if reading.past_limits is None else reading.past_limits.text(model.name)
    with run.lock("import"):
        n = write_imported(reading.chunks, run.path,
                           source={"kind": "import", "csv": str(Path(csv_path).resolve()),
                                   "angle_unit": options.angle_unit, "length_unit": options.length_unit,
                                   "rotation": options.rotation, "limit_slack_rad": options.limit_slack_rad,
                                   "limit_slack_m": options.limit_slack_m, "past_limits": past,
                                   "columns": dict(options.columns or {}),
                                   "columns_source": getattr(options.columns, "source", "--columns"),
                                   "pose_ids": "file" if reading.numbered is None else "numbered",
                                   "warnings": [w.as_json() for w in warnings]},
                           robot=model)
        if not run.has_config:
            run.record_robot(spec, tool_frame=tool_frame, base_frame=base_frame)
    return ImportResult(n, tuple(warnings), past, model.name, reading.numbered)


def plan_pose_ids(chunks, run, robot) -> tuple:
    """(ids (n,) int64, what was done in words) for the rows of a file without pose_id imported
    into a planned run: each row the planned pose (RUN/plan/poses.csv) whose joints all lie within
    PLAN_MATCH_TOL_RAD of its joints, a pose measured again the plan's next repeat of it (its
    ids in increasing order), so the plan's validation poses and repeats are found by calibrate.
    A row matching no planned pose (or measured more often than planned) gets an id of its own
    after the plan's (another pose id modulo REPEAT_ID_STRIDE than any planned pose's); a file
    of which no row matches is numbered 0..n-1 in file order."""
    import numpy as np
    from scipy.spatial import cKDTree

    from campaign.measure.driver import read_plan
    from campaign.plan.selection import REPEAT_ID_STRIDE, base_pose_id
    from campaign.tolerances import PLAN_MATCH_TOL_RAD

    q = np.concatenate([c.q for c in chunks])
    plan_ids, plan_q, _ = read_plan(run.path)
    if plan_q.shape[1] != q.shape[1]:
        return None, None
    poses, group = np.unique(plan_q, axis=0, return_inverse=True)
    group = group.reshape(-1)
    order = np.lexsort((plan_ids, group))  # each planned pose's ids in increasing order
    starts = np.searchsorted(group[order], np.arange(len(poses)))
    counts = np.bincount(group, minlength=len(poses))
    _, near = cKDTree(poses).query(q, p=np.inf, distance_upper_bound=PLAN_MATCH_TOL_RAD)
    ids = np.full(len(q), -1, dtype=np.int64)
    used = np.zeros(len(poses), dtype=np.int64)
    for k, g in enumerate(near):
        if g < len(poses) and used[g] < counts[g]:
            ids[k] = plan_ids[order[starts[g] + used[g]]]
            used[g] += 1
    lost = ids < 0
    if lost.all():
        return None, None
    free = (int(plan_ids.max()) // REPEAT_ID_STRIDE + 1) * REPEAT_ID_STRIDE + int(base_pose_id(plan_ids).max()) + 1
    ids[lost] = free + np.arange(int(lost.sum()))
    said = f"are the plan's poses by their joints ({run.poses_csv}: {int((~lost).sum())} of {len(plan_ids)} planned)"
    if lost.any():
        said += (f"; {int(lost.sum())} row(s) match no planned pose (or one measured more often than planned), "
                 f"the first data row {int(np.flatnonzero(lost)[0]) + 1}: ids of their own from {free}")
    return ids, said


def import_warnings(csv_path, robot, options, run_dir=None) -> list:
    """The plausibility warnings of a validated CSV (its first rows; see
    campaign.measure.plausibility.check_data), orientation readings tested for 6-D data. A
    measured point or tool mounting is placed on the rows calibrate will train on (the split of
    ``run_dir``), so import and calibrate say one value."""
    import numpy as np

    from campaign.identify.split import run_split
    from campaign.measure.csvio import ROTATIONS, read_check_sample, rotation_readings_table
    from campaign.measure.plausibility import check_data, measured_point

    sample, orient = read_check_sample(csv_path, robot, options)
    train = np.flatnonzero(~run_split(run_dir, sample.pose_id)) if run_dir is not None else None
    point = measured_point(robot, sample.kind)
    checked = robot if point is None else robot.with_tool_point(point)
    orientation = None
    if orient is not None:
        # the other unit tried too: degrees read as rad, or rad read as degrees beside joints in degrees
        scales = (1.0, 3.141592653589793 / 180) if options.angle_unit == "rad" else (1.0, 180 / 3.141592653589793)
        orientation = (orient, ROTATIONS[options.rotation][0], options.rotation, rotation_readings_table(), scales)
    return check_data(checked, sample, orientation=orientation, fit_rows=train)


def column_mapping(robot, columns=None) -> dict:
    """The file's column names as {column in the file: name used}: ``columns`` (``--columns``
    text or a parsed mapping) when given, else robot.yaml's ``columns:``. import, predict and
    compensate read their CSVs through it."""
    from campaign.measure.csvio import ColumnMap, parse_columns

    if not columns:
        return ColumnMap(robot_yaml_columns(robot), f"{robot.meta_path}: columns:")
    if isinstance(columns, ColumnMap):  # where it was given, kept (a run's import's, recorded)
        return columns
    return ColumnMap(columns if isinstance(columns, dict) else parse_columns(columns), "--columns")


def robot_yaml_columns(robot) -> dict:
    """robot.yaml's ``columns: {name used: column in the file, ...}`` as {column in the file: name used}."""
    from campaign.fileio import read_yaml_mapping
    from campaign.measure.csvio import parse_columns

    if robot.meta_path is None:
        return {}
    cols = read_yaml_mapping(robot.meta_path, ConfigError).get("columns")
    if cols is None:
        return {}
    if not isinstance(cols, dict):
        raise ConfigError(f"{robot.meta_path}: field 'columns' must map names to the file's columns "
                          "({x: X_mm, q1: J1, ...})")
    return parse_columns(cols)


def recorded_source(run_dir) -> dict:
    """The log's ``source`` meta (what `import` recorded: units, reading, limit slack, warnings), {} if none."""
    src = RunFolder(run_dir).meta("source", {}) or {}
    return src if isinstance(src, dict) else {}


def recorded_columns(run_dir) -> dict:
    """The column mapping ({column in the file: name used}) the run's import read its file with
    (``--columns``, else robot.yaml's ``columns:``); {} when none or not recorded."""
    from campaign.measure.csvio import ColumnMap

    src = recorded_source(run_dir)
    cols = src.get("columns") or {}
    if not isinstance(cols, dict) or not cols:
        return {}
    given = str(src.get("columns_source") or "--columns")
    return ColumnMap({str(k): str(v) for k, v in cols.items()},
                     f"the --columns of {run_dir}'s import" if given == "--columns" else given)


def joint_slack(run_dir, robot):
    """Per joint, how far past the URDF limits the run's readings were accepted (N,), rad or m:
    JOINT_LIMIT_SLACK plus the ``--limit-slack`` the import recorded."""
    import numpy as np

    from campaign.tolerances import JOINT_LIMIT_SLACK

    src = recorded_source(run_dir)
    return JOINT_LIMIT_SLACK + np.where(robot.prismatic, float(src.get("limit_slack_m") or 0.0),
                                        float(src.get("limit_slack_rad") or 0.0))


def _frames(tool_frame, base_frame) -> str:
    given = [f"{k} {v!r}" for k, v in (("tool_frame", tool_frame), ("base_frame", base_frame)) if v]
    return f" ({', '.join(given)})" if given else ""
