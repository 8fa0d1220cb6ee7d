"""Robots by name (`--robot ur10`, `campaign robots`) and `campaign --version`."""

import subprocess
import sys
from importlib import metadata

import numpy as np
import pinocchio as pin
import pytest

from campaign.cli import main
from campaign.config import load_config
from campaign.paths import DEFAULT_CONFIG
from campaign.errors import ConfigError
from campaign.model.kinematics import forward
from campaign.model.robot import RobotModel

from fcl_reference import erd_robot


def test_robots_lists_the_example_robot_data_arms_with_their_tool_frames(capsys):
    erd_robot("ur_description")  # skips without the test extra
    assert main(["robots"]) == 0
    lines = {line.split()[0]: line.split() for line in capsys.readouterr().out.splitlines() if line.strip()}
    assert lines["ur10"][1] == "tool0" and lines["panda"][1] == "panda_hand" and lines["xarm7"][1] == "link_eef"
    assert lines["tiago"][2] == "base_footprint" and "comau_racer5_080" in lines
    assert not any("not installed" in " ".join(v) for v in lines.values())


@pytest.mark.parametrize("name, path, tool", [("ur10", "ur_description/urdf/ur10_robot.urdf", "tool0"),
                                              ("panda", "panda_description/urdf/panda.urdf", "panda_hand")])
def test_a_name_is_its_urdf_with_its_usual_tool_frame(name, path, tool, rng):
    urdf = erd_robot(path)
    by_name, by_path = RobotModel.load(name), RobotModel.load(urdf, tool_frame=tool)
    assert by_name.tool_frame == tool and by_name.joint_names == by_path.joint_names
    q = rng.uniform(by_name.q_lower, by_name.q_upper, size=(20, by_name.n_joints))
    T = forward(by_name, q)
    assert np.allclose(T, forward(by_path, q), atol=1e-12)
    model = pin.buildModelFromUrdf(str(urdf))  # the URDF read by Pinocchio, not by us
    data, fid = model.createData(), model.getFrameId(tool)
    for i in range(len(q)):
        qp = pin.neutral(model)
        for j, jn in enumerate(by_name.joint_names):
            qp[model.joints[model.getJointId(jn)].idx_q] = q[i, j]
        pin.framesForwardKinematics(model, data, qp)
        assert np.allclose(data.oMf[fid].homogeneous, T[i], atol=1e-9)


def test_an_unknown_robot_name_points_to_campaign_robots(tmp_path, capsys):
    assert main(["model", "chain", "--robot", "no_such_arm"]) == 1
    err = capsys.readouterr().err.strip()
    assert len(err.splitlines()) == 1 and "`campaign robots`" in err and "no_such_arm" in err


def test_version_is_the_installed_distribution_version():
    out = subprocess.run([sys.executable, "-m", "campaign.cli", "--version"], capture_output=True, text=True)
    assert out.returncode == 0 and out.stdout.strip() == f"campaign {metadata.version('campaign')}"


def test_a_folder_without_robot_yaml_does_not_hide_a_name(tmp_path, monkeypatch):
    erd_robot("ur_description")  # skips without the test extra
    monkeypatch.chdir(tmp_path)
    (tmp_path / "ur3").mkdir()  # the run folder of `campaign plan --run ur3 --robot ur3`
    assert RobotModel.load("ur3").urdf_path.name == "ur3_robot.urdf"
    assert load_config(DEFAULT_CONFIG).with_robot("ur3").robot == "ur3"  # what campaign.yaml records
    (tmp_path / "ur3" / "robot.yaml").write_text("not: a robot\n")  # a robot.yaml folder is the user's robot
    with pytest.raises(ConfigError, match="robot.yaml"):
        RobotModel.load("ur3")
