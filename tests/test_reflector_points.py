"""Raw reflector data identified from the reflectors' positions (no pose fitted first): the point
rows' Jacobian, every pose with one reflector seen contributing, two-reflector tools end to end,
and bad input. The truth is read only after calibrate has answered."""

import json
import re

import numpy as np
import pytest
import yaml

from campaign.cli import main
from campaign.effects.base import EffectSet, make_effect, model_pose
from campaign.identify.solver import CalibrationModel
from campaign.identify.split import train_test_split
from campaign.measure.csvio import ImportOptions, read_measured_csv, write_measured_csv
from campaign.measure.data import MeasuredPoses
from campaign.model.base_params import base_parameters
from campaign.model.kinematics import forward
from campaign.model.robot import RobotModel


UR10 = "ur_description/urdf/ur10_robot.urdf"
TRIAD = np.array([[0.05, 0, 0], [0, 0.05, 0], [0, 0, 0.05]])


def _points_of(T, P):
    """Points P (k, 3) of the tool frame under poses T (n, 4, 4), computed here: (n, k, 3)."""
    return np.einsum("nij,kj->nki", T[:, :3, :3], P) + T[:, None, :3, 3]


def test_point_rows_jacobian_is_the_derivative_of_the_reflector_positions():
    robot = RobotModel.load("comau_racer5_080")
    rng = np.random.default_rng(4)
    q = rng.uniform(robot.q_lower, robot.q_upper, size=(7, robot.n_joints))
    base = base_parameters(robot, position_only=True, points=TRIAD)
    # a model away from nominal: base parameters and the effects' parameters non-zero
    effects = ("joint_compliance", "ground_compliance")
    es = EffectSet(tuple(make_effect(e, robot) for e in effects))
    x_b = rng.normal(0.0, 2e-3, size=base.n_base)
    theta = rng.normal(0.0, 1e-4, size=es.n_params)
    # any fit gives the model its base set and effects; the derivative is taken at x_b, theta
    y = _points_of(forward(robot, q), TRIAD)
    model = CalibrationModel(robot=robot, points=TRIAD, effects=effects, max_iter=1).fit(q, y)
    J = model.point_jacobian(q, base_params=x_b, effect_params=theta)
    assert J.shape == (7, 3, 3, base.n_base + es.n_params)

    def positions(xb, th):  # the perturbed model's reflectors, from the kinematics and the effects alone
        return _points_of(model_pose(robot, q, base.expand(xb), es, th, {}), TRIAD)

    h = 1e-6
    for j in range(base.n_base + es.n_params):
        xb_p, xb_m, th_p, th_m = x_b.copy(), x_b.copy(), theta.copy(), theta.copy()
        if j < base.n_base:
            xb_p[j] += h
            xb_m[j] -= h
        else:
            th_p[j - base.n_base] += h
            th_m[j - base.n_base] -= h
        fd = (positions(xb_p, th_p) - positions(xb_m, th_m)) / (2 * h)
        scale = max(np.abs(fd).max(), 1e-3)
        assert np.abs(J[..., j] - fd).max() <= 1e-5 * scale, (model.unknown_names_[j], np.abs(J[..., j] - fd).max())
    # without effects: against forward() of the perturbed geometric parameters
    geo = CalibrationModel(robot=robot, points=TRIAD, max_iter=1).fit(q, y)
    Jg = geo.point_jacobian(q, base_params=x_b)
    for j in range(base.n_base):
        e = np.zeros(base.n_base)
        e[j] = h
        fd = (_points_of(forward(robot, q, base.expand(x_b + e)), TRIAD)
              - _points_of(forward(robot, q, base.expand(x_b - e)), TRIAD)) / (2 * h)
        np.testing.assert_allclose(Jg[..., j], fd, atol=1e-7)


