"""Real files as they come (issue 29, items 11-16): what a user at the command line hit with
FIGAROH's and a FANUC cell's files, each a working result or one clear line. References: files
written in the test itself (synth's seeded data, read back independently with numpy)."""

import csv
import json
import re

import numpy as np
import pytest
import yaml

from campaign.cli import main


def _synth(tmp_path, name, *args):
    out = tmp_path / f"{name}.csv"
    assert main(["synth", "--csv", str(out), *args]) == 0
    return out


def _read(path):
    with open(path, newline="") as fh:
        rows = list(csv.reader(fh))
    return rows[0], np.array([[float(c) if c else np.nan for c in r] for r in rows[1:]])


def _write(path, header, values):
    with open(path, "w", newline="") as fh:
        w = csv.writer(fh)
        w.writerow(header)
        w.writerows([[repr(float(v)) for v in row] for row in values])


def test_a_file_without_pose_id_is_imported_with_its_rows_numbered_and_says_so(tmp_path, capsys):
    src = _synth(tmp_path, "ur10", "--robot", "ur10", "--poses", "30", "--seed", "2")
    header, values = _read(src)
    _write(tmp_path / "noid.csv", header[1:], values[:, 1:])  # FIGAROH's files have no pose_id
    capsys.readouterr()
    assert main(["import", str(tmp_path / "noid.csv"), "--run", str(tmp_path / "run"), "--robot", "ur10",
                 "--quiet"]) == 0
    out = capsys.readouterr().out
    assert "no pose_id column: the 30 rows are numbered 0..29 in file order" in out
    assert main(["export", str(tmp_path / "run"), "--csv", str(tmp_path / "back.csv")]) == 0
    back_header, back = _read(tmp_path / "back.csv")
    assert back_header == header
    np.testing.assert_array_equal(back[:, 0], np.arange(30))
    np.testing.assert_allclose(back[:, 1:], values[:, 1:], rtol=0, atol=1e-12)


@pytest.fixture(scope="module")
def named_ur10(tmp_path_factory):
    """A UR10 run imported from a file with its own column names (robot.yaml's ``columns:``),
    calibrated; the joints of the file, as written."""
    from campaign.model.robot import RobotModel

    tmp = tmp_path_factory.mktemp("named")
    src = _synth(tmp, "ur10", "--robot", "ur10", "--poses", "60", "--seed", "3")
    header, values = _read(src)
    names = {"pose_id": "id", **{f"q{j}": f"J{j}" for j in range(1, 7)}, "x": "X", "y": "Y", "z": "Z"}
    _write(tmp / "named.csv", [names.get(h, h) for h in header], values)
    ur10 = RobotModel.load("ur10")
    meta = tmp / "ur10" / "robot.yaml"
    meta.parent.mkdir()
    meta.write_text(yaml.safe_dump({"urdf": str(ur10.urdf_path), "tool_frame": "tool0", "columns": names}))
    run = tmp / "run"
    assert main(["import", str(tmp / "named.csv"), "--run", str(run), "--robot", str(meta), "--quiet"]) == 0
    assert main(["calibrate", str(run), "--no-ann", "--no-report", "--quiet"]) == 0
    return run, values[:, [header.index(f"q{j}") for j in range(1, 7)]]


@pytest.mark.parametrize("cmd", ["predict", "compensate"])
def test_predict_and_compensate_read_the_files_own_column_names_as_import_does(named_ur10, tmp_path, capsys, cmd):
    run, q = named_ur10
    q = q[:8]
    _write(tmp_path / "plain.csv", [f"q{j}" for j in range(1, 7)], q)
    _write(tmp_path / "yaml.csv", [f"J{j}" for j in range(1, 7)], q)  # robot.yaml's names, no x,y,z here
    _write(tmp_path / "flag.csv", [f"A{j}" for j in range(1, 7)], q)
    out = {name: ["--out", str(tmp_path / f"{name}_out.csv")] for name in ("plain", "yaml", "flag")}
    assert main([cmd, str(run), "--csv", str(tmp_path / "plain.csv"), *out["plain"]]) == 0
    assert main([cmd, str(run), "--csv", str(tmp_path / "yaml.csv"), *out["yaml"]]) == 0
    assert main([cmd, str(run), "--csv", str(tmp_path / "flag.csv"), *out["flag"]]) == 1
    err = capsys.readouterr().err  # the mapping robot.yaml gave, named as robot.yaml's (no --columns was given)
    assert "robot.yaml: columns: names column(s) J1, J2, J3, J4, J5, J6, which the header does not have" in err
    assert main([cmd, str(run), "--csv", str(tmp_path / "flag.csv"), *out["flag"],
                 "--columns", ",".join(f"q{j}=A{j}" for j in range(1, 7))]) == 0
    ref_header, ref = _read(tmp_path / "plain_out.csv")
    for name in ("yaml", "flag"):
        got_header, got = _read(tmp_path / f"{name}_out.csv")
        assert got_header == ref_header
        np.testing.assert_array_equal(got, ref)
    if cmd == "predict":  # the joints read are the file's
        np.testing.assert_allclose(ref[:, 1:7], q, rtol=0, atol=1e-12)


def test_a_near_miss_column_name_points_to_columns_and_an_empty_file_names_the_header(tmp_path, capsys):
    src = _synth(tmp_path, "ur10", "--robot", "ur10", "--poses", "5", "--seed", "4")
    header, values = _read(src)
    _write(tmp_path / "near.csv", [{"q1": "Q1", "q2": "q_2"}.get(h, h) for h in header], values)
    assert main(["import", str(tmp_path / "near.csv"), "--run", str(tmp_path / "a"), "--robot", "ur10"]) == 1
    assert "missing column(s) q1, q2 in the header (the file's own names: --columns q1=Q1,q2=q_2" \
        in capsys.readouterr().err
    (tmp_path / "empty.csv").write_text("")
    assert main(["import", str(tmp_path / "empty.csv"), "--run", str(tmp_path / "b"), "--robot", "ur10"]) == 1
    assert "empty file (expected header [pose_id,][time_s,]q1,...,q6, then x,y,z,rx,ry,rz" in capsys.readouterr().err


