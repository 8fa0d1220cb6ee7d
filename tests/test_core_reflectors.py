import numpy as np
import pytest

from campaign.errors import DataError
from campaign.measure.reflectors import (frame_from_setup_points, invert, kabsch, pose_from_reflectors,
                                         transform_points)
from campaign.model.kinematics import forward
from campaign.model.rotations import rotvec_to_matrix


def random_T(rng, n=None):
    shape = () if n is None else (n,)
    T = np.zeros(shape + (4, 4))
    T[..., :3, :3] = rotvec_to_matrix(rng.normal(size=shape + (3,)))
    T[..., :3, 3] = rng.normal(size=shape + (3,))
    T[..., 3, 3] = 1
    return T


def test_kabsch_recovers_an_exact_rigid_transform(rng):
    P = rng.normal(size=(3, 3)) * 0.1
    T = random_T(rng, 50)
    np.testing.assert_allclose(kabsch(P, transform_points(T, np.broadcast_to(P, (50, 3, 3)))), T, atol=1e-12)


def test_kabsch_never_returns_a_reflection(rng):
    P = rng.normal(size=(3, 3))
    mirrored = P * np.array([1, 1, -1])
    T = kabsch(P, mirrored[None])
    assert np.linalg.det(T[0, :3, :3]) > 0


def test_setup_points_define_T_LI(rng):
    T_LI = random_T(rng)
    pts_I = np.array([[0, 0, 0], [0.3, 0, 0], [0.05, 0.3, 0]])  # y point off-axis: only its plane matters
    pts_L = transform_points(T_LI, pts_I)
    np.testing.assert_allclose(frame_from_setup_points(*pts_L), T_LI, atol=1e-12)


def test_degenerate_setup_points_are_rejected():
    with pytest.raises(DataError, match="on the x axis"):
        frame_from_setup_points([0, 0, 0], [1, 0, 0], [2, 0, 0])


def test_pose_from_noise_free_reflectors_is_exact(robot, rng):
    q = rng.uniform(robot.q_lower, robot.q_upper, size=(20, 6))
    T_IE = forward(robot, q)
    T_LI = random_T(rng)
    P_L = transform_points(T_LI @ T_IE, np.broadcast_to(robot.reflector_positions_in_E, (20, 3, 3)))
    T, rms = pose_from_reflectors(T_LI, robot.reflector_positions_in_E, P_L)
    np.testing.assert_allclose(T, T_IE, atol=1e-12)
    assert rms.max() < 1e-12
    np.testing.assert_allclose(invert(invert(T_LI)), T_LI, atol=1e-15)
