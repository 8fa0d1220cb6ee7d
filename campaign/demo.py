"""`campaign demo`: the whole story on the embedded defaults, as the README's first command.

It is `campaign auto RUN --sim` (campaign.auto) on the default cell (hidden: geometric errors and
the elastic ground): plan the short campaign (``--select 0``: every suitable pose) → measure it on
the simulated cell → calibrate → diagnose → add the effect the diagnosis names → calibrate and
diagnose again, until "at the measurement noise: nothing left to find"; each step is printed as
it happens, one line per round, then the error falling over the calibrations.
"""

from __future__ import annotations

from pathlib import Path


def register(sub):
    p = sub.add_parser("demo", help="the whole story on the embedded defaults (simulated hardware): campaign auto")
    p.add_argument("--run", default="runs/demo", metavar="DIR",
                   help="run folder (default: %(default)s); a folder holding measurements is refused, never replaced")
    p.add_argument("--grid-scale", type=float, default=1.0, help="plan grid scale (default: 1 = 1,428,000 candidates)")
    p.add_argument("--select", type=int, default=None, metavar="N",
                   help="a short campaign of the N most informative poses for the physical model (default: the "
                        "short campaign, 120); 0: every suitable pose, the long campaign")
    p.set_defaults(func=_demo)


def _demo(args):
    import sys

    from campaign.auto import AutoOptions, CellSource, auto
    from campaign.identify.report import history_table
    from campaign.run import RunFolder

    options = AutoOptions(grid_scale=args.grid_scale, select=args.select).check()
    run = Path(args.run)
    folder = RunFolder(run)
    folder.refuse_if_measured("the demo", f"give the demo a new folder (--run {run}-2)")
    print(f"$ campaign auto {run} --sim" + (f" --grid-scale {args.grid_scale:g}" if args.grid_scale != 1 else "")
          + (f" --select {args.select}" if args.select is not None else ""), flush=True)
    print("  (the simulated cell hides geometric errors and the elastic ground)", flush=True)
    result = auto(run, CellSource(sim=True), options, say=lambda line: print(line, flush=True),
                  progress=sys.stderr.isatty())
    print("\nthe error over the calibrations (held-out test set):")
    print(history_table(run))
    print(f"\nreports: {run}/auto/report.html, {run}/calibration/report.html, {run}/plan/tour.png")
    return 0 if result.final.reason in ("at_floor", "unexplained") else 1