def _mounting():
    """A marker plate 115 mm from the UR10's flange, turned 29° (FIGAROH's UR10 file)."""
    from scipy.spatial.transform import Rotation

    X = np.eye(4)
    X[:3, :3] = Rotation.from_rotvec(np.deg2rad(29.0) * np.array([1.0, 0.3, 0.0]) / np.hypot(1.0, 0.3)).as_matrix()
    X[:3, 3] = [0.02, -0.04, 0.106]
    return X


@pytest.fixture(scope="module")
def mounted_ur10(tmp_path_factory):
    """UR10 6-D data and raw-reflector data measured on a plate the URDF does not describe (true
    geometric errors of the paper's size, 10 µm noise), in the robot's frame; the truth kept apart."""
    from campaign.model.robot import RobotModel
    from campaign.sim.truth import make_truth, random_joint_poses

    tmp = tmp_path_factory.mktemp("mounted")
    ur10 = RobotModel.load("ur10")
    truth = make_truth(ur10, seed=8)
    X = _mounting()
    q = random_joint_poses(ur10, 120, seed=9)
    T = truth.pose(q) @ X
    rng = np.random.default_rng(10)
    from campaign.model.rotations import matrix_to_rotvec

    xyz = T[:, :3, 3] + rng.normal(0, 1e-5, (len(q), 3))
    qcols = [f"q{j}" for j in range(1, 7)]
    _write(tmp / "pose.csv", ["pose_id", *qcols, "x", "y", "z", "rx", "ry", "rz"],
           np.column_stack([np.arange(len(q)), q, xyz, matrix_to_rotvec(T[:, :3, :3])]))
    plate = np.array([[0.05, 0.0, 0.0], [0.0, 0.05, 0.0], [-0.04, -0.03, 0.02]])  # m, in the plate's frame
    (tmp / "plate.yaml").write_text(yaml.safe_dump({"markers": plate.tolist()}))
    M = np.einsum("nij,kj->nki", T[:, :3, :3], plate) + T[:, None, :3, 3] + rng.normal(0, 1e-5, (len(q), 3, 3))
    _write(tmp / "markers.csv", ["pose_id", *qcols, *(f"m{i}_{a}" for i in (1, 2, 3) for a in "xyz")],
           np.column_stack([np.arange(len(q)), q, M.reshape(len(q), 9)]))
    return tmp, truth, X, q


@pytest.mark.parametrize("kind", ["pose", "markers"])
def test_an_unknown_tool_mounting_is_said_and_fitted_not_blamed_on_the_joint_convention(mounted_ur10, tmp_path,
                                                                                         capsys, kind):
    tmp, truth, X, q = mounted_ur10
    run = tmp_path / "run"
    extra = ["--markers", str(tmp / "plate.yaml")] if kind == "markers" else []
    capsys.readouterr()
    assert main(["import", str(tmp / f"{kind}.csv"), "--run", str(run), "--robot", "ur10", "--quiet", *extra]) == 0
    err = capsys.readouterr().err
    assert "the tool frame is 29° and 115 mm from the URDF's (tool0): a tool mounting" in err
    assert "[nominal_residual]" not in err and "joint convention" not in err
    assert main(["calibrate", str(run), "--no-ann", "--no-report"]) == 0
    err = capsys.readouterr().err
    assert "the tool frame is 29° and 115 mm from the URDF's (tool0): a tool mounting, fitted" in err
    assert "[large_corrections]" not in err and "[nominal_residual]" not in err and "joint convention" not in err
    params = yaml.safe_load((run / "calibration" / "params.yaml").read_text())
    mounting = params["tool_mounting_in_tool"]
    np.testing.assert_allclose(mounting["translation_m"], X[:3, 3], atol=5e-3)  # the truth's tool errors beside it
    # the calibrated model against the truth (read only now), at poses it never saw, and the exported
    # URDF against the calibrated model (Pinocchio)
    import pinocchio as pin

    from campaign.sim.truth import random_joint_poses

    q_new = random_joint_poses(truth.robot, 6, seed=11)
    _write(tmp_path / "q.csv", [f"q{j}" for j in range(1, 7)], q_new)
    assert main(["predict", str(run), "--csv", str(tmp_path / "q.csv"), "--out", str(tmp_path / "p.csv")]) == 0
    header, pred = _read(tmp_path / "p.csv")
    T_true = truth.pose(q_new) @ X
    assert np.abs(pred[:, 7:10] - T_true[:, :3, 3]).max() < 2e-4
    assert main(["export", str(run), "--urdf", str(tmp_path / "cal.urdf")]) == 0
    model = pin.buildModelFromUrdf(str(tmp_path / "cal.urdf"))
    data = model.createData()
    frame = model.getFrameId("tool0")
    for k in range(len(q_new)):
        pin.framesForwardKinematics(model, data, q_new[k])
        np.testing.assert_allclose(data.oMf[frame].translation, pred[k, 7:10], atol=1e-9)
        np.testing.assert_allclose(pin.log3(data.oMf[frame].rotation), pred[k, 10:13], atol=1e-9)


