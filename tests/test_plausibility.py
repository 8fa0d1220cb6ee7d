"""Plausibility said out loud (issue 20, item 1): the traps a real user falls into give `warning:`
lines naming the cause and the fix, metrics.json's ``warnings``, and with ``--strict`` exit 1 and
nothing written; a clean run has ``warnings: []``.

References: the truth of the simulation (read after the pipeline answered) and the nominal model
evaluated by Pinocchio with a registration by numpy's SVD, outside the package."""

import json
import re
from dataclasses import replace

import numpy as np
import pinocchio as pin
import pytest
import yaml

from campaign.cli import main
from campaign.measure.csvio import write_measured_csv
from campaign.paths import DEFAULT_ROBOT
from campaign.sim.truth import make_truth, random_joint_poses, synthesize, synthesize_kind

N_POSES = 150


def run_cli(*argv):
    return main([str(a) for a in argv])


@pytest.fixture(scope="module")
def campaign_data(robot):
    """150 COMAU poses measured on a seeded truth; q2 and q3 kept to the middle 45 % of their
    range, so that a FANUC-style coupled q3 (q3 + q2) stays inside the joint limits."""
    q = random_joint_poses(robot, N_POSES, seed=3)
    for j in (1, 2):
        q[:, j] = robot.q_mid[j] + 0.45 * (q[:, j] - robot.q_mid[j])
    return synthesize(make_truth(robot, seed=2), q, seed=4)


@pytest.fixture(scope="module")
def good_csv(tmp_path_factory, campaign_data):
    path = tmp_path_factory.mktemp("plaus") / "poses.csv"
    write_measured_csv(path, campaign_data)
    return path


def warning_lines(text):
    return [ln for ln in text.splitlines() if ln.startswith("warning: ")]


def metrics(run):
    return json.loads((run / "calibration" / "metrics.json").read_text())


def _pin_positions(robot, q):
    """Nominal tool positions (n, 3) from Pinocchio's model of the URDF."""
    model = robot.pinocchio_model
    data = model.createData()
    fid = model.getFrameId("E")
    out = []
    for qi in q:
        pin.framesForwardKinematics(model, data, qi)
        out.append(np.array(data.oMf[fid].translation))
    return np.array(out)


def _registered_rms(A, B):
    """rms (m) of B about the rigid registration of A onto it (numpy SVD, no package code)."""
    a, b = A - A.mean(axis=0), B - B.mean(axis=0)
    U, _, Vt = np.linalg.svd(a.T @ b)
    D = np.diag([1, 1, np.sign(np.linalg.det(Vt.T @ U.T))])
    R = Vt.T @ D @ U.T
    return float(np.sqrt(np.mean(np.sum((a @ R.T - b) ** 2, axis=1))))


def test_a_clean_run_has_no_warning(good_csv, tmp_path, capsys):
    run = tmp_path / "run"
    assert run_cli("import", good_csv, "--run", run, "--quiet", "--strict") == 0
    assert run_cli("calibrate", run, "--no-ann", "--quiet", "--no-report", "--strict") == 0
    captured = capsys.readouterr()
    assert warning_lines(captured.err) == [] and warning_lines(captured.out) == []
    m = metrics(run)
    assert m["warnings"] == []
    assert m["stages"]["geometric"]["test"]["position_mm"]["mean"] < 0.05  # a real calibration


