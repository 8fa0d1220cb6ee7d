"""Every output of one calibrate (and one diagnose) is written whole or not at all (issue 20, item 3).

A real `campaign calibrate` subprocess on a small imported run is killed at random moments
(SIGKILL, and SIGTERM and SIGINT once each): afterwards RUN/calibration holds exactly one
calibration_id across metrics.json, params.yaml, report.html and the history's last entry
(the previous calibration's or the new one's, never a mix), the history lists only completed
calibrations, and `campaign predict` works on what is there. The next calibrate removes
what a killed one left. diagnose keeps every diagnosis in RUN/diagnoses/<id>/ (item 9)."""

import json
import os
import re
import signal
import subprocess
import sys
import time

import numpy as np
import pytest
import yaml

from campaign.cli import main

SEED = 20
CALIBRATE = [sys.executable, "-m", "campaign.cli", "calibrate"]


@pytest.fixture(scope="module")
def small_run(tmp_path_factory):
    """60 synthetic 6-D poses of the default robot, imported, calibrated once (the 'old' calibration)."""
    tmp = tmp_path_factory.mktemp("atomic")
    csv, run = tmp / "m.csv", tmp / "run"
    assert main(["synth", "--csv", str(csv), "--poses", "60", "--seed", "3"]) == 0
    assert main(["import", str(csv), "--run", str(run)]) == 0
    t0 = time.perf_counter()  # the 'old' calibration, as the killed ones run: a subprocess, timed
    assert subprocess.run(CALIBRATE + [str(run), "--no-ann", "--quiet"], capture_output=True).returncode == 0
    joints = tmp / "q.csv"
    q = np.loadtxt(csv, delimiter=",", skiprows=1, max_rows=5)[:, 2:8]
    joints.write_text("q1,q2,q3,q4,q5,q6\n" + "\n".join(",".join(repr(float(v)) for v in row) for row in q) + "\n")
    return run, joints, time.perf_counter() - t0


def outputs_ids(run) -> dict:
    """The calibration id every output of RUN/calibration states (by file)."""
    cal = run / "calibration"
    report = (cal / "report.html").read_text()
    return {
        "link": os.readlink(cal).rsplit("/", 1)[-1],
        "metrics.json": json.loads((cal / "metrics.json").read_text())["calibration_id"],
        "params.yaml": yaml.safe_load((cal / "params.yaml").read_text())["calibration_id"],
        "report.html": re.search(r"Calibration <code>([^<]+)</code>", report).group(1),
        "history.json": json.loads((cal / "history.json").read_text())["runs"][-1]["calibration_id"],
    }


def history_ids(run) -> list:
    return [r["calibration_id"] for r in json.loads((run / "calibration" / "history.json").read_text())["runs"]]


def calibrate_killed(run, sig, delay_s):
    """Start `campaign calibrate RUN` in a subprocess and send ``sig`` after ``delay_s``; its return code."""
    proc = subprocess.Popen(CALIBRATE + [str(run), "--no-ann", "--quiet"],
                            stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, text=True)
    time.sleep(delay_s)
    proc.send_signal(sig)
    _, err = proc.communicate(timeout=60)
    return proc.returncode, err


def test_calibrate_killed_at_random_moments_leaves_one_calibration_and_predict_works(small_run, tmp_path, capsys):
    run, joints, duration_s = small_run
    rng = np.random.default_rng(SEED)
    kills = [signal.SIGKILL] * 10 + [signal.SIGTERM, signal.SIGINT]
    delays = rng.uniform(0.0, duration_s, size=len(kills))  # anywhere in a whole calibrate
    before = history_ids(run)
    outcomes = []
    for sig, delay in zip(kills, delays):
        rc, err = calibrate_killed(run, sig, float(delay))
        ids = outputs_ids(run)
        assert len(set(ids.values())) == 1, (sig, delay, ids)  # one calibration, never a mix
        now = history_ids(run)
        changed = now != before
        # the history is the previous one, or the previous one plus this (completed) calibration
        assert now == before or (now[:-1] == before and now[-1] == ids["link"]), (before, now)
        if rc == 130:  # Ctrl-C: one line
            assert err.strip().endswith("interrupted") and "Traceback" not in err, err
        if rc == 0:
            assert changed  # exit 0 only after the new calibration is the current one
        capsys.readouterr()
        out = tmp_path / "pred.csv"
        assert main(["predict", str(run), "--csv", str(joints), "--out", str(out)]) == 0
        pred = np.loadtxt(out, delimiter=",", skiprows=1)
        assert pred.shape == (5, 15) and np.isfinite(pred).all()  # 13 + in_domain, sigma_mm (issue 30)
        outcomes.append((sig.name, round(float(delay), 2), "new" if changed else "old"))
        before = now
    assert "old" in {o[2] for o in outcomes}, outcomes  # killed before the end: the old one whole
    # at most the current calibration and the one before it are kept; a killed one's folder is removed next time
    assert main(["calibrate", str(run), "--no-ann", "--quiet", "--no-report"]) == 0
    left = sorted(p.name for p in (run / "calibrations").iterdir())
    assert len(left) == 2 and not [n for n in left if n.endswith(".partial")], left
    assert not [p for p in run.iterdir() if p.name.endswith(".link")]
    metrics = json.loads((run / "calibration" / "metrics.json").read_text())
    assert metrics["calibration_id"] == os.readlink(run / "calibration").rsplit("/", 1)[-1] == history_ids(run)[-1]
    assert metrics["warnings"] == [] or isinstance(metrics["warnings"], list)
    assert not (run / "calibration" / "report.html").exists()  # --no-report: no report of another calibration


def test_an_older_calibration_folder_is_adopted_whole(small_run, tmp_path):
    """A run of the earlier layout (RUN/calibration a plain folder) keeps working and becomes a version."""
    import shutil

    run, joints, _ = small_run
    old = tmp_path / "old"
    shutil.copytree(run, old)  # the link copied as a plain folder: the earlier layout
    assert (old / "calibration").is_dir() and not (old / "calibration").is_symlink()
    assert main(["predict", str(old), "--csv", str(joints), "--out", str(tmp_path / "a.csv")]) == 0
    before = history_ids(old)
    assert main(["calibrate", str(old), "--no-ann", "--quiet", "--no-report"]) == 0
    assert (old / "calibration").is_symlink() and history_ids(old)[:-1] == before
    assert any(p.name.endswith("-legacy") for p in (old / "calibrations").iterdir())


def test_diagnose_keeps_each_diagnosis_and_links_the_newest(small_run, capsys):
    run, _, _ = small_run
    capsys.readouterr()
    ids = []
    for extra in ([], ["--no-report"]):
        assert main(["diagnose", str(run), "--json", "--folds", "3", "--candidates", "drift", *extra]) == 0
        doc = json.loads(capsys.readouterr().out)
        ids.append(doc["diagnosis_id"])
        folder = run / "diagnoses" / doc["diagnosis_id"]
        assert json.loads((folder / "diagnosis.json").read_text())["diagnosis_id"] == doc["diagnosis_id"]
    assert f"Diagnosis <code>{ids[0]}</code>" in (run / "diagnoses" / ids[0] / "report.html").read_text()
    assert ids[0] != ids[1]
    assert os.readlink(run / "diagnose") == f"diagnoses/{ids[1]}"
    assert (run / "diagnoses" / ids[0] / "report.html").is_file()  # the first stays readable
