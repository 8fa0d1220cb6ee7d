"""Rough edges a user hit (issue 29, items 1-10): each a clear answer or a working result, never a
traceback and never a silent wrong answer. Data are written here: nominal poses by Pinocchio
reading the URDF, adapters and URDFs in the test itself."""

import json
import re
from pathlib import Path

import numpy as np
import pinocchio as pin
import pytest
import yaml
from scipy.spatial.transform import Rotation

from campaign.cli import main
from campaign.model.robot import RobotModel
from campaign.paths import ROBOT_MODELS
from campaign.run import RunFolder

from fcl_reference import erd_robot

COMAU_URDF = ROBOT_MODELS / "comau_racer5_080" / "robot.urdf"


def one_line_error(capsys, argv, match) -> str:
    """Run the CLI in-process: exit 1, one stderr line matching ``match``, no traceback."""
    rc = main([str(a) for a in argv])
    err = capsys.readouterr().err
    lines = err.strip().splitlines()
    assert rc == 1 and len(lines) == 1 and "Traceback" not in err, err
    assert re.search(match, lines[0]), lines[0]
    return lines[0]


def comau_q(n: int = 40, seed: int = 0) -> np.ndarray:
    """Random joint vectors (n, 6) inside 80 % of the COMAU's limits (rad)."""
    model = pin.buildModelFromUrdf(str(COMAU_URDF))
    rng = np.random.default_rng(seed)
    return rng.uniform(model.lowerPositionLimit, model.upperPositionLimit, size=(n, model.nq)) * 0.8


def nominal_poses(q) -> np.ndarray:
    """The COMAU's nominal poses of E (n, 4, 4) at q (n, 6), by Pinocchio from the URDF."""
    model = pin.buildModelFromUrdf(str(COMAU_URDF))
    data, fid = model.createData(), model.getFrameId("E")
    out = []
    for qi in q:
        pin.framesForwardKinematics(model, data, qi)
        out.append(data.oMf[fid].homogeneous)
    return np.array(out)


def nominal_csv(path: Path, n: int = 40, seed: int = 0, q=None) -> Path:
    """The COMAU's nominal poses of E, computed by Pinocchio from the URDF: data a perfect
    calibration fits with zero error (what `predict --stage nominal` or a perfect adapter gives)."""
    q = comau_q(n, seed) if q is None else q
    rows = ["pose_id,q1,q2,q3,q4,q5,q6,x,y,z,rx,ry,rz"]
    for i, (qi, T) in enumerate(zip(q, nominal_poses(q))):
        values = [*qi, *T[:3, 3], *Rotation.from_matrix(T[:3, :3]).as_rotvec()]
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


# -- 4. diagnose describes the model the last calibration made -----------------------------------

def test_diagnose_after_calibrate_effects_describes_the_calibrated_model(nominal_run, tmp_path, capsys):
    run = run_copy(nominal_run, tmp_path / "run")
    assert main(["calibrate", str(run), "--no-ann", "--effects", "ground_compliance"]) == 0
    calibration_id = json.loads((run / "calibration" / "metrics.json").read_text())["calibration_id"]
    capsys.readouterr()
    assert main(["diagnose", str(run), "--json"]) == 0
    d = json.loads(capsys.readouterr().out)
    assert d["current_effects"] == ["ground_compliance"]  # params.yaml's, not campaign.yaml's (none)
    assert "ground_compliance" not in [c["effect"] for c in d["ranking"]]
    assert calibration_id in d["model_note"] and "campaign.yaml enables no effect" in d["model_note"]
    # campaign.yaml made to agree: no note
    cfg = run / "campaign.yaml"
    cfg.write_text(cfg.read_text().replace("effects: []", "effects: [ground_compliance]"))
    assert main(["diagnose", str(run), "--json"]) == 0
    d = json.loads(capsys.readouterr().out)
    assert d["current_effects"] == ["ground_compliance"] and d["model_note"] is None


# -- 3. a tracker adapter in millimetres stops the run at once ----------------------------------

