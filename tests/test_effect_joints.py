"""Joint-indexed effects take their joints: campaign.yaml's ``{effect: NAME, joints: [...]}``,
``--effects NAME:2,3,4``, any number of joints; defaults from the robot's gravity loads."""

import numpy as np
import pytest
import yaml

from campaign.config import load_config
from campaign.effects.base import (effect_label, make_effect, merge_effects, parse_effect_list, split_joints,
                                   without_joints)
from campaign.effects.gravity import gravity_torques, loaded_joints
from campaign.errors import ConfigError
from campaign.model.robot import RobotModel
from campaign.run import RunFolder
from campaign.sim.truth import random_joint_poses


@pytest.fixture(scope="module")
def panda():
    return RobotModel.load("panda")


def test_a_command_line_list_keeps_each_effects_joints():
    assert parse_effect_list("joint_compliance:2,3,4,backlash:5,ground_compliance") == (
        "joint_compliance:2,3,4", "backlash:5", "ground_compliance")
    assert split_joints("/a/b/runout.py:Runout:2,3") == ("/a/b/runout.py:Runout", (2, 3))
    assert split_joints("/a/b/runout.py:Runout") == ("/a/b/runout.py:Runout", None)


def test_joint_compliance_on_joint_7_of_the_panda_moves_only_joint_7_by_c_tau(panda):
    e = make_effect("joint_compliance:2,7", panda)
    assert e.param_names == ("c2", "c7")
    q = random_joint_poses(panda, 5, seed=1)
    dq = e.joint_offset(np.array([0.0, 1e-3]), q, {})
    tau = gravity_torques(panda, q)  # Pinocchio, independent of the effect's own bookkeeping
    assert np.allclose(dq[:, 6], 1e-3 * tau[:, 6]) and np.all(dq[:, :6] == 0)


@pytest.mark.parametrize("spec, match", [("joint_compliance:8", "joint 8 is not a joint of panda"),
                                         ("ground_compliance:2", "takes no joints"),
                                         ("backlash:3,3", "name a joint twice")])
def test_a_bad_joint_list_is_one_line_naming_the_effect(panda, spec, match):
    with pytest.raises(ConfigError, match=match):
        make_effect(spec, panda)


def test_default_joints_are_those_with_a_gravity_torque_worth_identifying(robot, panda):
    for r in (robot, panda):
        q = random_joint_poses(r, 300, seed=5)
        rms = np.sqrt(np.mean(gravity_torques(r, q) ** 2, axis=0))
        expected = tuple(int(j) + 1 for j in np.flatnonzero(rms >= 0.02 * rms.max()))
        assert loaded_joints(r) == expected
        assert make_effect("joint_compliance", r).joints == expected
    assert loaded_joints(robot) == (2, 3, 5)  # the COMAU's: joint 1 vertical, 4 and 6 barely loaded
    assert 7 not in loaded_joints(panda) and 4 in loaded_joints(panda)


def test_campaign_yaml_takes_the_mapping_form_and_writes_it_back(tmp_path, robot):
    run = tmp_path / "run"
    run.mkdir()
    (run / "campaign.yaml").write_text(yaml.safe_dump(
        {"effects": [{"effect": "joint_compliance", "joints": [2, 3, 4]}, "backlash:5", "ground_compliance"]}))
    assert load_config(run).effects == ("joint_compliance:2,3,4", "backlash:5", "ground_compliance")
    folder = RunFolder(run)
    assert folder.add_effects(["joint_compliance:6"]) == ("joint_compliance:2,3,4,6", "backlash:5",
                                                          "ground_compliance")
    written = yaml.safe_load((run / "campaign.yaml").read_text())["effects"]
    assert written[0] == {"effect": "joint_compliance", "joints": [2, 3, 4, 6]} and written[2] == "ground_compliance"
    folder.set_effects(["ground_compliance"])
    assert load_config(run).effects == ("ground_compliance",)


def test_a_bad_mapping_entry_names_the_field(tmp_path):
    (tmp_path / "campaign.yaml").write_text(yaml.safe_dump({"effects": [{"effect": "backlash", "joints": "two"}]}))
    with pytest.raises(ConfigError, match=r"effects\[0\]: backlash: joints must be a list"):
        load_config(tmp_path)


