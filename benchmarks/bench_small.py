"""Benchmark of small campaigns (issue 24): least squares against the model `calibrate --model
auto` chooses, on generated data as `campaign synth` makes it (hidden geometric errors of
Table 4's size, 10 µm tracker noise, data in the frame of a tracker at an unknown pose).

    OPENBLAS_NUM_THREADS=1 python benchmarks/bench_small.py [--seeds 5] [--poses 20,40,60,120]
        [--robots ur10,panda,comau] [--kinds point,pose,markers] [--large 1000]

For each robot, measurement kind, pose count and seed: the 80/20 split `calibrate` makes
(campaign.identify.split.campaign_split), the tracker registration (prepare_measured), then
least squares and ``fit_model(model="auto")`` on the training poses; their held-out mean position
error (tool point; raw reflectors: each reflector) over the test poses and over the noise floor
(the mean norm of the tracker's noise alone at the same test poses, from the truth, read after
the fits), and over 500 fresh poses of the same campaign's distribution (the truth's, measured
after the fits: the 4-24 test poses of a campaign scatter by more than the models differ). ``--large N``: one seed at N poses per robot and kind, where auto must equal least
squares and MAP (strength 1) must agree with it within 0.5 %. Writes benchmarks/results/small.json.
"""

from __future__ import annotations

import argparse
import json
import os
import time
from dataclasses import replace
from importlib import metadata
from pathlib import Path

import numpy as np

from campaign.identify.calibrate import prepare_measured
from campaign.identify.model_choice import expected_heldout_mm, fit_model
from campaign.identify.solver import CalibrationModel
from campaign.identify.split import campaign_split
from campaign.measure.reflectors import invert, transform_points
from campaign.model.robot import RobotModel
from campaign.sim.truth import random_joint_poses, random_tracker_pose, synthesize_kind, synthetic_campaign

ERD = "cmeel.prefix/share/example-robot-data/robots"
ROBOTS = {"ur10": ("ur_description/urdf/ur10_robot.urdf", "tool0"),
          "panda": ("panda_description/urdf/panda.urdf", "panda_hand"), "comau": (None, None)}


def load(which):
    rel, tool = ROBOTS[which]
    if rel is None:
        return RobotModel.load()
    return RobotModel.load(str(metadata.distribution("example-robot-data").locate_file(f"{ERD}/{rel}")), tool_frame=tool)


FRESH_POSES = 500


def joint_poses(robot, n, seed, narrow_rad=None):
    """n random joint vectors; ``narrow_rad``: within ± that of the middle of their range."""
    if narrow_rad is None:
        return random_joint_poses(robot, n, seed=seed)
    mid = 0.5 * (robot.q_lower + robot.q_upper)
    return mid + np.random.default_rng(seed).uniform(-narrow_rad, narrow_rad, size=(n, robot.n_joints))


def campaign_case(robot, kind, n, seed, narrow_rad=None):
    """What `campaign synth --kind KIND --frame tracker --poses n --seed seed` writes: (measured, truth);
    ``narrow_rad``: the joints instead within ± that of the middle of their range (a poorly excited
    campaign, as a cramped cell allows)."""
    _, truth = synthetic_campaign(robot, 1, seed=seed, position_only=kind == "point")
    truth = replace(truth, T_LI=random_tracker_pose(seed))
    q = joint_poses(robot, n, seed + 1, narrow_rad)
    return synthesize_kind(truth, q, kind=kind, frame="tracker", seed=seed + 2), truth


def fresh_poses(truth, kind, seed, narrow_rad, tracker):
    """FRESH_POSES more measurements of the campaign's distribution, brought into the robot's frame
    by the campaign's own tracker registration (``tracker``: prepare_measured's record)."""
    robot = truth.robot
    fresh = synthesize_kind(truth, joint_poses(robot, FRESH_POSES, seed + 1000, narrow_rad), kind=kind,
                            frame="tracker", seed=seed + 1001)
    L2I = invert(np.array(tracker["T_L_I_registration"]))
    T = L2I @ fresh.T_IE
    if not fresh.has_orientation:
        T[:, :3, :3] = np.eye(3)
    markers = None if fresh.markers is None else transform_points(L2I, fresh.markers)
    return replace(fresh, T_IE=T, markers=markers)


