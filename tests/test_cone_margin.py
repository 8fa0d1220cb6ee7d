"""The short campaign keeps its beams inside the nests' cones by plan.cone_margin_deg, so the real
tool, turned by the robot's errors, still shows every reflector (a MuJoCo twin with Table 4-sized
errors lost up to 33 of 156 poses without it). Beam angles from Pinocchio's forward kinematics."""

import csv

import numpy as np
import pinocchio as pin
import yaml

from campaign.cli import main
from campaign.model.robot import RobotModel
from campaign.paths import DEFAULT_SCENE
from campaign.plan.scene import load_scene


def _angles_deg(robot, q, tracker):
    """(k,) angle of each reflector's beam to the tracker from its nest axis, deg."""
    model, data = robot.pinocchio_model, robot.pinocchio_model.createData()
    pin.framesForwardKinematics(model, data, q)
    M = data.oMf[model.getFrameId(robot.tool_frame)]
    out = []
    for r in robot.reflectors:
        p = M.rotation @ r.position_in_E + M.translation
        a = M.rotation @ r.axis_in_E
        to = (tracker - p) / np.linalg.norm(tracker - p)
        out.append(np.degrees(np.arccos(np.clip(a @ to, -1, 1))) - np.degrees(r.half_angle))
    return np.array(out)  # negative: inside the cone by that much


def test_the_short_campaign_keeps_its_beams_two_degrees_inside_the_cones(tmp_path):
    robot = RobotModel.load()
    tracker = load_scene(DEFAULT_SCENE).placed(robot).tracker_position
    runs = {}
    for margin in (0.0, 2.0):
        cfg = tmp_path / f"c{margin}.yaml"
        cfg.write_text(yaml.safe_dump({"plan": {"cone_margin_deg": margin}}))
        run = tmp_path / f"run{margin}"
        assert main(["plan", "--config", str(cfg), "--run", str(run), "--grid-scale", "0.6", "--select", "20",
                     "--quiet"]) == 0
        rows = list(csv.DictReader(open(run / "plan" / "poses.csv")))
        q = np.array([[float(r[f"q{j}"]) for j in range(1, 7)] for r in rows])
        runs[margin] = np.array([_angles_deg(robot, qi, tracker).max() for qi in q])
    assert runs[2.0].max() <= -2.0 + 1e-9  # every beam of every pose 2° inside its cone
    assert runs[0.0].max() <= 1e-9 and runs[0.0].max() > -2.0  # without the margin the design uses the edge
