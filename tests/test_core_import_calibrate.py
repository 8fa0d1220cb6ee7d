"""`campaign import / export / calibrate` driven through the CLI, and bad input."""

import json

import numpy as np
import pytest

from campaign.cli import main
from campaign.measure.csvio import read_measured_csv, write_measured_csv
from campaign.sim.truth import make_truth, random_joint_poses, synthesize

HEADER = "pose_id,time_s,q1,q2,q3,q4,q5,q6,x,y,z,rx,ry,rz"


@pytest.fixture(scope="module")
def good_csv(tmp_path_factory, robot):
    path = tmp_path_factory.mktemp("csv") / "poses.csv"
    truth = make_truth(robot, seed=2)
    meas = synthesize(truth, random_joint_poses(robot, 400, seed=3), seed=4,
                      context={"temperature_c": np.linspace(20, 24, 400)})
    write_measured_csv(path, meas)
    return path


def run_cli(*argv):
    return main([str(a) for a in argv])


def test_import_calibrate_export_end_to_end(good_csv, tmp_path, capsys):
    run = tmp_path / "run"
    assert run_cli("import", good_csv, "--run", run) == 0
    assert run_cli("calibrate", run, "--no-ann", "--quiet") == 0
    out = capsys.readouterr().out
    assert "nominal" in out and "geometric" in out and "max ‖Δt‖ mm" in out
    metrics = json.loads((run / "calibration" / "metrics.json").read_text())
    assert metrics["order"] == ["nominal", "geometric"]
    for stage in metrics["order"]:
        for split in ("train", "test"):
            s = metrics["stages"][stage][split]
            assert set(s) == {"position_mm", "orientation_mrad", "n_poses"}
            assert set(s["position_mm"]) == {"max", "mean", "q90"}
    test = metrics["stages"]["geometric"]["test"]
    assert test["n_poses"] + metrics["stages"]["geometric"]["train"]["n_poses"] == 400
    assert test["position_mm"]["mean"] < 0.05 < metrics["stages"]["nominal"]["test"]["position_mm"]["mean"]
    import yaml

    params = yaml.safe_load((run / "calibration" / "params.yaml").read_text())
    assert len(params["base_parameters"]) == 30 and len(params["p_e_min_norm"]) == 48
    assert all(p["sigma"] > 0 for p in params["base_parameters"])
    out_csv = tmp_path / "back.csv"
    assert run_cli("export", run, "--csv", out_csv) == 0
    a, b = read_measured_csv(good_csv), read_measured_csv(out_csv)
    np.testing.assert_array_equal(a.q, b.q)
    np.testing.assert_allclose(a.T_IE, b.T_IE, atol=1e-15)
    np.testing.assert_allclose(b.context["temperature_c"], a.context["temperature_c"])


def rewrite(good_csv, tmp_path, edit):
    lines = good_csv.read_text().splitlines()
    lines = edit(lines)
    path = tmp_path / "bad.csv"
    path.write_text("\n".join(lines) + "\n")
    return path


def set_cell(lines, line_no, column, value):
    header = lines[0].split(",")
    cells = lines[line_no - 1].split(",")
    cells[header.index(column)] = value
    lines[line_no - 1] = ",".join(cells)
    return lines


@pytest.mark.parametrize("edit, message", [
    (lambda L: [L[0].replace(",rz", "")] + [l.rsplit(",", 2)[0] + "," + l.rsplit(",", 1)[1] for l in L[1:]],
     r"missing column\(s\) rz"),
    (lambda L: set_cell(L, 5, "q3", "nan"), r"line 5, column q3: nan is not a finite number"),
    (lambda L: set_cell(L, 7, "q2", "45.0"), r"line 7, column q2: 45 exceeds 2\*pi.*degrees"),
    (lambda L: set_cell(L, 3, "x", "812.5"), r"line 3, column x: 812.5 exceeds 20 m.*mm"),
    (lambda L: set_cell(L, 4, "q5", "1.9"), r"line 4, column q5: 1.9 rad is outside the joint limit"),
    (lambda L: set_cell(L, 6, "q1", "abc"), r"line 6, column q1: 'abc' is not a number"),
    (lambda L: set_cell(L, 9, "pose_id", "3"), r"pose_id 3 appears twice"),
    (lambda L: L[:4] + [L[4] + ",7"] + L[5:], r"line 5 has 16 fields, the header has 15"),
    (lambda L: [L[0]], r"no data rows"),
])
def test_bad_csv_gives_one_clear_line_and_no_run_folder(good_csv, tmp_path, capsys, edit, message):
    import re

    bad = rewrite(good_csv, tmp_path, edit)
    run = tmp_path / "run"
    assert run_cli("import", bad, "--run", run) == 1
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and re.search(message, err[0]), err
    assert str(bad) in err[0]
    assert not (run / "measurements.sqlite").exists()


def test_import_never_overwrites_an_existing_run(good_csv, tmp_path, capsys):
    run = tmp_path / "run"
    assert run_cli("import", good_csv, "--run", run) == 0
    before = (run / "measurements.sqlite").read_bytes()
    assert run_cli("import", good_csv, "--run", run) == 1
    assert "already holds measurements.sqlite" in capsys.readouterr().err
    assert (run / "measurements.sqlite").read_bytes() == before


def test_calibrate_of_a_folder_without_measurements_fails_cleanly(tmp_path, capsys):
    assert run_cli("calibrate", tmp_path, "--no-ann") == 1
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "no measurements.sqlite" in err[0]


def test_unknown_effect_is_named(good_csv, tmp_path, capsys):
    run = tmp_path / "run"
    run_cli("import", good_csv, "--run", run)
    assert run_cli("calibrate", run, "--no-ann", "--effects", "flux_capacitor") == 1
    assert "unknown effect 'flux_capacitor'" in capsys.readouterr().err


def test_base_params_command_prints_table3(capsys):
    assert run_cli("model", "base-params") == 0
    assert "30 identifiable base parameters" in capsys.readouterr().out
