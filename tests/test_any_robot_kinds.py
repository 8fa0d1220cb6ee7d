"""Issue 12, items 3-7 and 10: another robot's data of every kind, in the tracker's frame, through
the command line (synth -> import -> calibrate -> diagnose -> export). The truth is read only after
the pipeline has answered."""

import json
import sqlite3
from importlib import metadata
from pathlib import Path

import numpy as np
import pytest
import yaml

from campaign.cli import main
from campaign.identify.split import train_test_split
from campaign.measure.csvio import ImportOptions, read_measured_csv, write_measured_csv
from campaign.measure.store import open_run
from campaign.model.robot import RobotModel
from campaign.errors import DataError


def _erd(rel):
    try:
        dist = metadata.distribution("example-robot-data")
    except metadata.PackageNotFoundError:
        pytest.skip("example-robot-data (test extra) is not installed")
    return str(Path(dist.locate_file("cmeel.prefix/share/example-robot-data/robots")) / rel)


ROBOTS = {
    "ur10": ("ur_description/urdf/ur10_robot.urdf", "tool0"),  # 6R, z up, joint axes along y
    "panda": ("panda_description/urdf/panda.urdf", "panda_hand"),  # 7R
}


@pytest.mark.slow
@pytest.mark.parametrize("kind", ["pose", "point", "markers"])
@pytest.mark.parametrize("which", ["ur10", "panda"])
def test_heldout_error_reaches_the_noise_floor(which, kind, tmp_path, capsys):
    from campaign.sim.truth import read_truth

    rel, tool = ROBOTS[which]
    urdf = _erd(rel)
    csv_path, truth_path = tmp_path / "m.csv", tmp_path / "truth.yaml"
    extra = ["--miss-rate", "0.03"] if kind == "markers" else []
    assert main(["synth", "--csv", str(csv_path), "--truth", str(truth_path), "--robot", urdf, "--tool-frame", tool,
                 "--poses", "360", "--seed", "5", "--kind", kind, "--frame", "tracker", *extra]) == 0
    markers = []
    if kind == "markers":  # synth writes the nominal positions beside the CSV: the default triad here
        assert yaml.safe_load((tmp_path / "m.markers.yaml").read_text()) == \
            {"markers": [[0.05, 0, 0], [0, 0.05, 0], [0, 0, 0.05]]}
        markers = ["--markers", str(tmp_path / "m.markers.yaml")]
    run = tmp_path / "run"
    assert main(["import", str(csv_path), "--run", str(run), "--robot", urdf, "--tool-frame", tool,
                 "--frame", "tracker", "--quiet", *markers]) == 0
    # the reports once, on the least usual shape (7 joints, positions only); the numbers everywhere
    reports = [] if (which, kind) == ("panda", "point") else ["--no-report"]
    assert main(["calibrate", str(run), "--no-ann", "--quiet", *reports]) == 0
    metrics = json.loads((run / "calibration" / "metrics.json").read_text())
    test = metrics["stages"]["geometric"]["test"]
    assert metrics["frame"] == "tracker" and metrics["measurement_kind"] == kind
    assert ("orientation_mrad" in test) == (kind != "point")
    # only now the truth: the noise floor is the measurement's own error at the tool origin
    robot = RobotModel.load(urdf, tool_frame=tool)
    truth = read_truth(truth_path, robot)
    with open_run(run) as store:
        poses = store.load_measured()
        every = store.load_measured(include_unusable=True)  # raw reflectors: also rows of fewer than three
    ok = np.isfinite(poses.xyz).all(axis=1)
    te = train_test_split(poses.pose_id) & ok
    true_xyz = (truth.T_LI @ truth.pose(poses.q[te]))[:, :3, 3]
    floor_mm = 1e3 * np.linalg.norm(poses.xyz[te] - true_xyz, axis=1).mean()
    assert test["n_poses"] == int(te.sum())
    assert test["position_mm"]["mean"] <= 1.1 * floor_mm, (test["position_mm"]["mean"], floor_mm)
    # the nominal stage is the nominal model after registration: mm, not the tracker's metres away
    assert metrics["stages"]["nominal"]["test"]["position_mm"]["mean"] < 50
    T_LI = np.asarray(metrics["tracker"]["tracker_pose_identified"])
    assert 2.0 <= np.linalg.norm(np.linalg.inv(T_LI)[:3, 3]) <= 3.0 + 0.01
    capsys.readouterr()
    assert main(["diagnose", str(run), "--json", "--folds", "2", *reports]) == 0
    doc = json.loads(capsys.readouterr().out)
    assert "verdict" in doc and "ranking" in doc and "noise_floor_mm" in doc
    assert len(doc["ranking"]) >= 5  # every built-in candidate scored on this robot's data
    if not reports:
        assert (run / "calibration" / "joints_geometric.svg").is_file() and (run / "diagnose" / "report.html").is_file()
    # the calibrated model out as a URDF, and the measured data back out as a CSV of the same kind
    assert main(["export", str(run), "--urdf", str(tmp_path / "cal.urdf"), "--csv", str(tmp_path / "back.csv")]) == 0
    back = read_measured_csv(tmp_path / "back.csv", robot,
                             ImportOptions(markers=poses.marker_positions if kind == "markers" else None))
    # every imported row back out, those of fewer than three reflectors seen included
    assert back.kind == kind and len(back) == len(every) == 360
    np.testing.assert_allclose(back.q, every.q, atol=0)
    if kind == "markers":
        np.testing.assert_array_equal(np.isnan(back.markers), np.isnan(every.markers))


