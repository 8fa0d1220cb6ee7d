"""Simulated paper-size campaigns shared by the ANN benchmarks (bench_calibrate, bench_baseline).

Cases (``--case``):

* ``compliance+cyclic`` — bench_calibrate's generator since issue 5: hidden geometric errors of
  Table 4's size, joint compliance and cyclic transmission errors at their typical values.
* ``compliance-0.5mm`` — issue 15's outside measurement: hidden geometric errors + joint
  compliance scaled to 0.5 mm RMS of ‖Δt‖ at the tool over the poses, nothing else.

Both with the simulated tracker's 10 µm noise, poses uniform inside the joint limits.
"""

from __future__ import annotations

import numpy as np

from campaign.effects import make_effect
from campaign.measure.csvio import write_measured_csv
from campaign.measure.store import import_csv
from campaign.model.robot import RobotModel
from campaign.sim.truth import make_truth, random_joint_poses, synthesize

CASES = ("compliance+cyclic", "compliance-0.5mm")


def hidden_effects(case: str, robot, seed: int = 0) -> dict:
    """name -> parameters of the case's hidden smooth effects."""
    if case == "compliance+cyclic":
        return {name: make_effect(name, robot).typical_params(seed) for name in ("joint_compliance", "cyclic")}
    if case == "compliance-0.5mm":
        c = make_effect("joint_compliance", robot).typical_params(seed)
        q = random_joint_poses(robot, 2000, seed=seed + 99)
        base = make_truth(robot, seed=seed)
        with_c = make_truth(robot, seed=seed, effects={"joint_compliance": c})
        rms_m = float(np.sqrt(np.mean(np.sum((with_c.pose(q)[:, :3, 3] - base.pose(q)[:, :3, 3]) ** 2, axis=1))))
        return {"joint_compliance": c * (0.5e-3 / rms_m)}  # displacement is linear in c to first order
    raise ValueError(f"unknown case {case!r}; known: {', '.join(CASES)}")


def make_run(folder, case: str = "compliance+cyclic", poses: int = 14000, seed: int = 0):
    """Import a simulated campaign into ``folder/run``; returns (run path, hidden effects dict)."""
    from pathlib import Path

    robot = RobotModel.load()
    hidden = hidden_effects(case, robot, seed)
    truth = make_truth(robot, seed=seed, effects=hidden)
    meas = synthesize(truth, random_joint_poses(robot, poses, seed=seed + 1), seed=seed + 2)
    folder = Path(folder)
    csv_path = folder / "measured.csv"
    write_measured_csv(csv_path, meas)
    run = folder / "run"
    import_csv(csv_path, run, robot)
    return run, {k: [float(v) for v in th] for k, th in hidden.items()}
