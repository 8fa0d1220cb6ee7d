"""The neural stage on any serial robot: a 7R Panda (example-robot-data) with a hidden smooth
effect (joint compliance under gravity), through the command line (synth -> import -> calibrate
--ann -> predict / compensate), 6-D poses and one-reflector (position-only) data; the saved
network read back with torch's weights_only loader and evaluated by hand. The truth is read
only after the pipeline has answered."""

import csv
import json
from importlib import metadata
from pathlib import Path

import numpy as np
import pytest
import torch

from campaign.ann import ResidualNetwork, compensate_pose, joint_mapping
from campaign.cli import main
from campaign.errors import ConfigError, DataError
from campaign.identify.split import train_test_split
from campaign.measure.csvio import read_measured_csv
from campaign.model.kinematics import forward, pose_error
from campaign.model.robot import RobotModel

TOOL = "panda_hand"
GRID = ["--ann", "--sizes", "8x8,16x16", "--folds", "3", "--epochs", "60", "--quiet"]


def _panda_urdf():
    try:
        dist = metadata.distribution("example-robot-data")
    except metadata.PackageNotFoundError:
        pytest.skip("example-robot-data (test extra) is not installed")
    return str(Path(dist.locate_file("cmeel.prefix/share/example-robot-data/robots"))
               / "panda_description/urdf/panda.urdf")


def _calibrated(folder, kind):
    urdf = _panda_urdf()
    csv_path = folder / "m.csv"
    assert main(["synth", "--csv", str(csv_path), "--truth", str(folder / "truth.yaml"), "--robot", urdf,
                 "--tool-frame", TOOL, "--poses", "800", "--seed", "4", "--hidden", "joint_compliance",
                 "--kind", kind]) == 0
    run = folder / "run"
    assert main(["import", str(csv_path), "--run", str(run), "--robot", urdf, "--tool-frame", TOOL, "--quiet"]) == 0
    assert main(["calibrate", str(run), *GRID]) == 0
    return run, csv_path, RobotModel.load(urdf, tool_frame=TOOL)


@pytest.fixture(scope="module")
def panda_pose(tmp_path_factory):
    return _calibrated(tmp_path_factory.mktemp("panda_pose"), "pose")


@pytest.fixture(scope="module")
def panda_point(tmp_path_factory):
    return _calibrated(tmp_path_factory.mktemp("panda_point"), "point")


def _test(metrics, stage, block="position_mm", key="mean"):
    return metrics["stages"][stage]["test"][block][key]


def test_the_network_on_a_7_joint_robot_beats_geometry_on_held_out_poses(panda_pose):
    run, _, robot = panda_pose
    metrics = json.loads((run / "calibration" / "metrics.json").read_text())
    assert metrics["order"] == ["nominal", "geometric", "ann", "geometric+ann"]
    for block in ("position_mm", "orientation_mrad"):
        assert _test(metrics, "geometric+ann", block) < 0.8 * _test(metrics, "geometric", block)
        assert _test(metrics, "ann", block) < 0.8 * _test(metrics, "nominal", block)
    net = ResidualNetwork.load(run / "calibration" / "ann_geometric.pt")
    assert (net.n_inputs_, net.n_outputs_) == (7, 6)
    # the inputs are the Panda's joints normalised with its own limits
    ref = joint_mapping(robot.q_lower, robot.q_upper)
    np.testing.assert_allclose(net.input_mapping_.mean, ref.mean, rtol=1e-15)
    np.testing.assert_allclose(net.input_mapping_.scale, ref.scale, rtol=1e-15)


def test_the_saved_network_evaluated_by_hand_from_a_weights_only_load(panda_pose):
    """The file holds tensors only (torch.load(weights_only=True)); the documented layout (flat
    W1, b1, W2, b2, W3, b3 per member, mappings) evaluated by hand gives the loaded network's
    prediction."""
    run, csv_path, robot = panda_pose
    path = run / "calibration" / "ann_geometric.pt"
    state = torch.load(path, weights_only=True)
    q = read_measured_csv(csv_path, robot).q[:50]
    n1, n2 = (int(v) for v in state["hidden"])
    x = (q - state["input_mean"].numpy()) / state["input_scale"].numpy()
    W = state["weights"].numpy().reshape(-1, state["weights"].shape[-1])
    mean = state["target_mean"].numpy().reshape(len(W), -1)
    scale = state["target_scale"].numpy().reshape(len(W), -1)
    by_hand = []
    for w, mu, sd in zip(W, mean, scale):
        sizes = [n1 * 7, n1, n2 * n1, n2, 6 * n2, 6]
        W1, b1, W2, b2, W3, b3 = np.split(w, np.cumsum(sizes)[:-1])
        h1 = np.tanh(x @ W1.reshape(n1, 7).T + b1)
        h2 = np.tanh(h1 @ W2.reshape(n2, n1).T + b2)
        by_hand.append((h2 @ W3.reshape(6, n2).T + b3) * sd + mu)
    np.testing.assert_allclose(ResidualNetwork.load(path).predict(q), np.mean(by_hand, axis=0), rtol=1e-10,
                               atol=1e-15)


