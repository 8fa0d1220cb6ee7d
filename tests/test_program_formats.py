"""`campaign program`: every format checked by its structural checker, against golden files of a
small plan, and read back to the joint values of RUN/program/stops.csv in the format's units.

The golden files (tests/data/program/golden/) are rewritten by running this file with
CAMPAIGN_UPDATE_GOLDEN=1 after a deliberate change of a format; review their diff."""

import os
import shutil
from pathlib import Path

import numpy as np
import pytest
import yaml

from campaign.cli import main
from campaign.program.common import unit_scale
from campaign.program.generate import FORMATS, format_module, program_input
from campaign.program.stops import read_stops_csv, stops_path

DATA = Path(__file__).parent / "data" / "program"
GOLDEN = DATA / "golden"
#: formats with a trigger output (ROS 2 trajectories carry none)
TRIGGER = {"urscript": 1, "krl": 1, "rapid": 1, "fanuc-ls": 1, "pdl2": 1, "ros2-trajectory": None, "csv": None}


def _run(tmp_path, name="small"):
    run = tmp_path / name
    shutil.copytree(DATA / "plan", run / "plan")
    shutil.copy(DATA / "campaign.yaml", run / "campaign.yaml")
    return run


def _files(paths):
    return [(Path(p).name, Path(p).read_text()) for p in paths]


def _program(run, fmt, *extra):
    out = run / "out" / fmt
    assert main(["program", str(run), "--format", fmt, "--speed", "0.5", "--out",
                 str(out / ("prog" + format_module(fmt).EXTENSION)), *extra]) == 0
    return sorted(out.iterdir())


def _expected(run, robot, units):
    Q = np.array([s.q for s in read_stops_csv(stops_path(run))])
    return robot.to_controller_q(Q) * unit_scale(robot.prismatic, units)


@pytest.mark.parametrize("fmt", list(FORMATS))
def test_every_format_passes_its_check_and_reads_back_to_stops_csv(tmp_path, robot, fmt):
    run = _run(tmp_path)
    extra = ["--trigger-output", str(TRIGGER[fmt])] if TRIGGER[fmt] else []
    paths = _program(run, fmt, *extra)
    mod = format_module(fmt)
    files = _files(paths)
    assert mod.check(files, robot) == []
    got = mod.read_joints(files) if fmt in ("csv", "urscript") else mod.read_joints(files, robot.n_joints)
    want = _expected(run, robot, mod.UNITS)
    assert got.shape == want.shape == (9, 6)  # 6 poses, a via, 2 drift checks
    np.testing.assert_allclose(got, want, rtol=0, atol=0.5 * 10.0 ** -mod.DECIMALS * (1 + 1e-9))


@pytest.mark.parametrize("fmt", list(FORMATS))
def test_every_format_equals_its_golden_files(tmp_path, fmt):
    run = _run(tmp_path)
    extra = ["--trigger-output", str(TRIGGER[fmt])] if TRIGGER[fmt] else []
    paths = _program(run, fmt, *extra)
    golden = GOLDEN / fmt
    if os.environ.get("CAMPAIGN_UPDATE_GOLDEN"):
        shutil.rmtree(golden, ignore_errors=True)
        golden.mkdir(parents=True)
        for p in paths:
            shutil.copy(p, golden / p.name)
    assert [p.name for p in paths] == sorted(p.name for p in golden.iterdir())
    for p in paths:
        assert p.read_text() == (golden / p.name).read_text(), p.name


@pytest.mark.parametrize("fmt", ["krl", "rapid", "fanuc-ls", "pdl2"])
def test_a_long_program_is_split_into_parts_that_read_back_in_order(tmp_path, robot, fmt):
    run = _run(tmp_path)
    mod = format_module(fmt)
    inp = program_input(run, speed=1.0)
    files = mod.render(inp, per_part=4)
    assert mod.check(files, robot) == []
    stems = {n.rsplit(".", 1)[0] for n, _ in files}
    assert len(stems) >= 3  # 9 stops in parts of 4 (+ a main program calling them, but PDL2's)
    want = robot.to_controller_q(np.array([s.q for s in inp.stops])) * unit_scale(robot.prismatic, mod.UNITS)
    np.testing.assert_allclose(mod.read_joints(files, 6), want, atol=0.5 * 10.0 ** -mod.DECIMALS * (1 + 1e-9))


