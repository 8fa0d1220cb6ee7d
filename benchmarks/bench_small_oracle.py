"""What any prior could gain on `campaign synth` data (issue 24): the MAP with the prior the hidden
errors are drawn from (an oracle, unavailable to `calibrate`) against least squares.

    OPENBLAS_NUM_THREADS=1 python benchmarks/bench_small_oracle.py [--seeds 10] [--poses 40]
        [--robots ur10,panda,comau] [--kinds point,pose]

Default: the UR10 with one reflector at the tool point (``--robots ur10 --kinds point``); with
several robots and kinds, every cell and the mean over the cells (the issue's "on average"),
position-only (point) and 6-D (pose) data. Data carried into the robot's frame by the true tracker pose (so the truth is exactly the
generator's: base parameters of Table 4's magnitudes, each with a random sign and a factor in
[0.5, 1.5], i.e. a prior σ of |Table 4| · √(13/12)), 80/20 split. The oracle MAP is the Gauss-Newton
step from the least-squares fit with that prior (the problem is linear at this scale). Reports the
held-out mean position error of both over the noise floor (the tracker's noise alone at the test
poses, from the truth, as in bench_small.py). Writes
benchmarks/results/small_oracle.json (one cell) or small_oracle_cells.json (several).
"""

import argparse
import json
from importlib import metadata
from pathlib import Path

import numpy as np

from campaign.identify.solver import CalibrationModel
from campaign.sim.truth import TABLE4_BASE, make_truth, random_joint_poses, synthesize_kind
from campaign.measure.reflectors import invert, transform_points
from campaign.model.robot import RobotModel

ERD = "cmeel.prefix/share/example-robot-data/robots"
ROBOTS = {"ur10": ("ur_description/urdf/ur10_robot.urdf", "tool0"),
          "panda": ("panda_description/urdf/panda.urdf", "panda_hand"), "comau": (None, None)}
NOISE_M = 10e-6


def load(which):
    rel, tool = ROBOTS[which]
    if rel is None:
        return RobotModel.load()
    return RobotModel.load(str(metadata.distribution("example-robot-data").locate_file(f"{ERD}/{rel}")), tool_frame=tool)


def cell(robot, kind, n, seeds):
    """Least squares and the oracle MAP over ``seeds`` campaigns of ``n`` poses: per-seed rows.

    The data are `campaign synth --frame tracker`'s, carried into the robot's frame by the true
    tracker pose (the oracle knows it), so the truth is exactly the generator's base parameters; the
    floor is the tracker's noise alone at the test poses (as bench_small.py's), from the truth."""
    point = kind == "point"
    rows = []
    for seed in range(seeds):
        truth = make_truth(robot, seed=seed, position_only=point)
        q = random_joint_poses(robot, n, seed=seed + 1)
        poses = synthesize_kind(truth, q, kind=kind, frame="tracker", seed=seed + 2)
        T_IL = invert(truth.T_LI)
        T_meas = np.broadcast_to(np.eye(4), (n, 4, 4)).copy()
        T_meas[:, :3, 3] = transform_points(T_IL, poses.xyz[:, None, :])[:, 0]
        if not point:
            T_meas = T_IL @ poses.T_IE
        T_true = truth.pose(q)
        P_true = T_true[:, :3, 3]
        if point and len(robot.reflectors) == 1:
            P_true = transform_points(T_true, np.broadcast_to(robot.reflector_positions_in_E, (n, 1, 3)))[:, 0]
        te = np.arange(n) >= n - max(1, round(0.2 * n))
        tr = ~te
        floor = float(np.mean(np.linalg.norm(T_meas[te, :3, 3] - P_true[te], axis=1)))
        k = 3 if point else 6
        lsq = CalibrationModel(robot=robot, position_only=point).fit(q[tr], T_meas[tr])
        sig = lsq.row_sigma_
        J = lsq.jacobian(q[tr], T_meas[tr])[:, :k] / sig[None, :, None]
        e = lsq.residuals(q[tr], T_meas[tr])[:, :k] / sig
        J_te = lsq.jacobian(q[te], T_meas[te])[:, :3]
        e_te = lsq.residuals(q[te], T_meas[te])[:, :3]
        r = lsq.base_.n_base
        P = np.diag(1.0 / (np.abs(np.resize(TABLE4_BASE, r)) ** 2 * 13 / 12))
        J2 = J.reshape(-1, r)
        dx = -np.linalg.solve(J2.T @ J2 + P, J2.T @ e.ravel() + P @ lsq.base_params_)
        rows.append({"seed": seed, "floor_mm": 1e3 * floor,
                     "lsq_over_floor": float(np.mean(np.linalg.norm(e_te, axis=1)) / floor),
                     "oracle_map_over_floor": float(np.mean(np.linalg.norm(e_te + J_te @ dx, axis=1)) / floor)})
    return rows


def main():
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--seeds", type=int, default=10)
    ap.add_argument("--poses", type=int, default=40)
    ap.add_argument("--robots", default="ur10", help="comma-separated: ur10, panda, comau")
    ap.add_argument("--kinds", default="point", help="comma-separated: point, pose")
    args = ap.parse_args()
    robots, kinds = args.robots.split(","), args.kinds.split(",")
    n, cells = args.poses, []
    for which in robots:
        robot = load(which)
        for kind in kinds:
            rows = cell(robot, kind, n, args.seeds)
            cells.append({"robot": robot.name, "poses": n, "kind": kind, "frame": "robot",
                          "lsq_over_floor_mean": float(np.mean([r["lsq_over_floor"] for r in rows])),
                          "oracle_map_over_floor_mean": float(np.mean([r["oracle_map_over_floor"] for r in rows])),
                          "cases": rows})
            c = cells[-1]
            print(f"{robot.name} {kind}, {n} poses, {args.seeds} seeds: least squares {c['lsq_over_floor_mean']:.4f}x "
                  f"the floor, oracle MAP {c['oracle_map_over_floor_mean']:.4f}x")
    if len(cells) == 1:
        out = {"description": __doc__.splitlines()[0], **cells[0]}
        path = Path(__file__).parent / "results" / "small_oracle.json"
    else:
        out = {"description": __doc__.splitlines()[0], "poses": n, "seeds": args.seeds,
               "lsq_over_floor_mean_of_cells": float(np.mean([c["lsq_over_floor_mean"] for c in cells])),
               "oracle_map_over_floor_mean_of_cells": float(np.mean([c["oracle_map_over_floor_mean"] for c in cells])),
               "cells": cells}
        path = Path(__file__).parent / "results" / "small_oracle_cells.json"
        print(f"mean of the cells: least squares {out['lsq_over_floor_mean_of_cells']:.4f}x, oracle MAP "
              f"{out['oracle_map_over_floor_mean_of_cells']:.4f}x")
    path.write_text(json.dumps(out, indent=2))
    print(f"written {path}")


if __name__ == "__main__":
    main()
