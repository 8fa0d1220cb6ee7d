"""`campaign auto RUN (--sim | --cell SPEC | --controller HOST:PORT --tracker HOST:PORT) [--budget HOURS]
[--target-mm X] [--max-poses N]`: the loop of :mod:`campaign.auto`."""

from __future__ import annotations

import sys


def register(sub):
    p = sub.add_parser(
        "auto", help="plan, measure, calibrate, diagnose, and measure more until the model is understood",
        description="The campaign that measures until it understands the robot: plans the short campaign when RUN "
                    "has no plan, measures it, calibrates, diagnoses; then, while the model is above the noise floor "
                    "and the limits allow, adds the effect the diagnosis names, measures the poses that determine the "
                    "model best, or the poses that reveal an unexplained error, and stops when nothing more is to be "
                    "learnt, saying why (docs/auto.md). One line per round; killed, `campaign auto RUN` resumes.")
    p.add_argument("run", metavar="RUN", help="run folder (planned by auto when it has no plan)")
    src = p.add_mutually_exclusive_group()
    src.add_argument("--sim", action="store_true", help="measure on the simulated cell")
    src.add_argument("--cell", metavar="SPEC", default=None,
                     help="measure on a cell served from adapters, as `campaign run --cell SPEC` (sim, mujoco, "
                          "FILE.py, module or entry point; docs/cell.md)")
    src.add_argument("--controller", metavar="HOST:PORT", help="the robot controller")
    p.add_argument("--tracker", metavar="HOST:PORT", help="the laser tracker (with --controller)")
    p.add_argument("--options", metavar="FILE", default=None,
                   help="with --cell: the adapters' options (YAML with 'controller:' and 'tracker:' sections)")
    p.add_argument("--budget", type=float, metavar="HOURS", default=None,
                   help="campaign hours at most (the run's clock: motion, settle, tracker; default: no limit)")
    p.add_argument("--target-mm", type=float, metavar="X", default=None,
                   help="the model counts as well determined when its predicted mean position error against the "
                        "truth is at most X mm (default: half the noise floor)")
    p.add_argument("--max-poses", type=int, metavar="N", default=None,
                   help="planned poses at most (default: twice the short campaign's)")
    p.add_argument("--grid-scale", type=float, default=None,
                   help="the plan's grid scale when auto plans (default: 1 = 1,428,000 candidates)")
    p.add_argument("--select", type=int, metavar="N", default=None,
                   help="when auto plans: the N most informative poses (default: the short campaign; 0: all)")
    p.add_argument("--retry-failed", action="store_true",
                   help="measure the poses stored as failed again (as `campaign run --retry-failed`); a finished "
                        "loop goes on for them")
    p.add_argument("--allow-other-cell", action="store_true",
                   help="measure on another cell than the run's measurements so far came from (refused otherwise; "
                        "recorded in the run)")
    p.add_argument("--cell-segment", type=int, default=None, metavar="N",
                   help="a run measured on more than one cell whose segments are not one robot: calibrate and "
                        "diagnose the poses of its N-th cell segment alone (kept for the run's later rounds; "
                        "docs/cells.md)")
    p.add_argument("--no-report", action="store_true", help="no HTML reports at the end")
    p.add_argument("--quiet", action="store_true", help="no progress bars")
    from campaign.watch.commands import add_watch_argument

    add_watch_argument(p)
    p.set_defaults(func=_auto)


def _auto(args):
    from campaign.auto import AutoOptions, CellSource, auto
    from campaign.errors import ConfigError
    from campaign.measure.commands import _hostport

    if args.tracker and not args.controller:
        raise ConfigError("--tracker goes with --controller")
    if args.controller and not args.tracker:
        raise ConfigError("--controller needs --tracker HOST:PORT too")
    if args.options and not args.cell:
        raise ConfigError("--options goes with --cell (the adapters' options)")
    cell = None
    if args.sim or args.cell or args.controller:
        cell = CellSource(sim=args.sim, cell=args.cell, options=args.options,
                          controller=_hostport(args.controller, "controller") if args.controller else None,
                          tracker=_hostport(args.tracker, "tracker") if args.tracker else None)
    options = AutoOptions(budget_h=args.budget, target_mm=args.target_mm, max_poses=args.max_poses,
                          grid_scale=args.grid_scale if args.grid_scale is not None else 1.0,
                          select=args.select).check()
    from campaign.watch.commands import watching

    with watching(args.run, args.watch):
        auto(args.run, cell, options, say=lambda line: print(line, flush=True),
             progress=not args.quiet and sys.stderr.isatty(), report=not args.no_report,
             retry_failed=args.retry_failed, allow_other_cell=args.allow_other_cell, cell_segment=args.cell_segment)
    return 0
