"""`campaign import` as a library call: a measured-pose CSV into a run folder."""

from __future__ import annotations

from pathlib import Path

from campaign.errors import ConfigError, DataError
from campaign.paths import DEFAULT_ROBOT
from campaign.run import RunFolder, load_robot, same_robot


def import_run(csv_path, run_dir, *, robot: str | None = None, tool_frame: str | None = None,
               base_frame: str | None = None, options=None, markers_file=None, progress=None) -> int:
    """Import ``csv_path`` into ``run_dir``; returns the number of poses.

    robot: name, URDF or robot.yaml (None: the robot the run records, else the default).
    A run that records another robot is refused; a folder without campaign.yaml gets one
    recording the robot. The CSV is validated whole (streaming, bounded memory) before the
    folder is touched, then streamed into the log. options: campaign.measure.csvio.ImportOptions
    (units, frame); markers_file: YAML with the raw reflectors' nominal positions.
    progress: callable receiving the fraction done (0..1).
    """
    from dataclasses import replace

    from campaign.measure.csvio import ImportOptions, iter_measured_chunks, read_markers_file
    from campaign.measure.store import write_imported

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
        spec = robot if robot is not None else DEFAULT_ROBOT
        if robot is not None and Path(robot).exists():
            spec = str(Path(robot).resolve())
    model = load_robot(spec, tool_frame=tool_frame, base_frame=base_frame)
    if run.measurements_path.exists():  # checked again under the lock by write_imported
        raise DataError(f"{run.path}: already holds {run.measurements_path.name}; import into a new run folder")
    options = options or ImportOptions()
    if markers_file is not None:
        options = replace(options, markers=read_markers_file(markers_file))
    _, _, chunks = iter_measured_chunks(csv_path, model, options, progress=progress)
    with run.lock("import"):
        n = write_imported(chunks, run.path, source={"kind": "import", "csv": str(Path(csv_path).resolve()),
                                                     "angle_unit": options.angle_unit,
                                                     "length_unit": options.length_unit},
                           robot=model)
        if not run.has_config:
            run.record_robot(spec, tool_frame=tool_frame, base_frame=base_frame)
    return n


def _frames(tool_frame, base_frame) -> str:
    given = [f"{k} {v!r}" for k, v in (("tool_frame", tool_frame), ("base_frame", base_frame)) if v]
    return f" ({', '.join(given)})" if given else ""
