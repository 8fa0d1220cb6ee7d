"""The gravity-driven effects against independent computations (issue 11, item 5).

A two-link arm with point masses, written here, on a tilted mount and under a tilted gravity:
its gravity torques and overturning moment by hand (V = −Σ m_i g·p_i, τ = ∂V/∂q, M = Σ m_i p_i × g)
and by Pinocchio's RNEA on its URDF, the mount's rotation and gravity's direction set by hand.
The COMAU: gravity torques by Pinocchio's RNEA on its URDF with robot.yaml's gravity, and
joint_compliance's tool motion by Pinocchio's forward kinematics and frame Jacobian at the
deflected joint angles. (test_effects_user.py sums the COMAU's overturning moment over the
URDF's links.)
"""

import numpy as np
import pinocchio as pin
import pytest
import yaml

from campaign.effects import make_effect
from campaign.effects.base import EffectSet, model_pose
from campaign.effects.gravity import gravity_torques, gravity_vector, overturning_moment
from campaign.effects.joint_compliance import JointCompliance
from campaign.model.kinematics import forward
from campaign.model.robot import RobotModel
from campaign.model.rotations import matrix_to_rotvec, rotvec_to_matrix
from campaign.sim.truth import random_joint_poses

# -- the two-link arm ---------------------------------------------------------------------------
#: link masses (kg) and their points in the link frames (m); joint 2 sits L1 along link 1's x
M1, P1 = 7.0, np.array([0.3, 0.0, 0.0])
M2, P2 = 3.0, np.array([0.2, 0.05, 0.0])
L1 = 0.6
#: joint 1 sits H above the base frame F_I = link "b"; both joints turn about their y axes
H = 0.25
#: F_I in the URDF's root "world" (URDF rpy: R = Rz(yaw) Ry(pitch) Rx(roll))
MOUNT_XYZ, MOUNT_RPY = np.array([0.1, -0.2, 0.3]), (0.3, -0.2, 0.5)
#: gravity in F_I, m/s² (robot.yaml), not along any axis
G_I = np.array([2.0, -1.5, -9.5])
#: the base link's own mass: not carried by joint 1, so not in the moving arm's moment
BASE_MASS, BASE_COM = 20.0, np.array([0.15, 0.1, 0.05])

INERTIA0 = '<inertia ixx="0" ixy="0" ixz="0" iyy="0" iyz="0" izz="0"/>'
TWO_LINK_URDF = f"""<?xml version="1.0"?>
<robot name="two_link">
  <link name="world"/>
  <joint name="mount" type="fixed"><parent link="world"/><child link="b"/>
    <origin xyz="{' '.join(map(str, MOUNT_XYZ))}" rpy="{' '.join(map(str, MOUNT_RPY))}"/></joint>
  <link name="b"><inertial><origin xyz="{' '.join(map(str, BASE_COM))}"/><mass value="{BASE_MASS}"/>{INERTIA0}
    </inertial></link>
  <joint name="j1" type="revolute"><parent link="b"/><child link="l1"/><origin xyz="0 0 {H}"/><axis xyz="0 1 0"/>
    <limit lower="-3" upper="3" effort="100" velocity="1"/></joint>
  <link name="l1"><inertial><origin xyz="{' '.join(map(str, P1))}"/><mass value="{M1}"/>{INERTIA0}</inertial></link>
  <joint name="j2" type="revolute"><parent link="l1"/><child link="l2"/><origin xyz="{L1} 0 0"/><axis xyz="0 1 0"/>
    <limit lower="-3" upper="3" effort="100" velocity="1"/></joint>
  <link name="l2"><inertial><origin xyz="{' '.join(map(str, P2))}"/><mass value="{M2}"/>{INERTIA0}</inertial></link>
  <joint name="tool" type="fixed"><parent link="l2"/><child link="tip"/><origin xyz="0.45 0 0"/></joint>
  <link name="tip"/>
</robot>
"""


