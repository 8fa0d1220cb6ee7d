"""`campaign run RUN --sim | --controller HOST:PORT --tracker HOST:PORT`."""

from __future__ import annotations

import sys


def _hostport(text, name):
    from campaign.errors import ConfigError

    host, sep, port = str(text).rpartition(":")
    if not sep or not host or not port.isdigit() or not 0 < int(port) < 65536:
        raise ConfigError(f"--{name}: expected HOST:PORT, got {text!r}")
    return host, int(port)


def register(sub):
    p = sub.add_parser("run", help="run the measurement campaign of a planned run (simulated or real cell)")
    p.add_argument("run", metavar="RUN", help="run folder with plan/poses.csv (from `campaign plan`)")
    src = p.add_mutually_exclusive_group(required=True)
    src.add_argument("--sim", action="store_true", help="start the simulated cell, drive it, stop it")
    src.add_argument("--controller", metavar="HOST:PORT", help="the robot controller")
    p.add_argument("--tracker", metavar="HOST:PORT", help="the laser tracker (with --controller)")
    p.add_argument("--config", metavar="FILE", default=None,
                   help="configuration (default: RUN/campaign.yaml, else the embedded one)")
    p.add_argument("--max-poses", type=int, default=None, help="stop after this many poses (the rest stays for a re-run)")
    p.add_argument("--quiet", action="store_true", help="no progress bar")
    p.set_defaults(func=_run)


def _run(args):
    from pathlib import Path

    from campaign.config import load_config, resolve
    from campaign.errors import ConfigError
    from campaign.measure.driver import RunOptions, SimulatedCell, run_campaign
    from campaign.model.robot import RobotModel

    run = Path(args.run)
    cfg_path = args.config or (run / "campaign.yaml" if (run / "campaign.yaml").is_file() else None)
    cfg = load_config(cfg_path)
    robot_ref = resolve(cfg, cfg["robot"])
    robot = RobotModel.load(robot_ref if robot_ref.is_dir() else cfg["robot"])
    opts = RunOptions.from_config(cfg["run"])
    log = lambda msg: print(f"\n{msg}", file=sys.stderr, flush=True)  # noqa: E731
    progress = not args.quiet and sys.stderr.isatty()
    if args.sim:
        with SimulatedCell(cfg["_path"], run) as cell:
            res = run_campaign(run, robot, cell.controller, cell.tracker, opts, progress=progress, log=log,
                               max_poses=args.max_poses)
    else:
        if not args.tracker:
            raise ConfigError("--controller needs --tracker HOST:PORT too")
        res = run_campaign(run, robot, _hostport(args.controller, "controller"), _hostport(args.tracker, "tracker"),
                           opts, progress=progress, log=log, max_poses=args.max_poses)
    h = res.simulated_duration_s / 3600
    print(f"measured {res.measured}, failed {res.failed} (stored before this run: {res.stored_before}); "
          f"campaign clock {h:.2f} h = {h / 24:.2f} days; wall {res.wall_s:.1f} s"
          + (f"; {res.drift_warnings} drift warnings" if res.drift_warnings else ""))
    print(f"written: {run}/measurements.sqlite")
    if res.stopped:
        from campaign.errors import RobotFault

        if res.stopped.startswith("robot fault"):
            raise RobotFault(f"campaign stopped: {res.stopped}; everything measured is stored, re-run to resume")
        print(f"stopped: {res.stopped}", file=sys.stderr)
        return 130
    return 0