#: a perfect cell: the nominal robot (Pinocchio) seen by a tracker 2.4 m away; the tracker's
#: option ``scale`` multiplies its readings (1000: an adapter that returns millimetres)
PERFECT_CELL = '''
import numpy as np
import pinocchio as pin

WORLD = {"q": None}
T_LI = np.array([[0, -1, 0, 2.4], [1, 0, 0, 0.5], [0, 0, 1, -0.3], [0, 0, 0, 1.0]])
SETUP_I = {"setup_origin": [0, 0, 0], "setup_x": [0.3, 0, 0], "setup_y": [0, 0.3, 0]}


class Controller:
    joint_convention = "model"

    def __init__(self, robot, options):
        WORLD["q"] = np.array(robot.q_mid)

    def move(self, q):
        WORLD["q"] = np.array(q)


class Tracker:
    def __init__(self, robot, options):
        self.robot, self.scale = robot, float(options.get("scale", 1.0))

    def measure(self, aims):
        robot = self.robot
        model = robot.pinocchio_model
        data = model.createData()
        pin.framesForwardKinematics(model, data, robot.pinocchio_q(WORLD["q"])[0])
        T_IE = np.linalg.inv(robot.T_root_base) @ data.oMf[model.getFrameId(robot.tool_frame)].homogeneous
        T_LE = T_LI @ T_IE
        true = {r.name: T_LE[:3, :3] @ np.array(r.position_in_E) + T_LE[:3, 3] for r in robot.reflectors}
        true.update({k: T_LI[:3, :3] @ np.array(v, float) + T_LI[:3, 3] for k, v in SETUP_I.items()})
        return {name: self.scale * true[name] for name in aims}
'''


def stored_count(run: Path) -> int:
    import sqlite3

    if not (run / "measurements.sqlite").exists():
        return 0
    with sqlite3.connect(run / "measurements.sqlite") as db:
        return db.execute("SELECT COUNT(*) FROM poses").fetchone()[0]


@pytest.mark.parametrize("frame, match", [
    ("tracker", r"pose 1000: reflectors \w+ and \w+ read [\d.]+ m apart, 1,000× the [\d.]+ m of the robot's "
                r"reflector geometry .*millimetres"),
    ("robot", r"base-frame set-up: target setup_\w+ reads [\d,]+ m from the tracker, beyond any laser tracker's "
              r"range \(160 m\): the readings look like millimetres")])
def test_a_tracker_adapter_in_millimetres_stops_the_run_at_the_first_pose(runs, tmp_path, capsys, frame, match):
    import time

    run = runs.make(n=30, seed=3, run={"timeout_s": 5.0})
    (run / "my_cell_mm.py").write_text(PERFECT_CELL)
    (tmp_path / "mm.yaml").write_text("tracker: {scale: 1000.0}\n")
    t0 = time.perf_counter()
    line = one_line_error(capsys, ["run", run, "--cell", "my_cell_mm.py", "--options", tmp_path / "mm.yaml",
                                   "--frame", frame, "--quiet"], match)
    assert time.perf_counter() - t0 < 30
    assert "must return metres" in line and stored_count(run) == 0  # nothing wrong stored


def test_a_perfect_adapter_measures_and_calibrates_to_zero(runs, capsys):
    run = runs.make(n=30, seed=3, run={"timeout_s": 5.0})
    (run / "my_cell.py").write_text(PERFECT_CELL)
    assert main(["run", str(run), "--cell", "my_cell.py", "--quiet"]) == 0
    assert stored_count(run) == 30
    assert main(["calibrate", str(run), "--no-ann"]) == 0, capsys.readouterr().err
    metrics = json.loads((run / "calibration" / "metrics.json").read_text())
    assert metrics["stages"]["geometric"]["test"]["position_mm"]["max"] < 1e-6


# -- 6. --robot NAME is a name even when a folder of that name is here ---------------------------