def test_units_and_kinds_from_the_header(tmp_path):
    robot = RobotModel.load(_erd(ROBOTS["panda"][0]))
    rng = np.random.default_rng(3)
    q = rng.uniform(robot.q_lower, robot.q_upper, size=(12, 7))
    xyz = rng.uniform(-1, 1, size=(12, 3))
    head = "pose_id," + ",".join(f"q{j}" for j in range(1, 8)) + ",x,y,z,temperature_c\n"
    (tmp_path / "si.csv").write_text(head + "".join(
        f"{i}," + ",".join(repr(float(v)) for v in q[i]) + "," + ",".join(repr(float(v)) for v in xyz[i]) + ",21\n" for i in range(12)))
    (tmp_path / "degmm.csv").write_text(head + "".join(
        f"{i}," + ",".join(repr(float(v)) for v in np.rad2deg(q[i])) + "," + ",".join(repr(float(v)) for v in 1e3 * xyz[i]) + ",21\n"
        for i in range(12)))
    a = read_measured_csv(tmp_path / "si.csv", robot)
    b = read_measured_csv(tmp_path / "degmm.csv", robot, ImportOptions(angle_unit="deg", length_unit="mm"))
    assert a.kind == b.kind == "point" and not a.has_orientation and np.isnan(a.time_s).all()
    np.testing.assert_allclose(b.q, a.q, rtol=1e-14)
    np.testing.assert_allclose(b.xyz, a.xyz, rtol=1e-14)
    np.testing.assert_allclose(a.context["temperature_c"], 21)
    # degrees without the option: one line naming line and column
    with pytest.raises(DataError, match=r"degmm\.csv: line \d+, column q\d: .*--angle-unit deg"):
        read_measured_csv(tmp_path / "degmm.csv", robot)
    # a column beyond the robot's joints, and data outside its limits, name the robot
    six = RobotModel.load(_erd(ROBOTS["ur10"][0]), tool_frame="tool0")
    with pytest.raises(DataError, match=r"the file has 7 joint columns \(q1..q7\), ur10 has 6 \(q1..q6\): another robot"):
        read_measured_csv(tmp_path / "si.csv", six)
    (tmp_path / "lim.csv").write_text(head + "1," + ",".join(["0"] * 3 + ["0.5"] + ["0"] * 3) + ",0,0,0,21\n")
    with pytest.raises(DataError, match=r"line 2, column q4: 0.5 rad is outside the joint limit .* of panda"):
        read_measured_csv(tmp_path / "lim.csv", robot)


