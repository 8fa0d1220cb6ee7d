"""Benchmark of the calibrated domain and the uncertainty (issue 30), against the simulator's truth.

    python benchmarks/bench_domain.py [--sizes 20,60,300,1000] [--seeds 2] [--robots comau,ur10,panda]
                                      [--kinds pose,point,markers]
    python benchmarks/bench_domain.py --cost [--poses 14000] [--rounds 3] --before DIR
    (on a shared machine: OPENBLAS_NUM_THREADS=1)

Each campaign is generated from a seeded truth (Table-4-sized geometric errors, the simulated tracker's
10 µm noise, data in the robot's frame), written as a measured-pose CSV, imported and calibrated by
the commands (`import`, `calibrate --no-ann`); only after `calibrate` answered are the truth and
fresh poses used:

* in distribution (every joint spread over its range): on 500 fresh poses of the same spread, the
  ratio of the mean `sigma_mm` to the mean true model error (‖model − truth‖ at the tool point,
  noise-free; target 0.5-2), the share of true errors inside 2σ, and the share of the fresh poses
  flagged outside the domain (target at most 5 %);
* a model that lacks an effect of the truth (a typical ground compliance, COMAU, 6-D), with the
  tracker's noise stated (the noise floor: the fit's error beyond it enters sigma) and without;
* out of the domain (the COMAU and the UR10, 6-D): a campaign with joint 1 never moved (fresh poses
  at other q1), one over the lower half of joint 2's range (fresh poses beyond it) and one that never
  reached a workspace corner (joints 1 and 2 both in the upper 35 % of their ranges; fresh poses
  there): the share flagged, and the mean sigma_mm there against the true error.

``--cost``: the extra time of `calibrate --no-ann` on a 14,000-pose campaign, this tree against
``--before DIR`` (a source tree of the code before the change), alternating rounds of the two
commands as processes, wall and CPU time, with the load average.

Writes benchmarks/results/domain.json (the ``cost`` entry kept when not re-measured).
"""

from __future__ import annotations

import argparse
import json
import os
import sys
import tempfile
import time
from importlib import metadata
from pathlib import Path

import numpy as np
import yaml

from campaign.cli import main as cli
from campaign.measure.csvio import write_measured_csv
from campaign.model.robot import RobotModel
from campaign.sim.truth import make_truth, random_joint_poses, synthesize_kind, tool_points

ERD = "cmeel.prefix/share/example-robot-data/robots"
ROBOTS = {"comau": (None, None), "ur10": ("ur_description/urdf/ur10_robot.urdf", "tool0"),
          "panda": ("panda_description/urdf/panda.urdf", "panda_hand")}
FRESH = 500


def robot_args(which) -> list:
    rel, tool = ROBOTS[which]
    if rel is None:
        return []
    return ["--robot", str(metadata.distribution("example-robot-data").locate_file(f"{ERD}/{rel}")),
            "--tool-frame", tool]


def load(which) -> RobotModel:
    args = robot_args(which)
    return RobotModel.load() if not args else RobotModel.load(args[1], tool_frame=args[3])


def calibrated_case(tmp: Path, which, robot, kind, q, seed, hidden=None, stated_noise=False):
    """Generate, import and calibrate one campaign at joint vectors q; returns (CalibratedRobot,
    truth, T_LI measured, P_E the measured point or None, metrics). hidden: {effect: parameters} in
    the truth, not in the model; stated_noise: the tracker's noise stated in campaign.yaml (as from its
    data sheet: `tracker: {noise_m: ...}`), the noise floor of the calibration."""
    from campaign.identify.use import CalibratedRobot

    truth = make_truth(robot, seed=seed, position_only=kind == "point", effects=hidden)
    poses = synthesize_kind(truth, q, kind=kind, frame="robot", seed=seed + 2)
    csv = tmp / "m.csv"
    write_measured_csv(csv, poses, robot)
    extra = []
    if kind == "markers":
        (tmp / "markers.yaml").write_text(yaml.safe_dump({"markers": tool_points(robot).tolist()}))
        extra = ["--markers", str(tmp / "markers.yaml")]
    run = tmp / "run"
    if cli(["import", str(csv), "--run", str(run), "--quiet", *robot_args(which), *extra]) != 0:
        raise SystemExit(f"import failed: {which} {kind} {len(q)}")
    if stated_noise:
        cfg = yaml.safe_load((run / "campaign.yaml").read_text())
        cfg["tracker"] = {**(cfg.get("tracker") or {}), "noise_m": float(truth.noise_m)}
        (run / "campaign.yaml").write_text(yaml.safe_dump(cfg))
    if cli(["calibrate", str(run), "--no-ann", "--quiet", "--no-report"]) != 0:
        raise SystemExit(f"calibrate failed: {which} {kind} {len(q)}")
    metrics = json.loads((run / "calibration" / "metrics.json").read_text())
    # the pipeline has answered: from here on the truth may be read
    P_E = None
    if kind == "point":
        P_E = robot.reflector_positions_in_E[0] if len(robot.reflectors) == 1 else np.zeros(3)
    return CalibratedRobot(run), truth, poses.T_LI, P_E, metrics


