"""Issue 31, part 5: a run resumed on another cell (``--allow-other-cell``) is two cell segments,
modelled with one registration each (a step, never a drift), mixed only when the segments are one
robot beyond it, refused in one line otherwise; a run of one cell is left exactly as it was."""

import json
from pathlib import Path

import numpy as np
import pytest
import yaml

from campaign.cli import main
from campaign.errors import ConfigError, DataError
from campaign.measure.store import open_run
from campaign.paths import DEFAULT_SCENE

#: the sim's tracker noise (its default): σ per coordinate of a reflector centre, m
NOISE_M = 10e-6


def _half_then(runs, capsys, n, change, first=None, before=None, **make):
    """A run of ``n`` planned poses (``before(cfg, run)`` applied to its campaign.yaml first): the first
    half (``first`` poses) measured on `--sim`, then ``change(cfg, run)`` applied and the rest measured
    there with --allow-other-cell; (the run, the stderr of that)."""
    run = runs.make(n=n, **make)
    if before is not None:
        _changed(run, before)
    assert main(["run", str(run), "--sim", "--quiet", "--max-poses", str(first or n // 2)]) == 0
    _changed(run, change)
    capsys.readouterr()
    assert main(["run", str(run), "--sim", "--quiet", "--allow-other-cell"]) == 0
    return run, capsys.readouterr().err


def _move_tracker(cfg, run):
    doc = yaml.safe_load(DEFAULT_SCENE.read_text())
    doc["tracker"]["position_m"] = [0.6, -0.55, 2.8]  # 0.6 m aside, 0.2 m nearer, turned 20° about the vertical
    doc["tracker"]["rotation_cardan_deg"] = [90.0, 20.0, 180.0]
    (run.parent / "moved_scene.yaml").write_text(yaml.safe_dump(doc))
    cfg["scene"] = str(run.parent / "moved_scene.yaml")


def test_a_run_resumed_with_the_tracker_moved_is_one_model_with_a_step_per_segment_not_a_drift(runs, capsys, robot):
    run, err = _half_then(runs, capsys, 60, _move_tracker, sim={"hidden_effects": []})
    assert "moved" not in err  # the driver's drift check compares readings on one cell only
    assert "its own set-up is measured" in err
    assert main(["calibrate", str(run), "--no-ann", "--no-report"]) == 0
    out = capsys.readouterr().out
    said = [line for line in out.splitlines() if "registration per segment" in line]
    assert len(said) == 1 and "measured on 2 cells" in said[0] and "they agree" in said[0]
    metrics = json.loads((run / "calibration" / "metrics.json").read_text())
    cells = metrics["cells"]
    assert cells["decision"] == "mixed" and cells["agreement"]["agree"] and cells["reference_segment"] == 1
    assert [s["n_poses"] for s in cells["segments"]] == [30, 30]
    # the models' tests, and the reference pose measured on both cells (the drift checks) in each cell's
    # own set-up frame: the same place within the noise and the set-ups' errors
    assert [t["test"] for t in cells["agreement"]["tests"]] == ["paired", "paired", "repeat"]
    repeat = cells["agreement"]["tests"][2]
    assert repeat["n_poses"] == 1 and not repeat["disagrees"] and repeat["mean_distance_mm"] < 0.1
    assert metrics["drift"]["significant"] is not True
    # one robot, one model: the geometric model at the noise on the held-out poses of both cells
    # (a 6-D pose from three reflectors 5 cm apart: its position error about 1.6 σ; 40 µm allows 2.5x)
    assert metrics["stages"]["geometric"]["test"]["position_mm"]["mean"] < 4 * NOISE_M * 1e3
    assert metrics["stages"]["nominal"]["test"]["position_mm"]["mean"] < 20  # no step of 0.4 m left in the data

    assert main(["diagnose", str(run), "--json", "--no-report", "--candidates", "drift,thermal"]) == 0
    doc = json.loads(capsys.readouterr().out)
    assert doc["verdict"] is None and doc["cells"]["decision"] == "mixed"
    assert not any(c["significant"] for c in doc["ranking"])
    assert doc["drift"]["significant"] is not True

    # only now the truth: each segment's readings were derived with its own base-frame set-up (the
    # second cell measured its own, stored with it: the `setup` events), so the step from segment 2's
    # frame into segment 1's is T_LI,set-up 1⁻¹ T_LI,1 T_LI,2⁻¹ T_LI,set-up 2 (the set-ups' errors)
    from campaign.model.rotations import matrix_to_rotvec
    from campaign.plan.scene import load_scene

    with open_run(run) as store:
        setups = [np.asarray(d["T_LI"], dtype=float) for _, _, _, d in store.events("setup")]
    T1 = load_scene(DEFAULT_SCENE).placed(robot).T_LI
    T2 = load_scene(run.parent / "moved_scene.yaml").placed(robot).T_LI
    assert len(setups) == 2 and np.linalg.norm(setups[1][:3, 3] - setups[0][:3, 3]) > 0.3  # the tracker moved
    truth = np.linalg.inv(setups[0]) @ T1 @ np.linalg.inv(T2) @ setups[1]
    reg = cells["registration"][1]
    assert reg["segment"] == 2
    R = np.asarray(_rotvec_matrix(reg["rotation_vector_rad"]))
    # within the noise: 30 poses of 10 µm determine the step's six unknowns to a few µm (µrad over the
    # arm's metre), the set-ups' own errors (tens of µm) beside them
    assert np.linalg.norm(matrix_to_rotvec(truth[:3, :3])) > NOISE_M / 1.0  # a step the identity would miss
    assert np.linalg.norm(np.asarray(reg["translation_m"]) - truth[:3, 3]) < 2 * NOISE_M
    assert np.linalg.norm(matrix_to_rotvec(R.T @ truth[:3, :3])) < NOISE_M / 1.0


def _rotvec_matrix(r):
    from campaign.model.rotations import rotvec_to_matrix

    return rotvec_to_matrix(np.asarray(r, dtype=float))


def _another_robot(cfg, run):
    cfg["sim"]["seed"] = 5  # the seed draws the hidden geometric errors: another robot of the same type


def test_two_robots_in_one_run_are_refused_in_one_line_naming_the_segments(runs, capsys):
    run, _ = _half_then(runs, capsys, 60, _another_robot, sim={"hidden_effects": []})
    assert main(["calibrate", str(run), "--no-ann", "--no-report", "--quiet"]) == 1
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1, err
    assert "do not agree beyond a registration" in err[0] and "--cell-segment N" in err[0]
    assert "segment 1 (--sim, fingerprint" in err[0] and "segment 2 (--sim, fingerprint" in err[0]
    assert "30 poses, the 1st-30th measured" in err[0] and "30 poses, the 31st-60th measured" in err[0]
    assert "1 pose measured on both cells" in err[0]  # the reference pose, millimetres apart: it decides
    assert not (run / "calibration").exists()
    from campaign.diagnose.engine import diagnose

    with pytest.raises(DataError, match="do not agree beyond a registration"):
        diagnose(run, candidates="drift")

    # one segment, as the line says: the second robot's 30 poses alone, at the noise
    assert main(["calibrate", str(run), "--no-ann", "--no-report", "--cell-segment", "2"]) == 0
    metrics = json.loads((run / "calibration" / "metrics.json").read_text())
    geo = metrics["stages"]["geometric"]
    assert metrics["cells"]["decision"] == "segment" and metrics["cells"]["segment"] == 2
    assert geo["train"]["n_poses"] + geo["test"]["n_poses"] == 30
    assert geo["test"]["position_mm"]["mean"] < 4 * NOISE_M * 1e3
    assert metrics["cells"]["agreement"]["agree"] is False
    capsys.readouterr()
    assert main(["calibrate", str(run), "--no-ann", "--no-report", "--quiet", "--cell-segment", "3"]) == 1
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "--cell-segment 3: the run has 2 cell segments; give 1..2" in err[0]


def test_a_run_of_one_cell_is_calibrated_as_before(runs, capsys):
    run = runs.make(n=40)
    assert main(["run", str(run), "--sim", "--quiet"]) == 0
    assert main(["calibrate", str(run), "--no-ann", "--no-report"]) == 0
    first = json.loads((run / "calibration" / "metrics.json").read_text())
    assert main(["calibrate", str(run), "--no-ann", "--no-report", "--cell-segment", "1"]) == 0
    again = json.loads((run / "calibration" / "metrics.json").read_text())
    assert "cells" not in first and first["calibration_id"] != again["calibration_id"]
    assert {**first, "calibration_id": None} == {**again, "calibration_id": None}
    # its drift: every reading of the reference pose in one group, as the log holds them
    from campaign.measure.drift import fit_drift

    with open_run(run) as store:
        checks = [(t, d["xyz_m"]) for _, _, t, d in store.events("drift_check")]
        ref = store.get_meta("drift_reference")
        poses = store.load_measured()
    at = int(np.flatnonzero(poses.pose_id == ref["pose_id"])[0])
    t = np.r_[poses.time_s[at], [c[0] for c in checks]]
    xyz = np.vstack([poses.xyz[at], [c[1] for c in checks]])
    assert len(checks) >= 1 and first["drift"]["um_per_h"] == pytest.approx(fit_drift(t, xyz, np.zeros(len(t))).um_per_h,
                                                                              rel=1e-12)
    capsys.readouterr()
    assert main(["calibrate", str(run), "--no-ann", "--no-report", "--quiet", "--cell-segment", "2"]) == 1
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "the run has one cell segment (it was measured on one cell); give 1..1" in err[0]


def _planned(tmp_path, n_select=30, first=15, hidden=()):
    """A run planned on a small grid (`campaign plan --select`, its tour in visiting order), its
    ``first`` poses measured; hidden truth: geometry and the ``hidden`` effects."""
    cfg = tmp_path / "campaign.yaml"
    cfg.write_text(yaml.safe_dump({"plan": {"grid_cells": [9, 6, 6, 8, 4, 6], "motion_sample_deg": 2.0},
                                   "run": {"timeout_s": 0.5, "retries": 3, "backoff_s": 0.01},
                                   "sim": {"seed": 0, "hidden_effects": list(hidden)}}))
    run = tmp_path / "run"
    assert main(["plan", "--config", str(cfg), "--run", str(run), "--select", str(n_select), "--quiet"]) == 0
    assert main(["run", str(run), "--sim", "--quiet", "--max-poses", str(first)]) == 0
    return run


def _changed(run, change):
    cfg = yaml.safe_load((run / "campaign.yaml").read_text())
    change(cfg, run)
    (run / "campaign.yaml").write_text(yaml.safe_dump(cfg))


def test_auto_resumed_with_the_tracker_moved_models_the_step_and_adds_no_drift(tmp_path, capsys):
    run = _planned(tmp_path)
    _changed(run, _move_tracker)
    capsys.readouterr()
    assert main(["auto", str(run), "--sim", "--allow-other-cell", "--no-report", "--quiet"]) == 0
    story = capsys.readouterr().out.splitlines()
    said = [line for line in story if line.startswith("  cells: measured on 2 cells")]
    assert len(said) == 1 and "they agree beyond one registration per segment" in said[0]
    assert not any("drift" in line for line in story if line.startswith("round ")), story
    assert "drift" not in yaml.safe_load((run / "campaign.yaml").read_text()).get("effects", [])
    metrics = json.loads((run / "calibration" / "metrics.json").read_text())
    assert metrics["cells"]["decision"] == "mixed" and metrics["drift"]["significant"] is not True
    assert metrics["stages"][metrics["order"][-1]]["test"]["position_mm"]["mean"] < 4 * NOISE_M * 1e3


def test_auto_on_two_robots_stops_in_one_line_and_goes_on_with_one_segment(tmp_path, capsys):
    run = _planned(tmp_path)
    _changed(run, _another_robot)
    capsys.readouterr()
    assert main(["auto", str(run), "--sim", "--allow-other-cell", "--no-report", "--quiet"]) == 1
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "do not agree beyond a registration" in err[0] and "--cell-segment N" in err[0]
    # the second robot's poses alone, kept for the loop's later rounds
    assert main(["auto", str(run), "--cell-segment", "2", "--no-report", "--quiet"]) == 0
    metrics = json.loads((run / "calibration" / "metrics.json").read_text())
    assert metrics["cells"]["decision"] == "segment" and metrics["cells"]["segment"] == 2
    assert metrics["cells"]["segments"][0]["n_poses"] == 15
    geo = metrics["stages"][metrics["order"][-1]]
    assert geo["train"]["n_poses"] + geo["test"]["n_poses"] == metrics["cells"]["segments"][1]["n_poses"]
    assert geo["test"]["position_mm"]["mean"] < 4 * NOISE_M * 1e3


def test_a_run_begun_on_the_sim_and_resumed_on_the_mujoco_twin_is_two_segments_and_no_drift(tmp_path, capsys):
    """The twin takes its world (seed: the same geometric errors) from the sim section and puts the
    tracker where the scene does; its own physics (joint stiffness under gravity) stays inside what
    one model of the geometry fits on both."""
    run = _planned(tmp_path)
    assert main(["run", str(run), "--cell", "mujoco", "--quiet", "--allow-other-cell"]) == 0
    assert main(["calibrate", str(run), "--no-ann", "--no-report", "--quiet"]) == 0
    cells = json.loads((run / "calibration" / "metrics.json").read_text())["cells"]
    assert [s["spec"] for s in cells["segments"]] == ["--sim", "--cell mujoco"]
    assert cells["decision"] == "mixed" and cells["agreement"]["agree"]
    step = cells["registration"][1]
    assert np.linalg.norm(step["translation_m"]) < 1e-3  # the same tracker placement: no step worth a millimetre
    capsys.readouterr()
    assert main(["diagnose", str(run), "--json", "--no-report", "--candidates", "drift,thermal"]) == 0
    doc = json.loads(capsys.readouterr().out)
    assert doc["verdict"] not in ("drift", "thermal") and doc["cells"]["decision"] == "mixed"
    assert doc["drift"]["significant"] is not True


def test_data_in_the_trackers_frame_get_the_moved_trackers_registration(runs, capsys, robot):
    """Measured in the tracker's frame (`--frame tracker`, no base-frame set-up): each segment's
    readings are in its own tracker's frame, metres from the robot's; the step between them is the
    move of the tracker, T_LI,1 T_LI,2⁻¹."""
    run = runs.make(n=60, sim={"hidden_effects": []})
    assert main(["run", str(run), "--sim", "--quiet", "--max-poses", "30", "--frame", "tracker"]) == 0
    _changed(run, _move_tracker)
    assert main(["run", str(run), "--sim", "--quiet", "--allow-other-cell", "--frame", "tracker"]) == 0
    assert main(["calibrate", str(run), "--no-ann", "--no-report", "--quiet"]) == 0
    metrics = json.loads((run / "calibration" / "metrics.json").read_text())
    assert metrics["cells"]["decision"] == "mixed" and metrics["cells"]["agreement"]["agree"]
    assert metrics["stages"]["geometric"]["test"]["position_mm"]["mean"] < 4 * NOISE_M * 1e3
    from campaign.model.rotations import matrix_to_rotvec
    from campaign.plan.scene import load_scene

    truth = load_scene(DEFAULT_SCENE).placed(robot).T_LI @ np.linalg.inv(
        load_scene(run.parent / "moved_scene.yaml").placed(robot).T_LI)
    reg = metrics["cells"]["registration"][1]
    assert np.linalg.norm(np.asarray(reg["translation_m"]) - truth[:3, 3]) < 2 * NOISE_M
    R = _rotvec_matrix(reg["rotation_vector_rad"])
    assert np.linalg.norm(matrix_to_rotvec(R.T @ truth[:3, :3])) < NOISE_M / 1.0


def test_a_few_poses_of_another_robot_are_refused(runs, capsys):
    """Six poses on the second robot, too few for a model of their own: they pull the one model off
    the first robot's poses, which its own model fits at the noise."""
    run, _ = _half_then(runs, capsys, 36, _another_robot, first=30, sim={"hidden_effects": []})
    assert main(["calibrate", str(run), "--no-ann", "--no-report", "--quiet"]) == 1
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "do not agree beyond a registration" in err[0]
    assert "6 poses, the 31st-36th measured" in err[0] and "segment 1: held-out" in err[0] and "paired t" in err[0]
    assert "rests on the model" in err[0]  # no drift check on the second cell: no pose measured on both


def test_segments_follow_the_sessions_cells_in_the_log(tmp_path):
    """Each measured pose belongs to the cell of the session it was stored in; a session recorded
    before cells were (no cell) belongs to the cell before it, else the first; a cell measured on
    again adds to its segment; a failed pose makes no segment."""
    import time

    from campaign.measure.store import PoseRecord
    from campaign.run import RunFolder

    a = {"kind": "sim", "spec": "--sim", "fingerprint": "a" * 16, "detail": {}}
    b = {"kind": "cell", "spec": "--cell mujoco", "fingerprint": "b" * 16, "detail": {}}
    sessions = [(None, [1], "measured"), (a, [2], "measured"), (b, [3], "measured"), (b, [4], "failed"),
                (a, [5], "measured"), ({**b, "fingerprint": "c" * 16}, [6], "failed")]
    with open_run(tmp_path, create=True) as store:
        for cell, ids, status in sessions:
            store.add_event("session_start", {"cell": cell})
            time.sleep(0.002)
            for i in ids:
                store.add_pose(PoseRecord(i, status, (0.0,) * 6, seq=i, time_s=float(i), wall_time_unix_s=time.time(),
                                          xyz=(0.0, 0.0, 0.0) if status == "measured" else None,
                                          rotvec=(0.0, 0.0, 0.0) if status == "measured" else None))
            time.sleep(0.002)
    segments = RunFolder(tmp_path).cell_segments()
    assert [c["fingerprint"] for c in segments.cells] == ["a" * 16, "b" * 16, "c" * 16]
    assert segments.of([1, 2, 3, 5]).tolist() == [0, 0, 1, 0] and segments.mixed
    assert segments.describe(1) == "segment 2 (--cell mujoco, fingerprint bbbbbbbbbbbbbbbb): 1 pose, the 3rd measured (id 3)"
    assert [s["n_poses"] for s in segments.as_json()] == [3, 1, 0]


def test_a_cell_recorded_before_its_world_held_the_placement_is_the_same_cell(runs):
    """A run begun before the simulated world's fingerprint held the scene's placement, resumed on
    the same world: the same cell (no refusal, no second segment); a tracker moved from a recorded
    placement: another."""
    from campaign.config import load_config
    from campaign.measure.cell_identity import _fingerprint, cell_identity, refuse_other_cell, same_cell

    run = runs.make(n=4)
    cfg = load_config(run / "campaign.yaml")
    now = cell_identity(cfg, sim=True)
    world = {k: v for k, v in now["detail"]["world"].items() if k != "placement"}
    before = {**now, "detail": {"world": world}, "fingerprint": _fingerprint("sim", {"world": world})}
    assert before["fingerprint"] != now["fingerprint"] and same_cell(before, now) and same_cell(now, before)
    assert refuse_other_cell(run, before, now) == before
    _changed(run, _move_tracker)
    moved = cell_identity(load_config(run / "campaign.yaml"), sim=True)
    assert not same_cell(now, moved)  # (a record without its placement cannot tell a moved tracker)
    with pytest.raises(ConfigError, match=r"sim\.placement\.T_cell_L changed"):
        refuse_other_cell(run, now, moved)


def test_two_reflector_data_of_two_cells_take_each_cells_own_set_up(runs, capsys):
    """Two reflectors give no pose to register a segment by: one line says to calibrate one segment,
    and each segment's raw readings are carried into F_I by the set-up of its own cell (segment 1's
    by the first set-up, though the log's last is the moved tracker's)."""
    import campaign

    root = Path(campaign.__file__).parent / "data" / "robot_models" / "comau_racer5_080"
    doc = yaml.safe_load((root / "robot.yaml").read_text())
    doc.update(urdf=str(root / "robot.urdf"), name="comau_two", reflectors=doc["reflectors"][:2])

    def two_reflectors(cfg, run):
        (run.parent / "two.yaml").write_text(yaml.safe_dump(doc))
        cfg["robot"] = str(run.parent / "two.yaml")

    run, _ = _half_then(runs, capsys, 60, _move_tracker, before=two_reflectors, sim={"hidden_effects": []})
    assert main(["calibrate", str(run), "--no-ann", "--no-report", "--quiet"]) == 1
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "with a pose (three or more reflectors seen)" in err[0] and "--cell-segment N" in err[0]
    for n in (1, 2):
        assert main(["calibrate", str(run), "--no-ann", "--no-report", "--quiet", "--cell-segment", str(n)]) == 0
        metrics = json.loads((run / "calibration" / "metrics.json").read_text())
        assert metrics["cells"]["segment"] == n and metrics["measurement_kind"] == "markers"
        # in F_I: the nominal model millimetres off (the robot's errors), not the 0.4 m of another set-up
        assert metrics["stages"]["nominal"]["test"]["position_mm"]["mean"] < 20
        # each reflector at the noise: 10 µm per coordinate, its distance about 1.6 σ
        assert metrics["stages"]["geometric"]["test"]["position_mm"]["mean"] < 3 * NOISE_M * 1e3


def test_one_robot_on_two_parts_of_the_tour_with_an_effect_the_model_lacks_is_one_robot(tmp_path, capsys):
    """The tour's first half on one cell, the second (another part of the workspace) with the tracker
    moved, and compliances the geometric model lacks: each half's own model fits its part of the
    workspace far better than one model of both (the models' tests cannot tell that from two robots);
    the poses measured on both cells, each in its own set-up's frame, can, and decide."""
    run = _planned(tmp_path, n_select=60, first=49, hidden=("ground_compliance", "joint_compliance"))
    _changed(run, _move_tracker)
    assert main(["run", str(run), "--sim", "--quiet", "--allow-other-cell"]) == 0
    assert main(["calibrate", str(run), "--no-ann", "--no-report", "--quiet"]) == 0
    cells = json.loads((run / "calibration" / "metrics.json").read_text())["cells"]
    tests = {t["test"]: t for t in cells["agreement"]["tests"]}
    assert cells["decision"] == "mixed" and cells["agreement"]["agree"]
    assert tests["paired"]["disagrees"] and not tests["paired"]["decisive"]  # what the model lacks, not the cells
    assert not tests["repeat"]["disagrees"] and tests["repeat"]["n_poses"] >= 1