def test_missed_reflectors_are_zero_rows_and_one_seen_contributes():
    """A pose with one reflector seen adds three equations; the fit recovers the parameters."""
    robot = RobotModel.load("comau_racer5_080")
    rng = np.random.default_rng(8)
    q = rng.uniform(robot.q_lower, robot.q_upper, size=(60, robot.n_joints))
    base = base_parameters(robot, position_only=True, points=TRIAD)
    truth = rng.normal(0.0, 1e-3, size=base.n_base)
    y = _points_of(forward(robot, q, base.expand(truth)), TRIAD) + rng.normal(0.0, 1e-6, size=(60, 3, 3))
    y[:40, 1:] = np.nan  # two thirds of the poses: one reflector seen
    model = CalibrationModel(robot=robot, points=TRIAD).fit(q, y)
    assert model.n_equations_ == 3 * (40 + 20 * 3)
    assert np.all(np.isfinite(model.base_params_))
    err = _points_of(forward(robot, q, model.params_), TRIAD) - _points_of(forward(robot, q, base.expand(truth)), TRIAD)
    assert np.sqrt(np.mean(err ** 2)) < 2e-6
    res = model.point_residuals(q, y)
    assert np.isnan(res[:40, 1:]).all() and np.isfinite(res[:40, 0]).all()


def _markers_run(tmp_path, erd, *, miss_rate, poses=300, seed=5, robot_spec=None):
    urdf = erd(UR10)
    spec = ["--robot", urdf, "--tool-frame", "tool0"] if robot_spec is None else ["--robot", robot_spec]
    csv_path, truth_path = tmp_path / "m.csv", tmp_path / "truth.yaml"
    assert main(["synth", "--csv", str(csv_path), "--truth", str(truth_path), *spec, "--poses", str(poses),
                 "--seed", str(seed), "--kind", "markers", "--frame", "tracker", "--miss-rate", str(miss_rate)]) == 0
    return csv_path, truth_path, spec