def true_error_mm(cal, truth, T_LI, P_E, q) -> np.ndarray:
    """‖model − truth‖ (mm) at the point the model predicts (the tool point, or the measured one)."""
    T_true = truth.pose_in_measured_frame(q, T_LI)
    p_true = T_true[:, :3, 3] if P_E is None else (T_true[:, :3, :3] @ P_E) + T_true[:, :3, 3]
    return 1e3 * np.linalg.norm(cal.predict(q)[:, :3, 3] - p_true, axis=1)


def in_distribution(which, kind, n, seed) -> dict:
    robot = load(which)
    q = random_joint_poses(robot, n, seed=seed + 1)
    with tempfile.TemporaryDirectory(prefix="bench-domain-") as tmp:
        t0 = time.perf_counter()
        cal, truth, T_LI, P_E, metrics = calibrated_case(Path(tmp), which, robot, kind, q, seed)
        t_cal = time.perf_counter() - t0
        fresh = random_joint_poses(robot, FRESH, seed=seed + 1000)
        sigma = cal.sigma_mm(fresh)
        err = true_error_mm(cal, truth, T_LI, P_E, fresh)
        inside = cal.in_domain(fresh)
    test = metrics["stages"][metrics["order"][-1]]["test"]["position_mm"]["mean"]
    return {"robot": which, "kind": kind, "poses": n, "seed": seed, "calibrate_s": t_cal,
            "mean_sigma_mm": float(sigma.mean()), "mean_true_error_mm": float(err.mean()),
            "ratio": float(sigma.mean() / err.mean()), "inside_2sigma": float(np.mean(err < 2 * sigma)),
            "fresh_flagged": float(np.mean(~inside)), "heldout_mean_mm": test,
            "unidentifiable_warnings": sum(w["code"] == "unidentifiable" for w in metrics["warnings"])}


def unmodelled(which, n, seed, stated_noise) -> dict:
    """A truth with a typical ground compliance the model lacks: sigma against the true error with and
    without a noise floor (the stated tracker noise)."""
    from campaign.effects.base import make_effect

    robot = load(which)
    hidden = {"ground_compliance": make_effect("ground_compliance", robot).typical_params(seed)}
    q = random_joint_poses(robot, n, seed=seed + 1)
    with tempfile.TemporaryDirectory(prefix="bench-domain-") as tmp:
        cal, truth, T_LI, P_E, metrics = calibrated_case(Path(tmp), which, robot, "pose", q, seed, hidden, stated_noise)
        fresh = random_joint_poses(robot, FRESH, seed=seed + 1000)
        sigma = cal.sigma_mm(fresh)
        err = true_error_mm(cal, truth, T_LI, P_E, fresh)
    u = metrics["uncertainty"]["stages"][metrics["uncertainty"]["stage"]]
    return {"robot": which, "case": "unmodelled ground_compliance", "stated_noise": stated_noise, "poses": n,
            "seed": seed, "mean_sigma_mm": float(sigma.mean()), "mean_true_error_mm": float(err.mean()),
            "ratio": float(sigma.mean() / err.mean()), "inside_2sigma": float(np.mean(err < 2 * sigma)),
            "basis": u["basis"]}


