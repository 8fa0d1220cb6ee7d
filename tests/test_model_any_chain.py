"""Any serial chain from a URDF (issue 12, item 1): checked against Pinocchio on URDFs we did not
write (example-robot-data: UR10 with y-axis joints, Panda 7R, TIAGo with a prismatic torso),
against URDF text with perturbed joint origins, and against finite differences."""

import re
from importlib import metadata
from pathlib import Path

import numpy as np
import pinocchio as pin
import pytest

from campaign.errors import ConfigError
from campaign.model.base_params import base_parameters
from campaign.model.kinematics import PARAM_NAMES, error_jacobian, forward, frames, pose_error
from campaign.model.robot import RobotModel


def _erd(rel):
    try:
        dist = metadata.distribution("example-robot-data")
    except metadata.PackageNotFoundError:
        pytest.skip("example-robot-data (test extra) is not installed")
    path = Path(dist.locate_file("cmeel.prefix/share/example-robot-data/robots")) / rel
    if not path.is_file():
        pytest.skip(f"{rel} not in example-robot-data")
    return path


UR10 = "ur_description/urdf/ur10_robot.urdf"
PANDA = "panda_description/urdf/panda.urdf"
TIAGO = "tiago_description/robots/tiago.urdf"


@pytest.fixture(scope="module")
def ur10():
    return RobotModel.load(_erd(UR10), tool_frame="tool0")


@pytest.fixture(scope="module")
def panda():
    return RobotModel.load(_erd(PANDA))


@pytest.fixture(scope="module")
def tiago():
    return RobotModel.load(_erd(TIAGO), base_frame="base_footprint", tool_frame="arm_tool_link")


def _pin_fk(urdf, q_by_name, frame, base=None):
    """Pose of ``frame`` (in ``base`` or the root) from Pinocchio's full model of ``urdf``."""
    model = pin.buildModelFromUrdf(str(urdf))
    data = model.createData()
    qp = pin.neutral(model)
    for name, v in q_by_name.items():
        j = model.joints[model.getJointId(name)]
        if j.nq == 1:
            qp[j.idx_q] = v
        else:
            qp[j.idx_q:j.idx_q + 2] = (np.cos(v), np.sin(v))
    pin.framesForwardKinematics(model, data, qp)
    M = data.oMf[model.getFrameId(frame)]
    if base is not None:
        M = data.oMf[model.getFrameId(base)].inverse() * M
    return M.homogeneous


@pytest.mark.parametrize("which", ["ur10", "panda", "tiago"])
def test_nominal_fk_equals_pinocchio(which, request, rng):
    robot = request.getfixturevalue(which)
    q = rng.uniform(robot.q_lower, robot.q_upper, size=(25, robot.n_joints))
    T = forward(robot, q)
    for i in range(len(q)):
        ref = _pin_fk(robot.urdf_path, dict(zip(robot.joint_names, q[i])), robot.tool_frame,
                      None if which != "tiago" else "base_footprint")
        np.testing.assert_allclose(T[i], ref, atol=1e-12)


def test_chains_found_in_the_urdfs(ur10, panda, tiago):
    assert ur10.n_joints == 6 and ur10.n_params == 48 and ur10.base_frame == "world"
    np.testing.assert_allclose(ur10.gravity_in_root, [0, 0, -9.81])  # default: -z of the root
    assert panda.n_joints == 7 and panda.n_params == 54
    assert panda.tool_frame == "panda_hand"  # the walk stops where the fingers branch off
    assert tiago.n_joints == 8 and tiago.joint_types[0] == "prismatic"
    assert tiago.joint_names[0] == "torso_lift_joint" and tiago.joint_names[-1] == "arm_7_joint"
    assert tiago.param_names[6:12] == ("pL_01_x", "pL_01_y", "pR_01_z", "pR_01_x", "pR_01_y", "pd1")
    assert tiago.joint_frame_index == tuple(range(1, 9))
    R, t = frames(panda, np.zeros((1, 7)))
    assert R.shape == (1, 9, 3, 3) and t.shape == (1, 9, 3)


def test_comau_parameters_unchanged(robot):
    assert robot.param_names == PARAM_NAMES and robot.n_params == 48 and robot.n_joints == 6
    assert robot.joint_frame_index == (1, 2, 3, 4, 5, 6)
    assert robot.tool_frame == "E" and robot.base_frame == "I"
    np.testing.assert_allclose(robot.gravity_in_root, [0, 9.81, 0])


