import numpy as np
import pinocchio as pin
import pytest

from campaign.model.kinematics import N_PARAMS, PARAM_NAMES, error_jacobian, forward, frames, pose_error
from campaign.model.rotations import rot_x, rot_y, rot_z


def naive_T_IE(robot, q, p):
    """Independent reference: one 4x4 product per transform, eqs. (6)-(12) written out."""
    T = np.eye(4)
    for k in range(8):
        a, b, c = p[6 * k + 3 : 6 * k + 6]
        if 1 <= k <= 6:
            c = c + q[k - 1]
        A = np.eye(4)
        A[:3, :3] = robot.R_nominal[k] @ rot_x(a) @ rot_y(b) @ rot_z(c)
        A[:3, 3] = robot.t_nominal[k] + p[6 * k : 6 * k + 3]
        T = T @ A
    return T


def test_parameter_names_follow_table2():
    assert len(PARAM_NAMES) == 48
    assert PARAM_NAMES[:6] == ("pL_I0_x", "pL_I0_y", "pL_I0_z", "pR_I0_x", "pR_I0_y", "pR_I0_z")
    assert PARAM_NAMES[6:12] == ("pL_01_x", "pL_01_y", "pL_01_z", "pR_01_x", "pR_01_y", "pq1")
    assert PARAM_NAMES[-1] == "pR_6E_z"


def test_nominal_fk_equals_pinocchio_to_1e12(robot, rng):
    q = rng.uniform(robot.q_lower, robot.q_upper, size=(200, 6))
    T = forward(robot, q)
    model = robot.pinocchio_model
    data = model.createData()
    fid = model.getFrameId("E")
    for i in range(len(q)):
        pin.framesForwardKinematics(model, data, q[i])
        M = data.oMf[fid]
        assert np.max(np.abs(M.translation - T[i, :3, 3])) < 1e-12
        assert np.max(np.abs(M.rotation - T[i, :3, :3])) < 1e-12


def test_fk_with_errors_equals_independent_product(robot, rng):
    q = rng.uniform(robot.q_lower, robot.q_upper, size=(50, 6))
    p = rng.normal(0, 2e-3, N_PARAMS)
    T = forward(robot, q, p)
    for i in range(len(q)):
        np.testing.assert_allclose(T[i], naive_T_IE(robot, q[i], p), atol=1e-14)


def test_chunking_does_not_change_results(robot, rng):
    q = rng.uniform(robot.q_lower, robot.q_upper, size=(1000, 6))
    p = rng.normal(0, 1e-3, N_PARAMS)
    np.testing.assert_array_equal(forward(robot, q, p, chunk=97), forward(robot, q, p))
    np.testing.assert_allclose(error_jacobian(robot, q, p, chunk=33), error_jacobian(robot, q, p), atol=0)


def test_frames_end_in_tool_pose(robot, rng):
    q = rng.uniform(robot.q_lower, robot.q_upper, size=(10, 6))
    R, t = frames(robot, q)
    T = forward(robot, q)
    np.testing.assert_allclose(R[:, 7], T[:, :3, :3], atol=1e-15)
    np.testing.assert_allclose(t[:, 7], T[:, :3, 3], atol=1e-15)


def test_identification_jacobian_matches_central_differences(robot, rng):
    q = rng.uniform(robot.q_lower, robot.q_upper, size=(8, 6))
    p = rng.normal(0, 1e-3, N_PARAMS)
    T_meas = forward(robot, q, rng.normal(0, 3e-3, N_PARAMS))
    J = error_jacobian(robot, q, p, T_meas)
    h = 1e-6
    J_fd = np.empty_like(J)
    for j in range(N_PARAMS):
        d = np.zeros(N_PARAMS)
        d[j] = h
        J_fd[:, :, j] = (pose_error(forward(robot, q, p + d), T_meas) - pose_error(forward(robot, q, p - d), T_meas)) / (2 * h)
    np.testing.assert_allclose(J, J_fd, atol=1e-8)


def test_pose_error_is_zero_for_identical_poses_and_signed_model_minus_measured(robot, rng):
    q = rng.uniform(robot.q_lower, robot.q_upper, size=(5, 6))
    T = forward(robot, q)
    np.testing.assert_allclose(pose_error(T, T), 0.0, atol=1e-15)
    T2 = T.copy()
    T2[:, 0, 3] += 1e-3
    np.testing.assert_allclose(pose_error(T, T2)[:, 0], -1e-3, atol=1e-15)


def test_bad_shapes_are_rejected(robot):
    with pytest.raises(ValueError, match=r"\(n, 6\)"):
        forward(robot, np.zeros((3, 5)))
    with pytest.raises(ValueError, match=r"\(48,\)"):
        forward(robot, np.zeros((3, 6)), np.zeros(47))
