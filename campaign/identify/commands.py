"""`campaign import`, `campaign export`, `campaign calibrate`."""

from __future__ import annotations

import math
import sys


def _add_reading_options(p) -> None:
    """--columns and --limit-slack: how predict and compensate read a joints file, as the run's import did."""
    p.add_argument("--columns", default=None, metavar="NAME=COLUMN,...",
                   help="the file's own column names, e.g. q1=J1,q2=J2 (default: the mapping the run's import read "
                        "its file with, else robot.yaml's columns:)")
    p.add_argument("--limit-slack", type=float, default=None, metavar="DEG_OR_MM",
                   help="accept joint readings this far past the URDF's limits (deg for revolute joints, mm for "
                        "prismatic ones; default: what the run's import accepted)")


def register(sub):
    p = sub.add_parser("import", help="turn a measured-pose CSV, or a tracker's log matched to the program's stops, "
                                      "into a run folder")
    p.add_argument("csv", metavar="CSV", nargs="?",
                   help="measured-pose CSV ([pose_id,][time_s,]q1..qN, then x,y,z[,rx,ry,rz] or m1_x..mk_z[,extra...])")
    p.add_argument("--stream", metavar="LOG", default=None,
                   help="instead of CSV: a laser tracker's log (time_s or ISO 8601 time/timestamp, x, y, z, optional "
                        "target naming the reflector), continuous or one record per stable point, matched to "
                        "RUN/program/stops.csv (`campaign program RUN --format csv`); writes RUN/import/stream_match.csv. "
                        "A second log continues where the first ended")
    p.add_argument("--run", required=True, metavar="DIR", help="run folder to create (must not hold measurements)")
    p.add_argument("--robot", default=None,
                   help="robot: name, URDF or robot.yaml (default: the one the run records, else comau_racer5_080)")
    p.add_argument("--tool-frame", default=None, metavar="LINK",
                   help="the measured tool frame, a URDF link (default: robot.yaml's, else the chain's last link)")
    p.add_argument("--base-frame", default=None, metavar="LINK", help="the chain's base, a URDF link (default: root)")
    p.add_argument("--frame", choices=("robot", "tracker"), default="robot",
                   help="measurements in the robot's base frame (default) or in the tracker's: calibrate then "
                        "identifies the tracker's pose with the model")
    p.add_argument("--markers", default=None, metavar="FILE",
                   help="nominal positions of raw reflectors m1..mk in the tool frame (YAML: markers: [[x, y, z], ...], m)")
    p.add_argument("--angle-unit", choices=("rad", "deg"), default="rad",
                   help="unit of q and of the orientation angles in the CSV")
    p.add_argument("--length-unit", choices=("m", "mm"), default="m",
                   help="unit of positions (and prismatic joints) in the CSV")
    p.add_argument("--rotation", choices=("rotvec", "rpy", "abc", "quat"), default="rotvec",
                   help="how the CSV writes orientation: rotvec (rx,ry,rz rotation vector, default), rpy (rx,ry,rz "
                        "roll, pitch, yaw about fixed x, y, z: R = Rz Ry Rx, URDF/ROS), abc (KUKA's a,b,c: "
                        "R = Rz(a) Ry(b) Rx(c)), quat (qw,qx,qy,qz)")
    p.add_argument("--delimiter", default=None, metavar="CHAR",
                   help="field separator: ',' (default), ';', tab, space (any run of blanks), '|'")
    p.add_argument("--header", default=None, metavar="NAME,...",
                   help="the column names of a file without a header line, in order (e.g. pose_id,q1,...,q6,x,y,z)")
    p.add_argument("--columns", default=None, metavar="NAME=COLUMN,...",
                   help="the file's own column names, e.g. x=X_mm,q1=J1 (default: robot.yaml's columns:)")
    p.add_argument("--limit-slack", type=float, default=0.0, metavar="DEG_OR_MM",
                   help="accept joint readings this far past the URDF's limits (deg for revolute joints, mm for "
                        "prismatic ones); the readings accepted are counted and said")
    p.add_argument("--targets", default=None, metavar="REFLECTOR=NAME,...",
                   help="with --stream: the log's names of the robot's reflectors, e.g. rrr1=SMR1,rrr2=SMR2,brr=SMR3 "
                        "(default: the robot's own names)")
    p.add_argument("--strict", action="store_true",
                   help="refuse the import (exit 1, nothing written) when a plausibility check warns")
    p.add_argument("--quiet", action="store_true", help="no progress bar")
    p.set_defaults(func=_import)

    p = sub.add_parser("export", help="write a run's measured poses as a measured-pose CSV, or its calibrated "
                                      "geometric model as a URDF")
    p.add_argument("run", metavar="DIR", help="run folder")
    p.add_argument("--csv", metavar="OUT", help="CSV file to write (the measured poses)")
    p.add_argument("--urdf", metavar="OUT", help="URDF to write: the robot's URDF with the identified geometric "
                                                  "model folded into its joint origins (after `campaign calibrate`)")
    p.set_defaults(func=_export)

    p = sub.add_parser("calibrate", help="identify the model of a run; write calibration/metrics.json and params.yaml")
    p.add_argument("run", metavar="DIR", nargs="+",
                   help="run folder with measurements.sqlite; several (a fleet of robots): each calibrated as "
                        "alone, the runs spread over --workers processes or the Dask cluster, one line each")
    p.add_argument("--effects", metavar="NAME,...", default=None,
                   help="physical effects to identify with the geometry: built-in names, path/file.py:ClassName "
                        "(relative to the current directory) or installed entry points of group campaign.effects; "
                        "a joint-indexed one over its joints as NAME:2,3,4 (default: those in DIR/campaign.yaml; "
                        "docs/effects.md)")
    p.add_argument("--position-only", action="store_true", help="use measured positions only")
    p.add_argument("--strict", action="store_true",
                   help="exit 1 and write nothing when a plausibility check warns (the previous calibration stays)")
    p.add_argument("--keep-outliers", action="store_true",
                   help="keep training poses whose reading is a fault (far beyond the poses' robust scatter) in the "
                        "fit; by default they are left out, each named in an `outlier` warning (docs/outliers.md)")
    p.add_argument("--model", choices=("lsq", "map", "auto"), default="auto",
                   help="geometric model: lsq (base parameters by least squares), map (with the tolerance priors, "
                        "strength by cross-validation), auto (default: chosen by cross-validated held-out error "
                        "below 300 training poses, least squares from there); docs/priors.md")
    p.add_argument("--fix", metavar="NAME[=VALUE],...", default=None,
                   help="hold parameters at nominal or at VALUE (SI: m, rad): names (pL_6E_x), groups (base, tool, "
                        "offsets, joint<j>), patterns (pR_I0_*) or <effect>.<param>")
    p.add_argument("--cell-segment", type=int, default=None, metavar="N",
                   help="a run measured on more than one cell (resumed with --allow-other-cell): calibrate the "
                        "poses of its N-th cell segment alone (default: all, with a registration per segment, "
                        "when the segments agree beyond it; docs/cells.md)")
    ann = p.add_mutually_exclusive_group()
    ann.add_argument("--ann", dest="ann", action="store_true", default=None,
                     help="train the neural residual compensator (default from 250 training poses)")
    ann.add_argument("--no-ann", dest="ann", action="store_false", help="geometric (and effects) only")
    p.add_argument("--sizes", default=None, metavar="N1xN2,...",
                   help="hidden sizes for the ANN's cross-validation, e.g. 16x16,32x16,32x32,64x32")
    p.add_argument("--folds", type=int, default=None,
                   help="the network's cross-validation folds (default: from the data, leave-one-out below 60 "
                        "training poses, else 5)")
    p.add_argument("--epochs", type=int, default=None,
                   help="ANN training epochs at most (default: 2000 for adam, 2048 for br-lm)")
    p.add_argument("--ann-solver", choices=("auto", "adam", "br-lm"), default=None,
                   help="ANN training: adam (batched folds, early stopping, fold ensemble), br-lm (the paper's "
                        "Bayesian-regularised Levenberg-Marquardt, reports γ, α, β), or auto (default: br-lm "
                        "below 4,000 training poses, adam from there on)")
    p.add_argument("--workers", type=int, default=None,
                   help="local worker processes for the ANN grid (default: the usable cores); with --dask, "
                        "the local Dask cluster's workers")
    p.add_argument("--scheduler", default=None, metavar="tcp://HOST:PORT",
                   help="run the ANN grid's trainings on this Dask distributed scheduler. Dask sends tasks and "
                        "results as pickle: only a scheduler and workers you trust, on a network you trust (or "
                        "with Dask's TLS); never a scheduler someone else controls")
    p.add_argument("--dask", action="store_true",
                   help="run the ANN grid on a local Dask cluster of --workers (listening on 127.0.0.1 only)")
    p.add_argument("--device", default="auto",
                   help="torch device for adam training: auto (default: cuda where torch finds a GPU, else cpu), "
                        "cpu, cuda, cuda:N")
    p.add_argument("--no-report", action="store_true",
                   help="skip the HTML report and its plots (metrics.json, params.yaml and history.json are written; "
                        "the new calibration has no report: an earlier one's described another model)")
    p.add_argument("--quiet", action="store_true", help="no progress output")
    p.set_defaults(func=_calibrate)

    p = sub.add_parser("predict", help="calibrated pose of E in F_I for given joint coordinates")
    p.add_argument("run", metavar="DIR", help="run folder calibrated by `campaign calibrate`")
    p.add_argument("--csv", required=True, metavar="IN",
                   help="CSV with q1..qN (rad or --angle-unit, N the robot's joints), optional pose_id and context "
                        "columns (time_s, temperature_c, ...)")
    p.add_argument("--out", metavar="OUT", default=None,
                   help="CSV to write: pose_id,q1..qN,x,y,z (m),rx,ry,rz (rad),in_domain (1/0),sigma_mm "
                        "(default: standard output)")
    p.add_argument("--stage", default=None, help="model stage from metrics.json (default: the last, current one)")
    p.add_argument("--angle-unit", choices=("rad", "deg"), default="rad",
                   help="unit of the joint columns read and written (default: rad)")
    _add_reading_options(p)
    p.add_argument("--strict", action="store_true",
                   help="refuse (exit 1, nothing written) when a row lies outside the calibrated domain")
    p.set_defaults(func=_predict)

    p = sub.add_parser("compensate",
                       help="corrected joint commands that bring the real tool to the nominal poses of given commands")
    p.add_argument("run", metavar="DIR", help="run folder calibrated by `campaign calibrate`")
    src = p.add_mutually_exclusive_group(required=True)
    src.add_argument("--csv", metavar="IN",
                     help="CSV with nominal joint commands q1..qN (rad), optional pose_id and context columns")
    src.add_argument("--program", metavar="FILE",
                     help="a robot program whose joint and Cartesian targets are rewritten (with --format; every "
                          "other line left as it was, what could not be read listed; docs/programs.md)")
    p.add_argument("--format", metavar="F", default=None,
                   help="the program's language: urscript, krl (.src or .dat), rapid, fanuc-ls, pdl2, "
                        "ros2-trajectory, csv")
    p.add_argument("--out", metavar="OUT", default=None,
                   help="CSV to write: pose_id,q1..qN (corrected, rad),dq1..dqN,residual_position_mm,"
                        "residual_orientation_mrad,converged,within_limits,in_domain,sigma_mm (default: standard "
                        "output); with --program the filtered program (default: FILE's name with _compensated)")
    p.add_argument("--stage", default=None, help="model stage from metrics.json (default: the last, current one)")
    p.add_argument("--angle-unit", choices=("rad", "deg"), default="rad",
                   help="unit of the joint columns read and written, dq included (default: rad)")
    _add_reading_options(p)
    p.add_argument("--strict", action="store_true",
                   help="refuse (exit 1, nothing written) when a corrected command lies outside the calibrated domain")
    p.set_defaults(func=_compensate)


