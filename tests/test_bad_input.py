"""Bad input through the real command line: exit status 1, exactly one line on stderr naming
the file and the field (or the option), no traceback, and the run folder left as it was."""

import hashlib
import os
import re
import shutil
import sqlite3
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
import yaml

from campaign.cli import main
from campaign.paths import DEFAULT_SCENE, ROBOT_MODELS
from campaign.sim.truth import random_joint_poses


def folder_state(path: Path) -> dict:
    """{relative path: sha256} of every file under ``path`` ({} when it does not exist)."""
    path = Path(path)
    if not path.exists():
        return {}
    return {str(p.relative_to(path)): hashlib.sha256(p.read_bytes()).hexdigest()
            for p in sorted(path.rglob("*")) if p.is_file()}


def refused(capsys, argv, match, *folders):
    """Run the CLI in-process; assert exit 1, one stderr line matching ``match``, no traceback,
    and ``folders`` unchanged. Returns the line."""
    before = [folder_state(f) for f in folders]
    rc = main([str(a) for a in argv])
    err = capsys.readouterr().err
    lines = err.strip().splitlines()
    assert rc == 1, err
    assert len(lines) == 1, err
    assert "Traceback" not in err
    assert re.search(match, lines[0]), lines[0]
    assert [folder_state(f) for f in folders] == before
    return lines[0]


def write_yaml(path: Path, doc) -> Path:
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_text(doc if isinstance(doc, str) else yaml.safe_dump(doc))
    return path


def tiny_config(tmp_path, **sections) -> dict:
    doc = {"robot": "comau_racer5_080", "scene": str(DEFAULT_SCENE),
           "plan": {"grid_cells": [2, 2, 2, 2, 1, 1]}}
    for key, value in sections.items():
        if isinstance(value, dict) and isinstance(doc.get(key), dict):
            doc[key] = {**doc[key], **value}
        else:
            doc[key] = value
    return doc


def planned_run(tmp_path, robot, n=12, name="run", **sections) -> Path:
    """A run folder with a random plan and a campaign.yaml (no measurements)."""
    run = tmp_path / name
    q = random_joint_poses(robot, n, seed=1)
    lines = ["pose_id,q1,q2,q3,q4,q5,q6"] + [f"{100 + i}," + ",".join(repr(float(v)) for v in q[i]) for i in range(n)]
    (run / "plan").mkdir(parents=True)
    (run / "plan" / "poses.csv").write_text("\n".join(lines) + "\n")
    sections["run"] = {"timeout_s": 0.5, "backoff_s": 0.01, **sections.get("run", {})}
    write_yaml(run / "campaign.yaml", tiny_config(tmp_path, **sections))
    return run


# -- campaign.yaml: every bad value is one line naming the file and the field -----------------