def test_raw_markers_need_their_nominal_positions_and_missed_cells_are_empty(tmp_path, robot):
    head = "pose_id,time_s," + ",".join(f"q{j}" for j in range(1, 7)) + "," + \
        ",".join(f"m{i}_{a}" for i in (1, 2, 3, 4) for a in "xyz") + "\n"
    row = "1,0," + ",".join(["0.1"] * 6) + ",0.1,0,0.5,,,,0,0.1,0.5,0,0,0.6\n"
    (tmp_path / "m.csv").write_text(head + row)
    with pytest.raises(DataError, match=r"4 reflectors in the header, 3 nominal positions"):
        read_measured_csv(tmp_path / "m.csv", robot)
    P = np.array([[0.1, 0, 0], [0.05, 0.05, 0], [0, 0.1, 0], [0, 0, 0.1]])
    p = read_measured_csv(tmp_path / "m.csv", robot, ImportOptions(markers=P))
    assert p.kind == "markers" and np.isnan(p.markers[0, 1]).all() and np.isfinite(p.xyz).all()
    # the fit of the three seen reflectors: the tool origin (a pure translation here)
    np.testing.assert_allclose(p.xyz[0], [0.0, 0.0, 0.5], atol=1e-12)
    write_measured_csv(tmp_path / "back.csv", p)
    assert ",,," in (tmp_path / "back.csv").read_text()


def test_two_raw_reflectors_are_imported_as_their_positions(tmp_path, capsys):
    """Two reflectors give no pose: imported as raw reflector data (their positions), which
    calibrate identifies from the positions (tests/test_reflector_points.py); no pose is made up."""
    head = "pose_id,time_s," + ",".join(f"q{j}" for j in range(1, 7)) + "," + \
        ",".join(f"m{i}_{a}" for i in (1, 2) for a in "xyz") + "\n"
    (tmp_path / "m.csv").write_text(head + "1,0," + ",".join(["0.1"] * 6) + ",0.1,0,0.5,0,0.1,0.5\n"
                                    + "2,1," + ",".join(["0.2"] * 6) + ",,,,0,0.1,0.6\n")
    (tmp_path / "markers.yaml").write_text("markers: [[0.05, 0, 0], [0, 0.05, 0]]\n")
    run = tmp_path / "run"
    assert main(["import", str(tmp_path / "m.csv"), "--run", str(run), "--markers", str(tmp_path / "markers.yaml"),
                 "--quiet"]) == 0
    with open_run(run) as store:
        p = store.load_measured(include_unusable=True)
    assert p.kind == "markers" and p.markers.shape == (2, 2, 3) and np.isnan(p.xyz).all()
    np.testing.assert_allclose(p.markers[0], [[0.1, 0, 0.5], [0, 0.1, 0.5]], atol=0)
    assert np.isnan(p.markers[1, 0]).all() and np.allclose(p.markers[1, 1], [0, 0.1, 0.6])
    np.testing.assert_allclose(p.marker_positions, [[0.05, 0, 0], [0, 0.05, 0]])


def test_too_few_poses_is_one_line_saying_how_many(tmp_path, capsys):
    urdf = _erd(ROBOTS["ur10"][0])
    csv_path = tmp_path / "m.csv"
    assert main(["synth", "--csv", str(csv_path), "--robot", urdf, "--tool-frame", "tool0", "--poses", "8",
                 "--kind", "point"]) == 0
    run = tmp_path / "run"
    assert main(["import", str(csv_path), "--run", str(run), "--robot", urdf, "--tool-frame", "tool0",
                 "--quiet"]) == 0
    capsys.readouterr()
    assert main(["calibrate", str(run), "--no-ann", "--quiet"]) == 1
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "base parameters" in err[0] and "training poses" in err[0] and "ur10" in err[0]


def test_data_that_do_not_fit_the_runs_robot_name_robot_and_pose(tmp_path, capsys):
    urdf = _erd(ROBOTS["ur10"][0])
    csv_path = tmp_path / "m.csv"
    assert main(["synth", "--csv", str(csv_path), "--robot", urdf, "--tool-frame", "tool0", "--poses", "60"]) == 0
    run = tmp_path / "run"
    assert main(["import", str(csv_path), "--run", str(run), "--robot", urdf, "--tool-frame", "tool0",
                 "--quiet"]) == 0
    # a log written before the robot record (campaign.measure.robot_record; a log that records it refuses
    # another robot at once, tests/test_trust_log.py), told another robot afterwards: calibrate names
    # that robot and the first pose outside it
    with sqlite3.connect(run / "measurements.sqlite") as db:
        db.execute("DELETE FROM meta WHERE key = 'robot_record'")
    cfg = run / "campaign.yaml"
    cfg.write_text(cfg.read_text().replace(urdf, "comau_racer5_080").replace("tool_frame: tool0\n", ""))
    capsys.readouterr()
    assert main(["calibrate", str(run), "--no-ann", "--quiet"]) == 1
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "COMAU" in err[0] and "pose_id" in err[0] and "outside the joint limit" in err[0], err


