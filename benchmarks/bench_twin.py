"""Benchmark of the MuJoCo twin (issue 21, item 3): plan, measure on the twin, calibrate, diagnose.

    python benchmarks/bench_twin.py [--robot comau|ur10|panda|both] [--grid-scale S]

For each robot (the default COMAU in the default cell; example-robot-data's UR10, tool0, with its
STL meshes, in the same cell): `campaign plan` (the default short campaign), `campaign run RUN
--cell mujoco` (``--robot panda``: example-robot-data's Panda, tool frame panda_hand, the default
reflectors beyond its hand and fingers; timed: the goal is <= 3 min on 2 cores; the twin's simulated time is the campaign
clock), then `campaign calibrate --no-ann` and `campaign diagnose --json`; the effect diagnose names
is added to RUN/campaign.yaml's effects, and calibrate + diagnose run again, until diagnose names
none (at most three rounds). Reported: poses measured and failed (with the reasons), the twin's
contact count (RUN/cell/twin.json), the held-out error against the noise floor at each round, the
verdicts, and the identified joint compliances against the twin's servo stiffness (read from
RUN/cell/truth.yaml after the pipeline answered). Writes benchmarks/results/twin.json.
"""

from __future__ import annotations

import argparse
import json
import os
import sqlite3
import subprocess
import sys
import tempfile
import time
from collections import Counter
from pathlib import Path

import yaml

#: example-robot-data's arms by short name: (URDF under robots/, tool frame)
EXAMPLE_ROBOTS = {"ur10": ("ur_description/urdf/ur10_robot.urdf", "tool0"),
                  # 7R; its tool frame carries the hand and fingers: the default reflectors sit beyond them
                  "panda": ("panda_description/urdf/panda.urdf", "panda_hand")}


def _cli(*args, capture=True):
    t0 = time.perf_counter()
    out = subprocess.run([sys.executable, "-m", "campaign.cli", *map(str, args)], check=True, text=True,
                         capture_output=capture)
    return time.perf_counter() - t0, out.stdout if capture else ""


def _robot_args(name):
    if name == "comau":
        return []
    from importlib import metadata

    rel, tool = EXAMPLE_ROBOTS[name]
    share = Path(metadata.distribution("example-robot-data").locate_file("cmeel.prefix/share"))
    return ["--robot", str(share / "example-robot-data" / "robots" / rel), "--tool-frame", tool]


def bench(name, tmp, grid_scale):
    run = Path(tmp) / name
    res = {"robot": name}
    res["plan_wall_s"], _ = _cli("plan", "--run", run, "--quiet", "--grid-scale", grid_scale, *_robot_args(name))
    summary = json.loads((run / "plan" / "summary.json").read_text())
    res["planned_poses"] = summary["tour"]["poses"]
    res["via_poses"] = summary["tour"]["via_poses"]
    load_before = os.getloadavg()
    res["run_wall_s"], out = _cli("run", run, "--cell", "mujoco", "--quiet")
    res["run_load_average_before"], res["run_load_average_after"] = load_before, os.getloadavg()
    res["run_output"] = out.strip().splitlines()[0]
    with sqlite3.connect(run / "measurements.sqlite") as db:
        rows = db.execute("SELECT status, reason FROM poses").fetchall()
    res["measured"] = sum(1 for s, _ in rows if s == "measured")
    res["failed"] = sum(1 for s, _ in rows if s != "measured")
    res["failure_reasons"] = dict(Counter(r for s, r in rows if s != "measured"))
    res["twin"] = json.loads((run / "cell" / "twin.json").read_text())
    rounds = []
    for _ in range(3):
        wall_c, _ = _cli("calibrate", run, "--no-ann", "--no-report", "--quiet")
        wall_d, out = _cli("diagnose", run, "--json")
        diag = json.loads(out)
        metrics = json.loads((run / "calibration" / "metrics.json").read_text())
        stage = metrics["order"][-1]
        cfg = yaml.safe_load((run / "campaign.yaml").read_text())
        rounds.append({"effects": list(cfg.get("effects") or []), "stage": stage,
                       "test_mean_position_mm": metrics["stages"][stage]["test"]["position_mm"]["mean"],
                       "verdict": diag["verdict"], "noise_floor_mm": diag["noise_floor_mm"],
                       "model_to_noise": diag["model_to_noise"],
                       "ranking": [{k: r[k] for k in ("effect", "heldout_mean_position_mm_before",
                                                      "heldout_mean_position_mm_after", "significant")}
                                   for r in diag["ranking"][:3]],
                       "unexplained": {k: diag["unexplained"].get(k) for k in ("significant", "depends_on")}
                       if diag.get("unexplained") else None,
                       "calibrate_wall_s": wall_c, "diagnose_wall_s": wall_d})
        verdict = diag["verdict"]
        if verdict in (None, "unexplained") or verdict in rounds[-1]["effects"]:
            break
        cfg["effects"] = list(cfg.get("effects") or []) + [verdict]
        (run / "campaign.yaml").write_text(yaml.safe_dump(cfg, sort_keys=False))
    res["rounds"] = rounds
    params = yaml.safe_load((run / "calibration" / "params.yaml").read_text())
    truth = yaml.safe_load((run / "cell" / "truth.yaml").read_text())  # only now
    res["servo_compliance_rad_per_nm"] = [1.0 / k for k in truth["servo"]["stiffness"]]
    jc = (params.get("effects") or {}).get("joint_compliance")
    if jc:
        res["identified_joint_compliance"] = {p["name"]: {"value": p["value"], "sigma": p["sigma"]}
                                              for p in jc["parameters"]}
    return res


def main():
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--robot", choices=("comau", "ur10", "panda", "both"), default="both")
    ap.add_argument("--grid-scale", type=float, default=1.0)
    args = ap.parse_args()
    names = ["comau", "ur10"] if args.robot == "both" else [args.robot]
    path = Path(__file__).parent / "results" / "twin.json"
    # one robot's run replaces that robot's entry only
    results = json.loads(path.read_text()) if path.is_file() else {"robots": {}}
    results.update({"command": " ".join(["python", "benchmarks/bench_twin.py"] + sys.argv[1:]),
                    "cpus": os.cpu_count(), "goal_run_wall_s": 180.0})
    with tempfile.TemporaryDirectory() as tmp:
        for name in names:
            r = bench(name, tmp, args.grid_scale)
            results["robots"][name] = r
            last = r["rounds"][-1]
            print(f"{name}: plan {r['plan_wall_s']:.1f} s; run --cell mujoco {r['run_wall_s']:.1f} s wall "
                  f"(goal 180 s): measured {r['measured']} of {r['measured'] + r['failed']}, contacts "
                  f"{r['twin']['contacts']}, {r['twin']['steps']:,} steps; failures {r['failure_reasons']}; "
                  f"lost readings by why {r['twin'].get('lost_beams')}")
            for k, rd in enumerate(r["rounds"]):
                print(f"  round {k + 1}: effects {rd['effects']}: held-out {rd['model_to_noise']:.2f}x the noise floor "
                      f"({rd['noise_floor_mm']:.4f} mm); verdict {rd['verdict']}")
            if "identified_joint_compliance" in r:
                print(f"  joint compliance {r['identified_joint_compliance']} vs the servos' "
                      f"{r['servo_compliance_rad_per_nm'][0]:.3g} rad/(N·m)")
            print(f"  final: {last['model_to_noise']:.2f}x the noise floor (goal <= 1.5)")
    path.write_text(json.dumps(results, indent=2) + "\n")
    print(f"written: {path}")


if __name__ == "__main__":
    main()