def test_predict_reproduces_the_calibrated_test_errors_of_the_7_joint_robot(panda_pose, tmp_path):
    run, csv_path, robot = panda_pose
    out = tmp_path / "pred.csv"
    assert main(["predict", str(run), "--csv", str(csv_path), "--out", str(out)]) == 0
    rows = list(csv.DictReader(out.open()))
    assert list(rows[0])[:9] == ["pose_id", *(f"q{j}" for j in range(1, 8)), "x"]
    meas = read_measured_csv(csv_path, robot)
    xyz = np.array([[float(r[c]) for c in ("x", "y", "z")] for r in rows])
    dt_mm = np.linalg.norm(xyz - meas.xyz, axis=1) * 1e3
    test = train_test_split(meas.pose_id)
    metrics = json.loads((run / "calibration" / "metrics.json").read_text())
    assert dt_mm[test].mean() == pytest.approx(_test(metrics, "geometric+ann"), rel=1e-9)
    assert dt_mm[test].max() == pytest.approx(_test(metrics, "geometric+ann", key="max"), rel=1e-9)


def test_compensated_7_joint_commands_bring_the_true_tool_closer_with_the_network(panda_pose, tmp_path):
    from campaign.sim.truth import random_joint_poses, read_truth

    run, csv_path, robot = panda_pose
    q_nominal = random_joint_poses(robot, 30, seed=31, margin=0.3)
    inp = tmp_path / "commands.csv"
    with inp.open("w", newline="") as fh:
        w = csv.writer(fh)
        w.writerow(["pose_id", *(f"q{j}" for j in range(1, 8))])
        w.writerows([[i, *(repr(float(v)) for v in q)] for i, q in enumerate(q_nominal)])
    corrected = {}
    for stage in ("geometric", "geometric+ann"):
        out = tmp_path / f"{stage}.csv"
        assert main(["compensate", str(run), "--csv", str(inp), "--out", str(out), "--stage", stage]) == 0
        rows = list(csv.DictReader(out.open()))
        assert all(r["converged"] == "1" for r in rows)
        corrected[stage] = np.array([[float(r[f"q{j}"]) for j in range(1, 8)] for r in rows])
    # only now the truth: where does the true robot put its tool for each set of commands?
    truth = read_truth(csv_path.parent / "truth.yaml", robot)
    target = forward(robot, q_nominal)

    def true_error_mm(q):  # data in the robot's frame (up to the set-up points' error of some 10 µm)
        return 1e3 * np.linalg.norm(pose_error(truth.pose(q), target)[:, :3], axis=1).mean()

    before, geo, ann = true_error_mm(q_nominal), true_error_mm(corrected["geometric"]), \
        true_error_mm(corrected["geometric+ann"])
    assert before > 5.0
    assert ann < 0.8 * geo < 0.1 * before, (before, geo, ann)


def test_position_only_data_train_a_three_output_network(panda_point, tmp_path):
    run, csv_path, robot = panda_point
    out = run / "calibration"
    metrics = json.loads((out / "metrics.json").read_text())
    assert metrics["order"] == ["nominal", "geometric", "ann", "geometric+ann"]
    assert "orientation_mrad" not in metrics["stages"]["geometric+ann"]["test"]
    assert _test(metrics, "geometric+ann") < 0.8 * _test(metrics, "geometric")
    net = ResidualNetwork.load(out / "ann_geometric.pt")
    assert (net.n_inputs_, net.n_outputs_) == (7, 3)
    cv = json.loads((out / "ann_cv.json").read_text())
    assert all(r["max_orientation_mrad"] is None for b in cv.values() for r in b["sizes"])
    # predict: positions of the measured point reproduce the calibrated test errors
    pred = tmp_path / "pred.csv"
    assert main(["predict", str(run), "--csv", str(csv_path), "--out", str(pred)]) == 0
    xyz = np.array([[float(r[c]) for c in ("x", "y", "z")] for r in csv.DictReader(pred.open())])
    meas = read_measured_csv(csv_path, robot)
    test = train_test_split(meas.pose_id)
    dt_mm = np.linalg.norm(xyz - meas.xyz, axis=1)[test] * 1e3
    assert dt_mm.mean() == pytest.approx(_test(metrics, "geometric+ann"), rel=1e-9)


