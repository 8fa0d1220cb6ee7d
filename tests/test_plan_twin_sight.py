"""Issue 31, part 6: the plan's line of sight and the MuJoCo twin's agree on the robot's own
links beyond the tool frame (the Panda's hand and fingers, which example-robot-data hangs below
its tool frame 'panda_hand'). The twin (MuJoCo's ray cast) is the independent reference."""

import json

import pytest
import yaml

from campaign.cli import main


def _robot_yaml(tmp_path, erd, reflectors=None):
    doc = {"urdf": erd("panda_description/urdf/panda.urdf"), "name": "panda", "tool_frame": "panda_hand",
           "gravity_m_s2": [0, 0, -9.81], "locked_joints": {"panda_finger_joint1": 0.02, "panda_finger_joint2": 0.02}}
    if reflectors is not None:
        doc["reflectors"] = reflectors
    path = tmp_path / "robot.yaml"
    path.write_text(yaml.safe_dump(doc))
    return path


def test_the_plan_refuses_in_one_line_reflectors_the_pandas_own_hand_hides(tmp_path, erd, capsys):
    """Without reflectors in robot.yaml the default triad sits on the tool frame, inside the hand."""
    robot = _robot_yaml(tmp_path, erd)
    assert main(["plan", "--run", str(tmp_path / "r"), "--robot", str(robot), "--grid-scale", "0.5", "--select", "30",
                 "--quiet"]) == 1
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "the robot itself hides a reflector" in err[0] and "'panda_hand'" in err[0], err
    assert "robot.yaml reflectors" in err[0]
    assert not (tmp_path / "r" / "plan" / "poses.csv").exists()


def test_reflectors_beside_the_pandas_fingers_plan_only_poses_the_twin_sees(tmp_path, erd, capsys):
    """Wide nests between and beside the fingers: the fingers cross many beams the cones admit.
    Before the fix the plan accepted them and the twin lost 60 beams (15 of 69 poses failed)."""
    robot = _robot_yaml(tmp_path, erd, [
        {"name": "m1", "position_m": [0.0, 0.0, 0.09], "half_angle_deg": 60},
        {"name": "m2", "position_m": [0.06, 0.0, 0.10], "half_angle_deg": 60},
        {"name": "m3", "position_m": [-0.06, 0.0, 0.10], "half_angle_deg": 60}])
    run = tmp_path / "r"
    assert main(["plan", "--run", str(run), "--robot", str(robot), "--grid-scale", "0.5", "--select", "30",
                 "--quiet"]) == 0
    summary = json.loads((run / "plan" / "summary.json").read_text())
    assert summary["removed_by_filter"]["line_of_sight_robot"] > 0  # the fingers hide some
    assert main(["run", str(run), "--cell", "mujoco", "--quiet"]) == 0
    assert "failed 0" in capsys.readouterr().out
    stats = json.loads((run / "cell" / "twin.json").read_text())
    blocked = {k: v for k, v in stats["lost_beams"].items() if k.startswith("beam blocked")}
    assert blocked == {} and stats["contacts"] == 0, stats["lost_beams"]
