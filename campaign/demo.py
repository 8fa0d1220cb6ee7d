"""`campaign demo`: the whole story on the embedded defaults, as the README's first command.

plan a short campaign (the most informative poses; ``--select 0``: all of them) → simulated
campaign with a hidden physical effect → calibrate → diagnose → add the suggested effect →
calibrate again (with the neural compensator when the campaign is long) → the error, step by
step → diagnose again, which ends the demo with "at the measurement noise: nothing left to find".
Each step is the command line a user would type; the one step that is not a command (adding
the effect to RUN/campaign.yaml) is :meth:`campaign.run.RunFolder.add_effects`.
"""

from __future__ import annotations

import json
import sys
from pathlib import Path

from campaign.cli import main as cli


def register(sub):
    p = sub.add_parser("demo", help="the whole story on the embedded defaults (simulated hardware)")
    p.add_argument("--run", default="runs/demo", metavar="DIR",
                   help="run folder (default: %(default)s); a folder holding measurements is refused, never replaced")
    p.add_argument("--grid-scale", type=float, default=1.0, help="plan grid scale (default: 1 = 1,428,000 candidates)")
    p.add_argument("--select", type=int, default=120, metavar="N",
                   help="a short campaign of the N most informative poses for the physical model (default: "
                        "%(default)s); 0: every suitable pose, the long campaign a neural compensator needs")
    p.add_argument("--ann-epochs", type=int, default=None,
                   help="epochs of each network training at most (default: the ANN solver's own bound)")
    p.set_defaults(func=_demo)


def _step(title, *argv):
    print(f"\n=== {title}\n$ campaign {' '.join(str(a) for a in argv)}", flush=True)
    rc = cli([str(a) for a in argv])
    if rc != 0:
        print(f"campaign demo: step '{title}' failed", file=sys.stderr)
        sys.exit(rc)


def _demo(args):
    from campaign.config import check_int, check_number
    from campaign.run import RunFolder

    check_number(args.grid_scale, "--grid-scale", low=0.0, low_open=True)
    if args.ann_epochs is not None:
        check_int(args.ann_epochs, "--ann-epochs", low=1)
    run = Path(args.run)
    folder = RunFolder(run)
    folder.refuse_if_measured("the demo", f"give the demo a new folder (--run {run}-2)")
    check_int(args.select, "--select", low=0)
    with folder.lock("demo"):  # the steps below take it again (re-entrant); another command is refused
        return _story(args, run, folder)


def _story(args, run: Path, folder) -> int:
    from campaign.identify.report import history_table

    if args.select:
        _step(f"1. plan a short campaign (grid → suitable poses → the {args.select} most informative → "
              "collision-free tour)", "plan", "--run", run, "--grid-scale", args.grid_scale, "--select", args.select)
    else:
        _step("1. plan the long campaign (grid → every suitable pose → collision-free tour)", "plan", "--run", run,
              "--grid-scale", args.grid_scale, "--all")
    _step("2. measure it on the simulated cell (hidden: geometric errors + the elastic ground)", "run", run, "--sim")
    _step("3. calibrate the geometric model", "calibrate", run, "--no-ann")
    print(f"\n=== 4. where does the model fail, and which effect is missing?\n$ campaign diagnose {run}", flush=True)
    rc = cli(["diagnose", str(run)])
    if rc != 0:
        sys.exit(rc)
    first = json.loads((folder.diagnose_dir / "diagnosis.json").read_text())
    verdict = first["verdict"]
    # this diagnosis's own report: step 8's diagnosis becomes RUN/diagnose and leaves this one as it is
    first_report = Path("diagnoses", first["diagnosis_id"], "report.html")
    if verdict not in (None, "unexplained"):
        effects = folder.add_effects([verdict])
        print(f"\n=== 5. add the suggested effect: `effects: [{', '.join(effects)}]` in {folder.config_path}")
    _step("6. calibrate again, with the effect (and the neural residual compensator if the campaign is long "
          "enough for one)", "calibrate", run,
          "--sizes", "32x16,64x32", "--folds", "3", *(["--epochs", args.ann_epochs] if args.ann_epochs else []))
    print("\n=== 7. watch the error fall (held-out test set)")
    print(history_table(run))
    print(f"\nreports: {run}/calibration/report.html, {run / first_report} (step 4's diagnosis), "
          f"{run}/plan/tour.png")
    print(f"\n=== 8. is anything left to find?\n$ campaign diagnose {run}", flush=True)
    rc = cli(["diagnose", str(run)])
    if rc != 0:
        sys.exit(rc)
    return 0
