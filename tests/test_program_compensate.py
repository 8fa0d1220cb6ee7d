"""`campaign compensate RUN --program FILE --format F`: a program's targets filtered through the
calibration. Checked against the simulated truth (read only after the command answered): the
true robot at the rewritten joint targets, and the nominal controller's joints of the rewritten
Cartesian targets, reach the poses the program meant; every other line is left as it was."""

import shutil
from pathlib import Path

import numpy as np
import pytest

from campaign.cli import main
from campaign.measure.csvio import write_measured_csv
from campaign.model.ik import nominal_ik
from campaign.model.kinematics import forward, pose_error
from campaign.program.compensate import T_to_pose, pose_to_T, scan
from campaign.program.generate import format_module
from campaign.sim.truth import make_truth, random_joint_poses, synthesize

DATA = Path(__file__).parent / "data" / "program"


@pytest.fixture(scope="module")
def calibrated(tmp_path_factory, robot):
    """(run folder, truth, measured poses): 80 poses of a synthetic campaign, calibrated without ANN;
    joint 1 measured within ±1 rad only (its limits are ±2.93 rad: the domain ends there)."""
    tmp = tmp_path_factory.mktemp("comp")
    truth = make_truth(robot, seed=3)
    q = random_joint_poses(robot, 80, seed=3)
    q[:, 0] *= 1.0 / np.abs(q[:, 0]).max()
    poses = synthesize(truth, q, seed=4)
    write_measured_csv(tmp / "m.csv", poses)
    run = tmp / "run"
    assert main(["import", str(tmp / "m.csv"), "--run", str(run), "--quiet"]) == 0
    assert main(["calibrate", str(run), "--no-ann", "--quiet", "--no-report"]) == 0
    return run, truth, poses


def _true_pose(truth, poses, q):
    """The truth's tool pose in the frame the set-up points defined (the calibration's frame)."""
    return truth.pose_in_measured_frame(np.atleast_2d(q), poses.T_LI)


def _mm(T_a, T_b):
    return np.linalg.norm(pose_error(T_a, T_b)[:, :3], axis=1) * 1e3


@pytest.mark.parametrize("fmt", ["urscript", "krl", "rapid", "fanuc-ls", "pdl2", "ros2-trajectory", "csv"])
def test_joint_targets_of_every_program_reach_the_nominal_poses(tmp_path, robot, calibrated, fmt):
    run, truth, poses = calibrated
    prog_run = tmp_path / "p"
    shutil.copytree(DATA / "plan", prog_run / "plan")
    shutil.copy(DATA / "campaign.yaml", prog_run / "campaign.yaml")
    mod = format_module(fmt)
    assert main(["program", str(prog_run), "--format", fmt, "--out", str(tmp_path / ("prog" + mod.EXTENSION))]) == 0
    src = sorted(p for p in tmp_path.iterdir() if p.is_file() and p.stem.lower() == "prog")
    target_file = next(p for p in src if p.suffix != ".src")  # KRL: the .dat holds the targets
    out = tmp_path / ("filtered" + target_file.suffix)
    assert main(["compensate", str(run), "--program", str(target_file), "--format", fmt, "--out", str(out)]) == 0
    before, after = target_file.read_text(), out.read_text()
    files_before = [(p.name, p.read_text()) for p in src]
    files_after = [(p.name, after if p == target_file else p.read_text()) for p in src]
    read = (lambda f: mod.read_joints(f)) if fmt in ("csv", "urscript", "ros2-trajectory") else \
        (lambda f: mod.read_joints(f, 6))
    scale = np.where(robot.prismatic, 1e3, 180 / np.pi) if mod.UNITS == "deg" else np.ones(6)
    q_old, q_new = read(files_before) / scale, read(files_after) / scale
    T_meant = forward(robot, q_old)
    err_before, err_after = _mm(_true_pose(truth, poses, q_old), T_meant), _mm(_true_pose(truth, poses, q_new), T_meant)
    assert err_before.mean() > 0.3
    assert err_after.max() < 0.03, (err_before, err_after)
    changed = [k for k, (a, b) in enumerate(zip(before.splitlines(), after.splitlines())) if a != b]
    assert len(before.splitlines()) == len(after.splitlines()) and changed
    targets = {before.count("\n", 0, a) for t in scan(before, fmt, 6).targets for a, _ in t.spans}
    assert set(changed) <= targets  # nothing but target lines changed