def _import(args):
    if args.stream is not None or args.csv is None:
        return _import_stream(args)
    if args.targets is not None:
        from campaign.errors import ConfigError

        raise ConfigError("--targets: only with --stream (a measured-pose CSV names its reflectors m1..mk)")
    from campaign.measure.importer import import_run

    from campaign.measure.csvio import ImportOptions
    from campaign.progress import Progress

    from campaign.errors import Implausible
    from campaign.measure.csvio import parse_columns

    options = ImportOptions(angle_unit=args.angle_unit, length_unit=args.length_unit, frame=args.frame,
                            rotation=args.rotation, delimiter=args.delimiter, columns=parse_columns(args.columns),
                            header=None if args.header is None else tuple(h.strip() for h in args.header.split(",")),
                            limit_slack_rad=math.radians(args.limit_slack), limit_slack_m=args.limit_slack * 1e-3)
    bar = Progress("import", total=1000, enabled=not args.quiet and sys.stderr.isatty(), unit="‰")
    try:
        res = import_run(args.csv, args.run, robot=args.robot, tool_frame=args.tool_frame,
                         base_frame=args.base_frame, options=options, markers_file=args.markers,
                         progress=lambda f: bar.update(int(1000 * f) - bar.done), strict=args.strict)
    except Implausible as exc:
        bar.close()
        print_warnings(exc.warnings)
        raise
    bar.close()
    print(f"imported {res.n_poses} poses into {args.run}/measurements.sqlite")
    if res.numbered:
        print(res.numbered)
    if res.past_limits:
        print(res.past_limits)
    print_warnings(res.warnings)
    return 0


