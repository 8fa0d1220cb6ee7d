"""Write docs/img/domain.svg, the figure of docs/domain.md, from a generated campaign:

    python docs/domain_figure.py

60 poses of the default COMAU measured with joint 2 over the lower half of its range only and
joint 5 within ±10°, imported and calibrated by the pipeline (`campaign calibrate`); the figure is
the calibration report's own (domain.svg).
"""

from __future__ import annotations

import shutil
import sys
import tempfile
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parent.parent
sys.path.insert(0, str(ROOT))


def main() -> Path:
    from campaign.cli import main as cli
    from campaign.measure.csvio import write_measured_csv
    from campaign.model.robot import RobotModel
    from campaign.sim.truth import make_truth, random_joint_poses, synthesize

    robot = RobotModel.load()
    q = random_joint_poses(robot, 60, seed=2)
    lo, hi = robot.q_lower[1], robot.q_upper[1]
    q[:, 1] = lo + 0.05 + (q[:, 1] - lo - 0.05) * 0.5  # joint 2: the lower half of its range
    q[:, 4] = np.deg2rad(30.0) + np.deg2rad(20.0) * (np.random.default_rng(3).uniform(size=len(q)) - 0.5)
    poses = synthesize(make_truth(robot, seed=2), q, seed=4)
    with tempfile.TemporaryDirectory() as tmp:
        tmp = Path(tmp)
        write_measured_csv(tmp / "m.csv", poses, robot)
        assert cli(["import", str(tmp / "m.csv"), "--run", str(tmp / "run"), "--quiet"]) == 0
        assert cli(["calibrate", str(tmp / "run"), "--no-ann", "--quiet"]) == 0
        out = ROOT / "docs" / "img" / "domain.svg"
        shutil.copyfile(tmp / "run" / "calibration" / "domain.svg", out)
    return out


if __name__ == "__main__":
    print(f"wrote {main()}")
