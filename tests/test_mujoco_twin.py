"""Issue 21, item 3: the MuJoCo twin (`--cell mujoco`), checked against references outside it.

The truth's geometry is read back from RUN/cell/truth.yaml only after the twin has answered and
written as a URDF (campaign.model.export), which Pinocchio parses on its own: its forward
kinematics places the reflectors, its generalized gravity gives the sag the servos' stiffness
must produce. The tracker's lost beam and the planted collision use boxes written into the scene
file the twin reads, as a user would move one into the cell."""

import json

import numpy as np
import pytest
import yaml

from campaign.cell import CellContext, RobotFault, load_adapters
from campaign.config import load_config
from campaign.model.export import write_calibrated_urdf
from campaign.model.robot import RobotModel
from campaign.paths import DEFAULT_SCENE

#: two poses of the COMAU's default short campaign (default cell) whose reflectors all face the tracker
#: with 4° to spare, and whose tool passes 0.25 m from both on the motion between them
Q_A = np.array([0.0, 0.2478, 0.048, -0.2468, -0.2851, -1.5708])
Q_B = np.array([-0.345, -0.5061, -0.3726, 0.2468, 0.8552, -2.8274])


def _cell(tmp_path, extra_obstacles=(), controller=None, tracker=None):
    """The twin's two adapters for a run in tmp_path whose scene is the default cell plus
    ``extra_obstacles`` (scene entries)."""
    scene = yaml.safe_load(DEFAULT_SCENE.read_text())
    scene["obstacles"] += list(extra_obstacles)
    tmp_path.mkdir(parents=True, exist_ok=True)
    scene_path = tmp_path / "scene.yaml"
    scene_path.write_text(yaml.safe_dump(scene))
    cfg_path = tmp_path / "campaign.yaml"
    cfg_path.write_text(yaml.safe_dump({"scene": str(scene_path), "sim": {"seed": 4, "noise_m": 1e-5}}))
    robot = RobotModel.load()
    ctx = CellContext(run_dir=tmp_path, config=load_config(cfg_path), shared={})
    return load_adapters("mujoco", "mujoco", robot, {"controller": controller or {}, "tracker": tracker or {}},
                        cell_context=ctx)


def _truth_model(run_dir, robot):
    """Pinocchio's model and data of the truth's geometry (read after the twin answered)."""
    import pinocchio as pin

    truth = yaml.safe_load((run_dir / "cell" / "truth.yaml").read_text())
    urdf = write_calibrated_urdf(robot, np.array(truth["p_e"]), run_dir / "truth.urdf")
    model = pin.buildModelFromUrdf(str(urdf))
    model.gravity.linear = np.asarray(robot.gravity_in_I, dtype=float)  # the COMAU's root is F_I
    return model, model.createData(), truth


def _reflectors_pin(model, data, q, robot):
    import pinocchio as pin

    pin.framesForwardKinematics(model, data, q)
    return {r.name: data.oMf[model.getFrameId(r.name)].translation.copy() for r in robot.reflectors}


def test_reflectors_at_rest_without_gravity_are_pinocchio_fk_of_the_truth(tmp_path):
    ctrl, trk = _cell(tmp_path)
    twin = ctrl.twin
    rng = np.random.default_rng(0)
    robot = twin.robot
    qs = rng.uniform(robot.q_lower, robot.q_upper, size=(5, robot.n_joints))
    seen = []
    for q in qs:  # the kinematics of the compiled model, no dynamics
        twin.set_joints(q)
        seen.append({k: p for k, (p, _) in twin.reflectors_in_I().items()})
    model, data, _ = _truth_model(tmp_path, robot)
    for q, s in zip(qs, seen):
        ref = _reflectors_pin(model, data, q, robot)
        for name in ref:
            assert np.max(np.abs(s[name] - ref[name])) < 1e-9
    # the truth is not the nominal robot: the hidden errors move the reflectors by millimetres
    nominal = RobotModel.load().pinocchio_model
    nd = nominal.createData()
    import pinocchio as pin

    pin.framesForwardKinematics(nominal, nd, qs[0])
    assert np.linalg.norm(nd.oMf[nominal.getFrameId("rrr1")].translation - seen[0]["rrr1"]) > 1e-4


