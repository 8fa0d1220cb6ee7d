"""ISO 9283 pose accuracy and repeatability: the test plan (`plan --iso9283`), its figures
(`campaign iso9283`) recomputed here from the exported measurements, the repeatability of the
simulator's noise against a Monte Carlo of the tracker alone, and the accuracy after calibration.

References outside the code under test: Pinocchio's forward kinematics of the URDF, python-fcl
distances (tests/fcl_reference.py), a Kabsch fit written here, numpy on the exported CSV."""

import csv
import json

import numpy as np
import pinocchio as pin
import pytest
import yaml

from campaign.cli import main
from campaign.model.robot import RobotModel
from campaign.paths import DEFAULT_SCENE
from campaign.plan.checks import ClearanceChecker
from campaign.plan.scene import load_scene

from fcl_reference import FclReference

GRID_SCALE = "0.6"
CYCLES = 30


def test_the_five_poses_lie_on_the_diagonal_plane_at_a_tenth_of_the_diagonal_from_its_corners():
    from campaign.iso9283.plan import cube_axes, test_points

    axes = cube_axes([0.0, -9.81, 0.0])  # the COMAU's F_I: y up
    assert np.allclose(axes[:, 2], [0, 1, 0]) and np.allclose(axes.T @ axes, np.eye(3))
    c, h = np.array([0.1, -0.6, 0.5]), 0.2
    P = test_points(c, axes, h)
    corner = {k: c + axes @ (h * np.array(s)) for k, s in
              {1: (-1, -1, -1), 2: (1, -1, -1), 7: (1, 1, 1), 8: (-1, 1, 1)}.items()}
    assert np.allclose(P[0], c)
    L = np.linalg.norm(corner[7] - corner[1])
    assert L == pytest.approx(2 * h * np.sqrt(3))
    for k, (a, b) in zip((1, 2, 3, 4), ((1, 7), (2, 8), (7, 1), (8, 2))):
        assert np.linalg.norm(P[k] - corner[a]) == pytest.approx(0.1 * L)
        assert np.linalg.norm(P[k] - corner[b]) == pytest.approx(0.9 * L)
    normal = np.cross(corner[2] - corner[1], corner[8] - corner[1])
    assert np.allclose((P - corner[1]) @ normal, 0.0, atol=1e-12)  # all five in the plane C1-C2-C7-C8


def _config(tmp_path, seed=3):
    cfg = tmp_path / "campaign.yaml"
    cfg.write_text(yaml.safe_dump({"sim": {"seed": seed, "time_factor": 0.0, "noise_m": 10e-6},
                                   "run": {"timeout_s": 5.0}}))
    return str(cfg)


@pytest.fixture(scope="module")
def iso(tmp_path_factory):
    tmp = tmp_path_factory.mktemp("iso")
    cfg = _config(tmp)
    run = tmp / "iso"
    assert main(["plan", "--config", cfg, "--run", str(run), "--iso9283", "--cycles", str(CYCLES),
                 "--grid-scale", GRID_SCALE, "--quiet"]) == 0
    assert main(["run", str(run), "--sim", "--quiet"]) == 0
    return tmp, cfg, run


def _test(run):
    return json.loads((run / "plan" / "iso9283.json").read_text())


def test_iso_plan_reaches_its_targets_in_pinocchio_and_is_clear_in_fcl(iso):
    _, _, run = iso
    test = _test(run)
    robot = RobotModel.load()
    model, data = robot.pinocchio_model, robot.pinocchio_model.createData()
    fid = model.getFrameId("E")
    for p in test["poses"]:
        pin.framesForwardKinematics(model, data, np.asarray(p["q_command"]))
        assert np.allclose(data.oMf[fid].homogeneous, np.asarray(p["target_T_IE"]), atol=1e-9), p["name"]
    R = np.array([p["target_T_IE"] for p in test["poses"]])[:, :3, :3]
    assert np.allclose(R, R[0], atol=1e-9)  # one tool orientation for the five poses
    ref = FclReference(robot, DEFAULT_SCENE, np.eye(4))
    pairs = ref.pairs(ClearanceChecker(robot, load_scene(DEFAULT_SCENE).placed(robot), 0.035))
    assert min(ref.min_clearance(np.asarray(p["q_command"]), pairs) for p in test["poses"]) >= 0.035
    ids = [int(r["pose_id"]) for r in csv.DictReader(open(run / "plan" / "poses.csv"))]
    assert ids[:10] == [1, 5, 4, 3, 2, 11, 15, 14, 13, 12] and len(ids) == 5 * CYCLES
    assert test["cube"]["edge_m"] > 0.1


def test_iso_figures_equal_an_independent_computation_from_the_exported_measurements(iso, capsys):
    tmp, _, run = iso
    assert main(["iso9283", str(run), "--json"]) == 0
    doc = json.loads(capsys.readouterr().out)
    assert doc == json.loads((run / "iso9283" / "report.json").read_text())
    assert main(["export", str(run), "--csv", str(tmp / "iso.csv")]) == 0
    rows = list(csv.DictReader(open(tmp / "iso.csv")))
    test = _test(run)
    for k, p in enumerate(doc["poses"], start=1):
        x = np.array([[float(r[c]) for c in "xyz"] for r in rows if int(r["pose_id"]) % 10 == k])
        assert len(x) == CYCLES
        target = np.asarray(test["poses"][k - 1]["target_T_IE"])[:3, 3]
        ap = np.linalg.norm(x.mean(axis=0) - target) * 1e3
        l = np.linalg.norm(x - x.mean(axis=0), axis=1)
        rp = (l.mean() + 3 * l.std(ddof=1)) * 1e3
        assert p["pose"] == f"P{k}" and p["AP_p_mm"] == pytest.approx(ap, rel=0.01)
        assert p["RP_l_mm"] == pytest.approx(rp, rel=0.01)
        assert p["nominal"]["AP_p_mm"] == p["AP_p_mm"] and p["calibrated"] is None
        assert p["AP_p_mm"] > 0.5  # the simulated robot hides millimetre-size geometric errors


