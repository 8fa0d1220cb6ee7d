"""Identification time of the paper-size campaign against an earlier commit (issue 24: within 20 %).

    OPENBLAS_NUM_THREADS=1 python benchmarks/bench_identify_against.py [--commit 39fafb6] [--poses 14000] [--rounds 2]

Exports ``campaign/`` of the commit into a temporary folder (git archive) and times, alternately in
fresh processes, that commit's ``CalibrationModel.fit`` and this tree's identification as
`calibrate` runs it (``fit_model``, ``--model auto``) on the same 14,000 simulated poses (80 %
training); the best of each, their ratio and whether the base parameters agree. Writes
benchmarks/results/identify_against.json.
"""

import argparse
import json
import os
import subprocess
import sys
import tempfile
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parent.parent

CHILD = r'''
import json, sys, time
from campaign.identify.solver import CalibrationModel
from campaign.identify.split import train_test_split
from campaign.model.robot import RobotModel
from campaign.sim.truth import make_truth, random_joint_poses, synthesize
robot = RobotModel.load()
q = random_joint_poses(robot, int(sys.argv[1]), seed=1)
meas = synthesize(make_truth(robot, seed=0), q, seed=2)
tr = ~train_test_split(meas.pose_id)
try:
    from campaign.identify.model_choice import fit_model
    run = lambda: fit_model(lambda **kw: CalibrationModel(robot=robot, **kw), meas.q[tr], meas.T_IE[tr])[0]
except ImportError:
    run = lambda: CalibrationModel(robot=robot).fit(meas.q[tr], meas.T_IE[tr])
ts = []
for _ in range(2):
    t0 = time.perf_counter(); m = run(); ts.append(time.perf_counter() - t0)
print(json.dumps({"best_s": min(ts), "base_params": m.base_params_.tolist()}))
'''


def child(path, poses):
    env = dict(os.environ, PYTHONPATH=str(path))
    out = subprocess.run([sys.executable, "-c", CHILD, str(poses)], env=env, capture_output=True, text=True, check=True)
    return json.loads(out.stdout.strip().splitlines()[-1])


def main():
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--commit", default="39fafb6")
    ap.add_argument("--poses", type=int, default=14000)
    ap.add_argument("--rounds", type=int, default=2)
    args = ap.parse_args()
    with tempfile.TemporaryDirectory() as tmp:
        archive = subprocess.run(["git", "-C", str(ROOT), "archive", args.commit, "campaign"], capture_output=True,
                                 check=True).stdout
        subprocess.run(["tar", "-x", "-C", tmp], input=archive, check=True)
        base, here = [], []
        for _ in range(args.rounds):
            base.append(child(tmp, args.poses))
            here.append(child(ROOT, args.poses))
    import numpy as np

    b = min(r["best_s"] for r in base)
    h = min(r["best_s"] for r in here)
    diff = float(np.max(np.abs(np.array(base[0]["base_params"]) - np.array(here[0]["base_params"]))))
    out = {"commit": args.commit, "poses": args.poses, "base_best_s": b, "this_tree_best_s": h, "ratio": h / b,
           "max_abs_base_param_difference": diff, "load_average": list(os.getloadavg()), "time_unix_s": time.time(),
           "openblas_num_threads": os.environ.get("OPENBLAS_NUM_THREADS")}
    path = ROOT / "benchmarks" / "results" / "identify_against.json"
    path.write_text(json.dumps(out, indent=2))
    print(json.dumps(out, indent=2))


if __name__ == "__main__":
    main()
