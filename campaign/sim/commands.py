"""`campaign sim`: the simulated cell alone (for a real driver test); `campaign synth`: a
measured-pose CSV from a seeded truth, the truth kept apart."""

from __future__ import annotations

from pathlib import Path


def register(sub):
    s = sub.add_parser(
        "sim", help="run the simulated cell alone (controller and tracker ports), for a real driver test",
        description="Serve the simulated robot controller and laser tracker (docs/protocol.md) on two TCP ports "
                    "sharing one simulated world, until Ctrl-C. The hidden truth goes to RUN/sim/truth.yaml. "
                    "Drive it with `campaign run RUN --controller HOST:PORT --tracker HOST:PORT`.")
    s.add_argument("--config", metavar="FILE", default=None, help="configuration (default: the embedded one)")
    s.add_argument("--run", metavar="DIR", default="runs/sim", help="where the simulator keeps its truth (default: %(default)s)")
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
    p.add_argument("--robot", default="comau_racer5_080", help="robot (default: %(default)s)")
    p.set_defaults(func=_synth)


def _synth(args):
    from campaign.effects.base import parse_effect_list
    from campaign.errors import ConfigError
    from campaign.measure.csvio import write_measured_csv
    from campaign.run import load_robot
    from campaign.sim.truth import synthetic_campaign, write_truth

    if args.seed < 0:
        raise ConfigError(f"--seed must be >= 0, got {args.seed}")
    poses, truth = synthetic_campaign(load_robot(args.robot), args.poses, seed=args.seed,
                                      noise_m=args.noise_um * 1e-6, hidden=parse_effect_list(args.hidden))
    out = Path(args.csv)
    write_measured_csv(out, poses)
    truth_path = Path(args.truth) if args.truth else out.with_suffix(".truth.yaml")
    write_truth(truth, truth_path)
    print(f"wrote {len(poses)} poses to {out}; truth to {truth_path}")
    return 0


def _sim(args):
    import time

    from campaign.config import load_config
    from campaign.run import RunFolder
    from campaign.sim.cell import start_cell

    cfg = load_config(args.config)
    # a run that holds measurements continues its campaign clock (never backwards)
    world, ctrl, trk = start_cell(cfg, args.run, args.host, args.controller_port, args.tracker_port,
                                  RunFolder(args.run).clock_s())
    print(f"simulated cell: controller {args.host}:{ctrl.port}, tracker {args.host}:{trk.port} "
          f"(truth in {world.truth_path}); Ctrl-C stops", flush=True)
    try:
        while True:
            time.sleep(3600)
    except KeyboardInterrupt:
        return 0