@pytest.fixture(scope="module")
def two_link(tmp_path_factory):
    d = tmp_path_factory.mktemp("two_link")
    (d / "two_link.urdf").write_text(TWO_LINK_URDF)
    (d / "robot.yaml").write_text(yaml.safe_dump({"urdf": "two_link.urdf", "name": "two_link", "base_frame": "b",
                                                   "gravity_m_s2": G_I.tolist()}))
    return RobotModel.load(d / "robot.yaml")


@pytest.fixture(scope="module")
def q2():
    return np.random.default_rng(4).uniform(-3, 3, (25, 2))


def rot_y(a):
    """Rotation about y by a (n,) -> (n, 3, 3)."""
    c, s = np.cos(a), np.sin(a)
    R = np.zeros((len(a), 3, 3))
    R[:, 0, 0], R[:, 0, 2], R[:, 1, 1], R[:, 2, 0], R[:, 2, 2] = c, s, 1.0, -s, c
    return R


def d_rot_y(a):
    """d/da of rot_y(a)."""
    c, s = np.cos(a), np.sin(a)
    D = np.zeros((len(a), 3, 3))
    D[:, 0, 0], D[:, 0, 2], D[:, 2, 0], D[:, 2, 2] = -s, c, -c, -s
    return D


def hand_points(q):
    """The two point masses in F_I, (n, 3) each, and their derivatives d p_i / d q_j."""
    q1, q12 = q[:, 0], q[:, 0] + q[:, 1]
    o = np.array([0.0, 0.0, H])
    p1 = o + rot_y(q1) @ P1
    p2 = o + rot_y(q1) @ np.array([L1, 0, 0]) + rot_y(q12) @ P2
    dp = {(1, 1): d_rot_y(q1) @ P1, (1, 2): np.zeros_like(p1),
          (2, 1): d_rot_y(q1) @ np.array([L1, 0, 0]) + d_rot_y(q12) @ P2, (2, 2): d_rot_y(q12) @ P2}
    return (p1, p2), dp


def hand_torques(q):
    """τ_j = ∂V/∂q_j with V = −Σ m_i g·p_i: the torques that hold the arm, (n, 2) N·m."""
    _, dp = hand_points(q)
    return np.stack([-(M1 * dp[1, j] @ G_I + M2 * dp[2, j] @ G_I) for j in (1, 2)], axis=1)


def hand_moment(q):
    """Σ m_i p_i × g over the moving point masses, (n, 3) N·m in F_I (the vertical part of p_i
    adds nothing: it is parallel to g)."""
    (p1, p2), _ = hand_points(q)
    return M1 * np.cross(p1, G_I) + M2 * np.cross(p2, G_I)


def rpy_matrix(roll, pitch, yaw):
    """URDF rpy: Rz(yaw) Ry(pitch) Rx(roll)."""
    def rx(a):
        return np.array([[1, 0, 0], [0, np.cos(a), -np.sin(a)], [0, np.sin(a), np.cos(a)]])

    def ry(a):
        return np.array([[np.cos(a), 0, np.sin(a)], [0, 1, 0], [-np.sin(a), 0, np.cos(a)]])

    def rz(a):
        return np.array([[np.cos(a), -np.sin(a), 0], [np.sin(a), np.cos(a), 0], [0, 0, 1]])

    return rz(yaw) @ ry(pitch) @ rx(roll)


def pinocchio_loads(urdf_path, q, g_root, joint1="j1"):
    """Gravity torques by RNEA (v = a = 0) and joint 1's subtree mass and centre of mass (root
    frame) from Pinocchio's model of the whole URDF, gravity ``g_root`` in its root frame."""
    model = pin.buildModelFromUrdf(str(urdf_path))
    model.gravity.linear = np.asarray(g_root, dtype=float)
    data = model.createData()
    zero = np.zeros(model.nv)
    tau = np.array([pin.rnea(model, data, qi, zero, zero) for qi in q])
    j1 = model.getJointId(joint1)
    com = []
    for qi in q:
        pin.centerOfMass(model, data, qi)
        com.append(data.oMi[j1].act(data.com[j1]))
    return tau, float(data.mass[j1]), np.array(com)