def _perturbed(urdf_text, joint, xyz_delta=(0, 0, 0), rpy_delta=(0, 0, 0)):
    """URDF text with joint's origin xyz and rpy shifted."""
    pat = re.compile(r'(<joint name="%s".*?<origin )(rpy="([^"]*)" xyz="([^"]*)")' % re.escape(joint), re.S)
    m = pat.search(urdf_text)
    rpy = np.array(m.group(3).split(), dtype=float) + rpy_delta
    xyz = np.array(m.group(4).split(), dtype=float) + xyz_delta
    new = 'rpy="%s" xyz="%s"' % (" ".join(repr(float(v)) for v in rpy), " ".join(repr(float(v)) for v in xyz))
    return urdf_text[:m.start(2)] + new + urdf_text[m.end(2):]


def test_perturbed_urdf_origins_equal_the_error_parameters(ur10, tmp_path, rng):
    """UR10 (joint axes along y and z of their links): shift the elbow's and wrist_2's origins by
    d, d2 (in their parent links); tilt the elbow's origin about x; turn it about its own axis y.
    The model's pL, pR_x and pq then reproduce the edited URDF exactly."""
    original = Path(ur10.urdf_path).read_text()
    d, d2, e, z = np.array([1e-3, -2e-3, 0.5e-3]), np.array([-0.7e-3, 0.3e-3, 1.1e-3]), 2e-3, 1.5e-3
    k = ur10.joint_names.index("elbow_joint") + 1
    k2 = ur10.joint_names.index("wrist_2_joint") + 1
    q = rng.uniform(ur10.q_lower, ur10.q_upper, size=(40, 6))
    f = tmp_path / "ur10_perturbed.urdf"
    f.write_text(_perturbed(_perturbed(original, "elbow_joint", d), "wrist_2_joint", d2))
    p = np.zeros(ur10.n_params)
    # both joints follow a joint with its own axis alignment S: link = model frame · Sᵀ
    p[6 * k:6 * k + 3] = ur10.axis_alignment[k - 2].T @ d
    p[6 * k2:6 * k2 + 3] = ur10.axis_alignment[k2 - 2].T @ d2
    np.testing.assert_allclose(forward(ur10, q, p), forward(RobotModel.load(f, tool_frame="tool0"), q), atol=1e-13)
    # the elbow's axis is y and its model frame is link · Rx(-pi/2): a tilt about the link's x is
    # pR_x, a turn about y is the zero offset pq
    for rpy, slot, value in (((e, 0, 0), 3, e), ((0, z, 0), 5, z)):
        f.write_text(_perturbed(original, "elbow_joint", rpy_delta=rpy))
        pr = np.zeros(ur10.n_params)
        pr[6 * k + slot] = value
        np.testing.assert_allclose(forward(ur10, q, pr), forward(RobotModel.load(f, tool_frame="tool0"), q),
                                   atol=1e-13)


def _fd_jacobian(robot, q, p, T_meas, h=1e-6):
    J = np.empty((len(q), 6, robot.n_params))
    for j in range(robot.n_params):
        dp = np.zeros(robot.n_params)
        dp[j] = h
        J[:, :, j] = (pose_error(forward(robot, q, p + dp), T_meas)
                      - pose_error(forward(robot, q, p - dp), T_meas)) / (2 * h)
    return J


@pytest.mark.parametrize("which", ["panda", "tiago"])
def test_error_jacobian_matches_central_differences(which, request, rng):
    robot = request.getfixturevalue(which)
    q = rng.uniform(robot.q_lower, robot.q_upper, size=(6, robot.n_joints))
    p = rng.normal(0, 1e-3, robot.n_params)
    T_meas = forward(robot, q, rng.normal(0, 3e-3, robot.n_params))
    J = error_jacobian(robot, q, p, T_meas)
    np.testing.assert_allclose(J, _fd_jacobian(robot, q, p, T_meas), atol=1e-8)


