"""User code fails in one line, and so does a full disk (issue 20, item 5).

Three broken user effects, written here (one raises in its hook, one returns the wrong shape,
one returns NaN): calibrate and diagnose answer with one line naming the file, the class, the
hook, what was expected and what came back, and leave the run folder exactly as it was.

A full disk is simulated honestly with RLIMIT_FSIZE in a subprocess (SIGXFSZ ignored, so a write
past the limit fails with EFBIG "File too large", the way ENOSPC fails a write): while calibrate
writes its report, and before `campaign run` stores its first pose. One line each; the previous
calibration stays the current one, and a run folder without measurements stays without a log."""

import hashlib
import os
import re
import resource
import signal
import subprocess
import sys

import numpy as np
import pytest
import yaml

from campaign.cli import main

BROKEN = '''
import numpy as np
from campaign.effects import Effect


class Raises(Effect):
    name = "raises"
    param_names, param_units = ("k",), ("rad",)

    def joint_offset(self, params, q, context):
        return q[:, 1] / 0 if params[0] > 1 else {}["missing"]


class WrongShape(Effect):
    name = "wrong_shape"
    param_names, param_units = ("k",), ("rad",)

    def joint_offset(self, params, q, context):
        return params[0] * np.ones(q.shape[1])  # (N,), not (n, N)


class ReturnsNaN(Effect):
    name = "returns_nan"
    param_names, param_units = ("s",), ("1",)

    def pose_map(self, params, T_IE, q, context):
        T = T_IE.copy()
        with np.errstate(invalid="ignore"):  # log of a negative joint angle: NaN
            T[:, :3, 3] *= 1 + params[0] * np.log(q[:, [1]] + 0.1)
        return T
'''

CASES = [
    ("Raises", r"Raises\.joint_offset\(params, q, context\) raised KeyError: 'missing'; expected None or an "
               r"array of shape \(\d+, 6\)"),
    ("WrongShape", r"WrongShape\.joint_offset\(params, q, context\) returned shape \(6,\); expected None or an "
                   r"array of shape \(\d+, 6\)"),
    ("ReturnsNaN", r"ReturnsNaN\.pose_map\(params, T_IE, q, context\) returned \d+ of \d+ values not finite "
                   r"\(NaN\) for finite parameters and joints; expected an array of shape \(\d+, 4, 4\)"),
]


def folder_state(path) -> dict:
    """{relative path: sha256} of every file under ``path``, links followed."""
    out = {}
    for root, _, files in os.walk(path, followlinks=True):
        for f in files:
            p = os.path.join(root, f)
            with open(p, "rb") as fh:
                out[os.path.relpath(p, path)] = hashlib.sha256(fh.read()).hexdigest()
    return out


@pytest.fixture(scope="module")
def calibrated(tmp_path_factory):
    tmp = tmp_path_factory.mktemp("plugins")
    csv, run = tmp / "m.csv", tmp / "run"
    assert main(["synth", "--csv", str(csv), "--poses", "40", "--seed", "8"]) == 0
    assert main(["import", str(csv), "--run", str(run), "--quiet"]) == 0
    assert main(["calibrate", str(run), "--no-ann", "--quiet", "--no-report"]) == 0
    (run / "broken.py").write_text(BROKEN)
    return run


def one_line(capsys, argv) -> str:
    capsys.readouterr()
    assert main([str(a) for a in argv]) == 1
    err = capsys.readouterr().err
    assert len(err.strip().splitlines()) == 1 and "Traceback" not in err, err
    return err.strip()


@pytest.mark.parametrize("cls, expected", CASES)
def test_a_broken_user_effect_is_one_line_naming_file_class_hook_and_what_came_back(calibrated, capsys, cls,
                                                                                      expected):
    run = calibrated
    cfg = run / "campaign.yaml"
    doc = yaml.safe_load(cfg.read_text())
    cfg.write_text(yaml.safe_dump({**doc, "effects": [f"broken.py:{cls}"]}))
    try:
        before = folder_state(run)
        line = one_line(capsys, ["calibrate", run, "--no-ann", "--quiet"])
        assert f"effect {run / 'broken.py'}:{cls}" in line and re.search(expected, line), line
        assert folder_state(run) == before
        if cls == "Raises":  # the same line when diagnose tries it as a candidate
            cfg.write_text(yaml.safe_dump(doc))
            before = folder_state(run)
            line = one_line(capsys, ["diagnose", run, "--candidates", f"{run / 'broken.py'}:Raises", "--folds", "3",
                                      "--json"])
            assert re.search(expected, line), line
            assert folder_state(run) == before
    finally:
        cfg.write_text(yaml.safe_dump(doc))