def _import_stream(args):
    from campaign.errors import ConfigError
    from campaign.measure.csvio import parse_columns
    from campaign.progress import Progress
    from campaign.program.stream import import_stream

    if args.stream is None:
        raise ConfigError("give a measured-pose CSV, or --stream LOG (a tracker's log)")
    if args.csv is not None:
        raise ConfigError(f"give either a measured-pose CSV ({args.csv}) or --stream LOG, not both")
    given = [flag for flag, v in (("--robot", args.robot), ("--tool-frame", args.tool_frame),
                                  ("--base-frame", args.base_frame), ("--markers", args.markers),
                                  ("--header", args.header), ("--delimiter", args.delimiter)) if v is not None]
    given += [flag for flag, v in (("--angle-unit", args.angle_unit != "rad"), ("--rotation", args.rotation != "rotvec"),
                                   ("--limit-slack", args.limit_slack != 0), ("--strict", args.strict)) if v]
    if given:
        raise ConfigError(f"{', '.join(given)}: not with --stream (the run's robot and RUN/program/stops.csv say "
                          "what was measured)")
    bar = Progress("import --stream", total=1000, enabled=not args.quiet and sys.stderr.isatty(), unit="‰")
    try:
        res = import_stream(args.stream, args.run, length_unit=args.length_unit, frame=args.frame,
                            columns=parse_columns(args.columns), progress=lambda f: bar.update(int(1000 * f) - bar.done),
                            targets=parse_targets(args.targets))
    finally:
        bar.close()
    print(res.summary(args.stream, args.run))
    print(f"written: {res.match_csv}")
    return 0


