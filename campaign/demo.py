"""`campaign demo`: the whole story on the embedded defaults, as the README's first command."""

from __future__ import annotations

import sys
from pathlib import Path

from campaign.cli import main as cli


def register(sub):
    p = sub.add_parser("demo", help="the whole story on the embedded defaults (simulated hardware)")
    p.add_argument("--run", default="runs/demo", metavar="DIR", help="run folder (default: %(default)s)")
    p.add_argument("--poses", type=int, default=2000, help="simulated poses (default: %(default)s)")
    p.set_defaults(func=_demo)


def _step(title, *argv):
    print(f"\n$ campaign {' '.join(str(a) for a in argv)}    # {title}", flush=True)
    rc = cli([str(a) for a in argv])
    if rc != 0:
        print(f"campaign demo: step '{title}' failed", file=sys.stderr)
        sys.exit(rc)


def _demo(args):
    import shutil

    run = Path(args.run)
    if run.exists():
        shutil.rmtree(run)
    csv = run.parent / (run.name + "_measured.csv")
    _step("simulate measurements with hidden geometric errors", "synth", "--csv", csv, "--poses", args.poses,
          "--truth", run.parent / (run.name + "_truth.yaml"))
    _step("import them as a run", "import", csv, "--run", run)
    _step("identify the geometric model", "calibrate", run, "--no-ann")
    return 0
