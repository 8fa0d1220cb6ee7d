"""Issue 31, part 6: the plan's line of sight and the MuJoCo twin's agree on the robot's own
links beyond the tool frame (the Panda's hand and fingers, which example-robot-data hangs below
its tool frame 'panda_hand'). The twin (MuJoCo's ray cast) is the independent reference."""

import json

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
    """A 5 cm triad on the tool frame 'panda_hand' sits inside the hand: no beam leaves it."""
    robot = _robot_yaml(tmp_path, erd, [{"name": f"m{i + 1}", "position_m": p}
                                        for i, p in enumerate([[0.05, 0, 0], [0, 0.05, 0], [0, 0, 0.05]])])
    assert main(["plan", "--run", str(tmp_path / "r"), "--robot", str(robot), "--grid-scale", "0.5", "--select", "30",
                 "--quiet"]) == 1
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "the robot itself hides a reflector" in err[0] and "'panda_hand'" in err[0], err
    assert "robot.yaml reflectors" in err[0]
    assert not (tmp_path / "r" / "plan" / "poses.csv").exists()


def test_the_pandas_default_reflectors_sit_beyond_its_fingers_and_the_twin_sees_every_one(tmp_path, erd, capsys):
    """`--robot panda` (example-robot-data's, tool frame panda_hand): the default triad is mounted
    beyond the hand and fingers the tool frame carries; planned, every pose measures on the twin."""
    from campaign.run import load_robot

    erd("panda_description/urdf/panda.urdf")  # skips without the test extra
    robot = load_robot("panda")
    lifted = robot.with_default_reflectors().reflectors
    # the fingers' tips: the finger joints' origin (5.84 cm) plus the finger's own length (~5.4 cm)
    assert 0.10 < robot.default_reflector_lift_m - 0.01905 - 0.01 < 0.12
    assert all(r.position_in_E[2] >= robot.default_reflector_lift_m for r in lifted)
    run = tmp_path / "r"
    assert main(["plan", "--run", str(run), "--robot", "panda", "--grid-scale", "0.5", "--select", "30", "--quiet"]) == 0
    assert main(["run", str(run), "--cell", "mujoco", "--quiet"]) == 0
    assert "failed 0" in capsys.readouterr().out
    stats = json.loads((run / "cell" / "twin.json").read_text())
    assert stats["lost_beams"] == {} and stats["contacts"] == 0


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