def parse_targets(text) -> dict:
    """``--targets rrr1=SMR1,...`` to {reflector: the log's name}; ConfigError on a malformed item."""
    from campaign.errors import ConfigError

    out = {}
    for item in (text or "").split(",") if text else []:
        name, eq, log_name = (v.strip() for v in item.partition("="))
        if not eq or not name or not log_name:
            raise ConfigError(f"--targets: expected REFLECTOR=NAME,... (e.g. rrr1=SMR1), got {item.strip()!r}")
        if name in out:
            raise ConfigError(f"--targets: {name} named twice")
        out[name] = log_name
    return out


def print_warnings(warnings) -> None:
    """Plausibility warnings, one ``warning: ...`` line each on stderr."""
    for w in warnings:
        print(f"warning: {w.message} [{w.code}]", file=sys.stderr)


def _export(args):
    from campaign.errors import ConfigError
    from campaign.measure.csvio import write_measured_csv
    from campaign.run import RunFolder

    if not args.csv and not args.urdf:
        raise ConfigError("export: give --csv OUT and/or --urdf OUT")
    if args.urdf:
        from campaign.identify.use import calibrated_geometry, export_notes
        from campaign.model.export import write_calibrated_urdf

        robot, p_e = calibrated_geometry(args.run)
        notes = export_notes(args.run, robot)
        write_calibrated_urdf(robot, p_e, args.urdf, notes)
        print(f"wrote the calibrated geometric model of {robot.name} ({robot.n_params} parameters) to {args.urdf}")
        for note in notes:
            print(f"  {note}")
        if not args.csv:
            return 0
    with RunFolder(args.run).store() as store:
        poses = store.load_measured(include_unusable=True)  # raw reflectors: every row, as imported
    from campaign.identify.use import export_domain_columns

    appended, line = export_domain_columns(args.run, poses)
    write_measured_csv(args.csv, poses, RunFolder(args.run).robot(), appended)
    print(f"wrote {len(poses)} poses to {args.csv}")
    print(line)
    return 0