def assert_close(actual, expected, rel=1e-9):
    """Equal to ``rel`` of the largest magnitude of ``expected``."""
    np.testing.assert_allclose(actual, expected, rtol=0, atol=rel * np.abs(expected).max())


def test_two_link_gravity_torques_equal_the_hand_computation_and_pinocchio_rnea(two_link, q2):
    tau_hand = hand_torques(q2)
    assert np.abs(tau_hand).max() > 10  # N·m: a load worth testing
    assert_close(gravity_torques(two_link, q2), tau_hand)
    R_mount = rpy_matrix(*MOUNT_RPY)
    tau_pin, _, _ = pinocchio_loads(two_link.urdf_path, q2, R_mount @ G_I)
    assert_close(tau_pin, tau_hand)  # the reference agrees with the hand computation


def test_two_link_overturning_moment_equals_the_hand_computation_and_pinocchio(two_link, q2):
    M_hand = hand_moment(q2)
    assert_close(overturning_moment(two_link, q2), M_hand)
    R_mount = rpy_matrix(*MOUNT_RPY)
    _, mass, com_root = pinocchio_loads(two_link.urdf_path, q2, R_mount @ G_I)
    com_I = (com_root - MOUNT_XYZ) @ R_mount  # root -> F_I
    assert mass == pytest.approx(M1 + M2, rel=1e-12)  # the base link's mass is not moving
    assert_close(np.cross(com_I, mass * G_I), M_hand)
    # a payload at the tool point adds its own moment about the vertical through F_I's origin
    tool = forward(two_link, q2)[:, :3, 3]
    payload = np.linspace(0.0, 5.0, len(q2))
    assert_close(overturning_moment(two_link, q2, payload, tool),
                 M_hand + payload[:, None] * np.cross(tool, G_I))


def test_joint_compliance_deflects_each_joint_by_its_compliance_times_the_hand_torque(two_link, q2):
    e = JointCompliance(two_link, joints=(1, 2))
    c = np.array([4e-5, -7e-5])
    assert_close(e.joint_offset(c, q2, {}), c * hand_torques(q2))


def test_ground_compliance_tilts_about_its_pivot_by_the_hand_moment(two_link, q2):
    e = make_effect("ground_compliance", two_link)
    up = -G_I / np.linalg.norm(G_I)
    h = e.axes
    np.testing.assert_allclose(h @ h.T, np.eye(2), atol=1e-15)
    np.testing.assert_allclose(h @ up, 0.0, atol=1e-15)  # horizontal: perpendicular to this gravity
    k, pivot_below_m = np.array([2e-5, -3e-5]), 0.4
    params = np.concatenate([k, k * pivot_below_m])  # s_i = k_i · y_p
    T = forward(two_link, q2)
    out = e.pose_map(params, T, q2, {})
    m = hand_moment(q2) @ h.T
    dphi = (k * m) @ h  # rad, in F_I
    assert np.linalg.norm(dphi, axis=1).max() > 5e-4
    R = rotvec_to_matrix(dphi)
    np.testing.assert_allclose(out[:, :3, :3], R @ T[:, :3, :3], atol=1e-13)
    # rotation about the pivot y_p below F_I's origin: the effect is exact to first order in δφ
    pivot = -pivot_below_m * up
    exact = (R @ (T[:, :3, 3] - pivot)[..., None])[..., 0] + pivot
    second_order = 0.5 * np.linalg.norm(dphi, axis=1) ** 2 * pivot_below_m
    assert np.all(np.linalg.norm(out[:, :3, 3] - exact, axis=1) <= second_order * 1.001 + 1e-15)
    assert np.linalg.norm(exact - T[:, :3, 3], axis=1).min() > 100 * second_order.max()