def out_of_domain(which, case, n, seed) -> dict:
    """A campaign missing part of the space and fresh poses in that part."""
    robot = load(which)
    lo, hi = robot.q_lower, robot.q_upper
    span = hi - lo
    q = random_joint_poses(robot, 4 * n, seed=seed + 1)
    fresh = random_joint_poses(robot, 4 * FRESH, seed=seed + 1000)
    if case == "joint_never_moved":
        q = q[:n]
        q[:, 0] = lo[0] + 0.3 * span[0]
        fresh = fresh[np.abs(fresh[:, 0] - q[0, 0]) > 0.05 * span[0]][:FRESH]
    elif case == "half_joint_range":
        q = q[q[:, 1] < lo[1] + 0.5 * span[1]][:n]
        fresh = fresh[fresh[:, 1] > lo[1] + 0.5 * span[1]][:FRESH]
    else:  # workspace corner: joints 1 and 2 both high
        corner = lambda Q: (Q[:, 0] > lo[0] + 0.65 * span[0]) & (Q[:, 1] > lo[1] + 0.65 * span[1])  # noqa: E731
        q = q[~corner(q)][:n]
        fresh = fresh[corner(fresh)][:FRESH]
    with tempfile.TemporaryDirectory(prefix="bench-domain-") as tmp:
        cal, truth, T_LI, P_E, metrics = calibrated_case(Path(tmp), which, robot, "pose", q, seed)
        inside_train = cal.in_domain(q)
        sigma = cal.sigma_mm(fresh)
        err = true_error_mm(cal, truth, T_LI, P_E, fresh)
        flagged = ~cal.in_domain(fresh)
    return {"robot": which, "case": case, "poses": int(len(q)), "seed": seed, "test_poses": int(len(fresh)),
            "flagged": float(flagged.mean()), "training_poses_inside": float(inside_train.mean()),
            "mean_sigma_mm": float(sigma.mean()), "mean_true_error_mm": float(err.mean()),
            "ratio": float(sigma.mean() / err.mean()), "inside_2sigma": float(np.mean(err < 2 * sigma)),
            "unidentifiable_warnings": [w["message"][:160] for w in metrics["warnings"]
                                        if w["code"] == "unidentifiable"]}


def cost(args) -> dict:
    """`calibrate --no-ann` on args.poses poses: this tree against args.before, alternating rounds."""
    import statistics

    sys.path.insert(0, str(Path(__file__).parent))
    from bench_identify import _timed

    from campaign.sim.truth import synthesize

    root = Path(__file__).resolve().parents[1]
    robot = RobotModel.load()
    meas = synthesize(make_truth(robot, seed=0), random_joint_poses(robot, args.poses, seed=1), seed=2)
    trees = {"after": root, "before": Path(args.before)}
    env = {**os.environ, "OPENBLAS_NUM_THREADS": "1"}
    times = {k: [] for k in trees}
    loads = []
    with tempfile.TemporaryDirectory(prefix="bench-domain-cost-") as tmp:
        tmp = Path(tmp)
        write_measured_csv(tmp / "m.csv", meas)
        runs = {}
        for name, tree in trees.items():
            runs[name] = tmp / f"run_{name}"
            _timed([sys.executable, "-m", "campaign.cli", "import", str(tmp / "m.csv"), "--run", str(runs[name]),
                    "--quiet"], {**env, "PYTHONPATH": str(tree)}, tmp)
        for r in range(args.rounds):
            order = list(trees) if r % 2 == 0 else list(trees)[::-1]
            for name in order:
                wall, cpu, _ = _timed([sys.executable, "-m", "campaign.cli", "calibrate", str(runs[name]), "--no-ann",
                                       "--quiet"], {**env, "PYTHONPATH": str(trees[name])}, tmp)
                times[name].append((wall, cpu))
                loads.append(os.getloadavg()[0])
                print(f"round {r + 1} {name}: wall {wall:.2f} s, cpu {cpu:.2f} s (load {loads[-1]:.2f})", flush=True)
    med = {k: {"wall_s": statistics.median(w for w, _ in v), "cpu_s": statistics.median(c for _, c in v),
               "rounds": v} for k, v in times.items()}
    return {"poses": args.poses, "rounds": args.rounds, "before": str(args.before), "times": med,
            "extra_wall": med["after"]["wall_s"] / med["before"]["wall_s"] - 1,
            "extra_cpu": med["after"]["cpu_s"] / med["before"]["cpu_s"] - 1,
            "load_average_during": [min(loads), max(loads)], "target_extra": 0.10,
            "command": "campaign calibrate RUN --no-ann --quiet (report included)"}


def unmodelled_cases() -> list:
    out = []
    for stated in (True, False):
        for n in (60, 300, 1000):
            r = unmodelled("comau", n, 0, stated)
            out.append(r)
            print(f"comau  unmodelled compliance {n:4} {'floor' if stated else 'no floor'}: sigma/true {r['ratio']:.2f} "
                  f"(sigma {r['mean_sigma_mm']:.4f}, true {r['mean_true_error_mm']:.4f} mm), inside 2σ "
                  f"{100 * r['inside_2sigma']:.0f} %", flush=True)
    return out


