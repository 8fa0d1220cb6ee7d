"""Benchmark of `campaign diagnose` (issue 6): a 14,000-pose run with a hidden effect.

    python benchmarks/bench_diagnose.py [--poses 14000] [--hidden ground_compliance]

Synthesises the run (truth kept apart), imports it, times `diagnose` (library call, no
report) and prints the verdict. Writes benchmarks/results/diagnose.json.
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import tempfile
import time
from pathlib import Path


def main():
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--poses", type=int, default=14000)
    ap.add_argument("--hidden", default="ground_compliance")
    ap.add_argument("--seed", type=int, default=5)
    args = ap.parse_args()
    from campaign.diagnose import diagnose

    with tempfile.TemporaryDirectory() as tmp:
        csv = Path(tmp) / "m.csv"
        run = Path(tmp) / "run"
        exe = [sys.executable, "-m", "campaign.cli"]
        subprocess.run(exe + ["synth", "--csv", str(csv), "--poses", str(args.poses), "--seed", str(args.seed),
                              "--hidden", args.hidden], check=True, stdout=subprocess.DEVNULL)
        subprocess.run(exe + ["import", str(csv), "--run", str(run)], check=True, stdout=subprocess.DEVNULL)
        t0 = time.perf_counter()
        d = diagnose(run)
        wall = time.perf_counter() - t0
    print(d.text())
    print(f"\ndiagnose of {args.poses} poses ({d.n_train} training) with hidden {args.hidden!r}: {wall:.1f} s wall; "
          f"load average {os.getloadavg()[0]:.2f}")
    out = Path(__file__).parent / "results" / "diagnose.json"
    out.parent.mkdir(exist_ok=True)
    out.write_text(json.dumps({"poses": args.poses, "hidden": args.hidden, "wall_s": wall,
                               "verdict": d.verdict, "ranking": d.as_json()["ranking"]}, indent=2))


if __name__ == "__main__":
    main()
