"""`campaign run RUN --sim | --cell SPEC | --controller HOST:PORT --tracker HOST:PORT`."""

from __future__ import annotations

import sys


def _hostport(text, name):
    from campaign.errors import ConfigError

    host, sep, port = str(text).rpartition(":")
    if not sep or not host or not port.isdigit() or not 0 < int(port) < 65536:
        raise ConfigError(f"--{name}: expected HOST:PORT, got {text!r}")
    return host, int(port)


def register(sub):
    p = sub.add_parser(
        "run", help="run the measurement campaign of a planned run (simulated or real cell)",
        description="Measure every pose of RUN/plan/poses.csv that has no stored outcome yet: base-frame set-up "
                    "(T_LI), then move -> reached -> measure the three reflectors -> store, one SQLite transaction "
                    "per pose in RUN/measurements.sqlite. Re-running resumes; Ctrl-C stops after the current pose. "
                    "--sim starts the simulated cell (see `campaign sim`) and stops it at the end; --cell SPEC "
                    "does the same with `campaign serve` for any cell's adapters (docs/cell.md).")
    p.add_argument("run", metavar="RUN", help="run folder with plan/poses.csv (from `campaign plan`)")
    src = p.add_mutually_exclusive_group(required=True)
    src.add_argument("--sim", action="store_true", help="start the simulated cell, drive it, stop it")
    src.add_argument("--cell", metavar="SPEC",
                     help="start `campaign serve` for these adapters, drive it, stop it: sim (= --sim), mujoco, "
                          "FILE.py with classes Controller and Tracker (relative to here or to RUN's campaign.yaml), "
                          "package.module or an entry point of group campaign.cell")
    src.add_argument("--controller", metavar="HOST:PORT", help="the robot controller")
    p.add_argument("--tracker", metavar="HOST:PORT", help="the laser tracker (with --controller)")
    p.add_argument("--options", metavar="FILE", default=None,
                   help="with --cell: the adapters' options (YAML with 'controller:' and 'tracker:' sections)")
    p.add_argument("--token-file", metavar="FILE", default=None,
                   help="with --controller/--tracker: the shared secret of a cell served with --token-file")
    p.add_argument("--config", metavar="FILE", default=None,
                   help="configuration (default: RUN/campaign.yaml, else the embedded one)")
    p.add_argument("--poses", metavar="CSV", default=None,
                   help="pose list to measure instead of RUN/plan/poses.csv (same header: pose_id,q1..qN, rad)")
    p.add_argument("--max-poses", type=int, default=None,
                   help="measure at most this many poses (the rest stays for a re-run)")
    p.add_argument("--retry-failed", action="store_true",
                   help="forget the poses stored as failed and measure them again")
    p.add_argument("--allow-other-cell", action="store_true",
                   help="measure the rest of a run on another cell than the one it was measured on so far "
                        "(refused otherwise; the change is recorded in the run)")
    p.add_argument("--quiet", action="store_true", help="no progress bar")
    p.add_argument("--verbose", action="store_true", help="print every retry and reconnect on stderr")
    from campaign.watch.commands import add_watch_argument

    add_watch_argument(p)
    p.add_argument("--frame", choices=("robot", "tracker"), default="robot",
                   help="store poses in the robot's base frame from the set-up points (default), or in the "
                        "tracker's own frame without a set-up: calibrate then identifies the tracker's pose")
    p.set_defaults(func=_run)


def _run(args):
    from campaign.errors import ConfigError, Implausible, PeerError, RobotFault
    from campaign.measure.session import measure_run
    from campaign.watch.commands import watching

    run = args.run
    log = lambda msg: print(f"\n{msg}", file=sys.stderr, flush=True)  # noqa: E731
    local = args.sim or args.cell is not None
    if local and args.tracker:
        raise ConfigError(f"--tracker goes with --controller, not with {'--sim' if args.sim else '--cell'}")
    if not local and not args.tracker:
        raise ConfigError("--controller needs --tracker HOST:PORT too")
    if local and args.token_file:
        raise ConfigError("--token-file goes with --controller/--tracker (a cell started here serves on loopback)")
    peers = {} if local else {"controller": _hostport(args.controller, "controller"),
                              "tracker": _hostport(args.tracker, "tracker")}
    with watching(run, args.watch):
        res = measure_run(run, sim=args.sim, config=args.config, progress=not args.quiet and sys.stderr.isatty(),
                          log=log, max_poses=args.max_poses, poses_csv=args.poses, retry_failed=args.retry_failed,
                          verbose=args.verbose, frame=args.frame, cell=args.cell, options=args.options,
                          token_file=args.token_file, allow_other_cell=args.allow_other_cell, **peers)
    h = res.simulated_duration_s / 3600
    print(f"measured {res.measured}, failed {res.failed} (stored before this run: {res.stored_before}; "
          f"still to measure: {res.remaining}); campaign clock {h:.2f} h = {h / 24:.2f} days; wall {res.wall_s:.1f} s"
          + (f"; {res.drift_warnings} drift warnings" if res.drift_warnings else ""))
    print(f"written: {run}/measurements.sqlite")
    if res.stopped_kind == "interrupted":
        print(f"campaign run: {res.stopped}; everything measured is stored, re-run to resume", file=sys.stderr)
        return 130
    if res.stopped_kind == "implausible":
        raise Implausible(f"campaign stopped: {res.stopped}; fix it, then re-run to resume")
    if res.stopped_kind == "robot_fault":
        raise RobotFault(f"campaign stopped: {res.stopped}; everything measured is stored, re-run to resume")
    if res.stopped:
        raise PeerError(f"campaign stopped: {res.stopped}; everything measured is stored, re-run to resume")
    return 0