def test_static_sag_is_gravity_torque_over_stiffness(tmp_path):
    """At rest the servo springs hold the weight: q_link = q_cmd − K⁻¹ g(q_link) (Pinocchio's
    generalized gravity on the truth's URDF), and the reflectors sit where Pinocchio puts them."""
    import pinocchio as pin

    ctrl, trk = _cell(tmp_path, controller={"stiffness_nm_rad": 1e5})
    ctrl.move(Q_A)
    ctrl.move(Q_B)
    q_link = ctrl.twin.joint_positions()
    got = {k: p for k, (p, _) in ctrl.twin.reflectors_in_I().items()}
    assert np.allclose(ctrl.joints(), Q_B, atol=0)  # the encoders read the motor side: the command
    # the COMAU stands upright in F_I, whose y axis is vertical with up = −y (DESIGN.md, "Frames")
    assert np.allclose(ctrl.twin.model.opt.gravity, [0.0, 9.81, 0.0], atol=0)
    model, data, truth = _truth_model(tmp_path, ctrl.twin.robot)
    kp = np.array(truth["servo"]["stiffness"])
    q = Q_B.copy()
    for _ in range(20):  # the fixed point of the spring balance
        q = Q_B - pin.computeGeneralizedGravity(model, data, q) / kp
    assert np.max(np.abs(q_link - q)) < 1e-8
    ref = _reflectors_pin(model, data, q, ctrl.twin.robot)
    rigid = _reflectors_pin(model, data, Q_B, ctrl.twin.robot)
    sag = np.linalg.norm(rigid["rrr1"] - ref["rrr1"])
    assert 5e-5 < sag < 1e-3  # tenths of a millimetre
    for name in ref:
        assert np.linalg.norm(got[name] - ref[name]) < 1e-3 * sag


def test_tracker_loses_the_beam_behind_a_box_and_sees_the_others(tmp_path):
    ctrl, trk = _cell(tmp_path / "open", tracker={"noise_m": 0.0})
    ctrl.move(Q_A)
    aims = {"rrr1": None, "rrr2": None, "brr": None}
    clear = trk.measure(aims)
    assert all(v is not None for v in clear.values())
    # a 2 cm box on rrr1's beam, a third of the way to the tracker
    p = ctrl.twin.reflectors_in_I()["rrr1"][0]
    o = trk.T_IL[:3, 3]
    centre = p + (o - p) / 3
    box = {"name": "blocker", "box": {"center_m": [float(v) for v in centre], "size_m": [0.02, 0.02, 0.02]}}
    ctrl2, trk2 = _cell(tmp_path / "blocked", [box], tracker={"noise_m": 0.0})
    ctrl2.move(Q_A)
    blocked = trk2.measure(aims)
    assert blocked["rrr1"] is None
    assert trk2.twin.first_hit(o, p)[1] == "scene:blocker"
    stats = json.loads((tmp_path / "blocked" / "cell" / "twin.json").read_text())
    assert stats["lost_beams"] == {"beam blocked by scene:blocker": 1}
    for name in ("rrr2", "brr"):  # the same twin (same seed): the other beams pass, to the same point
        assert np.allclose(blocked[name], clear[name], atol=1e-12)
    # noise free, a reading is the site's position in the tracker frame
    x = np.linalg.inv(trk.T_IL) @ np.append(ctrl.twin.reflectors_in_I()["rrr2"][0], 1.0)
    assert np.allclose(clear["rrr2"], x[:3], atol=1e-12)
    # the tracker finds a reflector near where the driver aims it (5 cm), not 6 cm off
    near = trk.measure({"rrr2": x[:3] + [0.0, 0.03, 0.03]})
    far = trk.measure({"rrr2": x[:3] + [0.0, 0.0, 0.06]})
    assert np.allclose(near["rrr2"], x[:3], atol=1e-12) and far["rrr2"] is None