#: a defect per format that its checker must name: (text replaced, by, the message expected)
DEFECTS = {
    "urscript": ("\nend\n", "\n", "opened and never closed"),
    "krl": ("PTP XS3", "PTP XS99", "PTP target XS99 is not declared"),
    "rapid": ("ENDPROC", "", "opened and never closed"),
    "fanuc-ls": ("J P[2] 50% FINE", "J P[2] 150% FINE", "s in 1..100"),
    "pdl2": ("MOVE JOINT TO jp", "MOVE JOINT TO jq", "jq is not declared"),
    "ros2-trajectory": ("sec: 0, nanosec: 0}", "sec: 99, nanosec: 0}", "time_from_start must rise"),
    "csv": ("\n1,", "\n7,", "expected stop 1"),
}


@pytest.mark.parametrize("fmt", list(FORMATS))
def test_each_checker_names_a_defect(tmp_path, robot, fmt):
    run = _run(tmp_path)
    files = _files(_program(run, fmt))
    old, new, match = DEFECTS[fmt]
    k = next(i for i, (_, t) in enumerate(files) if old in t)
    files[k] = (files[k][0], files[k][1].replace(old, new, 1))
    problems = mod_check = format_module(fmt).check(files, robot)
    assert any(match in p for p in problems), mod_check


@pytest.mark.parametrize("fmt", ["urscript", "krl", "rapid", "fanuc-ls", "pdl2"])
def test_each_checker_names_a_joint_beyond_its_limit(tmp_path, robot, fmt):
    run = _run(tmp_path)
    mod = format_module(fmt)
    files = _files(_program(run, fmt))
    q1 = mod.read_joints(files, 6)[0, 1] if fmt != "urscript" else mod.read_joints(files)[0, 1]
    text = "\n".join(t for _, t in files)
    printed = next(s for s in _number_strings(text) if abs(float(s) - q1) < 1e-12)
    beyond = 170.0 if mod.UNITS == "deg" else 2.97  # joint 2 of the COMAU ends near 2.5 rad
    k = next(i for i, (_, t) in enumerate(files) if printed in t)
    files[k] = (files[k][0], files[k][1].replace(printed, f"{beyond:.{mod.DECIMALS}f}", 1))
    assert any("outside the joint limits" in p for p in mod.check(files, robot))


def _number_strings(text):
    import re

    return re.findall(r"-?\d+\.\d+", text)


def test_the_controller_coupling_is_applied(tmp_path, robot):
    """robot.yaml's controller: q_model = coupling · diag(sign) · q_controller + offset: the program's
    joints are q_controller (here joint 3 counted from joint 2, joint 1 reversed, joint 6 offset)."""
    from campaign.model.robot import RobotModel

    meta = yaml.safe_load((Path(robot.urdf_path).parent / "robot.yaml").read_text())
    meta["urdf"] = str(Path(robot.urdf_path).resolve())
    C = np.eye(6)
    C[2, 1] = -1.0
    meta["controller"] = {"coupling": C.tolist(), "sign": [-1, 1, 1, 1, 1, 1], "offset": [0, 0, 0, 0, 0, 0.5]}
    (tmp_path / "robot").mkdir()
    (tmp_path / "robot" / "robot.yaml").write_text(yaml.safe_dump(meta))
    run = _run(tmp_path)
    cfg = yaml.safe_load((run / "campaign.yaml").read_text())
    cfg["robot"] = str(tmp_path / "robot" / "robot.yaml")
    (run / "campaign.yaml").write_text(yaml.safe_dump(cfg))
    coupled = RobotModel.load(tmp_path / "robot" / "robot.yaml")
    paths = _program(run, "krl")
    got = format_module("krl").read_joints(_files(paths), 6)
    Q = np.array([s.q for s in read_stops_csv(stops_path(run))])
    q_ctrl_deg = np.degrees(np.linalg.solve(C @ np.diag([-1, 1, 1, 1, 1, 1.0]), (Q - [0, 0, 0, 0, 0, 0.5]).T).T)
    np.testing.assert_allclose(got, q_ctrl_deg, atol=0.5e-4 + 1e-9)
    assert np.abs(got - np.degrees(Q)).max() > 10  # not the model's joints
    assert format_module("krl").check(_files(paths), coupled) == []