def run_case(robot, kind, n, seed, models=("lsq", "auto"), narrow_rad=None):
    poses, truth = campaign_case(robot, kind, n, seed, narrow_rad)
    te = campaign_split(poses.pose_id)
    tr = ~te
    data, rob, tracker = prepare_measured(robot, poses, tr)
    raw = kind == "markers"
    Y = data.markers if raw else data.T_IE
    pts = data.marker_positions if raw else None
    fresh = fresh_poses(truth, kind, seed, narrow_rad, tracker)

    def make(**kw):
        return CalibrationModel(robot=rob, position_only=kind != "pose", points=pts, **kw)

    def heldout_mm(m, d=data, rows=te):
        if raw:
            return 1e3 * float(np.nanmean(np.linalg.norm(m.point_residuals(d.q[rows], d.markers[rows]), axis=2)))
        return 1e3 * float(np.mean(np.linalg.norm(m.residuals(d.q[rows], d.T_IE[rows])[:, :3], axis=1)))

    out = {"robot": robot.name, "kind": kind, "poses": n, "seed": seed, "train_poses": int(tr.sum()),
           "test_poses": int(te.sum())}
    for name in models:
        t0 = time.perf_counter()
        if name == "lsq":
            m, choice = make().fit(data.q[tr], Y[tr]), None
        elif name == "map1":
            m, choice = make(prior="tolerances").fit(data.q[tr], Y[tr]), None
        else:
            m, choice = fit_model(make, data.q[tr], Y[tr], model=name)
        t_fit = time.perf_counter() - t0
        out[name] = {"heldout_mean_position_mm": heldout_mm(m), "time_s": t_fit,
                     "fresh_mean_position_mm": heldout_mm(m, fresh, slice(None)),
                     "expected_heldout_mean_position_mm": expected_heldout_mm(m, data.q[te])}
        if choice is not None:
            out[name]["choice"] = choice.choice
            out[name]["strength"] = choice.strength
    # the floor, only now from the truth: the tracker's noise alone at the test poses (in its frame L)
    T_true_L = truth.T_LI @ truth.pose(poses.q[te])
    if raw:
        P_true = transform_points(T_true_L, np.broadcast_to(poses.marker_positions, poses.markers[te].shape))
        floor = np.nanmean(np.linalg.norm(poses.markers[te] - P_true, axis=2))
    else:
        P_true = T_true_L[:, :3, 3]
        if kind == "point" and len(robot.reflectors) == 1:
            P_true = transform_points(T_true_L, np.broadcast_to(robot.reflector_positions_in_E, (int(te.sum()), 1, 3)))[:, 0]
        floor = np.mean(np.linalg.norm(poses.xyz[te] - P_true, axis=1))
    out["floor_mm"] = 1e3 * float(floor)
    return out


def summarise(cases, models):
    """Per robot, kind and pose count: the means over seeds and the worst auto / lsq ratio."""
    groups = {}
    for c in cases:
        groups.setdefault((c["robot"], c["kind"], c["poses"]), []).append(c)
    rows = []
    for (robot, kind, n), cs in groups.items():
        row = {"robot": robot, "kind": kind, "poses": n, "seeds": len(cs),
               "floor_mm": float(np.mean([c["floor_mm"] for c in cs]))}
        for name in models:
            row[f"{name}_mean_mm"] = float(np.mean([c[name]["heldout_mean_position_mm"] for c in cs]))
            row[f"{name}_over_floor"] = float(np.mean([c[name]["heldout_mean_position_mm"] / c["floor_mm"] for c in cs]))
        if "auto" in models and "lsq" in models:
            ratios = [c["auto"]["heldout_mean_position_mm"] / c["lsq"]["heldout_mean_position_mm"] for c in cs]
            row["auto_over_lsq_mean"] = float(np.mean(ratios))
            row["auto_over_lsq_worst"] = float(np.max(ratios))
            fresh = [c["auto"]["fresh_mean_position_mm"] / c["lsq"]["fresh_mean_position_mm"] for c in cs]
            row["fresh_auto_over_lsq_mean"] = float(np.mean(fresh))
            row["fresh_auto_over_lsq_worst"] = float(np.max(fresh))
            row["choices"] = [c["auto"].get("choice") for c in cs]
        rows.append(row)
    return rows