# -- the COMAU -----------------------------------------------------------------------------------

def comau_gravity(robot):
    """Gravity as robot.yaml states it (F_I is the URDF's root for the COMAU)."""
    meta = yaml.safe_load((robot.urdf_path.parent / "robot.yaml").read_text())
    return np.array(meta["gravity_in_I_m_s2"], dtype=float)


@pytest.fixture(scope="module")
def comau_q(robot):
    return random_joint_poses(robot, 20, seed=11)


def test_comau_gravity_torques_and_joint_compliance_equal_pinocchio_rnea_on_its_urdf(robot, comau_q):
    g = comau_gravity(robot)
    np.testing.assert_array_equal(gravity_vector(robot), g)
    tau, _, _ = pinocchio_loads(robot.urdf_path, comau_q, g, joint1="joint1")
    assert np.abs(tau).max() > 20
    assert_close(gravity_torques(robot, comau_q), tau)
    e = make_effect("joint_compliance", robot)
    c = e.typical_params(0)
    expected = np.zeros_like(tau)
    cols = np.array(e.joints) - 1
    expected[:, cols] = c * tau[:, cols]
    assert_close(e.joint_offset(c, comau_q, {}), expected)


def pinocchio_tool(model, data, fid, q):
    """Pose (4, 4) of frame ``fid`` in the root."""
    pin.framesForwardKinematics(model, data, q)
    return data.oMf[fid].homogeneous


def test_joint_compliance_moves_the_tool_as_pinocchio_at_the_deflected_angles(robot, comau_q):
    """The effect's tool pose is Pinocchio's at q + Δq; its displacement is Pinocchio's frame
    Jacobian (itself checked by central differences of Pinocchio's FK) times Δq, to second
    order in Δq."""
    e = make_effect("joint_compliance", robot)
    c = 2 * e.typical_params(0)
    dq = e.joint_offset(c, comau_q, {})
    T_eff = model_pose(robot, comau_q, effects=EffectSet((e,)), theta=c)
    model = pin.buildModelFromUrdf(str(robot.urdf_path))
    data = model.createData()
    fid = model.getFrameId(robot.tool_frame)
    h = 1e-6
    for i, qi in enumerate(comau_q):
        T0, T1 = pinocchio_tool(model, data, fid, qi), pinocchio_tool(model, data, fid, qi + dq[i])
        np.testing.assert_allclose(T_eff[i], T1, atol=1e-12)
        J = pin.computeFrameJacobian(model, data, qi, fid, pin.LOCAL_WORLD_ALIGNED)
        J_fd = np.zeros((6, 6))
        for j in range(6):
            Tp = pinocchio_tool(model, data, fid, qi + h * np.eye(6)[j])
            Tm = pinocchio_tool(model, data, fid, qi - h * np.eye(6)[j])
            J_fd[:3, j] = (Tp[:3, 3] - Tm[:3, 3]) / (2 * h)
            J_fd[3:, j] = matrix_to_rotvec(Tp[:3, :3] @ Tm[:3, :3].T) / (2 * h)
        np.testing.assert_allclose(J, J_fd, atol=1e-8)
        # |Δp − J Δq| <= ½ N r |Δq|² (r = 1 m bounds every lever of the 0.8 m arm with its tool)
        bound = 0.5 * 6 * 1.0 * (dq[i] @ dq[i])
        assert np.linalg.norm(T_eff[i][:3, 3] - T0[:3, 3] - J[:3] @ dq[i]) <= bound
        dphi = matrix_to_rotvec(T_eff[i][:3, :3] @ T0[:3, :3].T)
        assert np.linalg.norm(dphi - J[3:] @ dq[i]) <= bound
    assert np.linalg.norm(T_eff[:, :3, 3] - forward(robot, comau_q)[:, :3, 3], axis=1).max() > 2e-4  # m