@pytest.mark.parametrize("name, joint", [("comau_racer5_080", None), ("ur10", "shoulder_pan_joint")])
def test_import_resolves_a_robot_name_shadowed_by_a_folder_as_model_and_plan_do(tmp_path, monkeypatch, capsys,
                                                                               name, joint):
    if name == "ur10" and not erd_robot("ur_description/urdf/ur10_robot.urdf").is_file():
        pytest.skip("example-robot-data is not installed")
    monkeypatch.chdir(tmp_path)
    assert main(["synth", "--csv", "data.csv", "--robot", name, "--poses", "30"]) == 0
    (tmp_path / name).mkdir()  # e.g. a run folder `campaign plan --run ur10` made
    assert main(["model", "chain", "--robot", name]) == 0
    assert main(["import", "data.csv", "--run", "run", "--robot", name, "--quiet"]) == 0, capsys.readouterr().err
    assert yaml.safe_load((tmp_path / "run" / "campaign.yaml").read_text())["robot"] == name
    robot = RunFolder(tmp_path / "run").robot()
    assert robot.joint_names == RobotModel.load(name).joint_names
    assert joint is None or robot.joint_names[0] == joint


# -- 7. predict and compensate use the limit slack the run's import accepted --------------------

def test_predict_and_compensate_accept_what_the_import_accepted_with_limit_slack(tmp_path, capsys):
    robot = RobotModel.load()
    q = comau_q(40, seed=5)
    q[3, 0] = robot.q_upper[0] + np.radians(0.3)  # a real reading 0.3 deg past the URDF's limit
    data = nominal_csv(tmp_path / "data.csv", q=q)
    run = tmp_path / "run"
    assert main(["import", str(data), "--run", str(run), "--limit-slack", "0.5", "--quiet"]) == 0
    assert main(["calibrate", str(run), "--no-ann", "--quiet", "--no-report"]) == 0
    out = tmp_path / "pred.csv"
    assert main(["predict", str(run), "--csv", str(data), "--out", str(out)]) == 0, capsys.readouterr().err
    got = np.loadtxt(out, delimiter=",", skiprows=1)
    assert np.allclose(got[:, 7:10], nominal_poses(q)[:, :3, 3], atol=1e-6)  # exact data: the nominal model
    assert main(["compensate", str(run), "--csv", str(data), "--out", str(tmp_path / "comp.csv")]) == 0
    # further past than the run accepted: refused, saying the slack in force; accepted when given
    q[3, 0] = robot.q_upper[0] + np.radians(0.8)
    far = nominal_csv(tmp_path / "far.csv", q=q)
    capsys.readouterr()
    for verb in ("predict", "compensate"):
        one_line_error(capsys, [verb, run, "--csv", far],
                       r"line 5, q1 = [\d.]+ rad is outside the joint limit [\d.]+ rad of COMAU Racer5-0\.80 "
                       r"\(limit slack in force: 0\.5 deg, as the run's import accepted; --limit-slack")
        assert main([verb, str(run), "--csv", str(far), "--limit-slack", "1", "--out", str(tmp_path / "x.csv")]) == 0


@pytest.fixture(scope="module")
def calibrated_run(nominal_run, tmp_path_factory):
    """A copy of ``nominal_run``, calibrated (geometry only, no report)."""
    run = run_copy(nominal_run, tmp_path_factory.mktemp("calibrated") / "run")
    assert main(["calibrate", str(run), "--no-ann", "--quiet", "--no-report"]) == 0
    return run


# -- 10. export into a directory ----------------------------------------------------------------

@pytest.mark.parametrize("option", ["--urdf", "--csv"])
def test_export_to_a_directory_is_one_line_naming_it_and_leaves_nothing(calibrated_run, tmp_path, capsys, option):
    out = tmp_path / "out"
    out.mkdir()
    (out / "keep.txt").write_text("mine")
    line = one_line_error(capsys, ["export", calibrated_run, option, out], rf"{re.escape(str(out))}: is a directory")
    assert "partial" not in line
    assert sorted(p.name for p in tmp_path.iterdir()) == ["out"] and [p.name for p in out.iterdir()] == ["keep.txt"]


# -- 9. a malformed URDF, a branching URDF -------------------------------------------------------