@pytest.mark.slow
def test_raw_reflectors_beat_the_pose_fit_at_20_percent_misses(tmp_path, erd, capsys):
    """UR10, three reflectors, 20 % missed each, in the tracker's frame: every pose with a seen
    reflector is used; the model is no worse against the truth than the fit of the poses of
    three seen reflectors, and the held-out reflectors reach the noise floor."""
    from campaign.sim.truth import read_truth

    csv_path, truth_path, spec = _markers_run(tmp_path, erd, miss_rate=0.2)
    markers = ["--markers", str(tmp_path / "m.markers.yaml")]
    run = tmp_path / "run"
    assert main(["import", str(csv_path), "--run", str(run), *spec, "--frame", "tracker", "--quiet", *markers]) == 0
    capsys.readouterr()
    assert main(["calibrate", str(run), "--no-ann", "--no-report"]) == 0
    out = capsys.readouterr()
    metrics = json.loads((run / "calibration" / "metrics.json").read_text())
    # the pose-based fit: the same data as 6-D poses (the rigid fit, three or more seen)
    robot = RobotModel.load(spec[1], tool_frame="tool0")
    raw = read_measured_csv(csv_path, robot, ImportOptions(markers=np.asarray(
        yaml.safe_load((tmp_path / "m.markers.yaml").read_text())["markers"]), frame="tracker"))
    has_pose = np.isfinite(raw.xyz).all(axis=1)
    assert 0.3 < has_pose.mean() < 0.7  # ≈ 0.8³ of the poses have all three seen
    six = raw.subset(np.flatnonzero(has_pose))
    six = MeasuredPoses(six.pose_id, six.time_s, six.q, six.T_IE, {}, kind="pose", frame="tracker")
    write_measured_csv(tmp_path / "six.csv", six, robot)
    run6 = tmp_path / "run6"
    assert main(["import", str(tmp_path / "six.csv"), "--run", str(run6), *spec, "--frame", "tracker",
                 "--quiet"]) == 0
    assert main(["calibrate", str(run6), "--no-ann", "--no-report", "--quiet"]) == 0
    metrics6 = json.loads((run6 / "calibration" / "metrics.json").read_text())
    n_missing = int((~has_pose).sum())
    assert f"{n_missing} of 300 poses have fewer than three reflectors seen: identified" in out.err
    assert "seen reflectors" in out.err
    # rows used: every pose (each has a reflector seen here) against those with a pose
    is_test = train_test_split(raw.pose_id)
    n_seen = np.isfinite(raw.markers).all(axis=2).sum(axis=1)
    assert (n_seen > 0).all()
    assert metrics["stages"]["geometric"]["train"]["reflector_position_mm"]["n_reflectors"] == \
        int(n_seen[~is_test].sum())
    assert metrics["stages"]["geometric"]["test"]["n_poses"] == int((is_test & has_pose).sum())
    assert metrics6["stages"]["geometric"]["train"]["n_poses"] == int((~is_test & has_pose).sum()) < \
        int((~is_test).sum())

    # only now the truth: each model's tool origin (in the tracker's frame) on every test pose
    truth = read_truth(truth_path, robot)
    true_origin = (truth.T_LI @ truth.pose(raw.q[is_test]))[:, :3, 3]

    def origin_error_mm(run_dir):
        from campaign.identify.use import CalibratedRobot

        reg = np.asarray(json.loads((run_dir / "calibration" / "metrics.json").read_text())
                         ["tracker"]["T_L_I_registration"])
        T = reg @ CalibratedRobot(run_dir).predict(raw.q[is_test])
        return 1e3 * np.linalg.norm(T[:, :3, 3] - true_origin, axis=1).mean()

    e_points, e_poses = origin_error_mm(run), origin_error_mm(run6)
    assert e_points <= e_poses, (e_points, e_poses)
    # the held-out reflectors against the noise floor: the measured reflectors' own error
    P_true = np.einsum("nij,kj->nki", (truth.T_LI @ truth.pose(raw.q[is_test]))[:, :3, :3], TRIAD) + \
        true_origin[:, None, :]
    floor_mm = 1e3 * np.nanmean(np.linalg.norm(raw.markers[is_test] - P_true, axis=2))
    held = metrics["stages"]["geometric"]["test"]["reflector_position_mm"]
    assert held["n_reflectors"] == int(n_seen[is_test].sum())
    assert held["mean"] <= 1.1 * floor_mm, (held["mean"], floor_mm)
    print(f"origin error vs truth: points {e_points:.4f} mm, poses {e_poses:.4f} mm; reflectors {held['mean']:.4f} "
          f"mm, floor {floor_mm:.4f} mm")


@pytest.mark.slow
def test_two_reflector_data_imported_and_calibrated_reach_the_noise_floor(tmp_path, erd, capsys):
    """A UR10 tool with two reflectors, 20 % missed each, in the tracker's frame: `import` of the
    m1..m2 columns, `calibrate` from the positions; a row with neither seen is left out with a
    count. The held-out reflectors' error is within 10 % of the tracker's own error there."""
    from campaign.sim.truth import read_truth

    two = [[0.06, 0.0, 0.04], [-0.03, 0.05, 0.04]]
    spec = tmp_path / "two.yaml"
    spec.write_text(yaml.safe_dump({"urdf": erd(UR10), "name": "ur10_two", "tool_frame": "tool0", "reflectors": [
        {"name": "a", "position_m": two[0]}, {"name": "b", "position_m": two[1]}]}))
    csv_path, truth_path, args = _markers_run(tmp_path, erd, miss_rate=0.2, seed=3, robot_spec=str(spec))
    assert csv_path.read_text().splitlines()[0].endswith("m1_x,m1_y,m1_z,m2_x,m2_y,m2_z")
    run = tmp_path / "run"
    assert main(["import", str(csv_path), "--run", str(run), *args, "--frame", "tracker", "--quiet"]) == 0
    capsys.readouterr()
    assert main(["calibrate", str(run), "--no-ann", "--no-report"]) == 0
    err = capsys.readouterr().err
    robot = RobotModel.load(str(spec))
    raw = read_measured_csv(csv_path, robot, ImportOptions(frame="tracker"))
    n_seen = np.isfinite(raw.markers).all(axis=2).sum(axis=1)
    assert (n_seen == 0).any() and f"{int((n_seen == 0).sum())} of 300 poses have no reflector seen: left out" in err
    metrics = json.loads((run / "calibration" / "metrics.json").read_text())
    test = metrics["stages"]["geometric"]["test"]
    is_test = train_test_split(raw.pose_id)
    assert test["n_poses"] == int((is_test & (n_seen > 0)).sum())
    assert test["reflector_position_mm"]["n_reflectors"] == int(n_seen[is_test].sum())
    # only now the truth
    truth = read_truth(truth_path, robot)
    T = truth.T_LI @ truth.pose(raw.q[is_test])
    floor_mm = 1e3 * np.nanmean(np.linalg.norm(raw.markers[is_test] - _points_of(T, np.array(two)), axis=2))
    assert test["reflector_position_mm"]["mean"] <= 1.1 * floor_mm, (test["reflector_position_mm"], floor_mm)


