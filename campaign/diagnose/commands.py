"""`campaign diagnose RUN [--json]`."""

from __future__ import annotations

import sys


def register(sub):
    p = sub.add_parser("diagnose", help="show where the model fails and which physical effect is missing")
    p.add_argument("run", metavar="DIR", help="run folder with measurements.sqlite")
    p.add_argument("--json", action="store_true", help="print the ranking as JSON on stdout")
    p.add_argument("--effects", metavar="NAME,...", default=None,
                   help="effects already in the model: built-in names, path/file.py:ClassName (relative to the "
                        "current directory) or installed entry points (default: those in DIR/campaign.yaml)")
    p.add_argument("--candidates", metavar="NAME,...", default=None,
                   help="candidate effects, named the same ways (default: every built-in and installed effect); a "
                        "joint-indexed one named without joints is searched over the robot's joints, NAME:2,3 "
                        "scores those joints only")
    p.add_argument("--folds", type=int, default=None,
                   help="held-out folds on the training set (default: from the data, leave-one-out below 60 "
                        "training poses, else 5)")
    p.add_argument("--no-report", action="store_true", help="skip the HTML report and plots")
    p.add_argument("--cell-segment", type=int, default=None, metavar="N",
                   help="a run measured on more than one cell: diagnose the poses of its N-th cell segment alone "
                        "(default: all, with a registration per segment, when they agree; docs/cells.md)")
    p.set_defaults(func=_diagnose)


def _diagnose(args):
    from campaign.diagnose.engine import diagnose
    from campaign.errors import ConfigError

    if args.folds is not None and args.folds < 2:
        raise ConfigError(f"--folds must be at least 2, got {args.folds}")
    from campaign.diagnose.report import diagnosis_doc, write_diagnosis
    from campaign.fileio import strict_json
    from campaign.run import RunFolder

    progress = None if args.json else (lambda msg: print(msg, file=sys.stderr, flush=True))
    with RunFolder(args.run).lock("diagnose"):  # no calibrate rewrites what it reads, nothing else writes diagnose/
        d = diagnose(args.run, effects=args.effects, candidates=args.candidates, folds=args.folds, progress=progress,
                     cell_segment=args.cell_segment)
        report = write_diagnosis(d, report=not args.no_report)
    if args.json:
        print(strict_json(diagnosis_doc(d, report.parent.name)))  # diagnosis.json, strict JSON
    else:
        # the diagnosis's own folder, which later diagnoses leave as it is (RUN/diagnose: the newest);
        # the verdict is the last line a person reads (the demo ends with it)
        print(f"{'report' if not args.no_report else 'written'}: {report}")
        print(d.text())
    return 0