def test_the_tracker_pose_in_metrics_maps_predict_and_the_exported_urdf_into_the_trackers_frame(tmp_path, capsys):
    import pinocchio as pin

    src = _synth(tmp_path, "ur10", "--robot", "ur10", "--poses", "120", "--seed", "12", "--frame", "tracker")
    run = tmp_path / "run"
    assert main(["import", str(src), "--run", str(run), "--robot", "ur10", "--frame", "tracker", "--quiet"]) == 0
    assert main(["calibrate", str(run), "--no-ann", "--no-report", "--quiet"]) == 0
    metrics = json.loads((run / "calibration" / "metrics.json").read_text())
    T_L_I = np.asarray(metrics["tracker"]["T_L_I"])
    for alias in ("T_L_I_registration", "tracker_pose_identified"):  # deprecated, the same matrix
        np.testing.assert_array_equal(metrics["tracker"][alias], T_L_I)
    header, values = _read(src)
    test = np.isin(values[:, 0], metrics["test_pose_ids"])
    q = values[test][:, 2:8]
    _write(tmp_path / "q.csv", [f"q{j}" for j in range(1, 7)], q)
    assert main(["predict", str(run), "--csv", str(tmp_path / "q.csv"), "--out", str(tmp_path / "p.csv")]) == 0
    pred = _read(tmp_path / "p.csv")[1][:, 7:10]
    measured_L = values[test][:, 8:11]  # the tracker's own readings of poses the fit never saw
    err_mm = 1e3 * np.linalg.norm(pred @ T_L_I[:3, :3].T + T_L_I[:3, 3] - measured_L, axis=1)
    assert err_mm.mean() < 0.05, err_mm.mean()  # 10 µm noise: about 0.016 mm mean, plus the fit's
    assert main(["export", str(run), "--urdf", str(tmp_path / "cal.urdf")]) == 0
    model = pin.buildModelFromUrdf(str(tmp_path / "cal.urdf"))
    data = model.createData()
    for k in range(len(q)):
        pin.framesForwardKinematics(model, data, q[k])
        y = T_L_I[:3, :3] @ data.oMf[model.getFrameId("tool0")].translation + T_L_I[:3, 3]
        assert np.linalg.norm(y - measured_L[k]) < 1e-4


@pytest.mark.parametrize("name, named", [
    ("comau_racer5_080", "robot.yaml names none"),
    ("ur10", "none named (ur10 was given without a robot.yaml)"),  # not "robot.yaml names none": it has none
])
def test_one_measured_point_is_said_by_import_calibrate_and_params_yaml(tmp_path, capsys, name, named):
    from campaign.model.robot import RobotModel
    from campaign.sim.truth import make_truth, random_joint_poses, random_tracker_pose

    robot = RobotModel.load(name)
    truth = make_truth(robot, seed=3, position_only=True)
    q = random_joint_poses(robot, 60, seed=4)
    T = truth.pose(q)
    P = T[:, :3, :3] @ np.array([0.08, -0.03, 0.06]) + T[:, :3, 3]  # a marker on the hand, 104 mm off
    T_L = random_tracker_pose(6)
    P = P @ T_L[:3, :3].T + T_L[:3, 3] + np.random.default_rng(7).normal(0, 1e-5, P.shape)
    _write(tmp_path / "p.csv", ["pose_id", *(f"q{j}" for j in range(1, 7)), "x", "y", "z"],
           np.column_stack([np.arange(len(q)), q, P]))
    run = tmp_path / "run"
    assert main(["import", str(tmp_path / "p.csv"), "--run", str(run), "--frame", "tracker", "--quiet",
                 "--robot", name]) == 0
    said_import = re.search(r"measured at (\([^)]*\) mm)", capsys.readouterr().err).group(1)
    assert main(["calibrate", str(run), "--no-ann", "--no-report"]) == 0
    said_calibrate = re.search(re.escape(named) + r": measured at (\([^)]*\) mm)",
                               capsys.readouterr().err).group(1)
    point = yaml.safe_load((run / "calibration" / "params.yaml").read_text())["measured_point_in_tool_m"]
    assert said_import == said_calibrate == "(" + ", ".join(f"{1e3 * v:.1f}" for v in point) + ") mm"
    np.testing.assert_allclose(point, [0.08, -0.03, 0.06], atol=5e-3)  # the truth's tool errors beside it


# -- item 16: the messages -------------------------------------------------------------------------
@pytest.fixture(scope="module")
def comau_run(tmp_path_factory):
    """A COMAU campaign (the default robot) imported and calibrated with ground compliance."""
    tmp = tmp_path_factory.mktemp("comau")
    src = _synth(tmp, "comau", "--poses", "80", "--seed", "13")
    assert main(["import", str(src), "--run", str(tmp / "run"), "--quiet"]) == 0
    assert main(["calibrate", str(tmp / "run"), "--no-ann", "--no-report", "--quiet",
                 "--effects", "ground_compliance"]) == 0
    return tmp / "run", src


def test_a_reading_past_a_limit_names_the_slack_in_force_and_a_forgotten_robot_gets_its_own_hint(comau_run,
                                                                                                 tmp_path, capsys):
    from campaign.model.robot import RobotModel

    _, src = comau_run
    header, values = _read(src)
    comau = RobotModel.load()
    values[4, header.index("q1")] = comau.q_upper[0] + np.deg2rad(0.01)  # 0.01 deg past, file line 6
    _write(tmp_path / "past.csv", header, values)
    assert main(["import", str(tmp_path / "past.csv"), "--run", str(tmp_path / "a"), "--limit-slack", "0.001"]) == 1
    err = capsys.readouterr().err
    assert "line 6, column q1" in err and "more than the --limit-slack in force: 0.001 deg" in err
    assert main(["import", str(tmp_path / "past.csv"), "--run", str(tmp_path / "b")]) == 1
    assert "readings slightly past a limit: --limit-slack DEG_OR_MM" in capsys.readouterr().err
    ur10 = _synth(tmp_path, "ur10", "--robot", "ur10", "--poses", "20", "--seed", "14")
    assert main(["import", str(ur10), "--run", str(tmp_path / "c")]) == 1  # --robot ur10 forgotten
    err = capsys.readouterr().err
    assert "no reading slightly past, but data of another robot" in err and "--robot NAME|URDF" in err
    assert "--limit-slack" not in err


def test_an_unknown_robot_lists_every_known_name(tmp_path, capsys):
    from campaign.model.catalog import known_robots

    assert main(["import", str(tmp_path / "x.csv"), "--run", str(tmp_path / "r"), "--robot", "ur11"]) == 1
    err = capsys.readouterr().err
    assert "did you mean ur10?" in err
    for known, _ in known_robots():
        assert known.name in err