def _calibrate(args):
    from campaign.identify.calibrate import calibrate, check_ann_options, summary_text

    ann_options = {} if args.folds is None else {"folds": args.folds}
    if args.sizes:
        from campaign.identify.ann_stage import parse_sizes

        ann_options["sizes"] = parse_sizes(args.sizes)
    if args.epochs is not None:
        ann_options["max_epochs"] = args.epochs
    for key in ("workers", "scheduler", "device"):
        if getattr(args, key) is not None:
            ann_options[key] = getattr(args, key)
    if args.ann is False and args.device == "auto":  # no network: torch (2.5 s to import) is not needed
        ann_options.pop("device")
    if args.ann_solver:
        ann_options["solver"] = args.ann_solver
    if args.dask:
        ann_options["dask"] = True
    check_ann_options(ann_options)
    ann = "auto" if args.ann is None else args.ann  # auto: not for a campaign too small for a network
    if len(args.run) > 1:
        return _calibrate_fleet(args, ann, ann_options)
    from campaign.errors import Implausible

    progress = None if args.quiet else _CalibrateProgress()
    try:
        result = calibrate(args.run[0], effects=args.effects, position_only=args.position_only, ann=ann,
                           ann_options=ann_options, progress=progress, report=not args.no_report, strict=args.strict,
                           model=args.model, fix=args.fix, cell_segment=args.cell_segment,
                           keep_outliers=args.keep_outliers)
    except Implausible as exc:
        if progress is not None:
            progress.close()
        print_warnings(exc.warnings)
        raise
    if progress is not None:
        progress.close()
    print(summary_text(result))
    print_warnings(result.warnings)
    return 0


def _calibrate_fleet(args, ann, ann_options) -> int:
    """Several runs: each calibrated as `campaign calibrate DIR` would (its outputs in its own
    folder), the runs spread over the executor; one line per run (the current model's held-out
    mean position error, or why it failed); exit 1 when any failed, after the others finished."""
    from pathlib import Path

    from campaign.ann.grid import make_executor
    from campaign.errors import ConfigError
    from campaign.identify.fleet import calibrate_runs

    runs = [str(Path(r)) for r in args.run]
    if len(set(runs)) < len(runs):
        dup = next(r for r in runs if runs.count(r) > 1)
        raise ConfigError(f"calibrate: run {dup} is named twice")
    if args.cell_segment is not None:  # a segment is one run's, not a fleet's
        raise ConfigError(f"--cell-segment {args.cell_segment}: names a cell segment of one run; calibrate the run "
                          "alone (`campaign calibrate DIR --cell-segment N`)")
    fleet_options = {k: v for k, v in ann_options.items() if k not in ("workers", "scheduler", "dask")}
    executor = make_executor(workers=ann_options.get("workers"), scheduler=ann_options.get("scheduler"),
                             dask=ann_options.get("dask", False))
    say = None if args.quiet else (lambda msg: print(msg, file=sys.stderr, flush=True))
    try:
        results = calibrate_runs(runs, executor=executor, progress=say, errors="collect", effects=args.effects,
                                 position_only=args.position_only, ann=ann, ann_options=fleet_options,
                                 report=not args.no_report, model=args.model, fix=args.fix,
                                 keep_outliers=args.keep_outliers)
    finally:
        executor.close()
    failed = 0
    for run in runs:
        m = results[run]
        if "error" in m:
            failed += 1
            print(f"campaign calibrate: {m['error']}", file=sys.stderr)
            continue
        stage = m["order"][-1]
        test = m["stages"][stage]["test"]
        warned = len(m.get("warnings") or [])
        print(f"{run}: {stage}: held-out mean position {test['position_mm']['mean']:.4g} mm "
              f"({test['n_poses']} test poses); outputs in {Path(run) / 'calibration'}"
              + (f"; {warned} plausibility warning(s) in metrics.json" if warned else ""))
    print(f"calibrated {len(runs) - failed} of {len(runs)} runs on {executor.name}")
    return 1 if failed else 0