def _cartesian_check(robot, truth, poses, T_meant, T_new, q_near):
    """The nominal controller, given T_new, moves to nominal IK(T_new) (the branch of q_near);
    the true robot there must be at T_meant."""
    q_ctrl, _, ok = nominal_ik(robot, T_new, q_near, max_iter=100)
    assert ok.all()
    return _mm(_true_pose(truth, poses, q_ctrl), T_meant), _mm(_true_pose(truth, poses, q_near), T_meant)


def _bits(q_deg):
    return sum(1 << j for j in range(6) if q_deg[j] < 0)


#: per format: (convention, head, a joint target line (the program's start), a pose line, end)
CARTESIAN = {
    "krl": ("mm_kuka_abc", "DEFDAT cell\n", "", "  DECL E6POS P{k}={{X {0:.4f},Y {1:.4f},Z {2:.4f},A {3:.5f},"
            "B {4:.5f},C {5:.5f},S 6,T {bits},E1 0.0,E2 0.0}}\n", "ENDDAT\n"),
    "rapid": ("mm_quat", "MODULE Cell\n", "", "  CONST robtarget p{k}:=[[{0:.4f},{1:.4f},{2:.4f}],[{3:.8f},{4:.8f},"
              "{5:.8f},{6:.8f}],[{cf1},{cf4},{cf6},0],[9E9,9E9,9E9,9E9,9E9,9E9]];\n", "ENDMODULE\n"),
    "urscript": ("m_rotvec", "def cell():\n", "  movej([{j}])\n", "  movel(p[{0:.7f}, {1:.7f}, {2:.7f}, {3:.9f}, "
                 "{4:.9f}, {5:.9f}], a=1.2, v=0.25)\n", "end\n"),
    "fanuc-ls": ("mm_fanuc_wpr", "/PROG CELL\n/MN\n   1:  L P[1] 100mm/sec FINE ;\n/POS\n",
                 "P[1]{{\n   GP1:\n\tUF : 0, UT : 1,\n\t{jls}\n}};\n",
                 "P[{k2}]{{\n   GP1:\n\tUF : 0, UT : 1,\t\tCONFIG : 'N U T, 0, 0, 0',\n"
                 "\tX = {0:.3f} mm,\tY = {1:.3f} mm,\tZ = {2:.3f} mm,\n\tW = {3:.3f} deg,\t"
                 "P = {4:.3f} deg,\tR = {5:.3f} deg\n}};\n", "/END\n"),
    "pdl2": ("mm_zyz", "PROGRAM cell\nBEGIN\n", "  JNT(jp, {jd})\n",
             "  p{k} := POS({0:.4f}, {1:.4f}, {2:.4f}, {3:.5f}, {4:.5f}, {5:.5f}, 'S')\n", "END cell\n"),
}