@pytest.mark.parametrize("cmd", ["predict", "compensate"])
def test_joints_in_degrees_given_to_predict_and_compensate_are_named(comau_run, tmp_path, capsys, cmd):
    run, src = comau_run
    header, values = _read(src)
    _write(tmp_path / "big.csv", [f"q{j}" for j in range(1, 7)], np.rad2deg(values[:4, 2:8]))
    assert main([cmd, str(run), "--csv", str(tmp_path / "big.csv")]) == 1
    assert "this looks like degrees; --angle-unit deg" in capsys.readouterr().err
    assert main([cmd, str(run), "--csv", str(tmp_path / "big.csv"), "--angle-unit", "deg",
                 "--out", str(tmp_path / "out.csv")]) == 0


def test_export_says_the_joint_convention_the_gravity_and_what_it_leaves_out(comau_run, tmp_path, capsys):
    import pinocchio as pin

    run, _ = comau_run
    capsys.readouterr()
    assert main(["export", str(run), "--urdf", str(tmp_path / "cal.urdf")]) == 0
    out = capsys.readouterr().out
    text = (tmp_path / "cal.urdf").read_text()
    for said in ("joints: the URDF's own convention", "gravity in the base frame 'I': (0, 9.81, 0) m/s^2",
                 "left out: the effects ground_compliance"):
        assert said in out and said in text
    from campaign.model.robot import RobotModel

    pin.buildModelFromUrdf(str(tmp_path / "cal.urdf"))  # still a URDF
    import xml.etree.ElementTree as ET

    ET.parse(tmp_path / "cal.urdf")  # and well-formed XML: no "--" in the comment
    # the exported URDF loaded as a robot (a bare URDF, no robot.yaml) has the COMAU's gravity, not -z
    exported = RobotModel.load(str(tmp_path / "cal.urdf"), tool_frame="E")
    np.testing.assert_allclose(exported.gravity_in_I, RobotModel.load().gravity_in_I, atol=1e-12)


# -- item 17: each held-out figure named by what it is ---------------------------------------------
def test_calibrate_and_diagnose_name_the_test_set_the_folds_and_the_model_choices_leave_one_out(comau_run, capsys):
    run, _ = comau_run
    capsys.readouterr()
    assert main(["calibrate", str(run), "--no-ann", "--no-report", "--effects", "ground_compliance"]) == 0
    out = capsys.readouterr().out
    metrics = json.loads((run / "calibration" / "metrics.json").read_text())
    n_train = metrics["stages"]["geometric"]["train"]["n_poses"]
    assert ("model: lsq for the geometry alone, chosen before the effects of geometric+ground_compliance "
            f"(scored on the test set below) (least squares: leave-one-out mean") in out
    assert f"on the {n_train} training poses" in out
    assert "test-set mean position error at the tool point" in out
    assert main(["diagnose", str(run), "--folds", "3", "--candidates", "drift", "--no-report"]) == 0
    said = capsys.readouterr().out
    assert "cross-validated mean" in said and "held-out folds of the training poses" in said
    for text in (out, said):
        assert "held-out mean" not in text and "cross-validated held-out" not in text  # no figure without its name


# -- item 18: one number, one count, one claim, said once --------------------------------------------
def test_the_history_table_and_chart_show_each_stage_from_the_last_calibration_that_fitted_it(tmp_path):
    from campaign.identify.report import history_table
    from campaign.identify.report_figures import svg_history

    def stats(mm):
        return {"position_mm": {"max": 2 * mm, "mean": mm, "q90": 1.5 * mm}, "n_poses": 30}

    runs = [{"order": ["nominal", "geometric"], "stages": {"nominal": stats(7.0267), "geometric": stats(0.1015)}},
            {"order": ["nominal", "geometric", "geometric+ground_compliance"],
             "stages": {"nominal": stats(7.0267), "geometric": stats(0.1015),
                        "geometric+ground_compliance": stats(0.01066)}},
            {"order": ["nominal", "geometric", "geometric+ground_compliance"],  # more poses measured
             "stages": {"nominal": stats(7.01), "geometric": stats(0.1003),
                        "geometric+ground_compliance": stats(0.01064)}}]
    (tmp_path / "calibration").mkdir()
    (tmp_path / "calibration" / "history.json").write_text(json.dumps({"runs": runs}))
    rows = history_table(tmp_path).splitlines()[1:]
    assert [r.split()[0] for r in rows] == ["3", "3", "3"]
    assert rows[-1].split()[1:3] == ["geometric+ground_compliance", "0.0106"]  # as the verdict rounds 0.01064
    svg_history(tmp_path / "calibration" / "history.json", tmp_path, noise_floor=None)
    chart = (tmp_path / "history.svg").read_text()
    assert "test-set mean" in chart


def test_the_fold_count_names_the_training_poses_and_their_distinct_poses_once():
    from campaign.diagnose.engine import folds_text
    from campaign.identify.split import FoldRule

    text = folds_text(5, 129, FoldRule(5, 120))
    assert text.startswith("5 held-out folds of 129 training poses (120 distinct: a pose and its repeats share a fold")


@pytest.mark.parametrize("rho, p, claim", [(-0.06, 0.4, "is a function of the gravity load"),
                                           (0.62, 1e-9, "grows with the gravity load")])
def test_the_signature_says_grows_with_the_load_only_when_the_errors_size_rises_with_it(rho, p, claim):
    from campaign.diagnose.signature import Signature

    text = Signature(("q2",), growth={"gravity load": {"share_of_gain": 0.85, "spearman_rho": rho,
                                                        "spearman_p": p}}).text()
    assert claim in text and f"Spearman ρ {rho:+.2f}" in text
    assert ("does not rise" in text) == (rho < 0.3)


def test_no_network_is_said_once_and_help_names_any_serial_arm(comau_run, capsys):
    run, _ = comau_run
    capsys.readouterr()
    assert main(["calibrate", str(run), "--no-report"]) == 0  # too few poses for the network: said why
    out, err = capsys.readouterr()
    assert (out + err).count("no neural compensator") == 1
    from campaign.cli import build_parser

    said = " ".join(build_parser().format_help().split())
    assert "6-axis" not in said and "any serial robot arm" in said