BAD_VALUES = [
    ({"plan": {"clearance_m": -0.5}}, r"plan\.clearance_m: must be a finite number >= 0, got -0\.5"),
    ({"plan": {"clearance_m": float("nan")}}, r"plan\.clearance_m: must be a finite number >= 0, got nan"),
    ({"plan": {"clearance_m": float("inf")}}, r"plan\.clearance_m: must be a finite number"),
    ({"plan": {"clearance_m": "0.035"}}, r"plan\.clearance_m: must be a finite number >= 0, got '0\.035'"),
    ({"plan": {"clearance_m": True}}, r"plan\.clearance_m: must be a finite number"),
    ({"plan": {"motion_clearance_m": -0.01}}, r"plan\.motion_clearance_m: must be a finite number >= 0"),
    ({"plan": {"motion_sample_deg": 0}}, r"plan\.motion_sample_deg: must be a finite number >= 0\.01"),
    ({"plan": {"motion_sample_deg": float("nan")}}, r"plan\.motion_sample_deg: must be a finite number"),
    ({"plan": {"settle_time_s": float("inf")}}, r"plan\.settle_time_s: must be a finite number >= 0, got inf"),
    ({"plan": {"tracker_time_per_reflector_s": "5 s"}}, r"plan\.tracker_time_per_reflector_s: must be a finite"),
    ({"plan": {"grid_cells": [-1, 10, 10, 14, 6, 10]}}, r"plan\.grid_cells\[0\]: must be an integer in 1\.\.10000, got -1"),
    ({"plan": {"grid_cells": [17, 0, 10, 14, 6, 10]}}, r"plan\.grid_cells\[1\]: must be an integer in 1\.\.10000, got 0"),
    ({"plan": {"grid_cells": [17, 10, 2.5, 14, 6, 10]}}, r"plan\.grid_cells\[2\]: must be an integer"),
    ({"plan": {"grid_cells": [17, 10, 10, 14, 6, 1e20]}}, r"plan\.grid_cells\[5\]: must be an integer"),
    ({"plan": {"grid_cells": "17x10"}}, r"plan\.grid_cells: must be a list of integers"),
    ({"plan": {"grid_cells": [9000, 9000, 9000, 10, 10, 10]}}, r"plan\.grid_cells: .* exceed"),
    ({"plan": {"foo": 1}}, r"unknown key 'plan\.foo'"),
    ({"plan": [1, 2]}, r"plan: expected a mapping"),
    ({"run": {"timeout_s": "fast"}}, r"run\.timeout_s: must be a finite number > 0"),
    ({"run": {"timeout_s": float("inf")}}, r"run\.timeout_s: must be a finite number > 0 and <= 86400, got inf"),
    ({"run": {"timeout_s": 0}}, r"run\.timeout_s: must be a finite number > 0"),
    ({"run": {"move_timeout_s": float("nan")}}, r"run\.move_timeout_s: must be a finite number"),
    ({"run": {"retries": 1.5}}, r"run\.retries: must be an integer in 0\.\.30, got 1\.5"),
    ({"run": {"retries": -1}}, r"run\.retries: must be an integer in 0\.\.30"),
    ({"run": {"retries": 100}}, r"run\.retries: must be an integer in 0\.\.30, got 100"),
    ({"run": {"reconnect_attempts": "many"}}, r"run\.reconnect_attempts: must be an integer"),
    ({"run": {"backoff_s": float("nan")}}, r"run\.backoff_s: must be a finite number"),
    ({"run": {"drift_check_every": -5}}, r"run\.drift_check_every: must be an integer >= 0, got -5"),
    ({"run": {"drift_threshold_mm": -1}}, r"run\.drift_threshold_mm: must be a finite number >= 0"),
    ({"sim": {"seed": -1}}, r"sim\.seed: must be an integer"),
    ({"sim": {"noise_m": float("nan")}}, r"sim\.noise_m: must be a finite number"),
    ({"sim": {"time_factor": -1}}, r"sim\.time_factor: must be a finite number >= 0"),
    ({"sim": {"hidden_effects": [1]}}, r"sim\.hidden_effects\[0\]: must be a string"),
    ({"sim": {"faults": {"drop": 2}}}, r"sim\.faults\.drop must be a rate in 0\.\.1, got 2"),
    ({"sim": {"faults": {"drop": float("nan")}}}, r"sim\.faults\.drop must be a rate in 0\.\.1"),
    ({"effects": [3]}, r"effects\[0\]: must be a string, got 3"),
    ({"effects": {"ground_compliance": "yes"}}, r"effects\.ground_compliance: must be true or false"),
    ({"robot": 5}, r": robot: must be a non-empty string, got 5"),
    ({"tool_frame": 3}, r": tool_frame: must be a non-empty string or null, got 3"),
    ({"scene": ""}, r": scene: must be a non-empty string"),
    ({"meteor": 1}, r"unknown key 'meteor'"),
]