@pytest.mark.parametrize("fmt", list(CARTESIAN))
def test_cartesian_targets_become_what_the_nominal_controller_needs(tmp_path, robot, calibrated, fmt):
    run, truth, poses = calibrated
    conv, head, joint_line, line, end = CARTESIAN[fmt]
    rng = np.random.default_rng(11)
    start = robot.q_mid + [0.0, 0.0, 0.0, 0.0, 0.7, 0.0]  # the wrist away from its singularity (q5 = 0)
    q = np.clip(start + np.cumsum(rng.normal(scale=0.08, size=(5, 6)), axis=0), robot.q_lower + 0.2,
                robot.q_upper - 0.2)  # a path: each target near the one before, as programs go
    T = forward(robot, q)
    q_deg = np.degrees(q)
    lead = np.degrees(start)
    text = head + joint_line.format(j=", ".join(f"{v:.9f}" for v in start),
                                    jd=", ".join(f"{v:.4f}" for v in lead),
                                    jls=",\t".join(f"J{i + 1}= {v:.3f} deg" for i, v in enumerate(lead)))
    for k in range(len(q)):
        text += line.format(*T_to_pose(T[k], conv, [0, 0, 0, 0, 0, 0, 1]), k=k, k2=k + 2, bits=_bits(q_deg[k]),
                            cf1=int(np.floor(q_deg[k, 0] / 90)), cf4=int(np.floor(q_deg[k, 3] / 90)),
                            cf6=int(np.floor(q_deg[k, 5] / 90)))
    text += end
    path = tmp_path / ("cell" + format_module(fmt).EXTENSION.replace(".src", ".dat"))
    path.write_text(text)
    assert main(["compensate", str(run), "--program", str(path), "--format", fmt]) == 0
    out = path.with_name(path.stem + "_compensated" + path.suffix)
    new = [t for t in scan(out.read_text(), fmt, 6).targets if t.kind == "pose"]
    assert len(new) == len(q)
    T_written = np.array([pose_to_T(t.values, conv) for t in scan(text, fmt, 6).targets if t.kind == "pose"])
    T_new = np.array([pose_to_T(t.values, conv) for t in new])
    after, before = _cartesian_check(robot, truth, poses, T_written, T_new, q)
    assert before.mean() > 0.3
    assert after.max() < 0.02, (before, after)
    if fmt in ("krl", "fanuc-ls", "pdl2"):  # the configuration flags as written
        flags = {"krl": r"S 6,T ", "fanuc-ls": "CONFIG : 'N U T, 0, 0, 0'", "pdl2": "'S')"}[fmt]
        assert out.read_text().count(flags) == len(q)


def test_what_is_not_understood_is_listed_and_left(tmp_path, robot, calibrated, capsys):
    run, *_ = calibrated
    text = ("MODULE Cell\n"
            "  CONST jointtarget j1:=[[10,20,30,0,40,0],[9E9,9E9,9E9,9E9,9E9,9E9]];\n"
            "  CONST robtarget p2:=Offs(p1,0,0,10);\n"
            "  ! a comment [[1,2,3]] that is no target\n"
            "  PROC main()\n    MoveAbsJ j1\\NoEOffs, v100, fine, tool0;\n  ENDPROC\nENDMODULE\n")
    (tmp_path / "cell.mod").write_text(text)
    assert main(["compensate", str(run), "--program", str(tmp_path / "cell.mod"), "--format", "rapid"]) == 0
    said = capsys.readouterr().out
    assert "1 joint and 0 Cartesian targets compensated" in said
    assert "line 3: not understood, left as written: a target declaration whose value could not be read" in said
    new = (tmp_path / "cell_compensated.mod").read_text().splitlines()
    old = text.splitlines()
    assert [k for k in range(len(old)) if old[k] != new[k]] == [1]
    assert new[1].startswith("  CONST jointtarget j1:=[[10.") and new[1].endswith("],[9E9,9E9,9E9,9E9,9E9,9E9]];")


def test_a_target_outside_the_calibrated_domain_is_named(tmp_path, robot, calibrated, capsys):
    """A measured pose is inside; joint 1 at 2.5 rad, where no pose was measured (±1 rad), is outside
    (campaign.identify.domain, the calibration's domain.json)."""
    run, _, poses = calibrated
    q_in = poses.q[0]
    q_out = poses.q[1].copy()
    q_out[0] = 2.5
    vals = [", ".join(f"{v:.9f}" for v in q) for q in (q_in, q_out)]
    (tmp_path / "a.script").write_text(f"def a():\n  movej([{vals[0]}])\n  movej([{vals[1]}])\nend\n")
    assert main(["compensate", str(run), "--program", str(tmp_path / "a.script"), "--format", "urscript"]) == 0
    said = capsys.readouterr().out
    assert "1 outside the calibrated domain" in said
    assert "line 3: target: outside the calibrated domain: q1 beyond the training range" in said