def test_a_malformed_urdf_is_one_line_with_line_and_column(tmp_path, capfd):
    text = COMAU_URDF.read_text()
    lines = text.splitlines()
    k = next(i for i, line in enumerate(lines) if line.strip() == "</joint>")
    lines[k] = lines[k].replace("</joint>", "</jont>")  # a typo in a closing tag
    bad = tmp_path / "bad.urdf"
    bad.write_text("\n".join(lines) + "\n")
    capfd.readouterr()
    for argv in (["model", "chain", "--robot", bad], ["import", nominal_csv(tmp_path / "d.csv"), "--run",
                                                      tmp_path / "run", "--robot", bad, "--quiet"]):
        assert main([str(a) for a in argv]) == 1
        err = capfd.readouterr().err  # the process's own stderr: a parser's lines would show here
        assert err.strip().splitlines() == [err.strip()], err
        assert re.search(rf"{re.escape(str(bad))}: not valid XML \(line {k + 1}, column \d+: mismatched tag\)", err)
    assert not (tmp_path / "run").exists()


def test_a_branching_urdf_without_a_tool_frame_is_refused_with_the_choices(tmp_path, capsys):
    extra = ('<link name="cam_base"/><link name="cam_tilt"/>'
             '<joint name="cam_pan_joint" type="revolute"><parent link="link1"/><child link="cam_base"/>'
             '<origin xyz="0 0.1 0" rpy="0 0 0"/><axis xyz="0 0 1"/>'
             '<limit lower="-1" upper="1" effort="1" velocity="1"/></joint>'
             '<joint name="cam_tilt_joint" type="revolute"><parent link="cam_base"/><child link="cam_tilt"/>'
             '<axis xyz="0 1 0"/><limit lower="-1" upper="1" effort="1" velocity="1"/></joint>')
    branching = tmp_path / "two_branches.urdf"
    branching.write_text(COMAU_URDF.read_text().replace("</robot>", extra + "</robot>"))
    one_line_error(capsys, ["model", "chain", "--robot", branching],
                   r"two_branches\.urdf: the tree branches at 'link1' into 2 branches: name the tool frame with "
                   r"--tool-frame .* \(the branches end at E, .*cam_tilt\)")
    robot = RobotModel.load(branching, tool_frame="E")  # named: the COMAU's chain, the camera beside it
    assert robot.joint_names == RobotModel.load().joint_names


# -- 5. the exported URDF of one-reflector data names the measured point ---------------------------

def test_export_urdf_of_a_one_marker_run_reproduces_predict_at_the_measured_point(tmp_path, capsys):
    point = np.array([0.04, -0.03, 0.15])  # the marker in E, m: robot.yaml names none
    q = comau_q(60, seed=8)
    q_true = q + np.array([0, 1.5e-3, -1e-3, 0, 0, 0])  # the robot's own errors: zero offsets
    T = nominal_poses(q_true)
    xyz = T[:, :3, 3] + np.einsum("nij,j->ni", T[:, :3, :3], point)
    rows = ["pose_id,q1,q2,q3,q4,q5,q6,x,y,z"] + [
        f"{i + 1}," + ",".join(repr(float(v)) for v in (*q[i], *xyz[i])) for i in range(len(q))]
    (tmp_path / "marker.csv").write_text("\n".join(rows) + "\n")
    run = tmp_path / "run"
    assert main(["import", str(tmp_path / "marker.csv"), "--run", str(run), "--quiet"]) == 0
    assert main(["calibrate", str(run), "--no-ann", "--quiet", "--no-report"]) == 0, capsys.readouterr().err
    capsys.readouterr()
    assert main(["export", str(run), "--urdf", str(tmp_path / "calibrated.urdf")]) == 0
    out = capsys.readouterr().out
    assert "frame 'E_measured_point'" in out
    q_check = comau_q(20, seed=9)
    (tmp_path / "q.csv").write_text("pose_id,q1,q2,q3,q4,q5,q6\n" + "".join(
        f"{i},{','.join(repr(float(v)) for v in qi)}\n" for i, qi in enumerate(q_check)))
    assert main(["predict", str(run), "--csv", str(tmp_path / "q.csv"), "--stage", "geometric",
                 "--out", str(tmp_path / "pred.csv")]) == 0
    pred = np.loadtxt(tmp_path / "pred.csv", delimiter=",", skiprows=1)
    model = pin.buildModelFromUrdf(str(tmp_path / "calibrated.urdf"))  # the URDF read by Pinocchio
    data, fid = model.createData(), model.getFrameId("E_measured_point")
    for qi, row in zip(q_check, pred):
        pin.framesForwardKinematics(model, data, qi)
        assert np.allclose(data.oMf[fid].translation, row[7:10], atol=1e-6)
        assert np.allclose(data.oMf[fid].rotation, Rotation.from_rotvec(row[10:13]).as_matrix(), atol=1e-6)
    # and the calibration is right: the true marker positions (q_true) within the noise-free fit
    assert np.allclose(pred[:, 7:10], (nominal_poses(q_check + q_true[0] - q[0])[:, :3, :3] @ point)
                       + nominal_poses(q_check + q_true[0] - q[0])[:, :3, 3], atol=2e-5)


