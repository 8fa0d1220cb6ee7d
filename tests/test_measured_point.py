"""One-reflector data measured at a point robot.yaml does not name (a marker stuck on the hand, as
in FIGAROH's TIAGo file): the point and the tracker's pose are registered from the training poses,
and the tolerance priors hold around them. References: the generating point and tracker pose
(noise-free nominal data); least squares on the same data, which the registration cannot change."""

import json
import re

import numpy as np
import pytest
import yaml

from campaign.cli import main
from campaign.measure.reflectors import register_measured_point
from campaign.model.kinematics import forward
from campaign.sim.truth import make_truth, random_joint_poses, random_tracker_pose

POINT = np.array([0.08, -0.03, 0.06])  # m in the tool frame: 40 tool tolerances of 1.5 mm away


def _points(T_IE, point, T_LI, noise_m, seed):
    P = T_IE[:, :3, :3] @ point + T_IE[:, :3, 3]
    P = P @ T_LI[:3, :3].T + T_LI[:3, 3]
    return P + np.random.default_rng(seed).normal(0.0, noise_m, P.shape)


def test_the_point_and_the_tracker_pose_of_noise_free_nominal_data_are_found_exactly(robot):
    q = random_joint_poses(robot, 12, seed=1)
    T = forward(robot, q)
    T_LI = random_tracker_pose(5)
    T_found, p = register_measured_point(T, _points(T, POINT, T_LI, 0.0, 0))
    np.testing.assert_allclose(p, POINT, atol=1e-9)
    np.testing.assert_allclose(T_found, T_LI, atol=1e-9)
    T_found, p = register_measured_point(T, _points(T, POINT, np.eye(4), 0.0, 0), tracker=False)
    np.testing.assert_allclose(p, POINT, atol=1e-12)
    np.testing.assert_array_equal(T_found, np.eye(4))


def _campaign(tmp_path, robot, point, name):
    truth = make_truth(robot, seed=3, position_only=True)
    q = random_joint_poses(robot, 40, seed=4)
    P = _points(truth.pose(q), point, random_tracker_pose(6), 1e-5, 7)
    csv = tmp_path / f"{name}.csv"
    header = "pose_id," + ",".join(f"q{j + 1}" for j in range(robot.n_joints)) + ",x,y,z"
    np.savetxt(csv, np.column_stack([np.arange(len(q)), q, P]), delimiter=",", header=header, comments="",
               fmt=["%d"] + ["%.17g"] * (robot.n_joints + 3))
    run = tmp_path / name
    assert main(["import", str(csv), "--run", str(run), "--frame", "tracker", "--quiet"]) == 0
    return run


def _calibrate(run, model):
    """(held-out mean position error mm, the measured point m, the warnings' codes)"""
    assert main(["calibrate", str(run), "--no-ann", "--no-report", "--quiet", "--model", model]) == 0
    metrics = json.loads((run / "calibration" / "metrics.json").read_text())
    params = yaml.safe_load((run / "calibration" / "params.yaml").read_text())
    return (metrics["stages"]["geometric"]["test"]["position_mm"]["mean"], np.array(params["measured_point_in_tool_m"]),
            [w["code"] for w in metrics["warnings"]])


@pytest.fixture(scope="module")
def off_point_run(tmp_path_factory, robot):
    return _campaign(tmp_path_factory.mktemp("point"), robot, POINT, "off")


def test_import_says_where_the_marker_is_instead_of_blaming_the_joint_convention(tmp_path, robot, capsys):
    _campaign(tmp_path, robot, POINT, "said")
    err = capsys.readouterr().err
    assert "[measured_point]" in err and "[nominal_residual]" not in err
    said = re.search(r"measured at \(([-\d.]+), ([-\d.]+), ([-\d.]+)\) mm in the tool frame", err)
    assert np.linalg.norm(np.array([float(v) for v in said.groups()]) * 1e-3 - POINT) < 3e-3


def test_a_marker_off_the_tool_frame_is_found_and_the_fit_corrects_instead_of_reshaping(off_point_run):
    lsq, p_lsq, warned = _calibrate(off_point_run, "lsq")
    map_, p_map, _ = _calibrate(off_point_run, "map")
    # the truth's own tool errors move the point the nominal model sees by about a millimetre
    assert np.linalg.norm(p_lsq - POINT) < 3e-3 and np.array_equal(p_lsq, p_map)
    # at the tool frame's origin the fit's tool correction was 77 mm, 6 % of the arm (large_corrections)
    assert "large_corrections" not in warned
    assert map_ < 1.05 * lsq


def test_data_measured_at_the_tool_frame_keep_the_origin(tmp_path, robot, capsys):
    run = _campaign(tmp_path, robot, np.zeros(3), "origin")
    assert "warning" not in capsys.readouterr().err
    _, point, _ = _calibrate(run, "lsq")
    np.testing.assert_array_equal(point, np.zeros(3))
