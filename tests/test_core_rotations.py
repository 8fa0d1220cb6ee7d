import numpy as np
import pytest

from campaign.model import rotations as rot


def test_cardan_is_intrinsic_xyz_product(rng):
    a, b, c = rng.uniform(-3, 3, 3)
    expected = rot.rot_x(a) @ rot.rot_y(b) @ rot.rot_z(c)
    np.testing.assert_allclose(rot.cardan_xyz(a, b, c), expected, atol=1e-15)


def test_urdf_rpy_is_fixed_axis_zyx_product(rng):
    r, p, y = rng.uniform(-3, 3, 3)
    np.testing.assert_allclose(rot.urdf_rpy(r, p, y), rot.rot_z(y) @ rot.rot_y(p) @ rot.rot_x(r), atol=1e-15)


def test_cardan_to_rpy_round_trips_to_the_same_rotation(rng):
    abc = rng.uniform([-np.pi, -np.pi / 2, -np.pi], [np.pi, np.pi / 2, np.pi], size=(200, 3))
    rpy = rot.cardan_to_rpy(abc)
    R_cardan = rot.cardan_xyz(abc[:, 0], abc[:, 1], abc[:, 2])
    np.testing.assert_allclose(rot.urdf_rpy(rpy[:, 0], rpy[:, 1], rpy[:, 2]), R_cardan, atol=1e-12)
    np.testing.assert_allclose(rot.rpy_to_cardan(rpy), abc, atol=1e-10)


def test_cardan_and_rpy_differ_for_a_generic_rotation():
    # same three numbers, different conventions -> different rotations
    assert not np.allclose(rot.cardan_xyz(0.3, 0.2, 0.1), rot.urdf_rpy(0.3, 0.2, 0.1))


def test_paper_base_rotation_converts_to_known_rpy():
    rpy = rot.cardan_to_rpy(np.array([np.pi / 2, 0.0, np.pi / 2]))
    np.testing.assert_allclose(rot.urdf_rpy(*rpy), rot.cardan_xyz(np.pi / 2, 0, np.pi / 2), atol=1e-15)


@pytest.mark.parametrize("angle", [0.0, 1e-9, 1e-3, 1.0, 3.0, np.pi - 1e-7, np.pi])
def test_rotvec_log_inverts_exp(angle, rng):
    axis = rng.normal(size=3)
    axis /= np.linalg.norm(axis)
    phi = angle * axis
    R = rot.rotvec_to_matrix(phi)
    phi2 = rot.matrix_to_rotvec(R)
    np.testing.assert_allclose(rot.rotvec_to_matrix(phi2), R, atol=1e-12)
    if angle < np.pi - 1e-6:
        np.testing.assert_allclose(phi2, phi, atol=1e-9)


def test_inverse_left_jacobian_matches_finite_differences(rng):
    phi = rng.normal(size=3) * 0.7
    R = rot.rotvec_to_matrix(phi)
    h = 1e-6
    J = np.empty((3, 3))
    for k in range(3):
        w = np.zeros(3)
        w[k] = h
        J[:, k] = (rot.matrix_to_rotvec(rot.rotvec_to_matrix(w) @ R) - rot.matrix_to_rotvec(rot.rotvec_to_matrix(-w) @ R)) / (2 * h)
    np.testing.assert_allclose(rot.inverse_left_jacobian(phi), J, atol=1e-8)