# -- item 19: a label off the UR10 tour plot -----------------------------------------------------------
def test_the_tour_plots_labels_stay_inside_their_axes(tmp_path):
    from campaign.plan.plot import tour_figure, tour_positions
    from campaign.run import RunFolder
    from campaign.sim.truth import random_joint_poses

    (tmp_path / "campaign.yaml").write_text("robot: ur10\n")
    run = RunFolder(tmp_path)
    robot, scene = run.robot(), run.scene()
    Q = random_joint_poses(robot, 40, seed=15)
    T = np.eye(4) if getattr(scene, "T_cell_I", None) is None else np.asarray(scene.T_cell_I)
    t = tour_positions(robot, Q) @ T[:3, :3].T + T[:3, 3]
    far = int(np.argmax(t[:, 2]))  # the pose nearest the tracker: at the right edge of both views
    Q[[far, 20]] = Q[[20, far]]
    front = np.arange(40) >= 20  # the front group begins at the edge, as in the UR10's plan
    fig = tour_figure(robot, scene, Q, front)
    fig.canvas.draw()
    renderer = fig.canvas.get_renderer()
    labels = 0
    for ax in fig.axes[:2]:
        box = ax.get_window_extent(renderer)
        for text in ax.texts:
            if "#" not in text.get_text():
                continue
            labels += 1
            t = text.get_window_extent(renderer)
            assert box.x0 - 1 <= t.x0 and t.x1 <= box.x1 + 1 and box.y0 - 1 <= t.y0 and t.y1 <= box.y1 + 1, \
                (text.get_text(), t, box)
    assert labels == 6  # start, end and the group's beginning in each view
    import matplotlib.pyplot as plt

    plt.close(fig)


@pytest.mark.parametrize("which, said, unsaid", [
    ("tool", "the measured tool frame is not the URDF's", "joint convention"),
    ("offset", "check the joint convention (an offset or a sign", "tool frame"),
])
def test_a_large_correction_names_the_cause_its_transform_points_to(robot, which, said, unsaid):
    from campaign.measure.plausibility import check_fit

    p = np.zeros(robot.n_params)
    k = 6 * (robot.n_joints + 1) + 3 if which == "tool" else robot.joint_offset_index[1]  # pR_6E_x or pq2
    p[k] = 0.5  # rad: 29 deg
    (finding,) = [f for f in check_fit(robot, p, noise_sigma_m=1e-5) if f.code == "large_corrections"]
    assert robot.param_names[k] in finding.message and said in finding.message and unsaid not in finding.message


# Variants checked from outside (issue 29's 'Done means'): files of a user's own


@pytest.fixture(scope="module")
def markers_ur10(tmp_path_factory):
    """A UR10 raw-reflector run (a reflector missed now and then: empty cells), calibrated."""
    tmp = tmp_path_factory.mktemp("markers")
    src = tmp / "m.csv"
    assert main(["synth", "--csv", str(src), "--robot", "ur10", "--poses", "50", "--seed", "4", "--kind", "markers",
                 "--miss-rate", "0.1"]) == 0
    run = tmp / "run"
    assert main(["import", str(src), "--run", str(run), "--robot", "ur10", "--markers",
                 str(tmp / "m.markers.yaml"), "--quiet"]) == 0
    assert main(["calibrate", str(run), "--no-ann", "--no-report", "--quiet"]) == 0
    return run, src


@pytest.mark.parametrize("cmd", ["predict", "compensate"])
def test_the_measured_file_itself_is_read_by_predict_its_empty_reflector_cells_unread(markers_ur10, tmp_path,
                                                                                     capsys, cmd):
    run, src = markers_ur10
    header, values = _read(src)
    assert np.isnan(values).any()  # the missed reflectors
    joints = ["pose_id"] + [f"q{j}" for j in range(1, 7)]
    _write(tmp_path / "joints.csv", joints, values[:, [header.index(h) for h in joints]])
    labelled = tmp_path / "labelled.csv"  # and a text label beside them
    with open(src) as fh, open(labelled, "w") as out:
        for k, line in enumerate(fh):
            out.write(("label," if k == 0 else f"P{k},") + line)
    outs = []
    for k, path in enumerate((tmp_path / "joints.csv", src, labelled)):
        outs.append(tmp_path / f"out{k}.csv")
        assert main([cmd, str(run), "--csv", str(path), "--out", str(outs[-1])]) == 0, capsys.readouterr().err
    first = _read(outs[0])[1]
    assert len(first) == len(values)
    for out in outs[1:]:
        np.testing.assert_array_equal(_read(out)[1], first)


def _planned(tmp_path, name, header, values):
    """A run folder whose plan (written here) lists the synth poses under grid-like ids, the
    first one measured twice (a repeat), 10 of them as its validation poses."""
    run = tmp_path / name
    (run / "plan").mkdir(parents=True)
    q = values[:, [header.index(f"q{j}") for j in range(1, 7)]]
    ids = 700_000 + 7 * np.arange(len(q))
    _write(run / "plan" / "poses.csv", ["pose_id"] + [f"q{j}" for j in range(1, 7)],
           np.column_stack([np.r_[ids, 1_000_000_000 + ids[0]], np.r_[q, q[:1]]]))
    (run / "plan" / "validation.csv").write_text("pose_id\n" + "".join(f"{i}\n" for i in ids[-10:]))
    return run, ids