# -- 8. calibrate --ann: Ctrl-C, a diverged size, an ETA that holds --------------------------------

def _children(pid: int) -> set:
    """Process ids whose parent is ``pid`` (from /proc)."""
    out = set()
    for d in Path("/proc").iterdir():
        if d.name.isdigit():
            try:
                if int((d / "stat").read_text().rsplit(")", 1)[1].split()[1]) == pid:
                    out.add(int(d.name))
            except (OSError, IndexError, ValueError):
                continue
    return out


def test_ctrl_c_stops_the_network_training_within_seconds_and_says_so(tmp_path):
    """A real Ctrl-C (SIGINT to the process group) while the workers train: one line at once,
    exit 130 within seconds, the workers gone, nothing written. (On 1,500 poses the former code
    took 61.6 s to exit: it waited for the running trainings; benchmarks/results/ann_interrupt.md.)"""
    import os
    import signal
    import subprocess
    import sys
    import threading
    import time

    # 600 poses: the grid still trains seconds after it starts on an idle machine (120 poses: done in 0.5 s)
    assert main(["synth", "--csv", str(tmp_path / "s.csv"), "--poses", "600", "--seed", "3"]) == 0
    run = tmp_path / "run"
    assert main(["import", str(tmp_path / "s.csv"), "--run", str(run), "--quiet"]) == 0
    proc = subprocess.Popen([sys.executable, "-m", "campaign.cli", "calibrate", str(run), "--ann", "--workers", "2",
                             "--model", "lsq", "--no-report"], stdout=subprocess.PIPE, stderr=subprocess.PIPE,
                            text=True, start_new_session=True)
    lines, started = [], threading.Event()

    def read():
        for line in proc.stderr:
            lines.append((time.monotonic(), line))
            if line.startswith("ANN:"):
                started.set()

    reader = threading.Thread(target=read, daemon=True)
    reader.start()
    assert started.wait(120), "".join(text for _, text in lines)
    time.sleep(1.5)  # the workers are training
    workers = _children(proc.pid)
    t0 = time.monotonic()
    os.killpg(proc.pid, signal.SIGINT)  # what Ctrl-C sends: to the whole process group, workers too
    proc.wait(60)
    took = time.monotonic() - t0
    reader.join(5)
    err = "".join(text for _, text in lines)
    assert proc.returncode == 130 and took < 10, (took, err)
    said = [t for t, text in lines if "interrupted (Ctrl-C): stopping the network's training" in text]
    assert said and said[0] - t0 < 2, err  # said at once, not after the workers are gone
    assert "Traceback" not in err and not (run / "calibration").exists()
    time.sleep(0.5)
    assert not {p for p in workers if Path(f"/proc/{p}").exists()
                and "spawn_main" in Path(f"/proc/{p}/cmdline").read_text()}  # no worker left training