@pytest.mark.parametrize("bad,match", BAD_VALUES, ids=[m.split(":")[0].replace("\\", "") for _, m in BAD_VALUES])
def test_a_bad_config_value_is_one_line_naming_the_file_and_the_field_before_any_work(tmp_path, capsys, bad, match):
    cfg = write_yaml(tmp_path / "cfg" / "campaign.yaml", tiny_config(tmp_path, **bad))
    run = tmp_path / "run"
    line = refused(capsys, ["plan", "--config", cfg, "--run", run, "--quiet"], match, tmp_path)
    assert line.startswith(f"campaign plan: {cfg}: ")
    assert not run.exists()


@pytest.mark.parametrize("text,match", [
    ("plan: [unclosed", r"campaign\.yaml: not valid YAML"),
    ("- a\n- b\n", r"campaign\.yaml: expected a mapping at the top level"),
])
def test_a_config_that_is_not_a_yaml_mapping_is_one_line(tmp_path, capsys, text, match):
    cfg = write_yaml(tmp_path / "campaign.yaml", text)
    refused(capsys, ["plan", "--config", cfg, "--run", tmp_path / "run"], match, tmp_path)


def test_a_config_file_that_does_not_exist_is_one_line(tmp_path, capsys):
    refused(capsys, ["plan", "--config", tmp_path / "nope.yaml", "--run", tmp_path / "run"],
            r"nope\.yaml: cannot read", tmp_path)


@pytest.mark.parametrize("bad,match", [
    ({"run": {"timeout_s": "fast"}}, r"campaign\.yaml: run\.timeout_s: must be a finite number"),
    ({"run": {"retries": float("inf")}}, r"campaign\.yaml: run\.retries: must be an integer"),
    ({"sim": {"noise_m": -1e-6}}, r"campaign\.yaml: sim\.noise_m: must be a finite number >= 0"),
])
def test_campaign_run_checks_the_runs_own_config_before_it_touches_anything(tmp_path, robot, capsys, bad, match):
    run = planned_run(tmp_path, robot, **bad)
    line = refused(capsys, ["run", run, "--sim", "--quiet"], match, run)
    assert str(run / "campaign.yaml") in line
    assert not (run / "measurements.sqlite").exists() and not (run / "sim").exists()


def test_an_unknown_hidden_effect_is_refused_before_the_simulated_cell_starts(tmp_path, robot, capsys):
    run = planned_run(tmp_path, robot, sim={"hidden_effects": ["bogus"]})
    refused(capsys, ["run", run, "--sim", "--quiet"], r"unknown effect 'bogus'", run)
    assert not (run / "sim").exists()


HOOK_RAISES = """
import numpy as np
from campaign.effects import Effect


class Boom(Effect):
    name = "boom"
    description = "a hook that raises"
    param_names = ("a",)
    param_units = ("rad",)

    def joint_twist(self, params, q, context):
        raise ValueError("boom from my effect")
"""


def test_a_hidden_effect_whose_hook_raises_is_refused_before_the_simulated_cell_starts(tmp_path, robot, capsys):
    # qa31c: the cell started, and auto stopped on "tracker: answered 'error' to the set-up measurement",
    # the reason left in RUN/sim/cell.log
    (tmp_path / "boom.py").write_text(HOOK_RAISES)
    run = planned_run(tmp_path, robot, sim={"hidden_effects": [{"effect": str(tmp_path / "boom.py") + ":Boom",
                                                                "params": [1e-3]}]})
    line = refused(capsys, ["run", run, "--sim", "--quiet"],
                   r"campaign\.yaml: sim\.hidden_effects\[0\]: effect .*boom\.py:Boom\.joint_twist\(params, q, "
                   r"context\) raised ValueError: boom from my effect", run)
    assert "set-up" not in line
    assert not (run / "sim").exists()


FAILING_TRACKER = """
class Controller:
    def __init__(self, robot, options): pass
    def move(self, q): pass


class Tracker:
    def __init__(self, robot, options): pass
    def measure(self, aims): raise LookupError("the SDK lost its licence")
"""