@pytest.mark.parametrize("args, match", [
    (["--program", "{p}"], "--program needs --format"),
    (["--csv", "{p}", "--format", "krl"], "--format goes with --program"),
    (["--program", "{p}", "--format", "gcode"], "--format 'gcode': compensate reads"),
    (["--program", "{tmp}/none.src", "--format", "krl"], "none.src: no such program file"),
    (["--program", "{p}", "--format", "krl", "--out", "{p}"], "is the program itself"),
    (["--program", "{p}", "--format", "fanuc-ls"], "no fanuc-ls targets found"),
])
def test_bad_program_compensation_input_is_one_line(tmp_path, calibrated, capsys, args, match):
    run, *_ = calibrated
    p = tmp_path / "x.dat"
    p.write_text("DEFDAT x\n  DECL E6AXIS XP1={A1 1.0,A2 2.0,A3 3.0,A4 4.0,A5 5.0,A6 6.0}\nENDDAT\n")
    assert main(["compensate", str(run), *[a.format(p=p, tmp=tmp_path) for a in args]]) == 1
    err = capsys.readouterr().err.strip()
    assert match in err and len(err.splitlines()) == 1
    assert p.read_text().startswith("DEFDAT x")


def test_a_run_without_calibration_is_refused_in_one_line(tmp_path, capsys):
    p = tmp_path / "x.script"
    p.write_text("def x():\n  movej([0, 0, 0, 0, 0, 0])\nend\n")
    (tmp_path / "run").mkdir()
    assert main(["compensate", str(tmp_path / "run"), "--program", str(p), "--format", "urscript"]) == 1
    assert "run `campaign calibrate" in capsys.readouterr().err


def test_the_configuration_written_chooses_the_branch(tmp_path, robot, calibrated):
    """One pose, two wrist configurations (q5 > 0 and its flip): KRL's T bits (the sign of each
    axis) say which one the controller takes, and the compensation follows it (the elbow, which
    the T bits do not give, is the one nearest the joints' mid-range here: no target before it)."""
    run, truth, poses = calibrated
    q_a = np.radians([20.0, 40.0, -60.0, 30.0, 40.0, 20.0])
    q_b = q_a + np.radians([0, 0, 0, -180.0, 0, -180.0])
    q_b[4] = -q_b[4]
    T = forward(robot, q_a[None])[0]
    np.testing.assert_allclose(forward(robot, q_b[None])[0], T, atol=1e-12)
    x, y, z, a, b, c = T_to_pose(T, "mm_kuka_abc", [0] * 6)
    for q in (q_a, q_b):
        bits = _bits(np.degrees(q))
        path = tmp_path / f"t{bits}.dat"
        path.write_text(f"DEFDAT t{bits}\n  DECL E6POS XP1={{X {x:.4f},Y {y:.4f},Z {z:.4f},A {a:.5f},B {b:.5f},"
                        f"C {c:.5f},S 2,T {bits}}}\nENDDAT\n")
        assert main(["compensate", str(run), "--program", str(path), "--format", "krl"]) == 0
        new = scan(path.with_name(path.stem + "_compensated.dat").read_text(), "krl", 6).targets
        T_new = pose_to_T(new[0].values, "mm_kuka_abc")[None]
        after, before = _cartesian_check(robot, truth, poses, T[None], T_new, q[None])
        assert after[0] < 0.02 < before[0]


def test_a_calibration_without_domain_json_falls_back_on_the_measured_ranges(tmp_path, robot, calibrated, capsys):
    run, _, poses = calibrated
    old = tmp_path / "old"
    shutil.copytree(run, old, symlinks=True)
    (old / "calibration" / "domain.json").unlink()  # a calibration made before domain.json
    q_out = poses.q[1].copy()
    q_out[0] = 2.5
    (tmp_path / "a.script").write_text("def a():\n  movej([" + ", ".join(f"{v:.9f}" for v in q_out) + "])\nend\n")
    assert main(["compensate", str(old), "--program", str(tmp_path / "a.script"), "--format", "urscript"]) == 0
    said = capsys.readouterr().out
    assert "line 2: target: q1 at 2.5000 is outside the measured range" in said and "no domain.json" in said


