"""Where in the chain the error arises: the rotation residual in the frame after each joint.

The frames of the unit test are Pinocchio's (from the URDF), not ours; the effects of the
end-to-end tests are written here, hidden by the generator, and the truth is looked at only
after diagnose answered.
"""

import json

import numpy as np
import pinocchio as pin
import pytest

from campaign.cli import main
from campaign.diagnose import diagnose
from campaign.diagnose.chain import ChainStructure, chain_structure, with_rotation_first
from campaign.effects import Effect
from campaign.model.robot import RobotModel
from test_diagnose_open_world import make_open_run


def pinocchio_joint_rotations(robot, q):
    """(n, N, 3, 3): each pose's frame of each moving joint, after its motion, from Pinocchio."""
    model = robot.pinocchio_model
    data = model.createData()
    ids = [model.getJointId(name) for name in robot.joint_names]
    out = np.empty((len(q), len(ids), 3, 3))
    for i, qi in enumerate(robot.pinocchio_q(q)):
        pin.forwardKinematics(model, data, qi)
        out[i] = [data.oMi[j].rotation for j in ids]
    return out


def folds_of(n, k, rng):
    fold = np.arange(n) % k
    rng.shuffle(fold)
    return fold


def rotation_data(robot, n, rng, amplitude_rad, noise_rad, joint=4):
    """Joint angles, a time column, folds, and a rotation error that arises at ``joint``: its axis
    tilts about x of its own frame by a sin(q) + b cos(q) of its own angle, seen in the base frame
    (fold fits' residuals and held-out residuals with their own noise)."""
    q = rng.uniform(robot.q_lower, robot.q_upper, size=(n, robot.n_joints))
    t = np.sort(rng.uniform(0, 3600, n))
    R = pinocchio_joint_rotations(robot, q)
    qj = q[:, joint - 1]
    tilt = amplitude_rad * (0.8 * np.sin(qj) + 0.6 * np.cos(qj))
    omega = tilt[:, None] * R[:, joint - 1, :, 0]  # about x of the joint's frame, in the base frame
    fold = folds_of(n, 5, rng)
    out = omega + rng.normal(0, noise_rad, omega.shape)
    fit = {k: omega[fold != k] + rng.normal(0, noise_rad, (int((fold != k).sum()), 3)) for k in range(5)}
    X = np.column_stack([q, t])
    names = tuple(f"q{j + 1}" for j in range(robot.n_joints)) + ("time_s",)
    return R, X, names, fold, fit, out, omega


def test_a_tilt_of_joint_4_is_found_on_q4_alone_in_a_frame_next_to_it():
    robot = RobotModel.load()
    rng = np.random.default_rng(4)
    R, X, names, fold, fit, out, omega = rotation_data(robot, 300, rng, 1e-3, 1e-4)
    c = chain_structure(R, X, names, 6, fold, fit, out, alpha=0.01, detection=0.02)
    assert c.significant and c.p_value < 1e-10, c
    assert c.depends_on(0.05)[0] == "q4" and c.result.importance["q4"] > 0.8, c.result.importance
    # in the frame after joint 3 the tilt is Rz(q4) times a function of q4: q4 alone there too
    assert c.joint in (3, 4), c.gains
    # in the frame after joint 1, the base and the tool, the joints between turn it: it predicts less
    assert c.gains[c.joint - 1] > c.gains[0] + 0.2 and c.gains[c.joint - 1] > c.gains[5] + 0.2, c.gains
    # what knowing the tilt exactly would reach: the noise alone left
    exact = 1 - np.linalg.norm(out - omega, axis=1).mean() / np.linalg.norm(out, axis=1).mean()
    assert 0.9 * exact < c.heldout_gain <= exact + 0.01, (c.heldout_gain, exact)
    doc = c.as_json()
    assert doc["joint"] == c.joint and set(doc["gain_by_joint_frame"]) == {f"J{j}" for j in range(1, 7)}


def test_noise_alone_is_no_rotation_structure():
    robot = RobotModel.load()
    rng = np.random.default_rng(5)
    R, X, names, fold, fit, out, _ = rotation_data(robot, 300, rng, 0.0, 1e-4)
    c = chain_structure(R, X, names, 6, fold, fit, out, alpha=0.01, detection=0.02)
    assert not c.significant and c.p_value > 0.01, c


class AxisTilt(Effect):
    """A joint's bearing: its axis tilts about x of its frame by a sin(q) + b cos(q) of its own angle."""

    name = "axis_tilt"
    description = "bearing run-out"
    joint = 5
    param_names = ("a", "b")
    param_units = ("rad", "rad")

    def joint_twist(self, params, q, context):
        xi = np.zeros((len(q), q.shape[1], 6))
        u = q[:, self.joint - 1]
        xi[:, self.joint - 1, 3] = params[0] * np.sin(u) + params[1] * np.cos(u)
        return xi


class WristTilt5(AxisTilt):
    name, joint = "wrist_tilt_5", 5


class ElbowTilt3(AxisTilt):
    name, joint = "elbow_tilt_3", 3