def test_one_reflector_off_the_tool_origin(tmp_path, capsys):
    """robot.yaml names one reflector 6 cm off tool0: x,y,z data are fitted at that reflector."""
    from campaign.sim.truth import read_truth

    (tmp_path / "robot.yaml").write_text(
        f"urdf: {_erd(ROBOTS['ur10'][0])}\nname: ur10_smr\ntool_frame: tool0\n"
        "reflectors:\n  - {name: smr, position_m: [0.03, 0.02, 0.05]}\n")
    spec = str(tmp_path / "robot.yaml")
    csv_path, truth_path = tmp_path / "m.csv", tmp_path / "t.yaml"
    assert main(["synth", "--csv", str(csv_path), "--truth", str(truth_path), "--robot", spec, "--poses", "300",
                 "--seed", "2", "--kind", "point", "--frame", "tracker"]) == 0
    run = tmp_path / "run"
    assert main(["import", str(csv_path), "--run", str(run), "--robot", spec, "--frame", "tracker", "--quiet"]) == 0
    assert main(["calibrate", str(run), "--no-ann", "--quiet", "--no-report"]) == 0
    test = json.loads((run / "calibration" / "metrics.json").read_text())["stages"]["geometric"]["test"]
    robot = RobotModel.load(spec)
    truth = read_truth(truth_path, robot)
    with open_run(run) as store:
        poses = store.load_measured()
    te = train_test_split(poses.pose_id)
    T = truth.T_LI @ truth.pose(poses.q[te])
    true_xyz = T[:, :3, 3] + T[:, :3, :3] @ np.array([0.03, 0.02, 0.05])
    floor_mm = 1e3 * np.linalg.norm(poses.xyz[te] - true_xyz, axis=1).mean()
    assert test["position_mm"]["mean"] <= 1.1 * floor_mm, (test["position_mm"]["mean"], floor_mm)
    capsys.readouterr()
    assert main(["diagnose", str(run), "--json", "--folds", "2", "--no-report"]) == 0
    doc = json.loads(capsys.readouterr().out)
    assert doc["ranking"] is not None


def test_correlated_pairs_are_a_count_and_the_worst_five(tmp_path):
    from campaign.identify.calibrate import CalibrationResult, summary_text
    from campaign.identify.metrics import error_stats
    from campaign.identify.solver import CalibrationModel
    from campaign.model.kinematics import forward

    robot = RobotModel.load(_erd("tiago_description/robots/tiago.urdf"), base_frame="base_footprint",
                            tool_frame="arm_tool_link")
    rng = np.random.default_rng(0)
    span = 0.2 * (robot.q_upper - robot.q_lower)  # a small corner of the workspace: parameters blur together
    q = robot.q_mid + rng.uniform(-0.5, 0.5, size=(40, robot.n_joints)) * span
    T = forward(robot, q, rng.normal(0, 1e-3, robot.n_params))
    T[:, :3, 3] += rng.normal(0, 1e-5, (40, 3))
    m = CalibrationModel(robot=robot, position_only=True).fit(q, T)
    assert len(m.correlated_pairs_) > 5
    st = {"train": error_stats(m.residuals(q, T), orientation=False)}
    st["test"] = st["train"]
    text = summary_text(CalibrationResult(tmp_path, {"geometric": st}, ["geometric"], m, np.zeros(40, bool)))
    line = next(ln for ln in text.splitlines() if ln.startswith("strongly correlated"))
    assert f"{len(m.correlated_pairs_)} pairs" in line and line.count(" ~ ") == 5
    worst = sorted(abs(r) for _, _, r in m.correlated_pairs_)[-1]
    assert f"{worst:.3f}" in line