def test_a_tracker_that_fails_the_set_up_says_why_in_the_one_line(tmp_path, robot, capsys):
    (tmp_path / "cell.py").write_text(FAILING_TRACKER)
    run = planned_run(tmp_path, robot)
    rc = main(["run", str(run), "--cell", str(tmp_path / "cell.py"), "--quiet"])
    lines = capsys.readouterr().err.strip().splitlines()
    assert rc == 1 and len(lines) == 1, lines
    assert re.search(r"tracker: answered 'error' to the set-up measurement: tracker adapter: LookupError: the SDK "
                     r"lost its licence$", lines[0]), lines[0]


@pytest.mark.parametrize("argv,match", [
    (["model", "base-params", "--poses", "0"], r"--poses: must be an integer >= 8, got 0"),
    (["model", "base-params", "--poses", "15", "--position-only"], r"--poses: must be an integer >= 16, got 15"),
    (["synth", "--csv", "{tmp}/s.csv", "--poses", "0"], r"--poses must be a positive integer, got 0"),
    (["synth", "--csv", "{tmp}/s.csv", "--noise-um", "nan"], r"--noise-um must be a finite number"),
    (["synth", "--csv", "{tmp}/s.csv", "--hidden", "bogus"], r"unknown effect 'bogus'"),
    (["plan", "--run", "{tmp}/run", "--grid-scale", "1e6"], r"plan\.grid_cells: .* candidates exceed"),
])
def test_bad_options_of_other_commands_are_one_line(tmp_path, capsys, argv, match):
    refused(capsys, [a.format(tmp=tmp_path) for a in argv], match, tmp_path)


def test_a_bad_scene_value_is_one_line_naming_the_scene_file(tmp_path, capsys):
    scene = yaml.safe_load(DEFAULT_SCENE.read_text())
    scene["tracker"]["min_range_m"] = float("nan")
    scene_path = write_yaml(tmp_path / "cell.yaml", scene)
    cfg = write_yaml(tmp_path / "campaign.yaml", tiny_config(tmp_path, scene=str(scene_path)))
    refused(capsys, ["plan", "--config", cfg, "--run", tmp_path / "run"],
            rf"{re.escape(str(scene_path))}: tracker\.min_range_m: must be positive", tmp_path)


def test_a_missing_scene_file_is_one_line(tmp_path, capsys):
    cfg = write_yaml(tmp_path / "campaign.yaml", tiny_config(tmp_path, scene="no_such_cell.yaml"))
    refused(capsys, ["plan", "--config", cfg, "--run", tmp_path / "run"], r"no_such_cell\.yaml: cannot read", tmp_path)


# -- robot.yaml and URDF ----------------------------------------------------------------------

def robot_copy(tmp_path, edit_yaml=None, edit_urdf=None) -> Path:
    folder = tmp_path / "robot"
    shutil.copytree(ROBOT_MODELS / "comau_racer5_080", folder)
    if edit_yaml:
        meta = yaml.safe_load((folder / "robot.yaml").read_text())
        edit_yaml(meta)
        (folder / "robot.yaml").write_text(yaml.safe_dump(meta))
    if edit_urdf:
        urdf = next(folder.glob("*.urdf"))
        urdf.write_text(edit_urdf(urdf.read_text()))
    return folder