def test_bad_raw_reflector_input_is_one_line(tmp_path, capsys):
    """'nan' written in a reflector cell (not an empty cell) and a half-given reflector are one
    line naming file, line and column; a row with no reflector seen is imported and left out by
    calibrate with a count (above)."""
    head = "pose_id," + ",".join(f"q{j}" for j in range(1, 7)) + "," + \
        ",".join(f"m{i}_{a}" for i in (1, 2, 3) for a in "xyz") + "\n"
    good = "1," + ",".join(["0.1"] * 6) + ",0.1,0,0.5,0,0.1,0.5,0,0,0.6\n"
    cases = {
        "nan.csv": ("2," + ",".join(["0.1"] * 6) + ",0.1,0,0.5,nan,0.1,0.5,0,0,0.6\n",
                    r"nan\.csv: line 3, column m2_x: nan is not a finite number"),
        "half.csv": ("2," + ",".join(["0.1"] * 6) + ",0.1,0,0.5,,0.1,0.5,0,0,0.6\n",
                     r"half\.csv: line 3, reflector m2: x, y, z must be all given or all empty"),
        "q.csv": ("2," + ",".join(["0.1"] * 5) + ",,0.1,0,0.5,,,,0,0,0.6\n",
                  r"q\.csv: line 3, column q6: '' is not a number"),
    }
    for name, (row, match) in cases.items():
        (tmp_path / name).write_text(head + good + row)
        run = tmp_path / f"run_{name}"
        assert main(["import", str(tmp_path / name), "--run", str(run), "--quiet"]) == 1
        lines = capsys.readouterr().err.strip().splitlines()
        assert len(lines) == 1 and re.search(match, lines[0]), lines
        assert not run.exists()
    # no reflector seen at all in a row: imported (the tracker saw nothing there), no pose
    (tmp_path / "none.csv").write_text(head + good + "2," + ",".join(["0.1"] * 6) + "," + "," * 8 + "\n")
    raw = read_measured_csv(tmp_path / "none.csv", None, ImportOptions(markers=TRIAD))
    assert np.isnan(raw.markers[1]).all() and np.isnan(raw.xyz[1]).all() and np.isfinite(raw.xyz[0]).all()


