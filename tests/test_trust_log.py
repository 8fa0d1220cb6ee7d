"""The measurement log is checked when opened and knows its robot (issue 20, item 4).

A log damaged on disk (2 KB of random bytes inside it, or a whole page of them) is refused by
run, calibrate and export in one line naming the file and what to do, and its bytes are left
exactly as they were. The robot is recorded in the log at import (and when `run` stores its
first measurement): a campaign.yaml emptied afterwards calibrates the recorded UR10, one that
names another robot is refused in one line, and a log without the record keeps working."""

import hashlib
import re
import sqlite3

import numpy as np
import pytest
import yaml

from campaign.cli import main

PAGE = 4096


def imported(tmp_path, n=40, extra=()):
    csv, run = tmp_path / "m.csv", tmp_path / "run"
    assert main(["synth", "--csv", str(csv), "--poses", str(n), "--seed", "5", *extra]) == 0
    assert main(["import", str(csv), "--run", str(run), "--quiet", *extra]) == 0
    return csv, run


def digest(path) -> str:
    return hashlib.sha256(path.read_bytes()).hexdigest()


def one_line(capsys, argv, pattern):
    capsys.readouterr()
    assert main([str(a) for a in argv]) == 1
    err = capsys.readouterr().err
    lines = err.strip().splitlines()
    assert len(lines) == 1 and "Traceback" not in err, err
    assert re.search(pattern, lines[0]), lines[0]
    return lines[0]


@pytest.fixture(scope="module")
def small_log(tmp_path_factory):
    tmp = tmp_path_factory.mktemp("log")
    csv, run = imported(tmp)
    q = np.loadtxt(csv, delimiter=",", skiprows=1)[:10, 2:8]  # a plan, so that `run` has poses to measure
    (run / "plan").mkdir()
    (run / "plan" / "poses.csv").write_text(
        "pose_id,q1,q2,q3,q4,q5,q6\n" + "".join(f"{9000 + i}," + ",".join(repr(float(v)) for v in row) + "\n"
                                                for i, row in enumerate(q)))
    return run


@pytest.mark.parametrize("damage", ["2 KB inside", "a whole page"])
def test_a_damaged_log_is_named_in_one_line_and_never_rewritten(small_log, tmp_path, capsys, damage):
    import shutil

    run = tmp_path / "run"
    shutil.copytree(small_log, run)
    log = run / "measurements.sqlite"
    data = bytearray(log.read_bytes())
    rng = np.random.default_rng(7)
    n_pages = len(data) // PAGE
    assert n_pages >= 4
    if damage == "2 KB inside":  # the cells of the poses table's root page (packed at the page's end)
        with sqlite3.connect(log) as db:
            page = db.execute("SELECT rootpage FROM sqlite_master WHERE name = 'poses'").fetchone()[0]
        start = page * PAGE - 2048
        data[start:start + 2048] = rng.bytes(2048)
    else:  # page 1 (the file header and the schema): random bytes
        data[0:PAGE] = rng.bytes(PAGE)
    log.write_bytes(bytes(data))
    before = digest(log)
    for argv in (["run", run, "--sim", "--quiet"], ["calibrate", run, "--no-ann", "--quiet"],
                 ["export", run, "--csv", tmp_path / "out.csv"], ["diagnose", run, "--no-report"]):
        line = one_line(capsys, argv, r"measurements\.sqlite: the measurement log is damaged \(SQLite: .*\); nothing "
                                      r"was changed .*restore it from a backup.*\.recover")
        assert str(log) in line
        assert digest(log) == before, argv  # not a byte rewritten
        assert not (run / "measurements.sqlite-wal").exists() and not (run / "measurements.sqlite-journal").exists()
    assert not (tmp_path / "out.csv").exists() and not (run / "calibration").exists()


def test_an_emptied_campaign_yaml_calibrates_the_recorded_ur10_and_another_robot_is_refused(tmp_path, capsys, erd):
    urdf = erd("ur_description/urdf/ur10_robot.urdf")
    csv, run = imported(tmp_path, n=60, extra=["--robot", urdf, "--tool-frame", "tool0"])
    with sqlite3.connect(run / "measurements.sqlite") as db:
        record = yaml.safe_load(db.execute("SELECT value FROM meta WHERE key = 'robot_record'").fetchone()[0])
    assert record["spec"] == urdf and record["tool_frame"] == "tool0" and record["n_joints"] == 6
    assert record["urdf_sha256"] == hashlib.sha256(open(urdf, "rb").read()).hexdigest()
    (run / "campaign.yaml").write_text("")  # lost its robot
    assert main(["calibrate", str(run), "--no-ann", "--quiet", "--no-report"]) == 0
    params = yaml.safe_load((run / "calibration" / "params.yaml").read_text())
    metrics = yaml.safe_load((run / "calibration" / "metrics.json").read_text())
    assert "ur10" in params["robot"].lower()
    # the UR10's model fits its data to the 10 µm noise (the COMAU's would miss by metres)
    assert metrics["stages"]["geometric"]["test"]["position_mm"]["mean"] < 0.05

    before = digest(run / "measurements.sqlite")
    (run / "campaign.yaml").write_text(yaml.safe_dump({"robot": "comau_racer5_080"}))
    for argv in (["calibrate", run, "--no-ann", "--quiet"], ["export", run, "--csv", tmp_path / "x.csv"],
                 ["predict", run, "--csv", csv]):
        one_line(capsys, argv, r"campaign\.yaml: robot 'COMAU Racer5-0\.80' is not the robot '.*ur10.*' .* was "
                               r"measured with \(URDF content .*tool frame 'tool0' measured, 'E' configured")
    assert digest(run / "measurements.sqlite") == before


def test_a_log_without_the_robot_record_keeps_working(tmp_path):
    _, run = imported(tmp_path)
    with sqlite3.connect(run / "measurements.sqlite") as db:
        db.execute("DELETE FROM meta WHERE key = 'robot_record'")
    assert main(["calibrate", str(run), "--no-ann", "--quiet", "--no-report"]) == 0
