"""The screenshot of the live page in docs/watch.md: a simulated campaign watched in headless Chromium.

    python benchmarks/screenshot_watch.py [--out docs/img/watch.png] [--poses 160] [--keep DIR]

Plans nothing (random valid poses, as the benchmarks do) but measures for real on the simulated
cell, whose hidden truth has a drifting tracker stand (85 µm per campaign hour, so the drift
checks cross their 0.05 mm threshold late in the campaign) and rejects 4 % of moves as
unreachable (failures with their reason). The first 60 % of the poses are measured fast and
calibrated (`campaign calibrate --no-ann`, `campaign diagnose`), then the rest is measured at
1/100 of real time with `campaign run --watch`, and the page is captured while that runs: state
"running", calibrated residuals beside the nominal ones, reports linked. Prints the page's
counts against the log's; exits 2 with one line when no Chromium is found.
"""

from __future__ import annotations

import argparse
import os
import re
import signal
import sqlite3
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import yaml

sys.path.insert(0, str(Path(__file__).parent))
from browser import Chromium  # noqa: E402
from screenshot_reports import find_browser  # noqa: E402

ROOT = Path(__file__).resolve().parents[1]
ENV = {**os.environ, "PYTHONPATH": str(ROOT)}


def cli(*args, cwd):
    return subprocess.run([sys.executable, "-m", "campaign.cli", *map(str, args)], check=True, capture_output=True,
                          text=True, cwd=cwd, env=ENV)


def make_run(run: Path, n: int) -> Path:
    from campaign.model.robot import RobotModel
    from campaign.paths import DEFAULT_SCENE
    from campaign.sim.truth import random_joint_poses

    (run / "plan").mkdir(parents=True)
    q = random_joint_poses(RobotModel.load(), n, seed=11)
    (run / "plan" / "poses.csv").write_text("pose_id,q1,q2,q3,q4,q5,q6\n" + "".join(
        f"{1000 + i}," + ",".join(repr(float(v)) for v in q[i]) + "\n" for i in range(n)))
    cfg = {"robot": "comau_racer5_080", "scene": str(DEFAULT_SCENE),
           "run": {"drift_check_every": 12, "timeout_s": 2.0},
           "sim": {"seed": 3, "time_factor": 0.0, "faults": {"robot_fault": 0.04},
                   "hidden_effects": ["ground_compliance", {"effect": "drift", "params": [0.0, 8e-5, 3e-5]}]}}
    (run / "campaign.yaml").write_text(yaml.safe_dump(cfg))
    return run


def measured_in_log(run: Path) -> int:
    with sqlite3.connect(f"file:{run / 'measurements.sqlite'}?mode=ro", uri=True) as db:
        return db.execute("SELECT COUNT(*) FROM poses WHERE status = 'measured'").fetchone()[0]


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--out", type=Path, default=ROOT / "docs" / "img" / "watch.png")
    ap.add_argument("--poses", type=int, default=160)
    ap.add_argument("--width", type=int, default=1280)
    ap.add_argument("--keep", type=Path, default=None, help="make the run here (kept) instead of a temporary folder")
    args = ap.parse_args(argv)
    if find_browser() is None:
        print("screenshot_watch: no chromium found (apt-get install chromium, or set CHROMIUM=/path)", file=sys.stderr)
        return 2
    with tempfile.TemporaryDirectory(prefix="watch-shot-") as tmp:
        here = (args.keep or Path(tmp)).resolve()  # the commands run here, on runs/cell-7 as a user types it
        run = make_run(here / "runs" / "cell-7", args.poses)
        first = int(args.poses * 0.6)
        t0 = time.perf_counter()
        cli("run", "runs/cell-7", "--sim", "--quiet", "--max-poses", first, cwd=here)
        cli("calibrate", "runs/cell-7", "--no-ann", cwd=here)
        cli("diagnose", "runs/cell-7", cwd=here)
        print(f"measured {first} poses, calibrated and diagnosed in {time.perf_counter() - t0:.0f} s")
        cfg = yaml.safe_load((run / "campaign.yaml").read_text())
        cfg["sim"]["time_factor"] = 0.01  # the rest in 1/100 of real time
        (run / "campaign.yaml").write_text(yaml.safe_dump(cfg))
        driver = subprocess.Popen([sys.executable, "-m", "campaign.cli", "run", "runs/cell-7", "--sim", "--quiet",
                                   "--watch", "0"], stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, text=True,
                                  cwd=here, env=ENV)
        try:
            port = int(re.search(r"http://127\.0\.0\.1:(\d+)/", driver.stderr.readline()).group(1))
            with Chromium(width=args.width, height=900) as browser:
                browser.goto(f"http://127.0.0.1:{port}/")
                target = first + (args.poses - first) // 2
                browser.wait_for(f"Number(document.getElementById('measured').textContent) >= {target}",
                                 timeout_s=600, every_s=0.5)
                time.sleep(0.6)  # the plots of this poll drawn
                height = browser.evaluate("document.documentElement.scrollHeight")
                browser.call("Emulation.setDeviceMetricsOverride", width=args.width, height=int(height),
                              deviceScaleFactor=1, mobile=False)
                time.sleep(0.3)
                shown = browser.evaluate("document.getElementById('measured').textContent")
                state = browser.evaluate("document.getElementById('state').textContent")
                png = browser.screenshot(args.out)
            print(f"page: measured {shown}, state {state}; log: measured {measured_in_log(run)}; written {png} "
                  f"({args.width}x{height})")
        finally:
            driver.send_signal(signal.SIGINT)  # Ctrl-C: the run stops after the current pose
            driver.wait()
    return 0


if __name__ == "__main__":
    sys.exit(main())
