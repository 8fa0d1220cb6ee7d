"""Benchmark of the geometric identification (issue 2).

    python benchmarks/bench_identify.py [--poses 14000] [--robot NAME|URDF|robot.yaml [--tool-frame LINK]]
    python benchmarks/bench_identify.py --robot panda   # the 7R case: example-robot-data's Panda
    python benchmarks/bench_identify.py --markers [--miss-rate 0.05]  # raw three-reflector rows
    (on a shared machine: OPENBLAS_NUM_THREADS=1, else BLAS threads fight over the cores)

Simulates a campaign with Table-4-sized geometric errors and 10 µm tracker noise,
identifies the 30 base parameters on the 80 % training split and reports wall time,
iterations, the worst |error| / σ of the recovered base parameters and the held-out
mean position error against the noise-only floor. Writes benchmarks/results/identify.json (the
default COMAU) or identify_<robot>.json. ``--robot panda`` loads the Panda (7 revolute joints,
tool panda_hand) of the test-only package example-robot-data. ``--markers``: the same poses as
raw reflector rows (the default triad, each reflector missed with ``--miss-rate``), identified
from the reflectors' positions as `calibrate` does for raw data; writes identify_markers.json.
"""

from __future__ import annotations

import argparse
import json
import os
import resource
import time
from pathlib import Path

import numpy as np

from campaign.identify.solver import CalibrationModel
from campaign.identify.split import train_test_split
from campaign.model.base_params import base_parameters
from campaign.model.kinematics import forward, pose_error
from campaign.model.robot import RobotModel
from campaign.sim.truth import make_truth, random_joint_poses, synthesize


def main():
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--poses", type=int, default=14000)
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--robot", default=None, help="robot (default: the COMAU); 'panda': the 7R case")
    ap.add_argument("--tool-frame", default=None)
    ap.add_argument("--markers", action="store_true", help="raw three-reflector rows, fitted at the reflectors")
    ap.add_argument("--miss-rate", type=float, default=0.0, help="with --markers: probability of a missed reflector")
    args = ap.parse_args()
    spec = args.robot
    if spec == "panda":
        from importlib import metadata

        spec = metadata.distribution("example-robot-data").locate_file(
            "cmeel.prefix/share/example-robot-data/robots/panda_description/urdf/panda.urdf")
    robot = RobotModel.load(spec, tool_frame=args.tool_frame) if spec else RobotModel.load()
    base = base_parameters(robot)  # cached analysis, as in calibrate
    truth = make_truth(robot, seed=args.seed)
    q = random_joint_poses(robot, args.poses, seed=args.seed + 1)
    meas = synthesize(truth, q, seed=args.seed + 2)
    is_test = train_test_split(meas.pose_id)
    tr, te = ~is_test, is_test

    if args.markers:  # the same poses as raw reflector rows in the set-up frame (the tracker's noise)
        from campaign.measure.reflectors import transform_points
        from campaign.sim.truth import tool_points

        P_E = tool_points(robot)
        rng = np.random.default_rng(args.seed + 3)
        T_true = truth.pose_in_measured_frame(meas.q, meas.T_LI)
        markers = transform_points(T_true, np.broadcast_to(P_E, (len(q),) + P_E.shape))
        markers = markers + rng.normal(0.0, 10e-6, size=markers.shape)
        markers[rng.uniform(size=markers.shape[:2]) < args.miss_rate] = np.nan
        base = base_parameters(robot, position_only=True, points=P_E)
        t0 = time.perf_counter()
        model = CalibrationModel(robot=robot, points=P_E).fit(meas.q[tr], markers[tr], base=base)
        t_fit = time.perf_counter() - t0
    else:
        t0 = time.perf_counter()
        model = CalibrationModel(robot=robot).fit(meas.q[tr], meas.T_IE[tr], base=base)
        t_fit = time.perf_counter() - t0
    t0 = time.perf_counter()
    base_parameters(robot)
    t_base = time.perf_counter() - t0

    expected = truth.expected_base_params(meas.T_LI)
    z = np.abs(model.base_params_ - expected) / model.base_sigma_
    dz = model.residuals(meas.q[te], meas.T_IE[te])
    floor = pose_error(truth.pose_in_measured_frame(meas.q[te], meas.T_LI), meas.T_IE[te])
    nominal = pose_error(forward(robot, meas.q[te]), meas.T_IE[te])
    mean = lambda d: float(np.linalg.norm(d[:, :3], axis=1).mean() * 1e3)
    res = {
        "robot": robot.name, "n_joints": robot.n_joints, "n_params": robot.n_params, "n_base": base.n_base,
        "poses": args.poses, "data": "raw reflectors" if args.markers else "6-D poses",
        "miss_rate": args.miss_rate if args.markers else None, "train_poses": int(tr.sum()), "test_poses": int(te.sum()),
        "identification_time_s": t_fit, "base_parameter_analysis_time_s": t_base,
        "iterations": model.n_iter_, "max_abs_error_over_sigma": float(z.max()),
        "heldout_mean_position_mm": {"nominal": mean(nominal), "geometric": mean(dz), "noise_floor": mean(floor)},
        "ratio_to_floor": mean(dz) / mean(floor),
        "peak_rss_mb": resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024,
        "load_average": os.getloadavg(),
        # on a shared 2-core machine a multi-threaded BLAS is many times slower (14 s vs 1 s measured)
        "openblas_num_threads": os.environ.get("OPENBLAS_NUM_THREADS"),
    }
    print(f"poses {args.poses} (train {res['train_poses']}, test {res['test_poses']})")
    print(f"identification {t_fit:.2f} s in {model.n_iter_} iterations (+ base-parameter analysis {t_base:.2f} s)")
    print(f"{robot.name}: {robot.n_joints} joints, {robot.n_params} error parameters")
    print(f"max |recovered - truth| / sigma over {base.n_base} base parameters: {z.max():.2f}")
    h = res["heldout_mean_position_mm"]
    print(f"held-out mean position error: nominal {h['nominal']:.3f} mm -> geometric {h['geometric']:.4f} mm "
          f"(noise floor {h['noise_floor']:.4f} mm, ratio {res['ratio_to_floor']:.3f})")
    print(f"peak RSS {res['peak_rss_mb']:.0f} MB; load average {res['load_average'][0]:.2f}")
    name = "identify" if args.robot is None else f"identify_{Path(str(args.robot)).stem}"
    out = Path(__file__).parent / "results" / (name + ("_markers" if args.markers else "") + ".json")
    out.write_text(json.dumps(res, indent=2))


if __name__ == "__main__":
    main()
