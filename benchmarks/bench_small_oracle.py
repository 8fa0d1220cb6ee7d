"""What any prior could gain on `campaign synth` data (issue 24): the MAP with the prior the hidden
errors are drawn from (an oracle, unavailable to `calibrate`) against least squares.

    OPENBLAS_NUM_THREADS=1 python benchmarks/bench_small_oracle.py [--seeds 10] [--poses 40]

UR10 with one reflector at the tool point, data in the robot's frame (so the truth is exactly the
generator's: base parameters of Table 4's magnitudes, each with a random sign and a factor in
[0.5, 1.5], i.e. a prior σ of |Table 4| · √(13/12)), 80/20 split. The oracle MAP is the Gauss-Newton
step from the least-squares fit with that prior (the problem is linear at this scale). Reports the
held-out mean position error of both over the noise floor σ√(8/π). Writes
benchmarks/results/small_oracle.json.
"""

import argparse
import json
from importlib import metadata
from pathlib import Path

import numpy as np

from campaign.identify.solver import CalibrationModel
from campaign.sim.truth import TABLE4_BASE, make_truth, random_joint_poses, synthesize_kind
from campaign.model.robot import RobotModel

ERD = "cmeel.prefix/share/example-robot-data/robots/ur_description/urdf/ur10_robot.urdf"
NOISE_M = 10e-6


def main():
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--seeds", type=int, default=10)
    ap.add_argument("--poses", type=int, default=40)
    args = ap.parse_args()
    robot = RobotModel.load(str(metadata.distribution("example-robot-data").locate_file(ERD)), tool_frame="tool0")
    floor = NOISE_M * np.sqrt(8 / np.pi)
    n, rows = args.poses, []
    for seed in range(args.seeds):
        truth = make_truth(robot, seed=seed, position_only=True)
        q = random_joint_poses(robot, n, seed=seed + 1)
        poses = synthesize_kind(truth, q, kind="point", frame="robot", seed=seed + 2)
        te = np.arange(n) >= n - max(1, round(0.2 * n))
        tr = ~te
        lsq = CalibrationModel(robot=robot, position_only=True).fit(poses.q[tr], poses.T_IE[tr])
        sig = lsq.row_sigma_
        J = lsq.jacobian(poses.q[tr], poses.T_IE[tr])[:, :3] / sig[None, :, None]
        e = lsq.residuals(poses.q[tr], poses.T_IE[tr])[:, :3] / sig
        J_te = lsq.jacobian(poses.q[te], poses.T_IE[te])[:, :3]
        e_te = lsq.residuals(poses.q[te], poses.T_IE[te])[:, :3]
        r = lsq.base_.n_base
        P = np.diag(1.0 / (np.abs(np.resize(TABLE4_BASE, r)) ** 2 * 13 / 12))
        J2 = J.reshape(-1, r)
        dx = -np.linalg.solve(J2.T @ J2 + P, J2.T @ e.ravel() + P @ lsq.base_params_)
        rows.append({"seed": seed, "lsq_over_floor": float(np.mean(np.linalg.norm(e_te, axis=1)) / floor),
                     "oracle_map_over_floor": float(np.mean(np.linalg.norm(e_te + J_te @ dx, axis=1)) / floor)})
    out = {"description": __doc__.splitlines()[0], "robot": robot.name, "poses": n, "kind": "point", "frame": "robot",
           "lsq_over_floor_mean": float(np.mean([r["lsq_over_floor"] for r in rows])),
           "oracle_map_over_floor_mean": float(np.mean([r["oracle_map_over_floor"] for r in rows])), "cases": rows}
    path = Path(__file__).parent / "results" / "small_oracle.json"
    path.write_text(json.dumps(out, indent=2))
    print(f"{n} poses, {args.seeds} seeds: least squares {out['lsq_over_floor_mean']:.4f}x the floor, oracle MAP "
          f"{out['oracle_map_over_floor_mean']:.4f}x; written {path}")


if __name__ == "__main__":
    main()
