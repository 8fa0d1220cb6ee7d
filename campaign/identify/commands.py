"""`campaign import`, `campaign export`, `campaign calibrate`."""

from __future__ import annotations

import sys


def register(sub):
    p = sub.add_parser("import", help="turn a measured-pose CSV into a run folder")
    p.add_argument("csv", metavar="CSV", help="measured-pose CSV (pose_id,time_s,q1..q6,x,y,z,rx,ry,rz[,extra...])")
    p.add_argument("--run", required=True, metavar="DIR", help="run folder to create (must not hold measurements)")
    p.add_argument("--robot", default="comau_racer5_080", help="robot for the joint-limit check (default: %(default)s)")
    p.set_defaults(func=_import)

    p = sub.add_parser("export", help="write a run's measured poses as a measured-pose CSV")
    p.add_argument("run", metavar="DIR", help="run folder")
    p.add_argument("--csv", required=True, metavar="OUT", help="CSV file to write")
    p.set_defaults(func=_export)

    p = sub.add_parser("calibrate", help="identify the model of a run; write calibration/metrics.json and params.yaml")
    p.add_argument("run", metavar="DIR", help="run folder with measurements.sqlite")
    p.add_argument("--effects", metavar="NAME,...", default=None,
                   help="physical effects to identify with the geometry (default: those in DIR/campaign.yaml)")
    p.add_argument("--position-only", action="store_true", help="use measured positions only")
    ann = p.add_mutually_exclusive_group()
    ann.add_argument("--ann", dest="ann", action="store_true", default=None,
                     help="train the neural residual compensator (default)")
    ann.add_argument("--no-ann", dest="ann", action="store_false", help="geometric (and effects) only")
    p.add_argument("--sizes", default=None, metavar="N1xN2,...",
                   help="hidden sizes for the ANN's cross-validation, e.g. 16x16,32x16,32x32,64x32")
    p.add_argument("--folds", type=int, default=5, help="cross-validation folds (default: %(default)s)")
    p.add_argument("--epochs", type=int, default=None, help="ANN training epochs at most (default: 2048)")
    p.add_argument("--quiet", action="store_true", help="no progress output")
    p.set_defaults(func=_calibrate)


def _import(args):
    from campaign.measure.store import import_csv
    from campaign.model.robot import RobotModel

    n = import_csv(args.csv, args.run, RobotModel.load(args.robot))
    print(f"imported {n} poses into {args.run}/measurements.sqlite")
    return 0


def _export(args):
    from campaign.measure.csvio import write_measured_csv
    from campaign.measure.store import open_run

    with open_run(args.run) as store:
        poses = store.load_measured()
    write_measured_csv(args.csv, poses)
    print(f"wrote {len(poses)} poses to {args.csv}")
    return 0


def _calibrate(args):
    from campaign.identify.calibrate import calibrate, summary_text

    ann_options = {"folds": args.folds}
    if args.sizes:
        from campaign.identify.ann_stage import parse_sizes

        ann_options["sizes"] = parse_sizes(args.sizes)
    if args.epochs:
        ann_options["max_epochs"] = args.epochs
    progress = None if args.quiet else (lambda msg: print(msg, file=sys.stderr, flush=True))
    ann = True if args.ann is None else args.ann
    result = calibrate(args.run, effects=args.effects, position_only=args.position_only, ann=ann,
                       ann_options=ann_options, progress=progress)
    print(summary_text(result))
    return 0