@pytest.mark.parametrize("spec, match", [("joint_compliance:", "no joints after ':'"),
                                         ("joint_compliance:a", "joints 'a' are not joint numbers"),
                                         ("backlash:-1", "joints '-1' are not joint numbers"),
                                         ("my/runout.py:Runout:", "no joints after ':'")])
def test_a_known_effect_with_a_joint_list_that_is_none_says_so_not_unknown_effect(robot, spec, match):
    with pytest.raises(ConfigError, match=match):
        make_effect(spec, robot)
    assert parse_effect_list("joint_compliance:2,,3,,backlash:5") == ("joint_compliance:2,3", "backlash:5")
    assert make_effect("joint_compliance : 4", robot).joints == (4,)  # spaced as in prose: read, not refused
    assert parse_effect_list("joint_compliance : 4, 5,backlash") == ("joint_compliance:4,5", "backlash")


def test_campaign_yaml_joints_as_a_string_a_repeat_an_unknown_field_and_a_joint_too_many(tmp_path, robot):
    def config(entry):
        (tmp_path / "campaign.yaml").write_text(yaml.safe_dump({"robot": "comau_racer5_080", "effects": [entry]}))
        return load_config(tmp_path)

    assert config({"effect": "joint_compliance", "joints": "2, 3,4"}).effects == ("joint_compliance:2,3,4",)
    assert config({"effect": "joint_compliance", "joints": "4"}).effects == ("joint_compliance:4",)
    with pytest.raises(ConfigError, match=r"campaign.yaml: effects\[0\]: joint_compliance: joints \[2, 2\] name a joint twice"):
        config({"effect": "joint_compliance", "joints": [2, 2]})
    with pytest.raises(ConfigError, match=r"effects\[0\]: 'harmonics' is not a field of an effect entry"):
        config({"effect": "cyclic", "joints": [1], "harmonics": [1, 2, 3]})
    # qa31c: this said "joints '2' are not joint numbers", the 2 being one
    with pytest.raises(ConfigError, match=r"campaign.yaml: effects\[0\]: joint_compliance:2: joints given twice, in the "
                                          r"name and as joints: \[3\] \(write \{effect: joint_compliance, joints"):
        config({"effect": "joint_compliance:2", "joints": [3]})
    config({"effect": "joint_compliance", "joints": [7]})  # the robot is not known to the file alone
    with pytest.raises(ConfigError, match=r"campaign.yaml: effects: .*joint 7 is not a joint of COMAU"):
        RunFolder(tmp_path).effects


def test_merging_a_joint_into_a_bare_name_uses_the_robots_default_joints(robot):
    assert merge_effects(["joint_compliance"], ["joint_compliance:4"], robot) == ("joint_compliance:2,3,4,5",)
    assert without_joints("joint_compliance:2,4", [4]) == "joint_compliance:2"
    assert without_joints("joint_compliance:4", [4]) is None
    assert effect_label("joint_compliance:4") == "joint_compliance of joint 4"


def test_the_simulated_truth_hides_an_effect_on_the_joints_it_names(tmp_path):
    (tmp_path / "campaign.yaml").write_text(yaml.safe_dump(
        {"sim": {"hidden_effects": [{"effect": "joint_compliance", "joints": [4], "params": [2e-3]}]}}))
    cfg = load_config(tmp_path)
    assert cfg.hidden_effects() == (("joint_compliance:4", (2e-3,)),)
    assert cfg.as_yaml_dict()["sim"]["hidden_effects"] == [{"effect": "joint_compliance", "joints": [4],
                                                            "params": [2e-3]}]


def test_a_hidden_effect_on_a_joint_the_robot_lacks_names_the_file_and_entry(tmp_path, robot):
    from campaign.measure.session import check_simulated_cell

    (tmp_path / "campaign.yaml").write_text(yaml.safe_dump(
        {"sim": {"hidden_effects": ["ground_compliance", {"effect": "joint_compliance", "joints": [9]}]}}))
    with pytest.raises(ConfigError, match=r"campaign.yaml: sim.hidden_effects\[1\]: .*joint 9 is not a joint of COMAU"):
        check_simulated_cell(load_config(tmp_path), robot)
