"""Rough edges a user hit (issue 29, items 1-10): each a clear answer or a working result, never a
traceback and never a silent wrong answer. Data are written here: nominal poses by Pinocchio
reading the URDF, adapters and URDFs in the test itself."""

import json
import re
from pathlib import Path

import numpy as np
import pinocchio as pin
import pytest
from scipy.spatial.transform import Rotation

from campaign.cli import main
from campaign.paths import ROBOT_MODELS

COMAU_URDF = ROBOT_MODELS / "comau_racer5_080" / "robot.urdf"


def one_line_error(capsys, argv, match) -> str:
    """Run the CLI in-process: exit 1, one stderr line matching ``match``, no traceback."""
    rc = main([str(a) for a in argv])
    err = capsys.readouterr().err
    lines = err.strip().splitlines()
    assert rc == 1 and len(lines) == 1 and "Traceback" not in err, err
    assert re.search(match, lines[0]), lines[0]
    return lines[0]


def nominal_csv(path: Path, n: int = 40, seed: int = 0) -> Path:
    """The COMAU's nominal poses of E, computed by Pinocchio from the URDF: data a perfect
    calibration fits with zero error (what `predict --stage nominal` or a perfect adapter gives)."""
    model = pin.buildModelFromUrdf(str(COMAU_URDF))
    data, fid = model.createData(), model.getFrameId("E")
    rng = np.random.default_rng(seed)
    q = rng.uniform(model.lowerPositionLimit, model.upperPositionLimit, size=(n, model.nq)) * 0.8
    rows = ["pose_id,q1,q2,q3,q4,q5,q6,x,y,z,rx,ry,rz"]
    for i, qi in enumerate(q):
        pin.framesForwardKinematics(model, data, qi)
        T = data.oMf[fid]
        values = [*qi, *T.translation, *Rotation.from_matrix(T.rotation).as_rotvec()]
        rows.append(f"{i + 1}," + ",".join(repr(float(v)) for v in values))
    path.write_text("\n".join(rows) + "\n")
    return path


# -- 1. zero or constant residuals -------------------------------------------------------------

def test_exact_nominal_data_calibrate_and_report(tmp_path, capsys):
    run = tmp_path / "run"
    assert main(["import", str(nominal_csv(tmp_path / "nominal.csv")), "--run", str(run), "--quiet"]) == 0
    assert main(["calibrate", str(run), "--no-ann"]) == 0, capsys.readouterr().err
    metrics = json.loads((run / "calibration" / "metrics.json").read_text())
    assert metrics["stages"]["nominal"]["test"]["position_mm"]["max"] < 1e-6  # Pinocchio's round-off
    page = (run / "calibration" / "report.html").read_text()
    assert "distributions.svg" in page and (run / "calibration" / "distributions.svg").stat().st_size > 0


@pytest.mark.parametrize("value_mm", [0.0, 0.25])
def test_report_figures_draw_zero_and_constant_errors(tmp_path, value_mm):
    from campaign.identify.report_figures import write_figures

    n = 30
    rng = np.random.default_rng(1)
    dz = np.zeros((n, 6))
    dz[:, 0] = value_mm * 1e-3  # m: every pose the same error along x
    residuals = {"nominal": dz, "geometric": dz.copy()}
    q, xyz = rng.uniform(-1, 1, (n, 6)), rng.uniform(-1, 1, (n, 3))
    is_test = np.arange(n) % 5 == 0
    with np.errstate(all="raise"):
        dist, joints, ws, _ = write_figures(tmp_path, residuals, ["nominal", "geometric"], q, xyz, is_test,
                                            tmp_path, None)
    svg = (tmp_path / dist[0]).read_text()
    assert not re.search(r"\b(nan|inf)\b", svg.lower())
    assert len(joints) == 2 and ws


@pytest.fixture(scope="module")
def nominal_run(tmp_path_factory):
    """An imported run of exact nominal COMAU poses (not calibrated)."""
    tmp = tmp_path_factory.mktemp("nominal")
    run = tmp / "run"
    assert main(["import", str(nominal_csv(tmp / "nominal.csv", n=40)), "--run", str(run), "--quiet"]) == 0
    return run


def run_copy(run: Path, dst: Path) -> Path:
    import shutil

    shutil.copytree(run, dst)
    return dst


# -- 2. an effect named twice -------------------------------------------------------------------

def test_an_effect_named_twice_in_effects_is_refused_before_any_fit(nominal_run, capsys):
    one_line_error(capsys, ["calibrate", nominal_run, "--no-ann", "--effects", "ground_compliance,ground_compliance"],
                   r"--effects: 'ground_compliance' is named twice")
    assert not (nominal_run / "calibration").exists()


def test_an_effect_named_twice_in_campaign_yaml_is_refused_by_calibrate_and_auto(nominal_run, tmp_path, capsys):
    run = run_copy(nominal_run, tmp_path / "run")
    cfg = run / "campaign.yaml"
    cfg.write_text(cfg.read_text().replace("effects: []", "effects: [ground_compliance, ground_compliance]"))
    for argv in (["calibrate", run, "--no-ann"], ["auto", run, "--sim"]):
        one_line_error(capsys, argv, r"campaign\.yaml: effects: 'ground_compliance' is named twice")
    assert not (run / "calibration").exists()


def test_two_specs_of_one_effect_name_are_refused(nominal_run, tmp_path, capsys):
    mine = tmp_path / "mine.py"
    mine.write_text("from campaign.effects.ground_compliance import GroundCompliance\n\n\n"
                    "class Mine(GroundCompliance):\n    pass\n")
    one_line_error(capsys, ["calibrate", nominal_run, "--no-ann", "--effects", f"ground_compliance,{mine}:Mine"],
                   r"both named 'ground_compliance'")
