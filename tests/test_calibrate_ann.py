"""`campaign calibrate` with the neural compensator, then `campaign predict` and `campaign compensate`,
on a small simulated campaign (hidden geometric errors, a hidden smooth gravity effect, tracker noise).

The truth is read only after the pipeline has answered, to score its answer.
"""

import csv
import json

import numpy as np
import pytest

from campaign.cli import main
from campaign.effects import make_effect
from campaign.identify.split import train_test_split
from campaign.identify.use import CalibratedRobot
from campaign.measure.csvio import read_measured_csv, write_measured_csv
from campaign.model.kinematics import forward, pose_error
from campaign.sim.truth import make_truth, random_joint_poses, synthesize

N_POSES = 1200


def run_cli(*argv):
    return main([str(a) for a in argv])


@pytest.fixture(scope="module")
def calibrated(tmp_path_factory, robot):
    """A run calibrated with the ANN (small sizes, few folds and epochs: a test, not the benchmark)."""
    folder = tmp_path_factory.mktemp("ann_run")
    hidden = {"joint_compliance": make_effect("joint_compliance", robot).typical_params(7)}
    truth = make_truth(robot, seed=7, effects=hidden)
    meas = synthesize(truth, random_joint_poses(robot, N_POSES, seed=8), seed=9)
    csv_path = folder / "measured.csv"
    write_measured_csv(csv_path, meas)
    run = folder / "run"
    assert run_cli("import", csv_path, "--run", run) == 0
    assert run_cli("calibrate", run, "--ann", "--sizes", "8x8,16x16", "--folds", "3", "--epochs", "30") == 0
    return run, csv_path, (truth, meas.T_LI)


def _stats(metrics, stage, block, key):
    return metrics["stages"][stage]["test"][block][key]


def test_calibrate_writes_table5_table6_ratios_and_the_report(calibrated):
    run, _, _ = calibrated
    out = run / "calibration"
    metrics = json.loads((out / "metrics.json").read_text())
    assert metrics["order"] == ["nominal", "geometric", "ann", "geometric+ann"]
    cv = metrics["ann_cross_validation"]
    assert set(cv) == {"nominal", "geometric"}
    for block in cv.values():
        assert [r["hidden"] for r in block["sizes"]] == [[8, 8], [16, 16]]
        best = min(block["sizes"], key=lambda r: r["rmse_normalised"])
        assert block["best"] == best["hidden"]
        assert all(len(r["epochs"]) == 3 for r in block["sizes"])
    ratios = metrics["ratio_to_nominal_test"]
    for stage in metrics["order"]:
        for block in ("position_mm", "orientation_mrad"):
            for key in ("max", "mean", "q90"):
                expect = _stats(metrics, stage, block, key) / _stats(metrics, "nominal", block, key)
                assert ratios[stage][block][key] == pytest.approx(expect, rel=1e-12)
    # the networks learn something beyond their prior models, and the prior helps, as in the paper
    for block in ("position_mm", "orientation_mrad"):
        assert _stats(metrics, "geometric+ann", block, "mean") < 0.8 * _stats(metrics, "geometric", block, "mean")
        assert _stats(metrics, "ann", block, "mean") < 0.8 * _stats(metrics, "nominal", block, "mean")
        assert _stats(metrics, "geometric+ann", block, "mean") < _stats(metrics, "ann", block, "mean")
    html = (out / "report.html").read_text()
    assert "Table 5" in html and "geometric+ann" in html
    assert all((out / f"joints_{s.replace('+', '_')}.svg").is_file() for s in metrics["order"])  # every stage's figure
    assert (out / "distributions.svg").is_file() and (out / "history.svg").is_file()
    assert (out / "ann_nominal.pt").is_file() and (out / "ann_geometric.pt").is_file()


