import numpy as np
import pytest

from campaign.errors import ConfigError
from campaign.model.kinematics import frames
from campaign.model.robot import RobotModel
from campaign.model.rotations import cardan_xyz

PI = np.pi
# the paper's Table 1 (Cardan x-y-z angles) and the nominal lengths recorded in the URDF
TABLE1 = [
    ((PI / 2, 0, PI / 2), (0, 0, 0)),
    ((0, 0, 0), (0, 0, 0.189)),
    ((-PI / 2, 0, -PI / 2), (0.050, 0, 0.176)),
    ((0, 0, PI / 2), (0.370, 0, 0)),
    ((PI / 2, PI / 2, 0), (0.0405, -0.050, 0)),
    ((-PI / 2, 0, -PI / 2), (0, 0, 0.345)),
    ((PI / 2, PI / 2, 0), (0.080, 0, 0)),
    ((0, 0, PI / 4), (0.016, -0.040, 0.100)),
]


def test_urdf_joint_origins_reproduce_table1_cardan_chain(robot):
    for k, (abc, t) in enumerate(TABLE1):
        np.testing.assert_allclose(robot.R_nominal[k], cardan_xyz(*abc), atol=1e-12, err_msg=f"transform {k}")
        np.testing.assert_allclose(robot.t_nominal[k], t, atol=1e-12)


def test_joint_limits_are_those_of_eq17(robot):
    deg = np.rad2deg
    np.testing.assert_allclose(deg(robot.q_lower), [-168, -83, -178, -198, -98, -180], atol=1e-9)
    np.testing.assert_allclose(deg(robot.q_upper), [168, 133, 63, 198, 98, 180], atol=1e-9)


def test_wrist_axes_meet_in_one_point(robot, rng):
    q = rng.uniform(robot.q_lower, robot.q_upper, size=(20, 6))
    R, t = frames(robot, q)
    for i in range(20):
        # axes 4, 5, 6 are z of frames 4, 5, 6 through their origins; frame 5's origin lies on all three
        c = t[i, 5]
        for k in (4, 6):
            d = c - t[i, k]
            z = R[i, k][:, 2]
            assert np.linalg.norm(d - (d @ z) * z) < 1e-12


def test_reach_to_wrist_centre_matches_datasheet(robot):
    # stretched arm: q2 brings the upper arm horizontal, q3 aligns the forearm
    q2, q3 = np.meshgrid(np.linspace(-1.4, 2.3, 371), np.linspace(-3.1, 1.09, 420))
    q = np.zeros((q2.size, 6))
    q[:, 1], q[:, 2] = q2.ravel(), q3.ravel()
    _, t = frames(robot, q)
    best = np.max(np.hypot(t[:, 5, 0], t[:, 5, 2]))
    assert abs(best - 0.809) < 0.005


def test_gravity_points_down_the_vertical_y_axis(robot):
    np.testing.assert_allclose(robot.gravity_in_I, [0, 9.81, 0])
    R, _ = frames(robot, np.zeros((1, 6)))
    # joint 1's axis (z of F_0 and F_1) points up, against gravity
    assert R[0, 0][:, 2] @ robot.gravity_in_I < -9.8


def test_urdf_loads_with_yourdfpy_and_pinocchio_from_the_same_file(robot):
    assert set(robot.urdf.actuated_joint_names) == {f"joint{i}" for i in range(1, 7)}
    model = robot.pinocchio_model
    assert model.nq == 6
    np.testing.assert_allclose(model.gravity.linear, [0, 9.81, 0])
    total = sum(inert.mass for inert in model.inertias)
    assert 28.0 < total < 40.0


def test_reflectors_have_the_papers_acceptance_angles(robot):
    assert [r.name for r in robot.reflectors] == ["rrr1", "rrr2", "brr"]
    np.testing.assert_allclose(np.rad2deg([r.half_angle for r in robot.reflectors]), [26.5, 26.5, 20.0])


def test_missing_robot_folder_is_one_clear_error(tmp_path):
    with pytest.raises(ConfigError, match="robot.yaml"):
        RobotModel.load(tmp_path)


def test_robot_yaml_missing_field_is_named(tmp_path):
    (tmp_path / "robot.yaml").write_text("urdf: robot.urdf\nchain: []\n")
    with pytest.raises(ConfigError, match=r"missing field 'gravity_m_s2' \(or 'gravity_in_I_m_s2'\)"):
        RobotModel.load(tmp_path)