def test_a_box_moved_into_a_motion_fails_the_pose_with_its_reason(tmp_path):
    from campaign.model.kinematics import forward

    robot = RobotModel.load()
    mid = forward(robot, (0.5 * (Q_A + Q_B))[None])[0][:3, 3]  # the tool half-way along the motion
    box = {"name": "planted", "box": {"center_m": [float(v) for v in mid], "size_m": [0.1, 0.1, 0.1]}}
    open_ctrl, _ = _cell(tmp_path / "open")
    open_ctrl.move(Q_A)
    open_ctrl.move(Q_B)  # the motion is clear in the cell as planned
    ctrl, trk = _cell(tmp_path / "planted", [box])
    ctrl.move(Q_A)
    with pytest.raises(RobotFault, match=r"^collision in the twin: .*scene:planted"):
        ctrl.move(Q_B)
    stats = json.loads((tmp_path / "planted" / "cell" / "twin.json").read_text())
    assert stats["contacts"] >= 1 and stats["collisions"] == 1 and stats["max_penetration_m"] > 0
    assert stats["motions"] == 2
    # the arm is back at rest where the motion began, and the encoders still read that command
    assert np.allclose(ctrl.joints(), Q_A, atol=0)
    assert np.max(np.abs(ctrl.twin.joint_positions() - Q_A)) < 2e-3
    ctrl.move(Q_A)  # and it moves on