@pytest.mark.parametrize("fmt, text, listed", [
    ("rapid", "MODULE M\n  PROC main()\n    MoveL Offs(p1,0,0,10), v100, fine, tool0;\n"
              "    MoveJ home, v100, z10, tool0;\n  ENDPROC\nENDMODULE\n",
     [(3, "a target computed when the program runs"), (4, "the target home is not defined in this file")]),
    ("fanuc-ls", "/PROG X\n/MN\n   1:J PR[1] 100% FINE    ;\n/POS\n/END\n",
     [(3, "a position register, held by the controller")]),
    ("urscript", "def a():\n  movej(home)\n  q = [0, 0, 0, 0, 0, 0]\n  movej(q, a=1)\nend\n",
     [(2, "the target home is not defined in this file")]),
    ("krl", "DEF a( )\n  PTP XP1\n  PTP $POS_ACT\nEND\n", [(2, "the target XP1 is not defined in this file (compensate its .dat)")]),
    ("pdl2", "PROGRAM a\nBEGIN\n  MOVE JOINT TO pnt0001j\nEND a\n", [(3, "the target pnt0001j is not defined")]),
])
def test_motions_to_targets_held_elsewhere_are_listed(fmt, text, listed):
    unclear = scan(text, fmt, 6).unclear
    assert len(unclear) == len(listed)
    assert [(u.line, u.why[:len(w)]) for u, (_, w) in zip(unclear, listed)] == listed


def test_a_target_beyond_the_real_reach_gets_the_nearest_and_another_configuration_is_left(
        tmp_path, robot, calibrated, capsys):
    """The elbow nearly stretched: the calibrated arm cannot reach a pose the nominal one does; the
    solver's nearest iterate is written (never farther from the pose than the written joints: the
    truth agrees). A target whose correction would swing a joint by tens of degrees (the shoulder
    beside its singularity) is left as written."""
    from campaign.identify.use import CalibratedRobot
    from campaign.tolerances import PROGRAM_BEST_EFFORT_STEP_RAD

    run, truth, poses = calibrated
    q = np.tile(np.radians([0.5, 40.0, -90.0, 10.0, 40.0, 20.0]), (81, 1))
    q[:, 2] = np.radians(np.linspace(-100.0, -80.0, 81))
    cal = CalibratedRobot(run)
    q_new, _, ok = cal.compensate(forward(robot, q), q)
    near = np.flatnonzero(~ok & (np.abs(q_new - q).max(axis=1) < PROGRAM_BEST_EFFORT_STEP_RAD))
    assert len(near)  # this truth's arm is shorter there
    swing = poses.q[1].copy()
    swing[0] = 2.5
    q_swing, _, _ = cal.compensate(forward(robot, swing[None]), swing[None])
    assert np.abs(q_swing - swing).max() > 2 * PROGRAM_BEST_EFFORT_STEP_RAD
    chosen = np.vstack([q[near[0]], swing])
    lines = [f"  movej([{', '.join(f'{v:.9f}' for v in qq)}])" for qq in chosen]
    (tmp_path / "a.script").write_text("def a():\n" + "\n".join(lines) + "\nend\n")
    assert main(["compensate", str(run), "--program", str(tmp_path / "a.script"), "--format", "urscript"]) == 0
    said = capsys.readouterr().out
    assert "line 2: joint target: reached to within" in said
    assert "line 3: joint target: the correction would move q" in said
    new = (tmp_path / "a_compensated.script").read_text().splitlines()
    assert new[2] == lines[1]  # left as written
    q_written = np.array([float(v) for v in new[1].split("[")[1].split("]")[0].split(",")])
    T_meant = forward(robot, chosen[:1])
    assert _mm(_true_pose(truth, poses, q_written), T_meant)[0] < _mm(_true_pose(truth, poses, chosen[:1]), T_meant)[0]