def _file_size_limit(limit_bytes):
    def apply():
        signal.signal(signal.SIGXFSZ, signal.SIG_IGN)  # a write past the limit: EFBIG, not a killed process
        resource.setrlimit(resource.RLIMIT_FSIZE, (limit_bytes, limit_bytes))
    return apply


def test_a_full_disk_while_calibrate_writes_is_one_line_and_the_previous_calibration_stays(calibrated):
    run = calibrated
    before = folder_state(run)
    current = os.readlink(run / "calibration")
    # 12 KB: metrics.json (~5 KB) and params.yaml (~7 KB) fit, the report's figures (SVG, 15-26 KB each) do not
    proc = subprocess.run([sys.executable, "-m", "campaign.cli", "calibrate", str(run), "--no-ann", "--quiet"],
                          capture_output=True, text=True, preexec_fn=_file_size_limit(12 * 1024), timeout=300)
    err = proc.stderr.strip()
    assert proc.returncode == 1 and len(err.splitlines()) == 1 and "Traceback" not in err, err
    assert re.search(r"campaign calibrate: .*/calibration: cannot write the new version \(File too large( writing [\w.]+)?\); nothing "
                     r"of it was kept, the current one is unchanged", err), err
    assert os.readlink(run / "calibration") == current and folder_state(run) == before
    assert not [p for p in (run / "calibrations").iterdir() if p.name.endswith(".partial")]


def test_a_full_disk_before_the_first_pose_of_run_is_one_line_and_no_log(tmp_path, runs):
    run = runs.make(n=5, seed=3)
    before = folder_state(run)
    cell = subprocess.Popen([sys.executable, "-m", "campaign.cli", "sim", "--run", str(run)],
                            stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    try:
        line = cell.stdout.readline()
        ports = dict(re.findall(r"(controller|tracker) 127\.0\.0\.1:(\d+)", line))
        assert set(ports) == {"controller", "tracker"}, line + cell.stderr.read()
        before = {k: v for k, v in folder_state(run).items() if not k.startswith("sim")}
        proc = subprocess.run([sys.executable, "-m", "campaign.cli", "run", str(run), "--controller",
                               f"127.0.0.1:{ports['controller']}", "--tracker", f"127.0.0.1:{ports['tracker']}",
                               "--quiet"], capture_output=True, text=True, preexec_fn=_file_size_limit(1024),
                              timeout=120)
    finally:
        cell.send_signal(signal.SIGINT)
        cell.wait(timeout=30)
    err = proc.stderr.strip()
    assert proc.returncode == 1 and len(err.splitlines()) == 1 and "Traceback" not in err, err
    # SQLite reports the refused write as an I/O error (EFBIG; ENOSPC reads "database or disk is full")
    assert re.search(r"measurements\.sqlite: cannot open the measurement log \((disk I/O error|database or disk is "
                     r"full)\)", err), err
    assert not (run / "measurements.sqlite").exists()
    assert {k: v for k, v in folder_state(run).items() if not k.startswith("sim")} == before


def test_a_constructor_that_raises_and_initial_params_of_the_wrong_length_are_one_line_each(tmp_path, robot):
    from campaign.effects.base import EffectSet, make_effect
    from campaign.errors import ConfigError, PluginError

    (tmp_path / "more.py").write_text('''
from campaign.effects import Effect
from campaign.errors import ConfigError


class Fails(Effect):
    name = "fails"

    def __init__(self, robot):
        raise RuntimeError("no calibration table for this robot")


class ShortStart(Effect):
    name = "short_start"
    param_names, param_units = ("a", "b"), ("m", "m")

    def initial_params(self):
        return [0.0]


class SaysWhy(Effect):
    name = "says_why"
    param_names, param_units = ("a",), ("m",)

    def pose_map(self, params, T_IE, q, context):
        raise ConfigError("says_why: needs a payload_kg column")
''')
    with pytest.raises(PluginError, match=r"more\.py:Fails\.__init__\(robot\) raised RuntimeError: no calibration "
                                          r"table for this robot; expected it to build the effect"):
        make_effect(f"{tmp_path / 'more.py'}:Fails", robot)
    short = EffectSet((make_effect(f"{tmp_path / 'more.py'}:ShortStart", robot),))
    with pytest.raises(PluginError, match=r"ShortStart\.initial_params\(\) returned shape \(1,\); expected an array "
                                          r"of shape \(2,\)"):
        short.initial_params()
    why = EffectSet((make_effect(f"{tmp_path / 'more.py'}:SaysWhy", robot),))
    with pytest.raises(ConfigError, match=r"^says_why: needs a payload_kg column$"):  # a line said on purpose, as it is
        why.pose_map([0.0], np.tile(np.eye(4), (2, 1, 1)), np.zeros((2, 6)), {})