def test_metres_imported_as_mm_warn_and_strict_refuses(good_csv, campaign_data, tmp_path, capsys):
    run = tmp_path / "mm"
    assert run_cli("import", good_csv, "--run", run, "--length-unit", "mm", "--quiet") == 0
    err = capsys.readouterr().err
    (line,) = warning_lines(err)
    assert "[workspace_scale]" in line and "metres imported with --length-unit mm" in line
    scale = float(re.search(r"span ([0-9.e+-]+)× the nominal", line).group(1))
    assert scale == pytest.approx(1e-3, rel=0.01)  # the truth: metres read as mm
    assert run_cli("calibrate", run, "--no-ann", "--quiet", "--no-report") == 0
    out = capsys.readouterr()
    m = metrics(run)
    # the confident wrong answer the checks are there for: a shrunken robot fitted to 0.000 mm
    assert m["stages"]["geometric"]["test"]["position_mm"]["mean"] < 1e-3
    assert m["stages"]["nominal"]["test"]["position_mm"]["mean"] > 500
    codes = [w["code"] for w in m["warnings"]]
    assert {"workspace_scale", "large_corrections", "noise_below_floor"} <= set(codes)
    assert len(warning_lines(out.err)) == len(codes)
    noise = next(w["message"] for w in m["warnings"] if w["code"] == "noise_below_floor")
    sigma_um = float(re.search(r"noise σ of ([0-9.e+-]+) µm", noise).group(1))
    assert sigma_um < 0.3 and "metres imported as mm" in noise
    # --strict: exit 1 and nothing written, on import and on calibrate
    assert run_cli("import", good_csv, "--run", tmp_path / "strict", "--length-unit", "mm", "--quiet",
                   "--strict") == 1
    err = capsys.readouterr().err
    assert "--strict" in err.splitlines()[-1] and "workspace_scale" in err.splitlines()[-1]
    assert not (tmp_path / "strict").exists()
    before = (run / "calibration" / "metrics.json").read_bytes()
    assert run_cli("calibrate", run, "--no-ann", "--quiet", "--no-report", "--strict") == 1
    assert "nothing written" in capsys.readouterr().err
    assert (run / "calibration" / "metrics.json").read_bytes() == before


def test_a_missing_coupling_is_named_and_the_named_convention_fits(robot, campaign_data, tmp_path, capsys):
    # FANUC-style controller: J3 measured from the horizontal, q3_model = q3_ctrl - q2
    q_ctrl = campaign_data.q.copy()
    q_ctrl[:, 2] += q_ctrl[:, 1]
    coupled = tmp_path / "coupled.csv"
    write_measured_csv(coupled, replace(campaign_data, q=q_ctrl))
    run = tmp_path / "coupled"
    assert run_cli("import", coupled, "--run", run, "--quiet") == 0
    lines = warning_lines(capsys.readouterr().err)
    nominal = next(ln for ln in lines if ln.endswith("[nominal_residual]"))
    conv = next(ln for ln in lines if ln.endswith("[joint_convention]"))
    assert "joint 3 looks coupled to joint 2 (q3 - q2)" in conv
    # the numbers: Pinocchio's nominal model registered by SVD, at the q as read and as meant
    P_meas = campaign_data.xyz
    rms_read = _registered_rms(_pin_positions(robot, q_ctrl), P_meas)
    rms_meant = _registered_rms(_pin_positions(robot, campaign_data.q), P_meas)
    before, after = (float(v) for v in re.search(r"rms ([0-9.]+) mm -> ([0-9.]+) mm", conv).groups())
    assert rms_read > 0.2 and before == pytest.approx(rms_read * 1e3, rel=5e-3)
    assert after == pytest.approx(rms_meant * 1e3, rel=5e-3)
    assert f"disagree by {before:.0f} mm" in nominal
    assert run_cli("calibrate", run, "--no-ann", "--quiet", "--no-report") == 0
    capsys.readouterr()
    m = metrics(run)
    assert m["stages"]["geometric"]["test"]["position_mm"]["mean"] > 20  # what the user saw, no word
    assert {"nominal_residual", "joint_convention", "model_residual"} <= {w["code"] for w in m["warnings"]}
    # the fix the warning gives, pasted into robot.yaml, calibrates the robot
    snippet = re.search(r"(controller: \{.*\}) \(docs", conv).group(1)
    meta = tmp_path / "fanuc_like" / "robot.yaml"
    meta.parent.mkdir()
    from campaign.model.robot import RobotModel

    urdf = RobotModel.load(DEFAULT_ROBOT).urdf_path
    base = yaml.safe_load((urdf.parent / "robot.yaml").read_text()) if (urdf.parent / "robot.yaml").is_file() else {}
    base.update(yaml.safe_load(snippet))
    base["urdf"] = str(urdf)
    meta.write_text(yaml.safe_dump(base))
    fixed = tmp_path / "fixed"
    assert run_cli("import", coupled, "--run", fixed, "--robot", meta, "--quiet", "--strict") == 0
    assert run_cli("calibrate", fixed, "--no-ann", "--quiet", "--no-report", "--strict") == 0
    assert warning_lines(capsys.readouterr().err) == []
    assert metrics(fixed)["stages"]["geometric"]["test"]["position_mm"]["mean"] < 0.05


