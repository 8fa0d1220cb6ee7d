"""`campaign sim`: the simulated cell alone (for a real driver test); `campaign synth`: a
measured-pose CSV from a seeded truth, the truth kept apart."""

from __future__ import annotations

from pathlib import Path


def register(sub):
    s = sub.add_parser(
        "sim", help="run the simulated cell alone (controller and tracker ports), for a real driver test",
        description="Serve the simulated robot controller and laser tracker (docs/protocol.md) on two TCP ports "
                    "sharing one simulated world, until Ctrl-C. The hidden truth goes to RUN/sim/truth.yaml; "
                    "one cell serves a run at a time (it holds RUN/sim/.lock while it serves). "
                    "Drive it with `campaign run RUN --controller HOST:PORT --tracker HOST:PORT`. "
                    "It is `campaign serve --controller sim --tracker sim` (docs/cell.md) with a default run. "
                    "With `campaign sim RUN --stream-out LOG` it serves nothing: the cell runs RUN's program "
                    "(RUN/program/stops.csv) and writes its tracker's continuous log (docs/stream.md).")
    s.add_argument("run_dir", metavar="RUN", nargs="?", default=None,
                   help="the run (the same as --run); with --stream-out, the run whose program is driven")
    s.add_argument("--stream-out", metavar="LOG", default=None,
                   help="instead of serving: drive the simulated cell through RUN/program/stops.csv (`campaign program "
                        "RUN --format csv`) and write the tracker's continuous log (time_s,x,y,z,target in m, the "
                        "tracker's frame, motion included, lost beams as sim.faults.beam_lost says) for "
                        "`campaign import --stream LOG --run RUN --frame tracker`")
    s.add_argument("--rate", type=float, default=100.0, metavar="HZ",
                   help="with --stream-out: the log's sample rate (default: %(default)s Hz)")
    s.add_argument("--config", metavar="FILE", default=None,
                   help="configuration (default: RUN/campaign.yaml, or the embedded one for a run without it)")
    s.add_argument("--robot", metavar="NAME|URDF|robot.yaml", default=None,
                   help="the cell's robot (default: the one RUN/campaign.yaml records, or the configuration's); "
                        "a run that records another robot is refused")
    s.add_argument("--tool-frame", metavar="LINK", default=None, help="the robot's tool frame (default: the robot's)")
    s.add_argument("--base-frame", metavar="LINK", default=None, help="the robot's base frame (default: the URDF's root)")
    s.add_argument("--run", metavar="DIR", default="runs/sim",
                   help="where the simulator keeps its truth (RUN/sim/) and whose campaign clock it continues "
                        "(default: %(default)s)")
    s.add_argument("--host", default="127.0.0.1", help="address to bind (default: %(default)s)")
    s.add_argument("--controller-port", type=int, default=0, help="controller port (default: any free port)")
    s.add_argument("--tracker-port", type=int, default=0, help="tracker port (default: any free port)")
    s.set_defaults(func=_sim)
    p = sub.add_parser("synth", help="write a measured-pose CSV from a seeded simulated truth (truth in a separate file)")
    p.add_argument("--csv", required=True, metavar="OUT", help="measured-pose CSV to write")
    p.add_argument("--truth", metavar="FILE", default=None, help="where to write the truth (default: OUT with .truth.yaml)")
    p.add_argument("--poses", type=int, default=2000, help="number of random poses (default: %(default)s)")
    p.add_argument("--seed", type=int, default=0, help="seed of truth, poses and noise (default: %(default)s)")
    p.add_argument("--noise-um", type=float, default=10.0, help="tracker noise σ per coordinate, µm (default: %(default)s)")
    p.add_argument("--hidden", metavar="EFFECT[,EFFECT...]", default="",
                   help="physical effects to hide in the truth, at their typical magnitude")
    p.add_argument("--robot", default="comau_racer5_080", help="robot: name, URDF or robot.yaml (default: %(default)s)")
    p.add_argument("--tool-frame", default=None, metavar="LINK", help="tool frame (default: the robot's)")
    p.add_argument("--base-frame", default=None, metavar="LINK", help="base frame (default: the URDF's root)")
    p.add_argument("--kind", choices=("pose", "point", "markers"), default="pose",
                   help="measurement kind: 6-D poses (default), one reflector (x,y,z), raw reflectors (m1_x,..)")
    p.add_argument("--frame", choices=("robot", "tracker"), default="robot",
                   help="data in the robot's base frame (default) or in the frame of a tracker at an unknown pose "
                        "2-3 m away")
    p.add_argument("--miss-rate", type=float, default=0.0,
                   help="raw reflectors: probability that the tracker misses one (empty cell)")
    p.set_defaults(func=_synth)