def main():
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--seeds", type=int, default=5)
    ap.add_argument("--poses", default="20,40,60,120")
    ap.add_argument("--robots", default="ur10,panda,comau")
    ap.add_argument("--kinds", default="point,pose,markers")
    ap.add_argument("--large", type=int, default=1000, help="pose count of the large-campaign check (0: none)")
    ap.add_argument("--narrow", type=float, default=0.15,
                    help="also: point and pose campaigns of 20 and 40 poses with the joints within ± this (rad) of "
                         "mid-range, where few directions are well excited (0: none)")
    ap.add_argument("--out", default=str(Path(__file__).parent / "results" / "small.json"))
    args = ap.parse_args()
    robots = {w: load(w) for w in args.robots.split(",")}
    kinds = args.kinds.split(",")
    counts = [int(v) for v in args.poses.split(",")]
    cases, large = [], []
    t0 = time.perf_counter()
    for w, robot in robots.items():
        for kind in kinds:
            for n in counts:
                for seed in range(args.seeds):
                    cases.append(run_case(robot, kind, n, seed))
                c = cases[-args.seeds:]
                print(f"{w:6s} {kind:8s} {n:4d}: lsq {np.mean([x['lsq']['heldout_mean_position_mm'] / x['floor_mm'] for x in c]):.3f}x "
                      f"auto {np.mean([x['auto']['heldout_mean_position_mm'] / x['floor_mm'] for x in c]):.3f}x the floor, "
                      f"choices {[x['auto']['choice'] for x in c]} ({time.perf_counter() - t0:.0f} s)", flush=True)
            if args.large:
                c = run_case(robot, kind, args.large, 0, models=("lsq", "auto", "map1"))
                large.append(c)
                print(f"{w:6s} {kind:8s} {args.large}: lsq {c['lsq']['heldout_mean_position_mm']:.5f} mm, auto "
                      f"{c['auto']['heldout_mean_position_mm']:.5f} mm ({c['auto']['choice']}), map(1) "
                      f"{c['map1']['heldout_mean_position_mm']:.5f} mm", flush=True)
    narrow = []
    if args.narrow:
        for w, robot in robots.items():
            for kind in ("point", "pose"):
                for n in (20, 40):
                    c = [run_case(robot, kind, n, seed, narrow_rad=args.narrow) for seed in range(args.seeds)]
                    narrow += c
                    print(f"{w:6s} {kind:8s} {n:4d} within ±{args.narrow} rad: lsq "
                          f"{np.mean([x['lsq']['heldout_mean_position_mm'] / x['floor_mm'] for x in c]):.3f}x auto "
                          f"{np.mean([x['auto']['heldout_mean_position_mm'] / x['floor_mm'] for x in c]):.3f}x the "
                          f"floor, choices {[x['auto']['choice'] for x in c]}; on {FRESH_POSES} fresh poses auto/lsq "
                          f"worst {max(x['auto']['fresh_mean_position_mm'] / x['lsq']['fresh_mean_position_mm'] for x in c):.4f}",
                          flush=True)
    summary = summarise(cases, ("lsq", "auto"))
    at40 = [r for r in summary if r["poses"] == 40]
    result = {
        "description": __doc__.splitlines()[0],
        "summary": summary,
        "large": [{**c, "auto_over_lsq": c["auto"]["heldout_mean_position_mm"] / c["lsq"]["heldout_mean_position_mm"],
                   "map1_over_lsq": c["map1"]["heldout_mean_position_mm"] / c["lsq"]["heldout_mean_position_mm"]}
                  for c in large],
        "worst_auto_over_lsq": max(r["auto_over_lsq_worst"] for r in summary),
        "worst_cell_mean_auto_over_lsq": max(r["auto_over_lsq_mean"] for r in summary),
        "fresh_poses": FRESH_POSES,
        "fresh_worst_auto_over_lsq": max(r["fresh_auto_over_lsq_worst"] for r in summary),
        "at_40_poses_auto_over_floor_mean": float(np.mean([r["auto_over_floor"] for r in at40])) if at40 else None,
        "at_40_poses_lsq_over_floor_mean": float(np.mean([r["lsq_over_floor"] for r in at40])) if at40 else None,
        "narrow_rad": args.narrow or None,
        "narrow_summary": summarise(narrow, ("lsq", "auto")) if narrow else [],
        "narrow_fresh_worst_auto_over_lsq": max((r["fresh_auto_over_lsq_worst"] for r in summarise(narrow, ("lsq", "auto"))),
                                                default=None),
        "narrow_cases": narrow,
        "cases": cases,
        "wall_time_s": time.perf_counter() - t0,
        "load_average": list(os.getloadavg()),
        "openblas_num_threads": os.environ.get("OPENBLAS_NUM_THREADS"),
    }
    Path(args.out).write_text(json.dumps(result, indent=2))
    print(f"worst auto/lsq {result['worst_auto_over_lsq']:.4f}; at 40 poses auto {result['at_40_poses_auto_over_floor_mean']}"
          f"x, lsq {result['at_40_poses_lsq_over_floor_mean']}x the floor; written {args.out}")


if __name__ == "__main__":
    main()