class _CalibrateProgress:
    """Status lines, and one progress bar per network training (stage, size, fold) showing the
    epoch, the running normalised MSE and the effective number of parameters γ."""

    def __init__(self):
        self.bar = None
        self.task = None

    def __call__(self, msg):
        from campaign.progress import Progress

        if isinstance(msg, str):
            self.close()
            print(msg, file=sys.stderr, flush=True)
            return
        if hasattr(msg, "tasks_done"):  # the whole ANN grid: one bar, in per mille of the expected work
            if self.task != "grid":
                self.close()
                self.task = "grid"
                self.bar = Progress("ANN grid", total=1000, enabled=True, unit="‰")
            # the bar's share: elapsed over elapsed + the time left, once the meter has timed a training
            share = msg.elapsed_s / (msg.elapsed_s + msg.eta_s) if msg.eta_s < float("inf") else \
                msg.done / max(msg.total, 1e-300)
            self.bar.update(max(0, int(1000 * share) - self.bar.done), extra=f"{msg.tasks_done}/{msg.tasks} trainings",
                            eta_s=msg.eta_s)
            return
        if msg.task != self.task:
            self.close()
            self.task = msg.task
            self.bar = Progress(msg.task, total=msg.max_epochs, enabled=True, unit=" epochs")
        self.bar.update(msg.epoch - self.bar.done, extra=f"mse {msg.mse:.4g} γ {msg.gamma:.0f}")

    def close(self):
        if self.bar is not None:
            self.bar.close()
        self.bar = self.task = None


def _predict(args):
    from campaign.identify.use import CalibratedRobot, predict_rows, read_joint_csv, run_joint_slack, write_table

    calibrated = CalibratedRobot(args.run, stage=args.stage)
    slack, source = run_joint_slack(args.run, calibrated.robot, args.limit_slack)
    pose_id, q, context = read_joint_csv(args.csv, calibrated.robot, calibrated.context_keys, args.angle_unit,
                                         columns=args.columns, slack=slack, slack_source=source, run_dir=args.run)
    _radians_as_degrees(args, calibrated.robot, q)
    header, rows, inside, sigma = predict_rows(calibrated, pose_id, q, context, args.angle_unit)
    why = _why_outside(calibrated, q, inside)
    _refuse_outside(args, pose_id, inside, "rows", why)
    write_table(args.out, header, rows)
    if args.out:
        print(f"wrote {len(rows)} calibrated poses ({calibrated.stage}) to {args.out}")
    _domain_line(calibrated, inside, sigma, "rows", bool(args.out), why)
    return 0


def _why_outside(calibrated, q, inside) -> list:
    """What puts each row outside the calibrated domain ("" inside; [] without a domain)."""
    if inside is None or inside.all():
        return []
    return calibrated.stored_domain.domain.why_outside(q, [f"q{j + 1}" for j in range(calibrated.robot.n_joints)])


def _refuse_outside(args, pose_id, inside, what, why=()) -> None:
    """--strict: one line naming the rows outside the calibrated domain (and why), before anything is written."""
    import numpy as np

    from campaign.errors import DataError

    if getattr(args, "strict", False) and inside is not None and not inside.all():
        rows = np.flatnonzero(~inside)
        named = [f"{int(pose_id[k])}" + (f" ({why[k]})" if len(why) else "") for k in rows[:10]]
        raise DataError(f"{args.csv}: {len(rows)} of {len(inside)} {what} outside the calibrated domain with --strict "
                        f"(pose_id {', '.join(named)}{', ...' if len(rows) > 10 else ''}): nothing written")


def _radians_as_degrees(args, robot, q) -> None:
    """warning on stderr when joints read in degrees all lie within 2 pi (radians given with
    --angle-unit deg): :func:`campaign.identify.use.radians_read_as_degrees`."""
    from campaign.identify.use import radians_read_as_degrees

    said = radians_read_as_degrees(q, robot, args.angle_unit)
    if said:
        print(f"warning: {args.csv}: {said}", file=sys.stderr)