def test_a_diverged_size_is_said_diverged_and_not_chosen():
    from campaign.ann.grid import DIVERGED_RMSE_NORMALISED, best_row, cv_row_text, cv_stats, diverged_folds
    from campaign.identify.ann_stage import format_table5

    rng = np.random.default_rng(2)
    dz = rng.normal(0, 1e-4, (50, 6))
    fold = np.arange(50) % 5
    scale = dz.std(axis=0)
    good, bad = dz * 0.3, dz * 0.1
    bad[fold == 3] = 2.5e15  # one fold's network left the data (m)
    rows = [{"hidden": [8, 8], **cv_stats(dz, good, scale), "diverged_folds": diverged_folds(dz, good, fold, scale)},
            {"hidden": [16, 8], **cv_stats(dz, bad, scale), "diverged_folds": diverged_folds(dz, bad, fold, scale)}]
    assert rows[0]["diverged_folds"] == [] and rows[1]["diverged_folds"] == [3]
    assert rows[1]["rmse_normalised"] > DIVERGED_RMSE_NORMALISED  # its numbers are the divergence's
    assert cv_row_text(rows[1]).startswith("CV (16, 8): diverged in fold 4") and "mm" not in cv_row_text(rows[1])
    assert best_row(rows)["hidden"] == [8, 8]  # a diverged size is not chosen, though its other folds fit better
    table = format_table5({"geometric": {"sizes": rows, "best": [8, 8], "solver": "br-lm"}})
    assert "diverged (fold 4)" in table and "e+1" not in table and "2500000" not in table


def _simulated_grid(spec, workers, seconds_per_epoch):
    """The reports an executor of ``workers`` delivers for tasks ``spec`` [(id, n_weights, member
    epochs)] trained in dispatch order, members one after another (BR-LM), a tick every 5 epochs:
    [(time s, "units" | "done", args)] in time order, and the time the grid ends."""
    import heapq

    free = [(0.0, w) for w in range(workers)]
    events = []
    for tid, n_w, eps in spec:
        t, w = heapq.heappop(free)
        spe, start = seconds_per_epoch(n_w), t
        events.append((t, "units", (tid, 0.0)))
        for ep in eps:
            events += [(t + e * spe, "units", (tid, 5.0 * n_w)) for e in range(5, ep + 1, 5)]
            t += ep * spe
            events.append((t, "units", (tid, ("member", ep))))
        events.append((t, "done", {"id": tid, "members": [{"epochs": e} for e in eps], "wall_s": t - start}))
        heapq.heappush(free, (t, w))
    events.sort(key=lambda e: e[0])
    return events, events[-1][0]


def test_the_grid_eta_holds_from_measured_times_when_the_largest_training_runs_last():
    """The largest size trains longest, on one worker, long after the small ones finished (the
    case whose ETA said 1-4 s for 90 s): the time left stays within 0.7-1.6x the truth from a
    fifth of the grid to 95 % of it."""
    from campaign.ann.grid import GridMeter

    spec = [("A", 3000, [400, 380, 420, 400, 390]), ("B", 1500, [300] * 5), ("C", 600, [150] * 5),
            ("D", 300, [100] * 5), ("E", 150, [80] * 5), ("F", 150, [60] * 5)]
    events, end = _simulated_grid(spec, 2, lambda n_w: 1e-6 * n_w ** 1.5)
    clock, seen = [0.0], []
    meter = GridMeter([{"id": t, "members": e, "n_weights": n} for t, n, e in spec], "br-lm", seen.append, 2,
                      clock=lambda: clock[0])
    for t, kind, args in events:
        clock[0] = t
        meter.units(*args) if kind == "units" else meter.done(args)
    ratios = [g.eta_s / (end - g.elapsed_s) for g in seen if 0.2 * end < g.elapsed_s < 0.95 * end]
    assert len(ratios) > 100 and 0.7 < min(ratios) and max(ratios) < 1.6, (min(ratios), max(ratios))
    assert seen[-1].eta_s == 0.0 and seen[-1].tasks_done == len(spec)