def test_a_position_only_correction_moves_the_position_and_keeps_the_rotation():
    rng = np.random.default_rng(2)
    T = np.tile(np.eye(4), (4, 1, 1))
    T[:, :3, 3] = rng.normal(size=(4, 3))
    dt = rng.normal(0, 1e-3, (4, 3))
    out = compensate_pose(T, dt)
    np.testing.assert_allclose(out[:, :3, 3], T[:, :3, 3] - dt, rtol=0, atol=1e-15)
    np.testing.assert_array_equal(out[:, :3, :3], T[:, :3, :3])
    with pytest.raises(DataError, match=r"\(n, 6\) or \(n, 3\)"):
        compensate_pose(T, np.zeros((4, 4)))


def test_br_lm_network_with_7_inputs_and_3_outputs_learns_and_reloads_identically(tmp_path):
    rng = np.random.default_rng(0)
    lo, hi = -np.full(7, 2.0), np.full(7, 2.0)
    q = rng.uniform(lo, hi, (400, 7))
    dt = np.stack([1e-4 * np.sin(q[:, 0] + q[:, 6]), 2e-4 * np.cos(q[:, 1]) * np.sin(q[:, 5]),
                   1e-4 * np.sin(q[:, 2] - q[:, 3])], axis=1)
    net = ResidualNetwork(hidden=(12, 8), q_lower=lo, q_upper=hi, max_epochs=120, seed=1).fit(q[:300], dt[:300])
    res = dt[300:] - net.predict(q[300:])
    assert np.sqrt(np.mean(res ** 2)) < 0.3 * np.sqrt(np.mean(dt[300:] ** 2))
    net.save(tmp_path / "net.pt")
    again = ResidualNetwork.load(tmp_path / "net.pt")
    np.testing.assert_array_equal(again.predict(q), net.predict(q))
    with pytest.raises(DataError, match="takes 7 joint values"):
        again.predict(q[:, :6])


def test_a_network_for_another_robot_needs_its_joint_limits():
    q = np.zeros((20, 7))
    with pytest.raises(ConfigError, match="7 joint values per pose: give q_lower and q_upper"):
        ResidualNetwork(hidden=(4, 4), max_epochs=1).fit(q, np.zeros((20, 6)))
    with pytest.raises(ConfigError, match="7 finite values each"):
        ResidualNetwork(hidden=(4, 4), max_epochs=1, q_lower=-np.ones(6), q_upper=np.ones(6)).fit(q, np.zeros((20, 6)))


def test_the_adam_grid_takes_7_joints_and_3_outputs():
    """The batched-Adam grid (the solver of large runs) on a 7-joint, position-only residual:
    the fold ensemble learns it (held-out RMS error well below the signal's) with 7 inputs."""
    from campaign.ann.grid import run_grid

    rng = np.random.default_rng(1)
    lo, hi = -np.full(7, 2.0), np.full(7, 2.0)
    q = rng.uniform(lo, hi, (700, 7))
    dt = np.stack([1e-4 * np.sin(q[:, 0] + q[:, 6]), 2e-4 * np.cos(q[:, 1]) * np.sin(q[:, 5]),
                   1e-4 * np.sin(q[:, 2] - q[:, 3])], axis=1)
    out = run_grid(q[:600], {"geometric": dt[:600]}, sizes=[(16, 8)], folds=3, solver="adam", q_lower=lo,
                   q_upper=hi, max_epochs=300, device="cpu")
    net, cv = out["geometric"]
    assert (net.n_inputs_, net.n_outputs_) == (7, 3) and net.weights_.shape[0] == 3
    assert cv["sizes"][0]["max_orientation_mrad"] is None
    res = dt[600:] - net.predict(q[600:])
    assert np.sqrt(np.mean(res ** 2)) < 0.3 * np.sqrt(np.mean(dt[600:] ** 2))