@pytest.mark.parametrize("field,value,match", [
    ("max_velocity_rad_s", [float("nan")] * 6, "'max_velocity_rad_s'"),
    ("max_velocity_rad_s", "fast", "'max_velocity_rad_s'"),
    ("max_acceleration_rad_s2", [1, 2, 3], "'max_acceleration_rad_s2'"),
    ("max_jerk_rad_s3", [-1.0] * 6, "'max_jerk_rad_s3'"),
    ("gravity_in_I_m_s2", "down", r"field 'gravity_in_I_m_s2' must be 3 finite numbers"),
    ("gravity_in_I_m_s2", [0.0, float("inf"), 0.0], r"field 'gravity_in_I_m_s2' must be 3 finite numbers"),
    ("gravity_in_I_m_s2", [0.0, 0.0, 0.0], r"field 'gravity_in_I_m_s2' must not be zero"),
    ("gravity_m_s2", [0.0, 9.81, 0.1], r"fields 'gravity_m_s2' and 'gravity_in_I_m_s2' are the same field and disagree"),
    ("locked_joints", {"joint1": float("nan")}, r"field 'locked_joints\.joint1' must be a finite number"),
    ("base_frame", "no_such_link", r"field 'base_frame': 'no_such_link' is not a link"),
    ("tool_frame", "no_such_link", r"field 'tool_frame': 'no_such_link' is not a link"),
    ("controller", {"coupling": [[1, 0, 0, 0, 0, 0]] * 6}, r"field 'controller\.coupling' is a singular matrix"),
    ("controller", {"sign": [1, 1, 1, 1, 1, 2]}, r"field 'controller\.sign' must be 6 values of 1 or -1"),
])
def test_a_bad_robot_yaml_field_is_one_line_naming_the_file_and_the_field(tmp_path, capsys, field, value, match):
    folder = robot_copy(tmp_path, edit_yaml=lambda m: m.__setitem__(field, value))
    cfg = write_yaml(tmp_path / "campaign.yaml", tiny_config(tmp_path, robot=str(folder)))
    line = refused(capsys, ["plan", "--config", cfg, "--run", tmp_path / "run"], match, tmp_path)
    assert "robot.yaml" in line


def edit_reflector(key, value):
    def edit(meta):
        meta["reflectors"][1][key] = value
    return edit


def drop_gravity(meta):
    del meta["gravity_in_I_m_s2"]


def spell_gravity(value):
    def edit(meta):
        del meta["gravity_in_I_m_s2"]
        meta["gravity_m_s2"] = value
    return edit


@pytest.mark.parametrize("edit,match", [
    # each message names the field as the file spells it
    (spell_gravity("down"), r"field 'gravity_m_s2' must be 3 finite numbers"),
    (spell_gravity([0, 0, 0]), r"field 'gravity_m_s2' must not be zero"),
    (drop_gravity, r"missing field 'gravity_m_s2' \(or 'gravity_in_I_m_s2'\): a robot\.yaml with 'chain'"),
    (edit_reflector("axis_in_E", [0, 0, 0]), r"field 'reflectors\[1\]\.axis_in_E' must be 3 finite numbers, not all zero"),
    (edit_reflector("half_angle_deg", float("nan")), r"field 'reflectors\[1\]\.half_angle_deg' must be a number in"),
    (edit_reflector("half_angle_deg", 120), r"field 'reflectors\[1\]\.half_angle_deg' must be a number in \(0, 90\]"),
    (edit_reflector("link", "joint9"), r"field 'reflectors\[1\]\.link': 'joint9' is not a link hanging from"),
])
def test_a_bad_robot_yaml_names_the_field_as_the_file_spells_it(tmp_path, capsys, edit, match):
    folder = robot_copy(tmp_path, edit_yaml=edit)
    cfg = write_yaml(tmp_path / "campaign.yaml", tiny_config(tmp_path, robot=str(folder)))
    line = refused(capsys, ["plan", "--config", cfg, "--run", tmp_path / "run"], match, tmp_path)
    assert "robot.yaml" in line


def test_a_reflector_position_names_its_index(tmp_path, capsys):
    def edit(meta):
        meta["reflectors"][2] = {"name": "brr", "position_m": [0.0, "x", 0.1]}
    folder = robot_copy(tmp_path, edit_yaml=edit)
    cfg = write_yaml(tmp_path / "campaign.yaml", tiny_config(tmp_path, robot=str(folder)))
    refused(capsys, ["plan", "--config", cfg, "--run", tmp_path / "run"],
            r"robot\.yaml: field 'reflectors\[2\]\.position_m' must be 3 finite numbers", tmp_path)