def test_a_planned_runs_file_without_pose_id_finds_the_plans_poses_and_own_ids_get_the_80_20_split(tmp_path,
                                                                                                      capsys):
    src = tmp_path / "c.csv"
    assert main(["synth", "--csv", str(src), "--poses", "50", "--seed", "8"]) == 0
    header, values = _read(src)
    values = np.r_[values, values[:1]]  # the first pose measured again: the plan's repeat
    run, ids = _planned(tmp_path, "noid", header, values)
    _write(tmp_path / "noid.csv", header[1:], values[:, 1:])
    capsys.readouterr()
    assert main(["import", str(tmp_path / "noid.csv"), "--run", str(run), "--quiet"]) == 0
    assert "the 51 rows are the plan's poses by their joints" in capsys.readouterr().out
    assert main(["calibrate", str(run), "--no-ann", "--no-report", "--quiet"]) == 0
    metrics = json.loads((run / "calibration" / "metrics.json").read_text())
    assert metrics["test_pose_ids"] == [int(i) for i in ids[-10:]]  # was: 0 test poses, calibrate refused
    assert metrics["stages"]["geometric"]["train"]["n_poses"] == 41  # 40 poses and the repeat

    own, _ = _planned(tmp_path, "own", header, values)
    _write(tmp_path / "own.csv", header, np.column_stack([np.arange(1, 52), values[:, 1:]]))
    assert main(["import", str(tmp_path / "own.csv"), "--run", str(own), "--quiet"]) == 0
    capsys.readouterr()
    assert main(["calibrate", str(own), "--no-ann", "--no-report"]) == 0
    assert "none of the 51 measured pose ids is one of the plan's" in capsys.readouterr().err
    n_test = json.loads((own / "calibration" / "metrics.json").read_text())["stages"]["geometric"]["test"]["n_poses"]
    assert 5 <= n_test <= 15  # the 80/20 split of 51 poses


def test_a_file_of_another_robots_joints_is_named_so_with_both_counts(tmp_path, capsys):
    src = tmp_path / "ur10.csv"
    assert main(["synth", "--csv", str(src), "--robot", "ur10", "--poses", "12", "--seed", "1"]) == 0
    capsys.readouterr()
    assert main(["import", str(src), "--run", str(tmp_path / "a"), "--robot", "panda"]) == 1
    err = capsys.readouterr().err  # was: missing column q7 ... --columns q7=COLUMN
    assert "the file has 6 joint columns (q1..q6), panda has 7 (q1..q7): another robot's data?" in err
    assert "--columns" not in err
    header, values = _read(src)
    _write(tmp_path / "eight.csv", header[:8] + ["q7", "q8"] + header[8:],
           np.column_stack([values[:, :8], np.zeros((12, 2)), values[:, 8:]]))
    assert main(["import", str(tmp_path / "eight.csv"), "--run", str(tmp_path / "b")]) == 1
    assert "the file has 8 joint columns (q1..q8), COMAU Racer5-0.80 has 6" in capsys.readouterr().err


@pytest.mark.parametrize("cmd", ["import", "predict"])
def test_blank_lines_above_the_header_are_skipped(markers_ur10, tmp_path, capsys, cmd):
    run, src = markers_ur10
    blank = tmp_path / "blank.csv"
    blank.write_text("\n \r\n" + src.read_text())
    (tmp_path / "none.csv").write_text("\n\n")

    def args(path, k):
        return (["import", str(path), "--run", str(tmp_path / f"r{k}"), "--robot", "ur10", "--markers",
                 str(src.with_suffix(".markers.yaml"))] if cmd == "import"
                else ["predict", str(run), "--csv", str(path), "--out", str(tmp_path / f"p{k}.csv")])

    assert main(args(blank, 0)) == 0, capsys.readouterr().err  # was: 'line 3 has 17 fields, the header has 0'
    assert main(args(tmp_path / "none.csv", 1)) == 1
    assert "none.csv: empty file (expected header" in capsys.readouterr().err


@pytest.mark.parametrize("cmd", ["predict", "compensate"])
def test_predict_reads_the_file_as_the_runs_import_did_with_its_columns(tmp_path, capsys, cmd):
    src = tmp_path / "s.csv"
    assert main(["synth", "--csv", str(src), "--robot", "ur10", "--poses", "40", "--seed", "6"]) == 0
    header, values = _read(src)
    names = {"pose_id": "Nr", **{f"q{j}": f"A{j}" for j in range(1, 7)}, "x": "X", "y": "Y", "z": "Z"}
    _write(tmp_path / "own.csv", [names.get(h, h) for h in header], values)
    run = tmp_path / "run"
    mapping = ",".join(f"{k}={v}" for k, v in names.items())
    assert main(["import", str(tmp_path / "own.csv"), "--run", str(run), "--robot", "ur10", "--columns", mapping,
                 "--quiet"]) == 0
    assert main(["calibrate", str(run), "--no-ann", "--no-report", "--quiet"]) == 0
    joints = [f"A{j}" for j in range(1, 7)]
    _write(tmp_path / "joints.csv", joints, values[:, [header.index(f"q{j}") for j in range(1, 7)]])
    plain = tmp_path / "plain.csv"
    _write(plain, [f"q{j}" for j in range(1, 7)], values[:, [header.index(f"q{j}") for j in range(1, 7)]])
    outs = [tmp_path / f"{k}.csv" for k in range(3)]
    for path, out in zip((tmp_path / "own.csv", tmp_path / "joints.csv", plain), outs):
        assert main([cmd, str(run), "--csv", str(path), "--out", str(out)]) == 0, capsys.readouterr().err
    ref = _read(outs[2])[1]  # was: 'missing column(s) q1, ..., q6' without --columns given again
    np.testing.assert_array_equal(_read(outs[1])[1], ref)
    np.testing.assert_array_equal(_read(outs[0])[1][:, 1:], ref[:, 1:])
    np.testing.assert_array_equal(_read(outs[0])[1][:, 0], values[:, 0])  # the file's own pose ids, Nr