def _domain_line(calibrated, inside, sigma, what, to_file: bool, why=()) -> None:
    """The summary line of in_domain and sigma_mm: beside "wrote ..." on stdout when the CSV went to a
    file, on stderr when the CSV itself is on stdout; why: what puts each row outside, counted."""
    from collections import Counter

    from campaign.identify.domain import domain_summary

    line = domain_summary(inside, sigma, what)
    counts = Counter(w for w in why if w)
    if counts:
        line += " (" + "; ".join(f"{w}: {n}" for w, n in counts.most_common(4)) + ")"
    if calibrated.network_members > 1 and sigma is not None:
        line += f" (with the spread of the network's {calibrated.network_members} cross-validation members)"
    elif calibrated.network is not None and sigma is not None:
        line += " (the physical model's; a single network's own uncertainty is not estimated)"
    elif sigma is None and inside is not None:
        line += f"; no sigma_mm for stage {calibrated.stage} (no physical model identified in it)"
    print(line, file=sys.stdout if to_file else sys.stderr)


def _compensate(args):
    from campaign.errors import ConfigError

    if args.program is not None:
        return _compensate_program(args)
    if args.format is not None:
        raise ConfigError("--format goes with --program (a CSV of joints is read with --csv alone)")
    from campaign.identify.use import (CalibratedRobot, compensate_rows, read_joint_csv, run_joint_slack,
                                      write_table)

    calibrated = CalibratedRobot(args.run, stage=args.stage)
    slack, source = run_joint_slack(args.run, calibrated.robot, args.limit_slack)
    pose_id, q, context = read_joint_csv(args.csv, calibrated.robot, calibrated.context_keys, args.angle_unit,
                                         columns=args.columns, slack=slack, slack_source=source, run_dir=args.run)
    _radians_as_degrees(args, calibrated.robot, q)
    header, rows, ok, inside, in_dom, sigma, q_cmd = compensate_rows(calibrated, pose_id, q, context, args.angle_unit)
    why = _why_outside(calibrated, q_cmd, in_dom)
    _refuse_outside(args, pose_id, in_dom, "corrected commands", why)
    write_table(args.out, header, rows)
    if args.out:
        print(f"wrote {len(rows)} corrected joint commands ({calibrated.stage}) to {args.out}")
    if not ok.all():
        print(f"warning: {int((~ok).sum())} pose(s) did not converge (column converged = 0)", file=sys.stderr)
    if not inside.all():
        print(f"warning: {int((~inside).sum())} corrected command(s) outside the joint limits "
              "(column within_limits = 0)", file=sys.stderr)
    _domain_line(calibrated, in_dom, sigma, "corrected commands", bool(args.out), why)
    return 0


def _compensate_program(args):
    from campaign.errors import ConfigError
    from campaign.program.compensate import compensate_program_file

    if args.format is None:
        raise ConfigError("--program needs --format (urscript, krl, rapid, fanuc-ls, pdl2, ros2-trajectory, csv)")
    if args.columns is not None or args.angle_unit != "rad":
        raise ConfigError("--columns and --angle-unit go with --csv; a program's units are its language's")
    from campaign.identify.use import CalibratedRobot, run_joint_slack

    calibrated = CalibratedRobot(args.run, stage=args.stage)
    slack = run_joint_slack(args.run, calibrated.robot, args.limit_slack)[0]
    out, res = compensate_program_file(args.run, args.program, args.format, out=args.out, stage=args.stage,
                                       slack=slack, strict=args.strict, progress=sys.stderr.isatty(),
                                       calibrated=calibrated)
    print(f"wrote {out}: {res.joints} joint and {res.poses} Cartesian targets compensated ({res.stage}), "
          f"{len(res.unclear)} not understood, {len(res.outside_domain)} outside the calibrated domain, "
          f"{len(res.outside) - len(res.outside_domain)} left as written or not reached exactly")
    for line, text, why in res.unclear:
        print(f"  line {line}: not understood, left as written: {why}: {text}")
    for line, why in res.outside:
        print(f"  line {line}: {why}")
    return 0
