"""Benchmark of `campaign run --sim` (issue 4): a campaign of ~14,000 poses against the simulated cell.

    python benchmarks/bench_run.py [--poses 14000] [--faults RATE]

Writes a plan of random valid poses (the planner is benchmarked on its own), runs
`campaign run RUN --sim` as a separate process, and reports the wall time and the simulated
campaign duration (compare: the paper's 13,919 poses took about 3.5 days). ``--faults RATE``
injects every fault but the emergency stop at that rate per request (late replies held back
50 ms, within the timeout) and checks that every pose ends measured or failed, once. Writes
benchmarks/results/run.json (run_faults.json with --faults).
"""

from __future__ import annotations

import argparse
import json
import os
import re
import sqlite3
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import yaml

from campaign.model.robot import RobotModel
from campaign.paths import DEFAULT_SCENE
from campaign.sim.truth import random_joint_poses


def main():
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--poses", type=int, default=14000)
    ap.add_argument("--faults", type=float, default=0.0, help="rate of every fault kind but estop (default: none)")
    args = ap.parse_args()
    robot = RobotModel.load()
    with tempfile.TemporaryDirectory() as tmp:
        run = Path(tmp) / "run"
        (run / "plan").mkdir(parents=True)
        q = random_joint_poses(robot, args.poses, seed=0)
        (run / "plan" / "poses.csv").write_text(
            "pose_id,q1,q2,q3,q4,q5,q6\n" + "\n".join(f"{i}," + ",".join(repr(float(v)) for v in q[i])
                                                        for i in range(len(q))) + "\n")
        cfg = {"robot": "comau_racer5_080", "scene": str(DEFAULT_SCENE),
               "sim": {"seed": 0, "hidden_effects": ["ground_compliance", "joint_compliance"]}}
        if args.faults:
            r = args.faults
            cfg["sim"]["faults"] = {"drop": r, "late": r, "late_delay_s": 0.05, "garble": r, "beam_lost": r,
                                    "robot_fault": r}
            cfg["run"] = {"timeout_s": 1.0, "backoff_s": 0.01}
        (run / "campaign.yaml").write_text(yaml.safe_dump(cfg))
        load_before = os.getloadavg()
        t0 = time.perf_counter()
        out = subprocess.run([sys.executable, "-m", "campaign.cli", "run", str(run), "--sim", "--quiet"],
                             capture_output=True, text=True, check=True).stdout
        wall = time.perf_counter() - t0
        with sqlite3.connect(run / "measurements.sqlite") as db:
            rows = db.execute("SELECT pose_id, status, reason FROM poses").fetchall()
        ids = sorted(r[0] for r in rows)
        complete = ids == list(range(args.poses)) and all(r[2] for r in rows if r[1] == "failed")
    m = re.search(r"measured (\d+), failed (\d+).*campaign clock ([\d.]+) h = ([\d.]+) days", out)
    res = {"poses": args.poses, "wall_s": wall, "measured": int(m.group(1)), "failed": int(m.group(2)),
           "simulated_hours": float(m.group(3)), "simulated_days": float(m.group(4)),
           "fault_rate": args.faults, "each_pose_once_with_reason_if_failed": complete,
           "paper": {"poses": 13919, "days": 3.5}, "load_average_before": load_before,
           "load_average": os.getloadavg()}
    print(out.strip())
    print(f"campaign run --sim of {args.poses} poses: {wall:.1f} s wall; simulated campaign {res['simulated_days']:.2f} days "
          f"(paper: 3.5 days for 13,919 poses); load average {res['load_average'][0]:.2f}")
    if args.faults:
        print(f"faults at {args.faults:.1%} per request: every pose stored once, failures with a reason: {complete}")
    path = Path(__file__).parent / "results" / ("run_faults.json" if args.faults else "run.json")
    path.write_text(json.dumps(res, indent=2))


if __name__ == "__main__":
    main()