def test_zero_offset_columns_are_the_joint_derivatives(tiago, rng):
    q = rng.uniform(tiago.q_lower, tiago.q_upper, size=(5, tiago.n_joints))
    p = rng.normal(0, 1e-3, tiago.n_params)
    J = error_jacobian(tiago, q, p)[:, :, list(tiago.joint_offset_index)]
    h = 1e-6
    T0 = forward(tiago, q, p)
    for j in range(tiago.n_joints):
        dq = np.zeros_like(q)
        dq[:, j] = h
        fd = (pose_error(forward(tiago, q + dq, p), T0) - pose_error(forward(tiago, q - dq, p), T0)) / (2 * h)
        np.testing.assert_allclose(J[:, :, j], fd, atol=1e-8)


def test_joint_twists_equal_a_product_of_exponentials(panda, rng):
    """forward(joint_twists=ξ) against frames(): T = F_j exp(ξ_j) ... built pose by pose."""
    from scipy.linalg import expm

    q = rng.uniform(panda.q_lower, panda.q_upper, size=(4, 7))
    p = rng.normal(0, 1e-3, panda.n_params)
    xi = rng.normal(0, 2e-3, size=(4, 7, 6))
    T = forward(panda, q, p, joint_twists=xi)
    for i in range(4):
        R, t = frames(panda, q[i:i + 1], p)
        M = np.eye(4)
        prev = np.eye(4)
        for k in range(9):
            F = np.eye(4)
            F[:3, :3], F[:3, 3] = R[0, k], t[0, k]
            M = M @ np.linalg.solve(prev, F)
            prev = F
            if 1 <= k <= 7:
                v, w = xi[i, k - 1, :3], xi[i, k - 1, 3:]
                X = np.zeros((4, 4))
                X[:3, :3] = [[0, -w[2], w[1]], [w[2], 0, -w[0]], [-w[1], w[0], 0]]
                X[:3, 3] = v
                M = M @ expm(X)
        np.testing.assert_allclose(T[i], M, atol=1e-13)
    J = error_jacobian(panda, q, p, joint_twists=xi)
    T_meas = forward(panda, q, p, joint_twists=xi)
    h = 1e-6
    for j in (0, 11, 17, 40, 53):
        dp = np.zeros(panda.n_params)
        dp[j] = h
        fd = (pose_error(forward(panda, q, p + dp, joint_twists=xi), T_meas)
              - pose_error(forward(panda, q, p - dp, joint_twists=xi), T_meas)) / (2 * h)
        np.testing.assert_allclose(J[:, :, j], fd, atol=1e-8)


@pytest.mark.parametrize("which", ["ur10", "panda", "tiago"])
def test_base_parameter_count_equals_the_rank_of_the_finite_difference_regressor(which, request, rng):
    robot = request.getfixturevalue(which)
    b = base_parameters(robot, n_poses=60)
    q = rng.uniform(robot.q_lower, robot.q_upper, size=(60, robot.n_joints))
    T = forward(robot, q)
    W = _fd_jacobian(robot, q, np.zeros(robot.n_params), T, h=1e-7).reshape(-1, robot.n_params)
    W = W / np.maximum(np.linalg.norm(W, axis=0), 1e-300)
    s = np.linalg.svd(W, compute_uv=False)
    assert b.n_base == int(np.sum(s > 1e-6 * s[0]))
    assert len(b.names) == b.n_base and all(n in robot.param_names for n in b.names)
    assert f"of {robot.n_params}" in b.table()


@pytest.mark.parametrize("which", ["ur10", "tiago"])
def test_exported_urdf_reproduces_the_identified_model(which, request, rng, tmp_path):
    import yourdfpy

    from campaign.model.export import write_calibrated_urdf

    robot = request.getfixturevalue(which)
    p = rng.normal(0, 2e-3, robot.n_params)
    out = write_calibrated_urdf(robot, p, tmp_path / "calibrated.urdf")
    yourdfpy.URDF.load(str(out), load_meshes=False)
    q = rng.uniform(robot.q_lower, robot.q_upper, size=(30, robot.n_joints))
    T = forward(robot, q, p)
    base = "base_footprint" if which == "tiago" else None
    for i in range(len(q)):
        ref = _pin_fk(out, dict(zip(robot.joint_names, q[i])), robot.tool_frame, base)
        assert np.max(np.abs(ref[:3, 3] - T[i, :3, 3])) < 1e-6
        assert np.max(np.abs(ref[:3, :3] - T[i, :3, :3])) < 1e-6
    again = RobotModel.load(out, tool_frame=robot.tool_frame, base_frame=robot.base_frame)
    np.testing.assert_allclose(forward(again, q), T, atol=1e-9)