def test_a_urdf_with_a_non_numeric_origin_is_one_line(tmp_path, capsys):
    folder = robot_copy(tmp_path, edit_urdf=lambda text: re.sub(r'xyz="[^"]*"', 'xyz="abc"', text, count=3))
    cfg = write_yaml(tmp_path / "campaign.yaml", tiny_config(tmp_path, robot=str(folder)))
    line = refused(capsys, ["plan", "--config", cfg, "--run", tmp_path / "run"], r"abc", tmp_path)
    assert ".urdf" in line


# -- plan -------------------------------------------------------------------------------------

def test_a_plan_with_no_suitable_pose_is_one_line_and_writes_nothing(tmp_path, capsys):
    cfg = write_yaml(tmp_path / "campaign.yaml", tiny_config(tmp_path, plan={"clearance_m": 10.0}))
    run = tmp_path / "run"
    refused(capsys, ["plan", "--config", cfg, "--run", run, "--quiet"], r"no suitable pose among 16 candidates",
            tmp_path)
    assert not (run / "campaign.yaml").exists() and not (run / "plan").exists()


@pytest.mark.parametrize("scale", ["0", "-1", "nan", "inf"])
def test_a_bad_grid_scale_is_one_line(tmp_path, capsys, scale):
    refused(capsys, ["plan", "--run", tmp_path / "run", "--grid-scale", scale], r"--grid-scale: must be|--grid-scale must",
            tmp_path)


@pytest.mark.parametrize("argv,match", [
    (["plan", "--grid-scale", "abc"], r"^campaign plan: argument --grid-scale: invalid float value: 'abc'"),
    (["calibrate", "{run}", "--folds", "x"], r"^campaign calibrate: argument --folds: invalid int value: 'x'"),
    (["run", "{run}", "--sim", "--controller", "h:1"], r"^campaign run: argument --controller: not allowed with"),
    (["teleport"], r"^campaign: argument COMMAND: invalid choice: 'teleport'"),
])
def test_a_bad_command_line_argument_is_one_line_and_exit_status_1(tmp_path, capsys, argv, match):
    refused(capsys, [a.format(run=tmp_path / "run") for a in argv], match, tmp_path)


# -- import -----------------------------------------------------------------------------------

def measured_csv(tmp_path, robot, pose_id=None, n=30) -> Path:
    from campaign.measure.csvio import write_measured_csv
    from campaign.sim.truth import make_truth, synthesize

    poses = synthesize(make_truth(robot, seed=0), random_joint_poses(robot, n, seed=2), seed=3)
    path = tmp_path / "poses.csv"
    write_measured_csv(path, poses)
    if pose_id is not None:
        lines = path.read_text().splitlines()
        cells = lines[5].split(",")
        cells[0] = pose_id
        lines[5] = ",".join(cells)
        path.write_text("\n".join(lines) + "\n")
    return path


@pytest.mark.parametrize("pose_id", ["1e20", "-3", "9007199254740992"])
def test_a_pose_id_out_of_range_is_refused_not_stored(tmp_path, robot, capsys, pose_id):
    csv_path = measured_csv(tmp_path, robot, pose_id)
    run = tmp_path / "run"
    refused(capsys, ["import", csv_path, "--run", run], r"line 6, column pose_id: .* is outside 0\.\.", tmp_path)
    assert not run.exists()


def test_import_with_another_robot_than_the_run_records_is_refused(tmp_path, robot, capsys):
    run = tmp_path / "run"
    folder = robot_copy(tmp_path, edit_yaml=lambda m: m.__setitem__("name", "other arm"))
    write_yaml(run / "campaign.yaml", {"robot": str(folder)})
    csv_path = measured_csv(tmp_path, robot)
    refused(capsys, ["import", csv_path, "--run", run, "--robot", "comau_racer5_080"], r"records robot", tmp_path)