def _synth(args):
    from campaign.effects.base import parse_effect_list
    from campaign.errors import ConfigError
    from campaign.measure.csvio import write_measured_csv
    from campaign.run import load_robot
    from campaign.sim.truth import synthetic_campaign, write_truth

    if args.seed < 0:
        raise ConfigError(f"--seed must be >= 0, got {args.seed}")
    robot = load_robot(args.robot, tool_frame=args.tool_frame, base_frame=args.base_frame)
    if args.kind == "pose" and args.frame == "robot" and args.miss_rate == 0:
        poses, truth = synthetic_campaign(robot, args.poses, seed=args.seed, noise_m=args.noise_um * 1e-6,
                                          hidden=parse_effect_list(args.hidden, "--hidden"))
    else:
        from dataclasses import replace

        from campaign.sim.truth import random_tracker_pose, synthesize_kind

        if not 0 <= args.miss_rate < 1:
            raise ConfigError(f"--miss-rate must be in [0, 1), got {args.miss_rate}")
        # one-reflector data identify fewer parameters: the truth's errors go where they can see them
        _, truth = synthetic_campaign(robot, 1, seed=args.seed, noise_m=args.noise_um * 1e-6,
                                      hidden=parse_effect_list(args.hidden, "--hidden"), position_only=args.kind == "point")
        if args.frame == "tracker":
            truth = replace(truth, T_LI=random_tracker_pose(args.seed))
        from campaign.sim.truth import random_joint_poses

        q = random_joint_poses(robot, args.poses, seed=args.seed + 1)
        context = {}
        for e in truth.effects.effects:
            if hasattr(e, "synthetic_context"):
                context.update(e.synthetic_context(len(q), args.seed))
        poses = synthesize_kind(truth, q, kind=args.kind, frame=args.frame, seed=args.seed + 2, context=context,
                                miss_rate=args.miss_rate)
    out = Path(args.csv)
    write_measured_csv(out, poses, robot)
    truth_path = Path(args.truth) if args.truth else out.with_suffix(".truth.yaml")
    write_truth(truth, truth_path)
    print(f"wrote {len(poses)} poses to {out}; truth to {truth_path}")
    if args.kind == "markers":  # the reflectors' nominal positions: what the user knows of the tool, not truth
        from campaign.fileio import atomic_write

        markers_path = out.with_suffix(".markers.yaml")
        atomic_write(markers_path, yaml_markers(poses.marker_positions))
        print(f"nominal reflector positions (tool frame, m) in {markers_path}: "
              f"`campaign import {out} --markers {markers_path} ...`")
    return 0


def yaml_markers(P) -> str:
    """``markers: [[x, y, z], ...]`` (m, tool frame), the file `campaign import --markers` reads."""
    import yaml

    return yaml.safe_dump({"markers": [[float(v) for v in p] for p in P]}, default_flow_style=None)


def _sim(args):
    from campaign.cell.server import serve_until_interrupted
    from campaign.errors import ConfigError
    from campaign.run import RunFolder
    from campaign.sim.cell import start_cell

    if args.run_dir is not None:
        if args.run != "runs/sim" and Path(args.run) != Path(args.run_dir):
            raise ConfigError(f"two runs given: {args.run_dir} and --run {args.run}")
        args.run = args.run_dir
    if args.stream_out is not None:
        return _stream_out(args)

    run = RunFolder(args.run, config=args.config)
    cfg = sim_config(run, args.robot, args.tool_frame, args.base_frame)
    # the cell writes RUN/sim/ while it serves and holds RUN/sim/.lock all that time (a driver
    # may hold RUN/.lock beside it: `campaign run RUN --controller ... --tracker ...`)
    with run.sim_lock("sim"):
        # a run that holds measurements continues its campaign clock (never backwards)
        world, cell = start_cell(cfg, run.path, args.host, args.controller_port, args.tracker_port, run.clock_s())
        print(f"simulated cell: {world.robot.name}, controller {args.host}:{cell.controller_port}, "
              f"tracker {args.host}:{cell.tracker_port} (truth in {world.truth_path}); Ctrl-C stops", flush=True)
        return serve_until_interrupted(cell)


def _stream_out(args):
    import sys

    from campaign.errors import ConfigError
    from campaign.progress import Progress
    from campaign.sim.streamlog import write_stream_log

    if args.run_dir is None:
        raise ConfigError("--stream-out LOG needs the run: campaign sim RUN --stream-out LOG")
    if (args.robot, args.tool_frame, args.base_frame) != (None, None, None):
        raise ConfigError("--robot, --tool-frame, --base-frame: not with --stream-out (the run's robot is driven)")
    bar = Progress("sim --stream-out", total=1000, enabled=sys.stderr.isatty(), unit="‰")
    try:
        res = write_stream_log(args.run, args.stream_out, rate_hz=args.rate, config=args.config,
                               progress=lambda f: bar.update(int(1000 * f) - bar.done))
    finally:
        bar.close()
    print(f"wrote {res['samples']:,} samples at {res['rate_hz']:g} Hz ({res['stops']} stops, "
          f"{res['duration_s'] / 3600:.2f} h, {res['lost']} stops with a lost beam) to {args.stream_out}; "
          f"truth in {res['truth']}")
    return 0


def sim_config(run, robot=None, tool_frame=None, base_frame=None):
    """The configuration a simulated cell for ``run`` serves: the run's (RUN/campaign.yaml, or
    the one given), with ``robot`` and its frames in place of its robot where given. A run that
    records another robot is a ConfigError: the cell never simulates a robot the run is not."""
    from campaign.errors import ConfigError
    from campaign.run import RunFolder, load_robot, same_robot

    run.check_recorded_robot()
    cfg = run.config
    asked = cfg.with_robot(robot, tool_frame, base_frame)
    if asked is cfg:
        return cfg
    wanted = load_robot(asked.robot_spec, tool_frame=asked.tool_frame, base_frame=asked.base_frame)
    recorded = RunFolder(run.path)
    if recorded.has_config and not same_robot(wanted, recorded.robot()):
        raise ConfigError(f"--robot {robot or cfg.robot}: {recorded.config_path} records robot "
                          f"{recorded.config.robot!r} (tool frame {recorded.robot().tool_frame}); "
                          f"simulate that one, or use another --run")
    return asked