def test_the_signature_leaves_out_time_when_the_time_test_says_the_same_poses_did_not_move(tmp_path, capsys):
    """The tour sweeps joints 2 and 3 over the campaign (time stands in for them); eight poses
    measured again afterwards did not move: the signature and the verdict say what the time test
    says, not 'depends on time_s ... grows with time' beside it."""
    src = _synth(tmp_path, "g", "--poses", "160", "--hidden", "ground_compliance", "--seed", "11")
    header, values = _read(src)
    col = {h: j for j, h in enumerate(header)}
    rank = np.argsort(np.argsort(values[:, col["q2"]] + values[:, col["q3"]]))
    values[:, col["time_s"]] = 30.0 * rank
    again = values[::20].copy()  # measured again after the campaign, tracker noise only
    again[:, col["pose_id"]] += 10 ** 9
    again[:, col["time_s"]] = 30.0 * len(values) + 60 + 30 * np.arange(len(again))
    again[:, [col["x"], col["y"], col["z"]]] += np.random.default_rng(0).normal(0, 1e-5, (len(again), 3))
    _write(tmp_path / "toured.csv", header, np.r_[values, again])
    run = tmp_path / "run"
    assert main(["import", str(tmp_path / "toured.csv"), "--run", str(run), "--quiet"]) == 0
    (run / "campaign.yaml").write_text((run / "campaign.yaml").read_text() + "tracker: {noise_m: 1.0e-5}\n")
    assert main(["calibrate", str(run), "--no-ann", "--no-report", "--quiet"]) == 0
    capsys.readouterr()
    assert main(["diagnose", str(run), "--no-report", "--candidates", "drift"]) == 0
    said = capsys.readouterr().out
    out = json.loads((run / "diagnose" / "diagnosis.json").read_text())
    assert out["time_test"] and not out["time_test"]["moved"], said
    assert out["unexplained"]["depends_on"] and "time_s" not in out["unexplained"]["depends_on"], said
    signature = out["unexplained"].get("signature") or out.get("signature")
    assert "time_s" not in signature["depends_on"] and "time_s" not in signature["growth"], said
    assert "grows with time" not in said and "depends on time_s" not in said  # was: both, beside the time test


def test_readings_a_little_past_2pi_or_in_degrees_already_are_past_a_limit_not_degrees(tmp_path, capsys):
    """A joint offset of another convention takes UR10's q6 past its ±2π limit, and a reading of
    400° given with --angle-unit deg is 40° past it: neither 'looks like degrees; --angle-unit deg'."""
    src = _synth(tmp_path, "u", "--robot", "ur10", "--poses", "20", "--seed", "2")
    header, values = _read(src)
    shifted = values.copy()
    shifted[:, header.index("q6")] = np.where(values[:, header.index("q6")] > 0, 6.5, -6.6)
    _write(tmp_path / "offset.csv", header, shifted)
    capsys.readouterr()
    assert main(["import", str(tmp_path / "offset.csv"), "--run", str(tmp_path / "a"), "--robot", "ur10"]) == 1
    err = capsys.readouterr().err
    assert "rad is outside the joint limit" in err and "joint convention" in err and "looks like degrees" not in err
    deg = values.copy()
    cols = [header.index(f"q{j}") for j in range(1, 7)]
    deg[:, cols] = np.degrees(values[:, cols])
    deg[3, header.index("q6")] = 400.0
    _write(tmp_path / "deg.csv", header, deg)
    assert main(["import", str(tmp_path / "deg.csv"), "--run", str(tmp_path / "b"), "--robot", "ur10",
                 "--angle-unit", "deg"]) == 1
    err = capsys.readouterr().err  # was: '6.98132 exceeds 2*pi ... (this looks like degrees; --angle-unit deg)'
    assert "q6: 6.98132 rad is outside the joint limit" in err and "40 deg past" in err
    assert "looks like degrees" not in err
    deg[3, header.index("q6")] = 700.0  # a file in degrees read as rad is still named so
    _write(tmp_path / "deg.csv", header, deg)
    assert main(["import", str(tmp_path / "deg.csv"), "--run", str(tmp_path / "c"), "--robot", "ur10"]) == 1
    assert "looks like degrees; --angle-unit deg" in capsys.readouterr().err


@pytest.mark.parametrize("cmd", ["predict", "compensate"])
def test_predict_names_a_reading_far_past_a_limit_without_suggesting_limit_slack(comau_run, tmp_path, capsys, cmd):
    run, _ = comau_run
    (tmp_path / "far.csv").write_text("q1,q2,q3,q4,q5,q6\n0.1,0.9,-1.2,0.3,-0.6,0.2\n3.5,0.9,-1.2,0.3,-0.6,0.2\n")
    (tmp_path / "near.csv").write_text("q1,q2,q3,q4,q5,q6\n2.933,0.9,-1.2,0.3,-0.6,0.2\n")
    capsys.readouterr()
    assert main([cmd, str(run), "--csv", str(tmp_path / "far.csv")]) == 1
    err = capsys.readouterr().err  # was: '(limit slack in force: none, ...; --limit-slack DEG_OR_MM to accept more)'
    from campaign.model.robot import RobotModel

    far = np.degrees(3.5 - RobotModel.load().q_upper[0])
    assert f"{far:.3g} deg past it" in err and "another robot, unit or joint convention" in err
    assert "--limit-slack" not in err
    assert main([cmd, str(run), "--csv", str(tmp_path / "near.csv")]) == 1
    assert "--limit-slack DEG_OR_MM to accept more" in capsys.readouterr().err  # slightly past: the slack


def test_two_reflectors_on_an_unknown_plate_are_a_tool_mounting_not_a_joint_convention(mounted_ur10, tmp_path,
                                                                                       capsys):
    """Two of the plate's three reflectors: their rotation about their line is not observed, but
    where they sit is; import names the mounting (was: nominal_residual, 'check the joint
    convention'), calibrate fits there (was: large_corrections, a 100 mm tool correction), and
    predict places both reflectors where the truth does, at poses it never saw."""
    tmp, truth, X, q = mounted_ur10
    header, values = _read(tmp / "markers.csv")
    _write(tmp_path / "two.csv", header[:13], values[:, :13])
    plate = np.array(yaml.safe_load((tmp / "plate.yaml").read_text())["markers"])[:2]
    (tmp_path / "two.yaml").write_text(yaml.safe_dump({"markers": plate.tolist()}))
    run = tmp_path / "run"
    capsys.readouterr()
    assert main(["import", str(tmp_path / "two.csv"), "--run", str(run), "--robot", "ur10", "--quiet",
                 "--markers", str(tmp_path / "two.yaml")]) == 0
    err = capsys.readouterr().err
    assert "a tool mounting" in err and "two reflectors: of the frames turned about their line" in err
    assert "[nominal_residual]" not in err and "joint convention" not in err
    assert main(["calibrate", str(run), "--no-ann", "--no-report"]) == 0
    err = capsys.readouterr().err
    assert "a tool mounting, fitted" in err and "[large_corrections]" not in err and "joint convention" not in err
    from campaign.sim.truth import random_joint_poses
    from campaign.model.rotations import rotvec_to_matrix

    q_new = random_joint_poses(truth.robot, 6, seed=11)
    _write(tmp_path / "q.csv", [f"q{j}" for j in range(1, 7)], q_new)
    assert main(["predict", str(run), "--csv", str(tmp_path / "q.csv"), "--out", str(tmp_path / "p.csv")]) == 0
    pred = _read(tmp_path / "p.csv")[1]
    R, t = rotvec_to_matrix(pred[:, 10:13]), pred[:, 7:10]
    T_true = truth.pose(q_new) @ X  # the truth, read only now
    got = np.einsum("nij,kj->nki", R, plate) + t[:, None]
    want = np.einsum("nij,kj->nki", T_true[:, :3, :3], plate) + T_true[:, None, :3, 3]
    assert np.abs(got - want).max() < 2e-4  # m: both reflectors where the truth has them


