"""Benchmark of `campaign plan` over five arms (issue 22, item 6): the embedded COMAU and
example-robot-data's UR10, Panda, xArm7 and Unitree Z1 with their meshes; with ``--more``, the
other serial arms example-robot-data ships (:data:`MORE_ARMS`: UR3, UR5, Kinova, SO-ARM100/101,
TIAGo, TIAGo Pro, TIAGo dual's arm, Baxter's, PR2's, TALOS's, the Kinova on ANYmal, the Z1 on B1),
each as a new user would name it (URDF, tool link, base link for an arm on a body).

    python benchmarks/bench_plan_arms.py [--all] [--more] [--arms comau,ur10,...] [--out NAME]

For each arm, `campaign plan --robot URDF --tool-frame LINK` (the default short campaign; with
``--all`` every suitable pose) runs in its own process; the wall time and that process's peak
RSS (``os.wait4``) are recorded with the counts (suitable, chosen, toured, dropped), the
predicted held-out error and the seconds per stage from summary.json. The yardstick, timed in
the same run for the same arm: a plain numpy forward kinematics of the arm's whole grid (4×4
products joint by joint, 100,000 poses at a time), so the plan's time is also given as a
ratio to it (the machine is shared; ``uptime`` before and after is recorded).
``os.getloadavg()`` before and after each arm is recorded too (``load_before``, ``load_after``).
An arm the planner refuses is recorded with its one-line error.
Results: benchmarks/results/plan_arms.json (``--all``: plan_arms_all.json; ``--more``:
plan_arms_more.json, plan_arms_more_all.json; or ``--out NAME``).
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import tempfile
import time
from importlib import metadata
from pathlib import Path

import numpy as np

#: arm name: (URDF under example-robot-data's robots/ or None for the embedded COMAU, tool frame)
ARMS = {"comau": (None, None),
        "ur10": ("ur_description/urdf/ur10_robot.urdf", "tool0"),
        "panda": ("panda_description/urdf/panda.urdf", "panda_hand"),
        "xarm7": ("xarm_description/urdf/xarm7.urdf", "link_eef"),
        "z1": ("z1_description/urdf/z1.urdf", "gripperStator")}
#: the other arms (``--more``): (URDF, tool frame, base frame or None for the URDF's root)
MORE_ARMS = {"ur3": ("ur_description/urdf/ur3_robot.urdf", "tool0", None),
             "ur5": ("ur_description/urdf/ur5_robot.urdf", "tool0", None),
             "kinova": ("kinova_description/robots/kinova.urdf", "j2s6s200_end_effector", None),
             "so100": ("so_arm_description/urdf/so100.urdf", "gripper", None),
             "so101": ("so_arm_description/urdf/so101.urdf", "gripper_frame_link", None),
             "tiago": ("tiago_description/robots/tiago.urdf", "arm_tool_link", "base_footprint"),
             "tiago_pro": ("tiago_pro_description/robots/tiago_pro.urdf", "arm_left_tool_link", "base_footprint"),
             "tiago_dual": ("tiago_description/robots/tiago_dual.urdf", "arm_left_tool_link", "base_footprint"),
             "baxter": ("baxter_description/urdf/baxter.urdf", "left_gripper_base_link", None),
             "pr2": ("pr2_description/urdf/pr2.urdf", "r_gripper_tool_frame", "base_footprint"),
             "talos": ("talos_data/robots/talos_reduced.urdf", "gripper_left_base_link", "torso_2_link"),
             "anymal_kinova": ("anymal_b_simple_description/robots/anymal-kinova.urdf", "j2s6s200_end_effector", None),
             "b1_z1": ("b1_description/urdf/b1-z1.urdf", "link06", None)}


def arm_urdf(name):
    """(URDF path or None, tool frame, base frame or None) of a benchmarked arm."""
    rel, tool, base = MORE_ARMS[name] if name in MORE_ARMS else (*ARMS[name], None)
    if rel is None:
        return None, None, None
    share = Path(metadata.distribution("example-robot-data").locate_file("cmeel.prefix/share"))
    return share / "example-robot-data" / "robots" / rel, tool, base


def numpy_fk_seconds(name, chunk=100_000):
    """Wall seconds of a plain numpy forward kinematics of the arm's default grid (every candidate's
    tool pose, 4×4 products joint by joint, ``chunk`` poses at a time)."""
    from campaign.model.robot import RobotModel
    from campaign.plan.grid import Grid

    urdf, tool, base = arm_urdf(name)
    robot = RobotModel.load(str(urdf), tool_frame=tool, base_frame=base) if urdf else RobotModel.load()
    grid = Grid.for_robot(robot)
    N = robot.n_joints
    Tn = np.zeros((N + 2, 4, 4))
    Tn[:, :3, :3], Tn[:, :3, 3], Tn[:, 3, 3] = robot.R_nominal, robot.t_nominal, 1.0
    t0 = time.perf_counter()
    acc = 0.0
    for s in range(0, grid.size, chunk):
        q = grid.q(np.arange(s, min(s + chunk, grid.size)))
        T = np.broadcast_to(Tn[0], (len(q), 4, 4))
        for k in range(N):
            c, sn = np.cos(q[:, k]), np.sin(q[:, k])
            J = np.zeros((len(q), 4, 4))
            J[:, 0, 0], J[:, 0, 1], J[:, 1, 0], J[:, 1, 1] = c, -sn, sn, c
            J[:, 2, 2] = J[:, 3, 3] = 1.0
            if robot.prismatic[k]:
                J[:, :3, :3] = np.eye(3)
                J[:, 0, 1] = J[:, 1, 0] = 0.0
                J[:, 2, 3] = q[:, k]
            T = T @ Tn[k + 1] @ J
        T = T @ Tn[N + 1]
        acc += float(T[:, :3, 3].sum())
    return time.perf_counter() - t0, grid.size


def run_plan(name, all_poses, tmp):
    urdf, tool, base = arm_urdf(name)
    cmd = [sys.executable, "-m", "campaign.cli", "plan", "--run", str(tmp), "--quiet"]
    if urdf:
        cmd += ["--robot", str(urdf), "--tool-frame", tool]
    if base:
        cmd += ["--base-frame", base]
    if all_poses:
        cmd.append("--all")
    t0 = time.perf_counter()
    p = subprocess.Popen(cmd, stdout=subprocess.DEVNULL, stderr=subprocess.PIPE)
    _, status, usage = os.wait4(p.pid, 0)
    wall = time.perf_counter() - t0
    err = p.stderr.read().decode()
    p.returncode = os.waitstatus_to_exitcode(status)
    if p.returncode != 0:
        return {"command": " ".join(cmd), "error": err.strip(), "wall_s": wall}
    s = json.loads((Path(tmp) / "plan" / "summary.json").read_text())
    sel = s.get("selection", {})
    pred = sel.get("predicted", {})
    return {"command": " ".join(cmd), "wall_s": wall, "cpu_s": usage.ru_utime + usage.ru_stime,
            "peak_rss_mb": usage.ru_maxrss / 1024,
            "candidates": s["candidates"], "suitable": s["suitable"],
            "chosen": sel.get("chosen"), "chosen_toured": sel.get("selected"),
            "toured": s["tour"]["poses"], "dropped": s["tour"]["dropped"], "vias": s["tour"]["via_poses"],
            "heldout_position_mm": pred.get("heldout_position_mm"),
            "model_position_mm": pred.get("model_position_mm"),
            "replacement": sel.get("replacement"), "reachable": s.get("reachable"),
            "stages_s": s["timing_s"], "selection_time_s": sel.get("time_s")}


def main():
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--all", action="store_true", help="plan every suitable pose (--all)")
    ap.add_argument("--more", action="store_true", help="the other arms of example-robot-data (MORE_ARMS)")
    ap.add_argument("--arms", default=None, help="comma-separated names (default: the five, or with --more the others)")
    ap.add_argument("--out", default=None)
    args = ap.parse_args()
    arms = args.arms.split(",") if args.arms else list(MORE_ARMS if args.more else ARMS)
    out = {"command": " ".join(["python", "benchmarks/bench_plan_arms.py"] + sys.argv[1:]),
           "uptime_before": subprocess.run(["uptime"], capture_output=True, text=True).stdout.strip(), "arms": {}}
    for name in arms:
        load_before = os.getloadavg()
        fk_s, size = numpy_fk_seconds(name)
        with tempfile.TemporaryDirectory() as tmp:
            r = run_plan(name, args.all, tmp)
        r["numpy_fk_s"], r["grid_size"] = fk_s, size
        r["load_before"], r["load_after"] = list(load_before), list(os.getloadavg())
        if "error" not in r:
            r["ratio_to_numpy_fk"] = r["wall_s"] / fk_s
        out["arms"][name] = r
        if "error" in r:
            print(f"{name}: FAILED {r['error']}")
        else:
            print(f"{name}: {r['wall_s']:.1f} s wall ({r['ratio_to_numpy_fk']:.1f}x numpy FK {fk_s:.2f} s), "
                  f"{r['cpu_s']:.1f} s CPU, "
                  f"{r['peak_rss_mb']:.0f} MB; suitable {r['suitable']:,}, chosen {r['chosen']}, chosen toured "
                  f"{r['chosen_toured']}, toured {r['toured']}, dropped {r['dropped']}; held-out "
                  f"{r['heldout_position_mm']}", flush=True)
    out["uptime_after"] = subprocess.run(["uptime"], capture_output=True, text=True).stdout.strip()
    name = args.out or ("plan_arms" + ("_more" if args.more else "") + ("_all" if args.all else ""))
    (Path(__file__).parent / "results" / f"{name}.json").write_text(json.dumps(out, indent=2))


if __name__ == "__main__":
    main()