def test_exported_comau_urdf_and_a_tool_on_the_last_joints_link(robot, rng, tmp_path):
    from campaign.model.export import write_calibrated_urdf

    p = rng.normal(0, 2e-3, 48)
    out = write_calibrated_urdf(robot, p, tmp_path / "comau.urdf")
    q = rng.uniform(robot.q_lower, robot.q_upper, size=(20, 6))
    again = RobotModel.load(out, tool_frame="E")
    np.testing.assert_allclose(forward(again, q), forward(robot, q, p), atol=1e-9)
    # tool frame = the last moving joint's child (no fixed joint to carry the tool's error)
    bare = RobotModel.load(robot.urdf_path, tool_frame="link6")
    out2 = write_calibrated_urdf(bare, p, tmp_path / "bare.urdf")
    np.testing.assert_allclose(forward(RobotModel.load(out2, tool_frame="link6"), q), forward(bare, q, p), atol=1e-9)


def test_bad_urdfs_are_one_line_naming_file_and_element(tmp_path, robot):
    text = Path(robot.urdf_path).read_text()
    bad = tmp_path / "bad.urdf"
    bad.write_text(text.replace('<origin xyz="0.37 0 0"', '<origin xyz="abc"', 1))
    with pytest.raises(ConfigError, match=r"bad\.urdf.*joint 'joint3'.*xyz=\"abc\""):
        RobotModel.load(bad)
    with pytest.raises(ConfigError, match=r"tool frame 'nope' is not a link"):
        RobotModel.load(robot.urdf_path, tool_frame="nope")
    with pytest.raises(ConfigError, match=r"not below base frame 'link3'.*no serial path"):
        RobotModel.load(robot.urdf_path, base_frame="link3", tool_frame="link1")
    with pytest.raises(ConfigError, match=r"robot 'no_such_robot'"):
        RobotModel.load("no_such_robot")
    with pytest.raises(ConfigError, match="branches"):
        RobotModel.load(_erd(TIAGO))


def test_robot_yaml_extras(tmp_path, robot):
    (tmp_path / "arm.urdf").write_text(Path(robot.urdf_path).read_text())
    (tmp_path / "robot.yaml").write_text(
        "urdf: arm.urdf\ntool_frame: link6\n"
        "controller: {sign: [1, -1, 1, 1, 1], offset: [0, 0.1, 0, 0, 0]}\n"
        "locked_joints: {joint6: 0.5}\n"
        "reflectors:\n  - {name: a, position_m: [0.1, 0, 0]}\n  - {name: b, position_m: [0, 0.1, 0]}\n")
    r = RobotModel.load(tmp_path)
    assert r.n_joints == 5 and r.n_params == 42  # joint6 locked
    np.testing.assert_allclose(r.gravity_in_root, [0, 0, -9.81])
    np.testing.assert_allclose(r.to_model_q([[0.2, 0.3, 0, 0, 0]]), [[0.2, -0.2, 0, 0, 0]])
    np.testing.assert_allclose(r.to_controller_q(r.to_model_q([[0.2, 0.3, 0, 0, 0]])), [[0.2, 0.3, 0, 0, 0]])
    np.testing.assert_allclose(r.reflector_positions_in_E, [[0.1, 0, 0], [0, 0.1, 0]])
    # the locked joint is folded at 0.5 rad: equal to the full model at q6 = 0.5
    q = np.random.default_rng(1).uniform(robot.q_lower[:5], robot.q_upper[:5], size=(5, 5))
    full = RobotModel.load(robot.urdf_path, tool_frame="link6")
    np.testing.assert_allclose(forward(r, q), forward(full, np.c_[q, np.full(5, 0.5)]), atol=1e-13)
    bad = tmp_path / "bad"
    bad.mkdir()
    (bad / "arm.urdf").write_text(Path(robot.urdf_path).read_text())
    (bad / "robot.yaml").write_text("urdf: arm.urdf\nlocked_joints: {jointX: 1}\n")
    with pytest.raises(ConfigError, match="locked_joints names 'jointX'"):
        RobotModel.load(bad)
