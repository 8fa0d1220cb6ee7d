"""Write docs/generated/*.txt: the real output of the commands the documentation shows.

    python docs/generate_outputs.py [--only NAME,...]

Runs each command on the embedded defaults (the COMAU in the default cell, the simulated
hardware) in a scratch folder, as a user would type it, and stores ``$ command`` followed by
what it printed on standard output. The pages include them with ``<!-- output: NAME -->``
(docs/hooks.py), so what the documentation shows is what the code printed when this was last run.
"""

from __future__ import annotations

import argparse
import json
import os
import resource
import shlex
import subprocess
import sys
import tempfile
import time
from pathlib import Path

OUT = Path(__file__).resolve().parent / "generated"

#: (name, command): run in order in one scratch folder; later commands use earlier runs
STEPS = (
    ("demo", "campaign demo --run runs/demo"),
    ("robots", "campaign robots"),
    ("model-base-params", "campaign model base-params"),
    ("plan", "campaign plan --run runs/cell1"),
    ("run", "campaign run runs/cell1 --sim"),
    ("calibrate", "campaign calibrate runs/cell1 --no-ann"),
    ("diagnose", "campaign diagnose runs/cell1"),
    ("calibrate-effect", "campaign calibrate runs/cell1 --no-ann --effects ground_compliance"),
    ("export", "campaign export runs/cell1 --csv cell1.csv --urdf cell1_calibrated.urdf"),
    ("predict", "campaign predict runs/cell1 --csv joints.csv"),
    ("compensate", "campaign compensate runs/cell1 --csv joints.csv"),
    ("synth", "campaign synth --csv ur10.csv --robot ur10 --poses 60 --seed 1 --kind point --frame tracker"),
    ("import", "campaign import ur10.csv --run runs/ur10 --robot ur10 --frame tracker"),
    ("calibrate-ur10", "campaign calibrate runs/ur10 --no-ann"),
    ("plan-iso9283", "campaign plan --iso9283 --run runs/iso"),
    ("run-iso9283", "campaign run runs/iso --sim"),
    ("plan-iso9283-compensated", "campaign plan --iso9283 --compensate runs/cell1 --run runs/iso-cal"),
    ("run-iso9283-compensated", "campaign run runs/iso-cal --sim"),
    ("iso9283", "campaign iso9283 runs/iso --calibrated runs/iso-cal"),
)

JOINTS_CSV = "pose_id,q1,q2,q3,q4,q5,q6\n1,0.1,0.9,-1.2,0.3,-0.6,0.2\n2,-0.4,1.1,-1.6,-0.2,-0.9,0.5\n"


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--only", default=None, help="names to write (the others still run: later steps need them)")
    args = ap.parse_args(argv)
    only = set(args.only.split(",")) if args.only else None
    OUT.mkdir(exist_ok=True)
    env = {**os.environ, "COLUMNS": "100", "OPENBLAS_NUM_THREADS": os.environ.get("OPENBLAS_NUM_THREADS", "1")}
    try:
        timings = json.loads((OUT / "timings.json").read_text())
    except (OSError, ValueError):
        timings = {}
    with tempfile.TemporaryDirectory(prefix="campaign-docs-") as tmp:
        (Path(tmp) / "joints.csv").write_text(JOINTS_CSV)
        for name, command in STEPS:
            t0 = time.perf_counter()
            argv_ = shlex.split(command)
            done = subprocess.run([sys.executable, "-m", "campaign.cli", *argv_[1:]], cwd=tmp, env=env,
                                  capture_output=True, text=True)
            if done.returncode != 0:
                print(f"{name}: `{command}` failed ({done.returncode}): {done.stderr.strip()}", file=sys.stderr)
                return 1
            wall = time.perf_counter() - t0
            if only is None or name in only:
                (OUT / f"{name}.txt").write_text(f"$ {command}\n{done.stdout}")
                # the children's peak so far: the first step's own, a bound for the later ones
                peak = resource.getrusage(resource.RUSAGE_CHILDREN).ru_maxrss / 1024
                timings[name] = {"wall_s": round(wall, 1), "load": round(os.getloadavg()[0], 1),
                                 "peak_rss_mb": round(peak) if name == STEPS[0][0] else None}
            print(f"{name:<26} {wall:6.1f} s", file=sys.stderr)
    (OUT / "timings.json").write_text(json.dumps(timings, indent=1) + "\n")
    return 0


if __name__ == "__main__":
    sys.exit(main())