@pytest.mark.parametrize("kind", ["pose", "point"])
def test_diagnose_of_exact_data_without_a_floor_says_round_off_and_finds_nothing(nominal_run, tmp_path, capsys,
                                                                                  kind):
    if kind == "pose":
        run = run_copy(nominal_run, tmp_path / "run")
    else:  # one reflector at the tool frame's origin, exact
        q = comau_q(80, seed=3)
        xyz = nominal_poses(q)[:, :3, 3]
        (tmp_path / "p.csv").write_text("pose_id,q1,q2,q3,q4,q5,q6,x,y,z\n" + "".join(
            f"{i + 1}," + ",".join(repr(float(v)) for v in (*q[i], *xyz[i])) + "\n" for i in range(len(q))))
        run = tmp_path / "run"
        assert main(["import", str(tmp_path / "p.csv"), "--run", str(run), "--quiet"]) == 0
    assert main(["calibrate", str(run), "--no-ann", "--quiet", "--no-report"]) == 0
    capsys.readouterr()
    assert main(["diagnose", str(run), "--json"]) == 0
    d = json.loads(capsys.readouterr().out)
    assert d["heldout_mean_position_mm"] < 1e-6 and d["noise_floor_mm"] is None  # no repeats, no stated noise
    assert d["verdict"] is None and not d["unexplained"]["significant"] and not any(c["significant"]
                                                                                 for c in d["ranking"])
    assert main(["diagnose", str(run)]) == 0
    assert "the model fits them to round-off" in capsys.readouterr().out


def test_one_joint_indexed_effect_over_two_joint_lists_is_refused_with_the_one_spec(nominal_run, tmp_path, capsys):
    one_line_error(capsys, ["calibrate", nominal_run, "--no-ann", "--effects", "joint_compliance:2,joint_compliance:3"],
                   r"'joint_compliance:2' and 'joint_compliance:3' are both 'joint_compliance'.*joint_compliance:2,3\)")
    run = run_copy(nominal_run, tmp_path / "run")
    cfg = run / "campaign.yaml"
    cfg.write_text(cfg.read_text().replace("effects: []", "effects: [joint_compliance:2, joint_compliance:3]"))
    for argv in (["calibrate", run, "--no-ann"], ["auto", run, "--sim"]):
        one_line_error(capsys, argv, r"campaign\.yaml: effects: 'joint_compliance:2' and 'joint_compliance:3' are "
                                     r"one effect; name it once: joint_compliance:2,3$")
    assert not (run / "calibration").exists() and not (nominal_run / "calibration").exists()


@pytest.mark.parametrize("text, match", [
    ('<?xml version="1.0"?>\n<robt name="x"><link name="a"/></robt>\n', r"root element <robt>, not <robot>: not a URDF$"),
    ('<robot name="x"><link name="a"/><link name="b"/><joint name="j" type="revolute"><child link="b"/>'
     '<limit lower="-1" upper="1" effort="1" velocity="1"/></joint></robot>\n',
     r"cannot read the URDF: joint 'j': no <parent link=\.\.\.>$"),
    ('<robot name="x"><link name="a"/></robot>\n', r"no moving joint below 'a' in x\.urdf \(1 links, 0 joints")])
def test_urdfs_that_are_xml_but_not_a_robot_arm_are_one_line_saying_why(tmp_path, capfd, text, match):
    path = tmp_path / "x.urdf"
    path.write_text(text)
    assert main(["model", "chain", "--robot", str(path)]) == 1
    err = capfd.readouterr().err.strip()
    assert len(err.splitlines()) == 1 and re.search(rf"{re.escape(str(path))}: {match}", err), err


def test_tracker_readings_name_the_unit_they_look_like():
    from campaign.measure.plausibility import check_tracker_readings

    P_E = np.array([[0.0, 0.0, 0.0], [0.1, 0.0, 0.0], [0.0, 0.06, 0.0]])  # m, in the tool frame
    T_L = np.array([2.0, 0.5, -0.3])  # the tool 2 m from the tracker
    names = ("a", "b", "c")
    assert check_tracker_readings(P_E + T_L, P_E, names) is None  # metres: plausible
    assert "look like inches" in check_tracker_readings((P_E + T_L) / 0.0254, P_E, names)
    assert "look like centimetres" in check_tracker_readings((P_E + T_L) * 100, P_E, names)
    odd = check_tracker_readings((P_E + T_L) * 7, P_E, names, "the default triad: robot.yaml names no reflectors")
    assert "7× the 0.1166 m" in odd and "the tool's reflectors are not the default triad" in odd
    # one reflector: the range alone; a reflector 0.2 m away read in mm
    far = check_tracker_readings(np.array([[0.0, 0.2, 0.0]]) * 1e3, P_E[:1], names[:1])
    assert "reads 200 m from the tracker" in far and "millimetres (0.2 m)" in far