@pytest.mark.parametrize("header, mapping", [
    ("id,joint1,joint2,joint3,joint4,joint5,joint6,x,y,z", "q1=joint1,q2=joint2,q3=joint3,q4=joint4,q5=joint5,q6=joint6"),
    ("id,axis_0,axis_1,axis_2,axis_3,axis_4,axis_5,x,y,z", "q1=axis_0,q2=axis_1,q3=axis_2,q4=axis_3,q5=axis_4,q6=axis_5"),
    ("pose_id,q1,q2,q3,q4,q5,q6,X_mm,Y_mm,Z_mm", "x=X_mm,y=Y_mm,z=Z_mm and --length-unit mm"),
])
def test_a_family_of_the_files_own_names_is_pointed_to_with_its_columns(tmp_path, capsys, header, mapping):
    (tmp_path / "own.csv").write_text(header + "\n1,0.1,0.2,0.3,0.4,0.5,0.6,0.5,0.1,0.9\n")
    capsys.readouterr()
    assert main(["import", str(tmp_path / "own.csv"), "--run", str(tmp_path / "r"), "--robot", "ur10"]) == 1
    assert f"(the file's own names: --columns {mapping}, or robot.yaml's columns:" in capsys.readouterr().err


def test_fewer_than_three_points_say_no_rigid_move_they_cannot_give(tmp_path, capsys):
    (tmp_path / "two.csv").write_text("pose_id,q1,q2,q3,q4,q5,q6,x,y,z\n1,0.1,0.2,0.3,0.4,0.5,0.6,0.5,0.1,0.9\n"
                                      "2,0.2,0.2,0.3,0.4,0.5,0.6,0.4,0.2,0.9\n")
    capsys.readouterr()
    main(["import", str(tmp_path / "two.csv"), "--run", str(tmp_path / "r"), "--robot", "ur10"])
    assert "nan" not in capsys.readouterr().err  # was: '... but nan mm after one rigid move'


@pytest.mark.parametrize("cmd", ["predict", "compensate"])
def test_radians_given_with_angle_unit_deg_are_named(comau_run, tmp_path, capsys, cmd):
    run, src = comau_run
    header, values = _read(src)
    q = values[:6, [header.index(f"q{j}") for j in range(1, 7)]]
    joints = [f"q{j}" for j in range(1, 7)]
    _write(tmp_path / "rad.csv", joints, q)
    _write(tmp_path / "deg.csv", joints, np.degrees(q))
    capsys.readouterr()
    assert main([cmd, str(run), "--csv", str(tmp_path / "rad.csv"), "--angle-unit", "deg", "--out",
                 str(tmp_path / "a.csv")]) == 0
    err = capsys.readouterr().err  # was: nothing; the poses near the zero pose, in the domain
    assert "every revolute joint of its 6 rows reads within ±2π" in err and "radians?" in err
    assert main([cmd, str(run), "--csv", str(tmp_path / "deg.csv"), "--angle-unit", "deg", "--out",
                 str(tmp_path / "b.csv")]) == 0
    assert "radians?" not in capsys.readouterr().err


def test_orientations_in_rad_beside_joints_in_degrees_are_named_so(tmp_path, capsys):
    src = _synth(tmp_path, "c", "--poses", "40", "--seed", "5")
    header, values = _read(src)
    cols = [header.index(f"q{j}") for j in range(1, 7)]
    values[:, cols] = np.degrees(values[:, cols])  # the controller's joints in degrees, the tracker's rotvec in rad
    _write(tmp_path / "mixed.csv", header, values)
    capsys.readouterr()
    assert main(["import", str(tmp_path / "mixed.csv"), "--run", str(tmp_path / "r"), "--angle-unit", "deg"]) == 0
    err = capsys.readouterr().err  # was: orientation_residual, 'no reading of rx,ry,rz ... fits'
    assert "columns rx,ry,rz read in degrees (--angle-unit deg, as the joints) disagree" in err
    assert "read in rad they agree to" in err and "[rotation_reading]" in err and "no reading" not in err


@pytest.mark.parametrize("kind", ["pose", "markers"])
def test_a_joint_convention_and_an_unknown_plate_at_once_are_both_named(mounted_ur10, tmp_path, capsys, kind):
    """The controller counts joint 2 the other way and the data were measured on the plate: neither
    explains the data alone (was: nominal_residual only); together they fit, and are named so."""
    tmp, truth, X, q = mounted_ur10
    header, values = _read(tmp / f"{kind}.csv")
    values[:, header.index("q2")] *= -1
    _write(tmp_path / "flipped.csv", header, values)
    extra = ["--markers", str(tmp / "plate.yaml")] if kind == "markers" else []
    capsys.readouterr()
    assert main(["import", str(tmp_path / "flipped.csv"), "--run", str(tmp_path / "r"), "--robot", "ur10",
                 *extra]) == 0
    err = capsys.readouterr().err
    assert ("joint 2's sign is flipped (q2 -> -q2): registered rms" in err
            and "with that convention and the tool frame is 29° and 115 mm from the URDF's (tool0)" in err), err
    assert "[0, -1, 0, 0, 0, 0]" in err and "[joint_convention]" in err
