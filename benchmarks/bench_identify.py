"""Benchmark of the geometric identification (issue 2).

    python benchmarks/bench_identify.py [--poses 14000] [--robot NAME|URDF|robot.yaml [--tool-frame LINK]]
    python benchmarks/bench_identify.py --robot panda   # the 7R case: example-robot-data's Panda
    python benchmarks/bench_identify.py --markers [--miss-rate 0.05]  # raw three-reflector rows
    python benchmarks/bench_identify.py --end-to-end [--repeat 3] [--before /work/main]  # the commands
    (on a shared machine: OPENBLAS_NUM_THREADS=1, else BLAS threads fight over the cores)

Simulates a campaign with Table-4-sized geometric errors and 10 µm tracker noise,
identifies the 30 base parameters on the 80 % training split and reports wall time,
iterations, the worst |error| / σ of the recovered base parameters and the held-out
mean position error against the noise-only floor. Writes benchmarks/results/identify.json (the
default COMAU) or identify_<robot>.json. ``--robot panda`` loads the Panda (7 revolute joints,
tool panda_hand) of the test-only package example-robot-data. ``--markers``: the same poses as
raw reflector rows (the default triad, each reflector missed with ``--miss-rate``), identified
from the reflectors' positions as `calibrate` does for raw data; writes identify_markers.json.

``--end-to-end`` (issue 22): the same data as a user runs them, each command a process timed as a
whole, against the yardstick of a plain numpy + scipy identification script
(benchmarks/plain_identify.py, same CSV, same model, same accuracy) in the same run: `campaign
calibrate RUN --no-ann` (report included), `campaign diagnose RUN` (report included) and
`campaign --help`; wall and CPU time (user + system, what a quiet machine's wall time would be for
these single-threaded commands), the median of ``--repeat`` rounds; ``--before DIR``: the same
commands with the `campaign` source tree in DIR (the code before the change) in the same rounds.
Writes the ``end_to_end`` entry of benchmarks/results/identify.json (the rest kept).
"""

from __future__ import annotations

import argparse
import json
import os
import resource
import subprocess
import sys
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
    ap.add_argument("--end-to-end", action="store_true", help="time the commands against the plain script")
    ap.add_argument("--repeat", type=int, default=3, help="with --end-to-end: rounds (the median is kept)")
    ap.add_argument("--before", default=None, help="with --end-to-end: a campaign source tree to compare")
    args = ap.parse_args()
    if args.end_to_end:
        return end_to_end(args)
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
    if out.is_file() and "end_to_end" in json.loads(out.read_text()):  # --end-to-end's entry stays
        res["end_to_end"] = json.loads(out.read_text())["end_to_end"]
    out.write_text(json.dumps(res, indent=2))



def _timed(cmd, env, cwd) -> tuple:
    """(wall s, CPU s of the process and its children) of one command, which must succeed."""
    before = resource.getrusage(resource.RUSAGE_CHILDREN)
    t0 = time.perf_counter()
    proc = subprocess.run(cmd, env=env, cwd=cwd, capture_output=True, text=True)
    wall = time.perf_counter() - t0
    after = resource.getrusage(resource.RUSAGE_CHILDREN)
    if proc.returncode:
        raise SystemExit(f"{' '.join(map(str, cmd))}: {proc.stderr.strip()}")
    return wall, (after.ru_utime - before.ru_utime) + (after.ru_stime - before.ru_stime), proc.stdout


def end_to_end(args) -> None:
    """The commands as a user runs them against the plain script, in the same rounds (see the module)."""
    import statistics
    import tempfile

    from campaign.measure.csvio import write_measured_csv

    root = Path(__file__).resolve().parents[1]
    robot = RobotModel.load()
    truth = make_truth(robot, seed=args.seed)
    meas = synthesize(truth, random_joint_poses(robot, args.poses, seed=args.seed + 1), seed=args.seed + 2)
    trees = {"after": root} | ({"before": Path(args.before)} if args.before else {})
    rows = {}
    with tempfile.TemporaryDirectory(prefix="bench-e2e-") as tmp:
        tmp = Path(tmp)
        csv = tmp / "measured.csv"
        write_measured_csv(csv, meas)
        env = {**os.environ, "OPENBLAS_NUM_THREADS": "1"}
        runs = {}
        for name, tree in trees.items():
            runs[name] = tmp / f"run_{name}"
            _timed([sys.executable, "-m", "campaign.cli", "import", str(csv), "--run", str(runs[name]), "--quiet"],
                   {**env, "PYTHONPATH": str(tree)}, tmp)
        cmds = {"plain_script": ([sys.executable, str(root / "benchmarks" / "plain_identify.py"), str(csv)], env)}
        for name, tree in trees.items():
            e = {**env, "PYTHONPATH": str(tree)}
            cli = [sys.executable, "-m", "campaign.cli"]
            cmds[f"calibrate_{name}"] = (cli + ["calibrate", str(runs[name]), "--no-ann"], e)
            cmds[f"diagnose_{name}"] = (cli + ["diagnose", str(runs[name])], e)
            cmds[f"help_{name}"] = (cli + ["--help"], e)
        times = {k: [] for k in cmds}
        outputs = {}
        for _ in range(args.repeat):  # rounds: every command once a round, so the load hits all alike
            for key, (cmd, e) in cmds.items():
                wall, cpu, out = _timed(cmd, e, tmp)  # cwd apart: `python -m` puts it first on the path
                times[key].append((wall, cpu))
                outputs[key] = out
        for key, v in times.items():
            rows[key] = {"wall_s": statistics.median(w for w, _ in v), "cpu_s": statistics.median(c for _, c in v),
                         "rounds": v}
    plain = rows["plain_script"]
    res = {"poses": args.poses, "repeat": args.repeat, "commands": {k: " ".join(map(str, c[0][1:]))
                                                                    for k, c in cmds.items()},
           "times": rows, "plain_script_output": outputs["plain_script"].strip(),
           "calibrate_output_tail": outputs["calibrate_after"].strip().splitlines()[-4:]}
    for name in trees:
        c = rows[f"calibrate_{name}"]
        res[f"calibrate_over_plain_{name}"] = {"wall": c["wall_s"] / plain["wall_s"], "cpu": c["cpu_s"] / plain["cpu_s"]}
    res["targets"] = {"calibrate_over_plain": 1.5, "diagnose_s": 15.0, "help_s": 0.5}
    res["load_average"] = os.getloadavg()
    res["openblas_num_threads"] = "1"
    for key, r in rows.items():
        print(f"{key:<18} wall {r['wall_s']:7.2f} s   cpu {r['cpu_s']:7.2f} s")
    for name in trees:
        ratio = res[f"calibrate_over_plain_{name}"]
        print(f"calibrate ({name}) / plain script: wall {ratio['wall']:.2f}x, cpu {ratio['cpu']:.2f}x")
    print(f"load average {res['load_average'][0]:.2f}")
    out = Path(__file__).parent / "results" / "identify.json"
    doc = json.loads(out.read_text()) if out.is_file() else {}
    doc["end_to_end"] = res
    out.write_text(json.dumps(doc, indent=2))


if __name__ == "__main__":
    main()