def test_import_with_another_tool_frame_than_the_run_records_is_refused(tmp_path, robot, capsys):
    run = tmp_path / "run"
    urdf = next((ROBOT_MODELS / "comau_racer5_080").glob("*.urdf"))
    write_yaml(run / "campaign.yaml", {"robot": str(urdf)})  # tool frame: the URDF's last link, E
    csv_path = measured_csv(tmp_path, robot)
    refused(capsys, ["import", csv_path, "--run", run, "--tool-frame", "link6"], r"records robot .*not the one asked",
            tmp_path)


def test_a_run_without_campaign_yaml_whose_log_records_another_robot_is_refused(tmp_path, robot, capsys):
    other = robot_copy(tmp_path, edit_yaml=lambda m: m.__setitem__("name", "other arm"))
    run = tmp_path / "run"
    assert main(["import", str(measured_csv(tmp_path, robot)), "--run", str(run), "--robot", str(other)]) == 0
    (run / "campaign.yaml").unlink()
    capsys.readouterr()
    refused(capsys, ["calibrate", run, "--no-ann"], r"record robot 'other arm' but it has no campaign\.yaml", run)


def test_campaign_run_with_a_config_naming_another_robot_than_the_run_records_is_refused(tmp_path, robot, capsys):
    run = planned_run(tmp_path, robot)
    other = robot_copy(tmp_path, edit_urdf=lambda text: text)
    cfg = write_yaml(tmp_path / "other.yaml", tiny_config(tmp_path, robot=str(next(other.glob("*.urdf")))))
    refused(capsys, ["run", run, "--sim", "--config", cfg, "--quiet"], r"is not the robot .* records", run)


# -- calibrate and diagnose options -----------------------------------------------------------

@pytest.fixture(scope="module")
def measured_run(tmp_path_factory, robot):
    tmp = tmp_path_factory.mktemp("measured")
    run = tmp / "run"
    assert main(["import", str(measured_csv(tmp, robot, n=150)), "--run", str(run)]) == 0
    return run


@pytest.mark.parametrize("argv,match", [
    (["calibrate", "{run}", "--folds", "1"], r"--folds must be an integer >= 2"),
    (["calibrate", "{run}", "--folds", "0"], r"--folds must be an integer >= 2"),
    (["calibrate", "{run}", "--folds", "1", "--no-ann"], r"--folds must be an integer >= 2"),
    (["calibrate", "{run}", "--epochs", "0"], r"--epochs must be an integer >= 1"),
    (["calibrate", "{run}", "--device", "tpu"], r"--device 'tpu': not a torch device"),
    (["calibrate", "{run}", "--workers", "0"], r"--workers must be at least 1"),
    (["calibrate", "{run}", "--sizes", "64by32"], r"--sizes: '64by32' is not of the form"),
    (["calibrate", "{run}", "--effects", "bogus", "--no-ann"], r"unknown effect 'bogus'"),
    (["diagnose", "{run}", "--candidates", "bogus"], r"unknown effect 'bogus'"),
    (["diagnose", "{run}", "--folds", "1"], r"--folds must be at least 2"),
    (["predict", "{run}", "--csv", "{run}/nope.csv"], r"not found; run `campaign calibrate"),
])
def test_bad_command_options_are_one_line_and_change_nothing(measured_run, capsys, argv, match):
    import time

    t0 = time.process_time()  # CPU, not wall: a loaded machine stretches the imports' wall time, not the work
    refused(capsys, [a.format(run=measured_run) for a in argv], match, measured_run)
    assert time.process_time() - t0 < 20.0  # refused before the fits


@pytest.mark.parametrize("argv", [["demo", "--run", "{run}"], ["plan", "--run", "{run}", "--quiet"],
                                  ["plan", "--run", "{run}", "--config", "{default}", "--quiet"]])