def test_a_markers_file_in_mm_is_named(robot, tmp_path, capsys):
    from campaign.sim.commands import yaml_markers

    truth = make_truth(robot, seed=5)
    data = synthesize_kind(truth, random_joint_poses(robot, 60, seed=6), kind="markers", seed=7)
    csv = tmp_path / "markers.csv"
    write_measured_csv(csv, data)
    in_mm = tmp_path / "markers_mm.yaml"
    in_mm.write_text(yaml_markers(np.asarray(data.marker_positions) * 1e3))
    run = tmp_path / "mk"
    assert run_cli("import", csv, "--run", run, "--markers", in_mm, "--quiet") == 0
    (line,) = warning_lines(capsys.readouterr().err)
    assert line.endswith("[reflector_layout]") and "the markers file looks like mm" in line
    ratio = float(re.search(r"are ([0-9.e+-]+)× as far apart", line).group(1))
    assert ratio == pytest.approx(1e-3, rel=0.01)
    assert run_cli("calibrate", run, "--no-ann", "--quiet", "--no-report") == 0
    capsys.readouterr()
    m = metrics(run)
    assert m["stages"]["nominal"]["test"]["position_mm"]["mean"] > 1e4  # errors of metres without a word
    assert m["warnings"][0]["code"] == "reflector_layout"


def test_the_fit_noise_below_a_stated_floor_warns(robot):
    from campaign.measure.plausibility import check_fit

    zero = np.zeros(robot.n_params)
    (w,) = check_fit(robot, zero, noise_sigma_m=1e-8, floor_sigma_m=10e-6)
    assert w.code == "noise_below_floor" and "1,000× below" in w.message
    assert check_fit(robot, zero, noise_sigma_m=8e-6, floor_sigma_m=10e-6) == []
    assert check_fit(robot, zero, noise_sigma_m=0.0, floor_sigma_m=0.0) == []  # a noise-free cell


def test_a_base_frame_offset_is_told_from_a_convention(robot, campaign_data):
    from campaign.measure.plausibility import check_data

    shifted = campaign_data.T_IE.copy()
    shifted[:, :3, 3] += [0.1, -0.05, 0.02]
    (w,) = check_data(robot, replace(campaign_data, T_IE=shifted))
    assert w.code == "base_frame" and "--frame tracker" in w.message
    assert check_data(robot, replace(campaign_data, T_IE=shifted, frame="tracker")) == []


def test_joints_in_rad_imported_as_degrees_are_named(robot, good_csv, campaign_data, tmp_path, capsys):
    assert run_cli("import", good_csv, "--run", tmp_path / "deg", "--angle-unit", "deg", "--quiet") == 0
    (line,) = warning_lines(capsys.readouterr().err)
    assert line.endswith("[workspace_scale]") and "joints in rad imported with --angle-unit deg" in line
    fits_mm = float(re.search(r"fits to ([0-9.]+) mm rms", line).group(1))
    # read as meant, Pinocchio's nominal model registered by SVD fits to the same rms
    assert fits_mm == pytest.approx(_registered_rms(_pin_positions(robot, campaign_data.q), campaign_data.xyz) * 1e3,
                                    rel=5e-3)


@pytest.mark.parametrize("joint, change, label", [
    (4, lambda q: -q, "joint 5's sign is flipped (q5 -> -q5)"),
    (3, lambda q: q + np.pi / 2, "joint 4 is offset by -90 deg (q4 - 90 deg)"),
    (0, lambda q: q + np.pi / 2, "joint 1 is offset by -90 deg (q1 - 90 deg)"),  # robot frame: not a set-up error
])
def test_a_sign_flip_or_an_offset_is_named(robot, campaign_data, joint, change, label):
    from campaign.measure.plausibility import check_data

    q = campaign_data.q.copy()
    q[:, joint] = change(q[:, joint])
    found = {w.code: w.message for w in check_data(robot, replace(campaign_data, q=q))}
    assert found["joint_convention"].startswith(label)
    after = float(re.search(r"-> ([0-9.]+) mm with that convention", found["joint_convention"]).group(1))
    if joint:  # registered: Pinocchio's nominal model at the q meant, registered by SVD
        ref = _registered_rms(_pin_positions(robot, campaign_data.q), campaign_data.xyz)
    else:  # as it stands in the robot's frame
        ref = np.sqrt(np.mean(np.sum((_pin_positions(robot, campaign_data.q) - campaign_data.xyz) ** 2, axis=1)))
    assert after == pytest.approx(ref * 1e3, rel=5e-3)