def test_joint_limits_and_strict_with_a_program(tmp_path, robot, calibrated, capsys):
    """A written joint target past a joint limit is named and left (--limit-slack reads it); --strict
    refuses a program with a target outside the calibrated domain, writing nothing."""
    run, _, poses = calibrated
    q_past = poses.q[2].copy()
    q_past[4] = robot.q_upper[4] + np.radians(0.5)  # half a degree past joint 5's limit
    q_out = poses.q[1].copy()
    q_out[0] = 2.5  # joint 1 where no pose was measured
    lines = [f"  movej([{', '.join(f'{v:.9f}' for v in qq)}])" for qq in (poses.q[0], q_past, q_out)]
    prog = tmp_path / "a.script"
    prog.write_text("def a():\n" + "\n".join(lines) + "\nend\n")
    assert main(["compensate", str(run), "--program", str(prog), "--format", "urscript"]) == 0
    said = capsys.readouterr().out
    assert "line 3: joint target: q5 = " in said and "is past its limit" in said
    assert (tmp_path / "a_compensated.script").read_text().splitlines()[2] == lines[1]
    assert main(["compensate", str(run), "--program", str(prog), "--format", "urscript", "--limit-slack", "1",
                 "--out", str(tmp_path / "b.script")]) == 0
    said = capsys.readouterr().out
    assert "line 3: joint target: q5 = " not in said  # read within the slack: compensated or named as corrected
    assert (tmp_path / "b.script").read_text().splitlines()[2] != lines[1] or "line 3: joint target: corrected" in said
    assert main(["compensate", str(run), "--program", str(prog), "--format", "urscript", "--strict",
                 "--out", str(tmp_path / "c.script")]) == 1
    err = capsys.readouterr().err.strip()
    assert "1 target(s) outside the calibrated domain with --strict (line 4): nothing written" in err
    assert not (tmp_path / "c.script").exists()


def test_a_controllers_file_keeps_its_line_ends_and_encoding_and_only_its_targets_change(tmp_path, robot,
                                                                                          calibrated):
    """A KUKA .dat as the controller keeps it: CRLF line ends and a comment in Windows-1252. Read
    with universal newlines every line came back with LF (all changed); the ß made it 'not a text
    file'. A URScript's set_tcp(p[...]) and force_mode's lists are no targets (they were rewritten as
    a pose and joint lists), a movel(p[...]) is no motion to a target 'p' defined elsewhere."""
    run, truth, poses = calibrated
    q = poses.q[np.abs(poses.q[:, 4]) > 0.6][:2]  # off the wrist's singularity
    d = np.degrees(q)
    dat = tmp_path / "weld.dat"
    rows = ["&ACCESS RVP", "DEFDAT  weld", "; Schweißnaht links"] + [
        "DECL E6AXIS XP%d={A1 %.4f,A2 %.4f,A3 %.4f,A4 %.4f,A5 %.4f,A6 %.4f,E1 0.0,E2 0.0,E3 0.0,E4 0.0,E5 0.0,"
        "E6 0.0}" % (k, *d[k]) for k in range(2)] + ["ENDDAT", ""]
    dat.write_bytes("\r\n".join(rows).encode("cp1252"))
    assert main(["compensate", str(run), "--program", str(dat), "--format", "krl", "--out", str(tmp_path / "o.dat")]) == 0
    before = dat.read_bytes().split(b"\r\n")
    after = (tmp_path / "o.dat").read_bytes().split(b"\r\n")
    assert len(after) == len(before) and b"\n" not in b"".join(after)
    assert [k for k, (a, b) in enumerate(zip(before, after)) if a != b] == [3, 4]
    assert after[2] == "; Schweißnaht links".encode("cp1252")
    T = forward(robot, q)
    pose = T_to_pose(T[0], "m_rotvec", [0.0] * 6)
    script = tmp_path / "a.script"
    script.write_text("def a():\n  set_tcp(p[0, 0, 0.1, 0, 0, 0])\n"
                      "  force_mode(p[0, 0, 0, 0, 0, 0], [0, 0, 1, 0, 0, 0], [0, 0, 10, 0, 0, 0], 2, "
                      "[0.1, 0.1, 0.1, 0.3, 0.3, 0.3])\n"
                      "  movel(p[" + ", ".join(f"{v:.7f}" for v in pose) + "], a=0.5)\nend\n")
    assert main(["compensate", str(run), "--program", str(script), "--format", "urscript",
                 "--out", str(tmp_path / "o.script")]) == 0
    a, b = script.read_text().splitlines(), (tmp_path / "o.script").read_text().splitlines()
    assert a[:3] == b[:3] and a[3] != b[3]
    from campaign.program.compensate import _unresolved

    assert _unresolved(script.read_text(), "urscript") == []