def test_demo_and_plan_refuse_a_run_that_holds_measurements(measured_run, capsys, argv):
    from campaign.paths import DEFAULT_CONFIG

    line = refused(capsys, [a.format(run=measured_run, default=DEFAULT_CONFIG) for a in argv],
                   r"holds 150 measured poses; .* refuses: .*--run", measured_run)
    assert "new" in line


def test_a_run_that_records_another_robot_never_gets_the_default(tmp_path, robot, capsys):
    run = tmp_path / "run"
    csv_path = measured_csv(tmp_path, robot)
    assert main(["import", str(csv_path), "--run", str(run)]) == 0
    capsys.readouterr()
    cfg = yaml.safe_load((run / "campaign.yaml").read_text())
    assert cfg["robot"] == "comau_racer5_080"  # import recorded the robot
    cfg["robot"] = str(tmp_path / "no_such_robot")
    (run / "campaign.yaml").write_text(yaml.safe_dump(cfg))
    for argv in (["calibrate", run, "--no-ann"], ["diagnose", run], ["plan", "--run", run]):
        refused(capsys, argv, r"no_such_robot", run)


# -- the cell's ports -------------------------------------------------------------------------

def test_deeply_nested_json_on_a_port_gets_an_error_reply(tmp_path, robot):
    import socket
    import struct

    from campaign.measure import protocol as P
    from campaign.sim.launcher import SimulatedCell

    run = planned_run(tmp_path, robot)
    with SimulatedCell(run / "campaign.yaml", run) as cell:
        for port in (cell.controller[1], cell.tracker[1]):
            body = b"[" * 50_000 + b"]" * 50_000
            body = body[: P.MAX_FRAME]
            s = socket.create_connection(("127.0.0.1", port), timeout=5)
            s.sendall(struct.pack(">I", len(body)) + body)
            conn = P.Connection(s, "cell")
            reply = conn.receive(5.0)
            conn.close()
            assert isinstance(reply, P.ErrorReply) and "nests JSON too deeply" in reply.message
        assert cell.proc.poll() is None


def test_many_simultaneous_connections_do_not_stall(tmp_path, robot):
    import socket
    import time

    from campaign.sim.launcher import SimulatedCell

    run = planned_run(tmp_path, robot)
    with SimulatedCell(run / "campaign.yaml", run) as cell:
        t0 = time.perf_counter()
        socks = [socket.create_connection(cell.controller, timeout=5) for _ in range(40)]
        elapsed = time.perf_counter() - t0
        for s in socks:
            s.close()
    assert elapsed < 0.9  # a SYN dropped by a full backlog is retried after 1 s


# -- a subprocess: the real entry point prints one line and no traceback ------------------------

def test_the_installed_entry_point_prints_one_line(tmp_path):
    cfg = write_yaml(tmp_path / "campaign.yaml", tiny_config(tmp_path, plan={"clearance_m": float("nan")}))
    proc = subprocess.run([sys.executable, "-m", "campaign.cli", "plan", "--config", str(cfg), "--run",
                           str(tmp_path / "run")], capture_output=True, text=True, timeout=120,
                          env={**os.environ, "PYTHONPATH": str(Path(__file__).resolve().parents[1])})
    assert proc.returncode == 1
    assert proc.stderr.strip().splitlines() == [
        f"campaign plan: {cfg}: plan.clearance_m: must be a finite number >= 0, got nan"]


def test_ctrl_c_while_the_commands_are_loaded_is_one_line_not_a_traceback(monkeypatch, capsys):
    # building the parser imports every command module: seconds on a loaded machine, where a
    # Ctrl-C printed a 20-line traceback of importlib
    import campaign.cli

    def interrupted():
        raise KeyboardInterrupt

    monkeypatch.setattr(campaign.cli, "build_parser", interrupted)
    assert campaign.cli.main(["plan", "--run", "r"]) == 130
    err = capsys.readouterr().err
    assert err == "campaign: interrupted\n"