def test_plan_then_run_on_the_twin_is_collision_free_and_calibrate_finds_its_stiffness(tmp_path):
    """`campaign plan --select` on a small grid, `campaign run --cell mujoco`: MuJoCo checks every
    motion of the tour step by step (no contact), every pose is stored once, a pose fails only by
    a lost beam (a nest at the edge of its cone: the plan's cones are the nominal robot's); then
    `calibrate --effects joint_compliance` identifies the servos' compliance 1/kp from the sag
    that MuJoCo's dynamics made (the stiffness read from the twin's truth only afterwards)."""
    import sqlite3

    from campaign.cli import main
    from campaign.measure.driver import read_plan

    cfg = tmp_path / "campaign.yaml"
    # no drift monitor (run.drift_check_every: 0): every motion the twin counts is then a motion of the tour
    cfg.write_text(yaml.safe_dump({"plan": {"grid_cells": [9, 6, 6, 8, 4, 6], "motion_sample_deg": 2.0},
                                   "sim": {"seed": 2, "noise_m": 1e-5}, "run": {"drift_check_every": 0}}))
    run = tmp_path / "run"
    assert main(["plan", "--config", str(cfg), "--run", str(run), "--select", "40", "--quiet"]) == 0
    assert main(["run", str(run), "--cell", "mujoco", "--quiet"]) == 0
    ids, _, vias = read_plan(run)
    with sqlite3.connect(run / "measurements.sqlite") as db:
        rows = db.execute("SELECT pose_id, status, reason FROM poses").fetchall()
    assert sorted(r[0] for r in rows) == sorted(int(i) for i in ids)
    failed = [r for r in rows if r[1] != "measured"]
    assert all(r[2].startswith("tracker after") and "beam_lost" in r[2] for r in failed), failed
    assert len(failed) <= 0.2 * len(rows)
    stats = json.loads((run / "cell" / "twin.json").read_text())
    assert stats["contacts"] == 0 and stats["max_penetration_m"] == 0.0
    assert set(stats["lost_beams"]) <= {"outside the nest's cone"}  # no beam blocked, none out of range
    assert stats["motions"] == len(ids) + sum(len(v) for v in vias.values())
    # the campaign clock is the twin's simulated time: every step of every motion, and 5 s a target
    # measured (10 set-up rounds of 3 points; 3 reflectors a pose, tried 4 times when a beam is lost)
    with sqlite3.connect(run / "measurements.sqlite") as db:
        clock = json.loads(db.execute("SELECT value FROM meta WHERE key = 'campaign_clock_s'").fetchone()[0])
    targets = 3 * (10 + (len(rows) - len(failed)) + 4 * len(failed))
    assert clock == pytest.approx(stats["steps"] * stats["timestep_s"] + 5.0 * targets, rel=1e-9)

    assert main(["calibrate", str(run), "--effects", "joint_compliance", "--no-ann", "--no-report", "--quiet"]) == 0
    params = yaml.safe_load((run / "calibration" / "params.yaml").read_text())
    found = {p["name"]: (p["value"], p["sigma"]) for p in params["effects"]["joint_compliance"]["parameters"]}
    truth = yaml.safe_load((run / "cell" / "truth.yaml").read_text())  # only now
    kp = truth["servo"]["stiffness"]
    for j in (2, 3):  # Δq = c·τ with τ the holding torque: the spring gives c = −1/kp
        c, sigma = found[f"c{j}"]
        assert sigma < 0.1 / kp[j - 1] and abs(c + 1.0 / kp[j - 1]) < 3 * sigma, (j, c, sigma)
    # each lost pose has a nest beyond its cone in the truth's geometry (Pinocchio, commanded q: the
    # sag turns the tool by hundredths of a degree), though inside it in the nominal one the plan used
    robot = RobotModel.load()
    model, data, _ = _truth_model(run, robot)
    T_LI = np.array(truth["tracker"]["T_LI"])
    tracker_I = -T_LI[:3, :3].T @ T_LI[:3, 3]
    q_by_id = dict(zip((int(i) for i in ids), read_plan(run)[1]))
    for pid, _, _ in failed:
        excess = []
        for model_, data_ in ((model, data), (robot.pinocchio_model, robot.pinocchio_model.createData())):
            import pinocchio as pin

            pin.framesForwardKinematics(model_, data_, q_by_id[pid])
            E = data_.oMf[model_.getFrameId("E")]
            worst = -np.inf
            for r in robot.reflectors:
                p = data_.oMf[model_.getFrameId(r.name)].translation
                v = tracker_I - p
                angle = np.arccos(E.rotation @ np.array(r.axis_in_E) @ v / np.linalg.norm(v))
                worst = max(worst, angle - r.half_angle)
            excess.append(np.degrees(worst))
        assert excess[0] > -0.1 and excess[1] <= 1e-9, (pid, excess)


def test_a_bad_option_is_one_line_naming_it(tmp_path):
    from campaign.errors import ConfigError

    with pytest.raises(ConfigError, match=r"^--controller mujoco: controller options: unknown option 'stifness_nm_rad'"):
        _cell(tmp_path, controller={"stifness_nm_rad": 1e5})
    with pytest.raises(ConfigError, match=r"stiffness_nm_rad: must be one number or 6 \(one per joint\), got 2"):
        _cell(tmp_path, controller={"stiffness_nm_rad": [1e5, 1e5]})


def test_twin_json_keeps_every_session_of_a_run(tmp_path):
    """Issue 31, part 5: a resumed run starts a new twin; cell/twin.json keeps the earlier session."""
    ctrl, _ = _cell(tmp_path / "run")
    ctrl.move(Q_A)
    ctrl.move(Q_B)
    first = json.loads((tmp_path / "run" / "cell" / "twin.json").read_text())
    assert first["motions"] == 2 and len(first["sessions"]) == 1
    ctrl2, _ = _cell(tmp_path / "run")  # the same run, served again
    ctrl2.move(Q_A)
    doc = json.loads((tmp_path / "run" / "cell" / "twin.json").read_text())
    assert doc["motions"] == 1  # this session's, as before
    assert [s["motions"] for s in doc["sessions"]] == [2, 1]
    assert doc["totals"]["motions"] == 3 and doc["totals"]["steps"] == first["steps"] + doc["steps"]