def _unmodelled_ratio(rows) -> dict:
    return {("floor" if r["stated_noise"] else "no_floor") + f"_{r['poses']}": r["ratio"] for r in rows}


def main():
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--sizes", default="20,60,300,1000")
    ap.add_argument("--seeds", type=int, default=2)
    ap.add_argument("--robots", default="comau,ur10,panda")
    ap.add_argument("--kinds", default="pose,point,markers")
    ap.add_argument("--cost", action="store_true", help="time calibrate --no-ann against --before")
    ap.add_argument("--poses", type=int, default=14000)
    ap.add_argument("--rounds", type=int, default=3)
    ap.add_argument("--before", default=None)
    ap.add_argument("--unmodelled-only", action="store_true", help="only the unmodelled-effect cases (entry replaced)")
    args = ap.parse_args()
    out = Path(__file__).parent / "results" / "domain.json"
    doc = json.loads(out.read_text()) if out.is_file() else {}
    if args.cost:
        if not args.before:
            raise SystemExit("--cost needs --before DIR (a source tree of the code before the change)")
        doc["cost"] = cost(args)
        c = doc["cost"]
        print(f"calibrate --no-ann on {args.poses} poses: +{100 * c['extra_wall']:.1f} % wall, "
              f"+{100 * c['extra_cpu']:.1f} % CPU (load {c['load_average_during']})")
        out.write_text(json.dumps(doc, indent=2))
        return
    if args.unmodelled_only:
        doc["unmodelled"] = unmodelled_cases()
        doc.setdefault("summary", {})["unmodelled_ratio"] = _unmodelled_ratio(doc["unmodelled"])
        out.write_text(json.dumps(doc, indent=2))
        return
    t0 = time.perf_counter()
    rows = []
    for which in args.robots.split(","):
        for kind in args.kinds.split(","):
            for n in (int(s) for s in args.sizes.split(",")):
                for seed in range(args.seeds):
                    r = in_distribution(which, kind, n, 10 * seed)
                    rows.append(r)
                    print(f"{which:6} {kind:7} {n:5} seed {seed}: sigma/true {r['ratio']:.2f} "
                          f"(sigma {r['mean_sigma_mm']:.4f}, true {r['mean_true_error_mm']:.4f} mm), "
                          f"inside 2σ {100 * r['inside_2sigma']:.0f} %, fresh flagged {100 * r['fresh_flagged']:.1f} %",
                          flush=True)
    ood = []
    for which in ("comau", "ur10"):
        for case in ("joint_never_moved", "half_joint_range", "workspace_corner"):
            for n in (60, 300):
                r = out_of_domain(which, case, n, 0)
                ood.append(r)
                print(f"{which:6} {case:18} {n:4}: flagged {100 * r['flagged']:.0f} %, sigma/true {r['ratio']:.2f} "
                      f"(sigma {r['mean_sigma_mm']:.3f}, true {r['mean_true_error_mm']:.3f} mm)", flush=True)
    unmod = unmodelled_cases()
    ratios = [r["ratio"] for r in rows]
    summary = {"ratio_min": min(ratios), "ratio_max": max(ratios),
               "ratio_by_size": {str(n): [min(r["ratio"] for r in rows if r["poses"] == n),
                                          max(r["ratio"] for r in rows if r["poses"] == n)]
                                 for n in sorted({r["poses"] for r in rows})},
               "inside_2sigma_mean": float(np.mean([r["inside_2sigma"] for r in rows])),
               "fresh_flagged_max": max(r["fresh_flagged"] for r in rows),
               "fresh_flagged_mean": float(np.mean([r["fresh_flagged"] for r in rows])),
               "out_of_domain_flagged": {c: [r["flagged"] for r in ood if r["case"] == c]
                                         for c in ("joint_never_moved", "half_joint_range", "workspace_corner")},
               "unmodelled_ratio": _unmodelled_ratio(unmod),
               "targets": {"ratio": [0.5, 2.0], "fresh_flagged_max": 0.05}}
    doc.update({"in_distribution": rows, "out_of_domain": ood, "unmodelled": unmod, "summary": summary,
                "elapsed_s": time.perf_counter() - t0, "load_average_end": os.getloadavg()})
    out.write_text(json.dumps(doc, indent=2))
    print(json.dumps(summary, indent=1))


if __name__ == "__main__":
    main()
