"""Benchmark of `campaign plan --all` (issue 3: every suitable pose, the full tour) at full size on the default cell.

    python benchmarks/bench_plan.py [--grid-scale 1.0] [--robot NAME|URDF|robot.yaml [--tool-frame LINK]]

``--robot`` plans for another robot (issue 12, item 9) on its default grid (campaign.plan.grid:
about a million candidates); ``--robot panda`` and ``--robot ur10`` name example-robot-data's
URDFs (Panda with tool frame panda_hand, UR10 with tool0). Results go to
benchmarks/results/plan.json (the default robot) or plan_<name>.json.

Runs `campaign plan --all` in a separate process and reports its wall time and peak memory
(max RSS of the child), the seconds per stage (``stages_s``: setup, filters, ordering,
motion_check, repair, outputs, plot, and the process start + CLI around them), the counts
per filter, the tour and the estimated duration, and the load average before and after (the
machine is shared: run it as ``flock /tmp/campaign-bench.lock python benchmarks/bench_plan.py``).
"""

from __future__ import annotations

import argparse
import json
import os
import resource
import subprocess
import sys
import tempfile
import time
from pathlib import Path


#: example-robot-data's arms by short name: (URDF under robots/, tool frame)
EXAMPLE_ROBOTS = {"panda": ("panda_description/urdf/panda.urdf", "panda_hand"),
                  "ur10": ("ur_description/urdf/ur10_robot.urdf", "tool0")}


def main():
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--grid-scale", type=float, default=1.0)
    ap.add_argument("--robot", default=None, help="a robot name, URDF or robot.yaml; panda, ur10: example-robot-data's")
    ap.add_argument("--tool-frame", default=None)
    args = ap.parse_args()
    robot_args, name = [], "plan"
    if args.robot is not None:
        spec, tool = args.robot, args.tool_frame
        if args.robot in EXAMPLE_ROBOTS:
            from importlib import metadata

            rel, default_tool = EXAMPLE_ROBOTS[args.robot]
            share = Path(metadata.distribution("example-robot-data").locate_file("cmeel.prefix/share"))
            spec, tool = str(share / "example-robot-data" / "robots" / rel), tool or default_tool
        robot_args = ["--robot", spec] + (["--tool-frame", tool] if tool else [])
        name = f"plan_{Path(args.robot).stem if args.robot not in EXAMPLE_ROBOTS else args.robot}"
    load_before = os.getloadavg()
    with tempfile.TemporaryDirectory() as tmp:
        t0 = time.perf_counter()
        subprocess.run([sys.executable, "-m", "campaign.cli", "plan", "--run", tmp, "--quiet", "--all",
                        "--grid-scale", str(args.grid_scale), *robot_args], check=True, stdout=subprocess.DEVNULL)
        wall = time.perf_counter() - t0
        peak_mb = resource.getrusage(resource.RUSAGE_CHILDREN).ru_maxrss / 1024
        summary = json.loads((Path(tmp) / "plan" / "summary.json").read_text())
    stages = dict(summary["timing_s"])
    # interpreter start, imports and the CLI around plan_campaign
    stages["process_start_and_cli"] = wall - stages.pop("total")
    res = {"command": " ".join(["python", "benchmarks/bench_plan.py"] + sys.argv[1:]),
           "wall_s": wall, "stages_s": stages, "peak_rss_mb": peak_mb,
           "load_average": os.getloadavg(), "load_average_before": load_before,
           "motion_time_s": summary["tour"]["motion_time_s"], "summary": summary}
    print(f"candidates {summary['candidates']:,}; suitable {summary['suitable']:,} "
          f"({100 * summary['suitable_fraction']:.2f} %); removed per filter {summary['removed_by_filter']}")
    print(f"tour {summary['tour']['poses']:,} poses, {summary['tour']['via_poses']} vias, {summary['tour']['dropped']} dropped, "
          f"motion {summary['tour']['motion_time_s'] / 3600:.2f} h; estimated campaign "
          f"{summary['estimated_campaign']['total_days']:.2f} days (paper 3.5 days / 13,919 poses)")
    print("stages (s wall): " + ", ".join(f"{k} {v:.2f}" for k, v in stages.items()))
    print(f"campaign plan ({summary['robot']}): {wall:.1f} s wall, peak memory {peak_mb:.0f} MB; "
          f"load average {res['load_average'][0]:.2f}")
    (Path(__file__).parent / "results" / f"{name}.json").write_text(json.dumps(res, indent=2))


if __name__ == "__main__":
    main()