def test_predict_reproduces_the_calibrated_test_errors(calibrated, tmp_path):
    """predict on the measured joints, compared with the measurements, gives metrics.json's numbers."""
    run, csv_path, _ = calibrated
    out = tmp_path / "pred.csv"
    assert run_cli("predict", run, "--csv", csv_path, "--out", out) == 0
    meas = read_measured_csv(csv_path)
    rows = list(csv.DictReader(out.open()))
    assert [int(r["pose_id"]) for r in rows] == list(meas.pose_id)
    xyz = np.array([[float(r[c]) for c in ("x", "y", "z")] for r in rows])
    dt_mm = np.linalg.norm(xyz - meas.xyz, axis=1) * 1e3
    test = train_test_split(meas.pose_id)
    metrics = json.loads((run / "calibration" / "metrics.json").read_text())
    assert dt_mm[test].mean() == pytest.approx(_stats(metrics, "geometric+ann", "position_mm", "mean"), rel=1e-9)
    assert dt_mm[test].max() == pytest.approx(_stats(metrics, "geometric+ann", "position_mm", "max"), rel=1e-9)
    # any stage can be asked for; the nominal stage is the nominal FK
    cal = CalibratedRobot(run, stage="nominal")
    assert np.abs(cal.predict(meas.q[:5]) - forward(cal.robot, meas.q[:5])).max() < 1e-15


def test_compensated_commands_bring_the_true_tool_to_the_nominal_poses(calibrated, tmp_path, robot):
    run, _, (truth, T_LI) = calibrated
    # commands away from singularities: at the stretched elbow, say, a nominal pose can lie
    # beyond the reach of the true (shorter) arm, and no command reaches it
    candidates = random_joint_poses(robot, 400, seed=21, margin=0.3)
    q_nominal = candidates[_smallest_singular_value(robot, candidates) > 0.05][:40]
    assert len(q_nominal) == 40
    inp = tmp_path / "commands.csv"
    with inp.open("w", newline="") as fh:
        w = csv.writer(fh)
        w.writerow(["pose_id", "q1", "q2", "q3", "q4", "q5", "q6"])
        w.writerows([[i, *(repr(float(v)) for v in q)] for i, q in enumerate(q_nominal)])
    out = tmp_path / "corrected.csv"
    assert run_cli("compensate", run, "--csv", inp, "--out", out) == 0
    rows = list(csv.DictReader(out.open()))
    assert all(r["converged"] == "1" and r["within_limits"] == "1" for r in rows)
    q_corrected = np.array([[float(r[f"q{j}"]) for j in range(1, 7)] for r in rows])
    assert np.allclose(q_corrected - q_nominal, [[float(r[f"dq{j}"]) for j in range(1, 7)] for r in rows])
    # only now, after the pipeline answered: where does the true robot put its tool?
    target = forward(robot, q_nominal)
    # the model was fitted in the frame the campaign's set-up points defined (T_LI)
    before = pose_error(truth.pose_in_measured_frame(q_nominal, T_LI), target)
    after = pose_error(truth.pose_in_measured_frame(q_corrected, T_LI), target)
    before_mm = np.linalg.norm(before[:, :3], axis=1).mean() * 1e3
    after_mm = np.linalg.norm(after[:, :3], axis=1).mean() * 1e3
    assert before_mm > 1.0
    assert after_mm < 0.1 * before_mm


def _smallest_singular_value(robot, q, h=1e-6):
    """σ_min of the 6x6 Jacobian of the nominal pose (m and rad per rad), by central differences."""
    T0 = forward(robot, q)
    J = np.empty((len(q), 6, 6))
    for j in range(6):
        dq = np.zeros(6)
        dq[j] = h
        J[:, :, j] = (pose_error(forward(robot, q + dq), T0) - pose_error(forward(robot, q - dq), T0)) / (2 * h)
    return np.linalg.svd(J, compute_uv=False)[:, -1]


def test_predict_and_compensate_name_bad_input(calibrated, tmp_path, capsys):
    run, _, _ = calibrated
    bad = tmp_path / "bad.csv"
    bad.write_text("pose_id,q1,q2,q4,q5,q6\n1,0,0,0,0,0\n")
    assert run_cli("predict", run, "--csv", bad) == 1
    assert "missing column(s) q3" in capsys.readouterr().err
    bad.write_text("q1,q2,q3,q4,q5,q6\n0,0,nan,0,0.5,0\n")
    assert run_cli("compensate", run, "--csv", bad) == 1
    err = capsys.readouterr().err
    assert "line 2, column q3" in err and len(err.strip().splitlines()) == 1
    bad.write_text("q1,q2,q3,q4,q5,q6\n0,0,9,0,0.5,0\n")
    assert run_cli("predict", run, "--csv", bad) == 1
    assert "q3" in capsys.readouterr().err
    assert run_cli("predict", run, "--csv", bad, "--stage", "geometric+flux") == 1
    assert "not a stage" in capsys.readouterr().err
    assert run_cli("predict", tmp_path, "--csv", bad) == 1
    assert "run `campaign calibrate" in capsys.readouterr().err
