"""Where does the neural compensator start to pay? (issue 14, "what a small campaign gives up")

    nice -n 5 python benchmarks/bench_select_ann.py [--sizes 60,120,250,500,1000,2000] [--epochs 300]

A simulated campaign with smooth effects the physical model lacks (hidden geometric errors +
joint_compliance + cyclic, as benchmarks/bench_calibrate.py: the case most favourable to the
network), 10 µm tracker noise. For each number of training poses: the geometric model, then
the network on its residual (hidden sizes chosen by 3-fold cross-validation on the training
poses, as `calibrate` does), scored on 2,000 fixed test poses and by the cross-validation
itself. Below the smallest size where the network's cross-validated error beats the physical
model's, `calibrate` does not train a network unless asked (campaign.identify.calibrate.
ANN_MIN_TRAIN_POSES). Writes benchmarks/results/select_ann.json.
"""

from __future__ import annotations

import argparse
import json
import os
import time
from pathlib import Path

import numpy as np

from campaign.ann import compensate_pose, fit_ann_stage
from campaign.effects import make_effect
from campaign.identify.solver import CalibrationModel
from campaign.model.kinematics import pose_error
from campaign.model.robot import RobotModel
from campaign.sim.truth import make_truth, random_joint_poses, synthesize


#: relative improvement that counts as the network beating the physical model
GAIN = 0.02


def mean_mm(dz):
    return 1e3 * float(np.mean(np.linalg.norm(dz[:, :3], axis=1)))


def main():
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--sizes", default="60,120,250,500,1000,2000")
    ap.add_argument("--epochs", type=int, default=300)
    ap.add_argument("--hidden", default="joint_compliance,cyclic")
    ap.add_argument("--out", default=str(Path(__file__).parent / "results" / "select_ann.json"))
    args = ap.parse_args()
    robot = RobotModel.load()
    hidden = {n: make_effect(n, robot).typical_params(0) for n in args.hidden.split(",") if n}
    truth = make_truth(robot, seed=0, effects=hidden)
    sizes = [int(s) for s in args.sizes.split(",")]
    n_test = 2000
    meas = synthesize(truth, random_joint_poses(robot, max(sizes) + n_test, seed=1), seed=2)
    te = np.arange(max(sizes), max(sizes) + n_test)
    rows = []
    t_all = time.perf_counter()
    for n in sizes:
        tr = np.arange(n)
        t0 = time.perf_counter()
        geo = CalibrationModel(robot=robot).fit(meas.q[tr], meas.T_IE[tr])
        dz = geo.residuals(meas.q, meas.T_IE)
        net, cv = fit_ann_stage(meas.q[tr], dz[tr], sizes=((16, 16), (32, 16)), folds=3, max_epochs=args.epochs,
                                q_lower=robot.q_lower, q_upper=robot.q_upper)
        dz_ann = pose_error(compensate_pose(geo.predict(meas.q), net.predict(meas.q)), meas.T_IE)
        best = [r for r in cv["sizes"] if tuple(r["hidden"]) == tuple(cv["best"])][0]
        row = {"train_poses": n, "geometric_test_mm": mean_mm(dz[te]), "geometric_ann_test_mm": mean_mm(dz_ann[te]),
               "geometric_train_mm": mean_mm(dz[tr]), "ann_cv_mean_position_mm": best["mean_position_mm"],
               "best_hidden": list(cv["best"]), "wall_s": time.perf_counter() - t0}
        # "beats": lower by more than GAIN (a network regularised to nothing differs by round-off)
        row["ann_beats_geometric_on_test"] = row["geometric_ann_test_mm"] < (1 - GAIN) * row["geometric_test_mm"]
        row["ann_cv_beats_geometric"] = row["ann_cv_mean_position_mm"] < (1 - GAIN) * row["geometric_train_mm"]
        rows.append(row)
        print(json.dumps(row), flush=True)
    first = next((r["train_poses"] for r in rows if r["ann_cv_beats_geometric"] and r["ann_beats_geometric_on_test"]),
                 None)
    report = {"hidden_effects": list(hidden), "test_poses": n_test, "max_epochs": args.epochs, "rows": rows,
              "smallest_size_where_ann_beats_geometric": first, "wall_s": time.perf_counter() - t_all,
              "load_average": os.getloadavg()}
    Path(args.out).write_text(json.dumps(report, indent=2))
    print(json.dumps({k: v for k, v in report.items() if k != "rows"}, indent=1))


if __name__ == "__main__":
    main()