def test_a_wrist_tilt_is_unexplained_with_its_own_joint_first(tmp_path, robot, capsys):
    run, _, _ = make_open_run(tmp_path, robot, [WristTilt5(robot)], [6e-4, -4e-4], n=260, bursts=10)
    d = diagnose(run, folds=4, candidates="cyclic,joint_compliance,backlash")
    assert d.verdict == "unexplained", d.text()
    assert d.chain_significant and d.depends_on[0] == "q5", d.text()
    capsys.readouterr()
    assert main(["diagnose", str(run), "--json", "--folds", "4", "--candidates", "cyclic,joint_compliance,backlash"]) == 0
    out = json.loads(capsys.readouterr().out)
    rot = out["unexplained"]["rotation"]
    assert rot["significant"] is True and rot["joint"] in (4, 5) and out["unexplained"]["depends_on"][0] == "q5"
    assert all(c["heldout_mean_rotation_mrad_before"] > 0 for c in out["ranking"])
    svg = (run / "diagnose" / "rotation.svg").read_text()  # the picture of it, in the report
    assert "q5 [deg]" in svg and "[µrad]" in svg and "rotation.svg" in (run / "diagnose" / "report.html").read_text()


def test_a_candidate_that_makes_the_rotation_worse_is_not_named(tmp_path):
    """A tilt of the UR10's elbow axis: cyclic of joint 3 fits part of its position error by a
    rotation about joint 3's axis that the robot does not have."""
    ur10 = RobotModel.load("ur10")
    run, _, _ = make_open_run(tmp_path, ur10, [ElbowTilt3(ur10)], [8e-4, 5e-4], n=260, bursts=10, seed=6,
                              robot_name="ur10")
    d = diagnose(run, folds=4, candidates="cyclic,joint_compliance,backlash")
    assert d.verdict == "unexplained" and d.depends_on[0] == "q3", d.text()
    cyclic = next(c for c in d.ranking if c.effect == "cyclic")
    assert not cyclic.significant, d.text()
    assert cyclic.p_value < 1e-6 and cyclic.gain > 0.1, d.text()  # it fits the position ...
    assert cyclic.rotation_p_worse < 0.01, d.text()  # ... and the rotation says no
    assert "at the rotation's expense" in d.text()


def test_a_weak_rotation_beside_a_strong_position_structure_does_not_lead():
    """The rotation test's inputs come first only when it predicts at least half the share of its
    own error that the position test predicts of the position error."""
    robot = RobotModel.load()
    rng = np.random.default_rng(4)
    R, X, names, fold, fit, out, _ = rotation_data(robot, 300, rng, 1e-3, 1e-4)
    c = chain_structure(R, X, names, 6, fold, fit, out, alpha=0.01, detection=0.02)
    assert isinstance(c, ChainStructure) and c.significant and c.depends_on(0.05)[0] == "q4"
    position = ["q2", "q3", "q1"]
    assert with_rotation_first(position, c, 0.05)[0] == "q4"  # no position test: the rotation leads
    assert with_rotation_first(position, c, 0.05, position_gain=c.heldout_gain)[0] == "q4"
    assert with_rotation_first(position, c, 0.05, position_gain=1.9 * c.heldout_gain)[0] == "q4"
    assert with_rotation_first(position, c, 0.05, position_gain=2.1 * c.heldout_gain) == position


def test_the_rotation_veto_holds_unless_a_candidate_explains_the_rotation_error():
    """A candidate that makes the rotation worse (p < 0.01) is not significant, with or without a
    rotation structure; except when the rotation test finds one that another candidate takes half of."""
    from dataclasses import replace

    from campaign.diagnose.engine import CandidateScore, rotation_veto

    worse = CandidateScore("joint_compliance", 0.0766, 0.0570, 1e-9, True, 0.4, spec="joint_compliance:3,4",
                           heldout_mean_rotation_mrad_before=0.304, heldout_mean_rotation_mrad_after=0.322,
                           rotation_p_worse=0.0048)
    other = replace(worse, effect="ground_compliance", spec="ground_compliance", heldout_mean_rotation_mrad_after=0.30,
                    rotation_p_worse=0.9)
    for chain in (None, ChainStructure(2, None, (0.0,) * 6, 1.0, False)):
        out = rotation_veto([worse, other], chain)
        assert not out[0].significant and out[0].rotation_veto and out[1].significant
    rot = type("R", (), {"heldout_gain": 0.6})()
    chain = ChainStructure(4, rot, (0.6,) * 6, 1e-20, True)
    assert rotation_veto([worse, other], chain)[0].rotation_veto  # none takes half of it: vetoed
    explains = replace(other, heldout_mean_rotation_mrad_after=0.12)  # 61 % of the rotation error
    assert not rotation_veto([worse, explains], chain)[0].rotation_veto


def test_without_a_measured_rotation_the_rotation_test_says_it_did_not_run(tmp_path, capsys):
    """One reflector per pose (a point, no rotation): diagnose says the rotation test did not run and
    what that leaves untold, rather than passing the position test's ranking on as the whole answer."""
    csv = tmp_path / "p.csv"
    assert main(["synth", "--csv", str(csv), "--robot", "ur10", "--poses", "120", "--seed", "1", "--kind", "point",
                 "--frame", "tracker"]) == 0
    assert main(["import", str(csv), "--run", str(tmp_path / "r"), "--robot", "ur10", "--frame", "tracker"]) == 0
    d = diagnose(tmp_path / "r", folds=4, candidates="cyclic")
    assert d.chain is None and d.structure is not None
    assert "rotation test: not run (fewer than three reflectors per pose" in d.text()
    assert d.as_json()["unexplained"]["rotation"] is None
