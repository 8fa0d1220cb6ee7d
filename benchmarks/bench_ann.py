"""Benchmark of the residual network's Bayesian-regularised training (issue 5).

    python benchmarks/bench_ann.py [--train 11000] [--reference] [--cv-grid]

Data: a simulated campaign with hidden geometric errors, hidden smooth non-geometric effects
(joint compliance and cyclic transmission errors) and 10 µm tracker noise; the targets are
the residuals after geometric calibration on the training poses. Times one (64, 32)
training with the matrix-free solver; with --reference, the same training with a plain
full-Jacobian LM, and the ratio of their final losses (normalised training MSE); with
--cv-grid, the 5-fold CV over the hidden sizes for both prior models. Writes
benchmarks/results/ann.json.
"""

from __future__ import annotations

import argparse
import json
import os
import time
from pathlib import Path

import numpy as np
import torch

from campaign.ann import ResidualNetwork, cross_validate
from campaign.effects import make_effect
from campaign.identify.solver import CalibrationModel
from campaign.model.kinematics import forward, pose_error
from campaign.model.robot import RobotModel
from campaign.sim.truth import make_truth, random_joint_poses, synthesize


def data(n_train, n_test=2000, seed=0):
    robot = RobotModel.load()
    hidden = {"joint_compliance": make_effect("joint_compliance", robot).typical_params(seed),
              "cyclic": make_effect("cyclic", robot).typical_params(seed)}
    truth = make_truth(robot, seed=seed, effects=hidden)
    q = random_joint_poses(robot, n_train + n_test, seed=seed + 1)
    meas = synthesize(truth, q, seed=seed + 2)
    geo = CalibrationModel(robot=robot).fit(meas.q[:n_train], meas.T_IE[:n_train])
    dz_geo = geo.residuals(meas.q, meas.T_IE)
    dz_nom = pose_error(forward(robot, meas.q), meas.T_IE)
    return robot, meas.q, dz_geo, dz_nom, n_train


def train(robot, q, dz, n, solver, hidden=(64, 32)):
    t0 = time.perf_counter()
    net = ResidualNetwork(hidden=hidden, q_lower=robot.q_lower, q_upper=robot.q_upper, solver=solver, seed=0)
    net.fit(q[:n], dz[:n])
    wall = time.perf_counter() - t0
    res = dz[n:] - net.predict(q[n:])
    return {"solver": solver, "hidden": list(hidden), "wall_s": wall, "epochs": net.n_epochs_, "stop": net.stop_reason_,
            "mse_normalised": net.mse_normalised_, "gamma": net.gamma_, "n_weights": net.net_.n_weights,
            "test_mean_position_mm": float(np.linalg.norm(res[:, :3], axis=1).mean() * 1e3),
            "test_mean_orientation_mrad": float(np.linalg.norm(res[:, 3:], axis=1).mean() * 1e3)}


def main():
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--train", type=int, default=11000)
    ap.add_argument("--reference", action="store_true", help="also train with the full-Jacobian LM")
    ap.add_argument("--cv-grid", action="store_true", help="time the full 5-fold CV grid")
    args = ap.parse_args()
    torch.set_num_threads(2)
    robot, q, dz_geo, dz_nom, n = data(args.train)
    out = {"train_poses": n, "threads": torch.get_num_threads()}
    print(f"training poses {n}; residual after geometric calibration (test) "
          f"{np.linalg.norm(dz_geo[n:, :3], axis=1).mean() * 1e3:.3f} mm mean")
    r = train(robot, q, dz_geo, n, "cg")
    out["matrix_free"] = r
    print(f"(64, 32) matrix-free BR-LM: {r['wall_s']:.1f} s, {r['epochs']} epochs ({r['stop']}), "
          f"normalised MSE {r['mse_normalised']:.5f}, γ {r['gamma']:.0f}/{r['n_weights']}, "
          f"test {r['test_mean_position_mm']:.4f} mm / {r['test_mean_orientation_mrad']:.4f} mrad", flush=True)
    if args.reference:
        f = train(robot, q, dz_geo, n, "full")
        out["full_jacobian"] = f
        out["loss_ratio"] = r["mse_normalised"] / f["mse_normalised"]
        print(f"(64, 32) full-Jacobian BR-LM: {f['wall_s']:.1f} s, {f['epochs']} epochs ({f['stop']}), "
              f"normalised MSE {f['mse_normalised']:.5f}; ratio matrix-free / full {out['loss_ratio']:.3f}", flush=True)
    if args.cv_grid:
        sizes = ((16, 16), (32, 16), (32, 32), (64, 32), (128, 64))
        grid = {}
        t0 = time.perf_counter()
        for name, dz in (("nominal", dz_nom), ("geometric", dz_geo)):
            t1 = time.perf_counter()
            cv = cross_validate(q[:n], dz[:n], sizes=sizes, folds=5, q_lower=robot.q_lower, q_upper=robot.q_upper)
            grid[name] = {"wall_s": time.perf_counter() - t1, "cv": cv}
            print(f"CV grid, prior {name}: {grid[name]['wall_s']:.0f} s; best {cv['best']}", flush=True)
        out["cv_grid"] = {"wall_s": time.perf_counter() - t0, "grids": grid}
    out["load_average"] = os.getloadavg()
    path = Path(__file__).parent / "results" / "ann.json"
    path.write_text(json.dumps(out, indent=2))


if __name__ == "__main__":
    main()