def test_ros2_json_and_the_trajectory_within_the_limits(tmp_path, robot):
    import json

    run = _run(tmp_path)
    out = tmp_path / "traj.json"
    assert main(["program", str(run), "--format", "ros2-trajectory", "--out", str(out)]) == 0
    mod = format_module("ros2-trajectory")
    files = [(out.name, out.read_text())]
    assert mod.check(files, robot) == []
    np.testing.assert_allclose(mod.read_joints(files), _expected(run, robot, "rad"), atol=1e-12)
    pts = json.loads(out.read_text())["points"]
    stops = read_stops_csv(stops_path(run))
    # the end of the trajectory: every Ruckig move and every dwell, at full speed
    from campaign.plan.timing import path_time

    total = path_time(robot, np.array([s.q for s in stops])) + sum(s.dwell_s for s in stops)
    t_end = pts[-1]["time_from_start"]["sec"] + pts[-1]["time_from_start"]["nanosec"] * 1e-9
    assert t_end == pytest.approx(total, abs=1e-6)


def test_ros2_refuses_a_trigger_and_urscript_an_output_it_lacks(tmp_path, capsys):
    run = _run(tmp_path)
    assert main(["program", str(run), "--format", "ros2-trajectory", "--trigger-output", "1"]) == 1
    assert main(["program", str(run), "--format", "urscript", "--trigger-output", "9"]) == 1
    assert main(["program", str(run), "--format", "csv", "--trigger-output", "1"]) == 1
    err = capsys.readouterr().err.strip().splitlines()
    assert "carries no digital outputs" in err[0] and "urscript writes digital outputs 0..7" in err[1]
    assert "a csv joint table carries no digital outputs" in err[2]
    assert not (run / "program").exists()


@pytest.fixture(scope="module")
def tiago():
    """The TIAGo's torso and arm (a prismatic joint, then 7 revolute), from example-robot-data."""
    from campaign.errors import ConfigError
    from campaign.model.robot import RobotModel

    try:
        return RobotModel.load("tiago")
    except ConfigError as exc:
        pytest.skip(f"example-robot-data not installed ({exc})")


@pytest.mark.parametrize("fmt", list(FORMATS))
def test_a_prismatic_joint_and_eight_joints_in_every_format(tmp_path, tiago, fmt):
    from campaign.sim.truth import random_joint_poses

    run = tmp_path / "tiago"
    (run / "plan").mkdir(parents=True)
    Q = random_joint_poses(tiago, 5, seed=2)
    head = "pose_id," + ",".join(f"q{j}" for j in range(1, 9))
    (run / "plan" / "poses.csv").write_text(head + "\n" + "".join(
        f"{100 + k}," + ",".join(repr(float(v)) for v in q) + "\n" for k, q in enumerate(Q)))
    (run / "campaign.yaml").write_text(yaml.safe_dump({"robot": "tiago", "run": {"drift_check_every": 0}}))
    mod = format_module(fmt)
    paths = _program(run, fmt)
    files = _files(paths)
    assert mod.check(files, tiago) == []
    got = mod.read_joints(files) if fmt in ("csv", "urscript", "ros2-trajectory") else mod.read_joints(files, 8)
    want = _expected(run, tiago, mod.UNITS)
    assert got.shape == want.shape == (5, 8)
    np.testing.assert_allclose(got, want, rtol=0, atol=0.5 * 10.0 ** -mod.DECIMALS * (1 + 1e-9))
    if mod.UNITS == "deg":  # the torso's lift in mm, the arm's joints in degrees
        np.testing.assert_allclose(got[:, 0], Q[:, 0] * 1e3, atol=0.5 * 10.0 ** -mod.DECIMALS + 1e-9)


#: a speed past the robot's limits, per format: (regex of the value, replacement, the message expected)
SPEEDING = {
    "urscript": (r"v=(\d+\.\d+)\)  # Ruckig [1-9]", lambda m: m.group(0).replace(m.group(1), f"{float(m.group(1)) * 3:.6f}"),
                 "exceed a joint's limit"),
    "krl": (r"\$VEL_AXIS\[2\] = 50\.0", lambda m: "$VEL_AXIS[2] = 150.0", "must be a percentage in (0, 100]"),
    "rapid": (r"\\T:=(\d+\.\d+)", lambda m: "\\T:=0.000", "\\T must be > 0"),
    "ros2-trajectory": (r"velocities: \[(-?\d+\.\d+), ", lambda m: "velocities: [99.0, ", "beyond the robot's limits"),
}


@pytest.mark.parametrize("fmt", list(SPEEDING))
def test_each_checker_names_a_speed_past_the_limits(tmp_path, robot, fmt):
    import re

    run = _run(tmp_path)
    files = _files(_program(run, fmt))
    pattern, repl, match = SPEEDING[fmt]
    k = next(i for i, (_, t) in enumerate(files) if re.search(pattern, t))
    files[k] = (files[k][0], re.sub(pattern, repl, files[k][1], count=1))
    assert any(match in p for p in format_module(fmt).check(files, robot))
