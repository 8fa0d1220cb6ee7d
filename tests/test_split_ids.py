"""The split is listed (issue 20, item 8): metrics.json's ``test_pose_ids`` are the held-out poses of
campaign/identify/split.py, and another tool fitting on the other poses reproduces the test metric;
diagnosis.json's ``fold_pose_ids`` are the folds' poses."""

import json

import numpy as np
from scipy.optimize import least_squares

from campaign.cli import main
from campaign.identify.split import campaign_split
from campaign.measure.csvio import read_measured_csv, write_measured_csv
from campaign.model.kinematics import forward
from campaign.sim.truth import make_truth, random_joint_poses, synthesize


def test_test_pose_ids_are_the_split_and_a_refit_on_them_reproduces_the_test_metric(robot, tmp_path):
    data = synthesize(make_truth(robot, seed=31), random_joint_poses(robot, 90, seed=32), seed=33)
    data = type(data)(data.pose_id * 7 + 100, *[getattr(data, f) for f in ("time_s", "q", "T_IE", "context")])
    csv = tmp_path / "poses.csv"
    write_measured_csv(csv, data)
    run = tmp_path / "run"
    assert main(["import", str(csv), "--run", str(run), "--quiet"]) == 0
    assert main(["calibrate", str(run), "--no-ann", "--quiet", "--no-report", "--position-only"]) == 0
    m = json.loads((run / "calibration" / "metrics.json").read_text())
    poses = read_measured_csv(csv)
    expected = poses.pose_id[campaign_split(poses.pose_id)]
    assert m["test_pose_ids"] == [int(i) for i in expected] and len(expected) == 18
    # another tool on the same split: scipy's trust-region least squares on the 48 parameters
    test = np.isin(poses.pose_id, m["test_pose_ids"])
    q_tr, p_tr = poses.q[~test], poses.xyz[~test]

    def residual(p):
        return (forward(robot, q_tr, p)[:, :3, 3] - p_tr).ravel()

    fit = least_squares(residual, np.zeros(robot.n_params), method="lm", xtol=1e-12, ftol=1e-12)
    err_mm = np.linalg.norm(forward(robot, poses.q[test], fit.x)[:, :3, 3] - poses.xyz[test], axis=1) * 1e3
    got = m["stages"]["geometric"]["test"]["position_mm"]
    assert abs(err_mm.mean() - got["mean"]) < 1e-6 and abs(err_mm.max() - got["max"]) < 1e-6
    assert m["stages"]["geometric"]["test"]["n_poses"] == len(m["test_pose_ids"])


def test_diagnosis_lists_the_poses_of_each_fold(robot, tmp_path):
    from campaign.diagnose.engine import diagnose, pose_folds

    data = synthesize(make_truth(robot, seed=41), random_joint_poses(robot, 80, seed=42), seed=43)
    csv = tmp_path / "poses.csv"
    write_measured_csv(csv, data)
    run = tmp_path / "run"
    assert main(["import", str(csv), "--run", str(run), "--quiet"]) == 0
    d = diagnose(run, candidates="backlash", structure=False, folds=4).as_json()
    folds = d["fold_pose_ids"]
    train = data.pose_id[~campaign_split(data.pose_id)]
    assert len(folds) == d["folds"] == 4
    assert sorted(i for f in folds for i in f) == sorted(int(i) for i in train)
    k = pose_folds(train, 4)
    assert folds == [[int(i) for i in train[k == j]] for j in range(4)]
    json.dumps(d, allow_nan=False)