def test_one_raw_reflector_column_set_is_one_reflector_data(tmp_path, capsys):
    """Raw columns m1 alone: imported and identified from that reflector's positions (no pose)."""
    csv_path = tmp_path / "m.csv"
    assert main(["synth", "--csv", str(csv_path), "--poses", "120", "--seed", "4", "--kind", "markers"]) == 0
    lines = csv_path.read_text().splitlines()
    head = lines[0].split(",")
    keep = [i for i, c in enumerate(head) if not c.startswith(("m2_", "m3_"))]
    csv_path.write_text("\n".join(",".join(r.split(",")[i] for i in keep) for r in lines) + "\n")
    (tmp_path / "m1.yaml").write_text("markers: [[0.05, 0, 0]]\n")
    run = tmp_path / "run"
    assert main(["import", str(csv_path), "--run", str(run), "--markers", str(tmp_path / "m1.yaml"), "--quiet"]) == 0
    capsys.readouterr()
    assert main(["calibrate", str(run), "--no-ann", "--no-report", "--quiet"]) == 0
    test = json.loads((run / "calibration" / "metrics.json").read_text())["stages"]["geometric"]["test"]
    is_test = train_test_split(np.arange(1, 121))
    assert "orientation_mrad" not in test and test["reflector_position_mm"]["n_reflectors"] == int(is_test.sum())
    assert test["position_mm"]["mean"] < 0.05  # the nominal model is millimetres off


@pytest.mark.slow
def test_raw_reflectors_with_misses_through_the_network_report_predict_and_compensate(tmp_path, capsys):
    """Three raw reflectors, 20 % missed: the neural stage trains on the rows with a pose (saying
    how many it skips), the noise floor and the report are there, `predict` and `compensate` use
    the calibrated model."""
    csv_path = tmp_path / "m.csv"
    assert main(["synth", "--csv", str(csv_path), "--poses", "200", "--seed", "6", "--kind", "markers",
                 "--miss-rate", "0.2"]) == 0
    run = tmp_path / "run"
    assert main(["import", str(csv_path), "--run", str(run), "--markers", str(tmp_path / "m.markers.yaml"),
                 "--quiet"]) == 0
    cfg = yaml.safe_load((run / "campaign.yaml").read_text()) or {}
    cfg["tracker"] = {"noise_m": 10e-6}
    (run / "campaign.yaml").write_text(yaml.safe_dump(cfg))
    capsys.readouterr()
    assert main(["calibrate", str(run), "--ann", "--sizes", "4x4", "--folds", "2", "--epochs", "30",
                 "--workers", "1"]) == 0
    err = capsys.readouterr().err
    raw = read_measured_csv(csv_path, None, ImportOptions(markers=TRIAD))
    has_pose = np.isfinite(raw.xyz).all(axis=1)
    seen = np.isfinite(raw.markers).all(axis=2).any(axis=1)  # rows with none seen are left out first
    assert (~seen).any() and f"{int((~seen).sum())} of 200 poses have no reflector seen: left out" in err
    assert f"the network on the {int(has_pose.sum())} poses with three or more reflectors seen " \
           f"({int((seen & ~has_pose).sum())} without a pose skipped)" in err, err
    metrics = json.loads((run / "calibration" / "metrics.json").read_text())
    assert metrics["order"] == ["nominal", "geometric", "ann", "geometric+ann"]
    n_test = int((train_test_split(raw.pose_id) & has_pose).sum())
    assert all(metrics["stages"][s]["test"]["n_poses"] == n_test for s in metrics["order"])
    assert metrics["noise_floor"]["mean_position_mm"] > 0 and (run / "calibration" / "report.html").is_file()
    # predict and compensate with the current model (geometric+ann), as for any run
    q = raw.q[:5]
    (tmp_path / "q.csv").write_text("pose_id," + ",".join(f"q{j}" for j in range(1, 7)) + "\n" + "".join(
        f"{i}," + ",".join(repr(float(v)) for v in row) + "\n" for i, row in enumerate(q)))
    assert main(["predict", str(run), "--csv", str(tmp_path / "q.csv"), "--out", str(tmp_path / "p.csv")]) == 0
    assert main(["compensate", str(run), "--csv", str(tmp_path / "q.csv"), "--out", str(tmp_path / "c.csv")]) == 0
    assert len((tmp_path / "p.csv").read_text().splitlines()) == 6
    assert len((tmp_path / "c.csv").read_text().splitlines()) == 6