def _kabsch_origin_error(P_E, P_meas):
    """Tool-origin error (n, 3) of the rigid fit of measured reflectors P_meas (n, k, 3) to P_E (k, 3)."""
    out = np.empty((len(P_meas), 3))
    a0 = P_E.mean(axis=0)
    for i, B in enumerate(P_meas):
        b0 = B.mean(axis=0)
        U, _, Vt = np.linalg.svd((P_E - a0).T @ (B - b0))
        D = np.diag([1, 1, np.sign(np.linalg.det(Vt.T @ U.T))])
        R = Vt.T @ D @ U.T
        out[i] = b0 - R @ a0  # the fitted origin of E (true origin at 0)
    return out


def test_repeatability_of_the_noise_alone_is_its_expected_value(iso):
    _, _, run = iso
    doc = json.loads((run / "iso9283" / "report.json").read_text()) if (run / "iso9283" / "report.json").exists() \
        else None
    if doc is None:
        assert main(["iso9283", str(run)]) == 0
        doc = json.loads((run / "iso9283" / "report.json").read_text())
    robot = RobotModel.load()
    P_E = robot.reflector_positions_in_E
    rng = np.random.default_rng(7)
    # RP_l of 30 cycles, averaged over many simulated tests of the tracker noise alone
    rp = []
    for _ in range(400):
        e = _kabsch_origin_error(P_E, P_E[None] + rng.normal(0, 10e-6, size=(CYCLES, *P_E.shape)))
        l = np.linalg.norm(e - e.mean(axis=0), axis=1)
        rp.append(l.mean() + 3 * l.std(ddof=1))
    expected_mm = 1e3 * float(np.mean(rp))
    measured = np.mean([p["RP_l_mm"] for p in doc["poses"]])
    assert measured == pytest.approx(expected_mm, rel=0.10), (measured, expected_mm)


def test_after_calibration_pose_accuracy_falls_to_the_noise_floor(iso, capsys):
    tmp, cfg, run = iso
    cal, comp = tmp / "cal", tmp / "iso-cal"
    assert main(["plan", "--config", cfg, "--run", str(cal), "--grid-scale", GRID_SCALE, "--quiet"]) == 0
    assert main(["run", str(cal), "--sim", "--quiet"]) == 0
    assert main(["calibrate", str(cal), "--no-ann", "--effects", "ground_compliance", "--quiet"]) == 0
    assert main(["plan", "--config", cfg, "--run", str(comp), "--iso9283", "--cycles", str(CYCLES),
                 "--compensate", str(cal), "--grid-scale", GRID_SCALE, "--quiet"]) == 0
    assert main(["run", str(comp), "--sim", "--quiet"]) == 0
    capsys.readouterr()
    assert main(["iso9283", str(run), "--calibrated", str(comp)]) == 0
    out = capsys.readouterr().out
    assert "calibrated" in out and "AP_P mm" in out
    doc = json.loads((run / "iso9283" / "report.json").read_text())
    floor = doc["noise_floor_mm"]
    assert 0.004 < floor < 0.03
    for p in doc["poses"]:
        assert p["calibrated"]["AP_p_mm"] <= 2 * floor, (p["pose"], p["calibrated"]["AP_p_mm"], floor)
        assert p["nominal"]["AP_p_mm"] > 50 * floor
    html = (run / "iso9283" / "report.html").read_text()
    assert "<svg" in html and "noise floor" in html
    # each compensated pose against the calibration's domain (issue 30), recorded by the plan and reported
    plan = json.loads((comp / "plan" / "iso9283.json").read_text())["compensated_with"]
    assert len(plan["in_domain"]) == len(plan["sigma_mm"]) == 5
    for p, inside, sigma in zip(doc["poses"], plan["in_domain"], plan["sigma_mm"]):
        assert p["in_domain"] is inside and p["sigma_mm"] == sigma and 0 < sigma < 2 * floor


def test_iso9283_bad_input_is_one_line(iso, tmp_path, capsys):
    _, cfg, run = iso
    assert main(["iso9283", str(tmp_path / "nothing")]) == 1
    err = capsys.readouterr().err
    assert "not an ISO 9283 run" in err and len(err.strip().splitlines()) == 1
    assert main(["plan", "--run", str(tmp_path / "x"), "--cycles", "5"]) == 1
    assert "--iso9283" in capsys.readouterr().err
    assert main(["plan", "--run", str(tmp_path / "x"), "--iso9283", "--select", "5"]) == 1
    assert "--select" in capsys.readouterr().err
    assert main(["plan", "--run", str(tmp_path / "x"), "--iso9283", "--cycles", "1"]) == 1
    assert "--cycles" in capsys.readouterr().err
    assert main(["iso9283", str(run), "--calibrated", str(run)]) == 1
    assert "nominal commands" in capsys.readouterr().err
