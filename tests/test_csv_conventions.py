"""Real files as they come (issue 20, item 7): orientation as roll-pitch-yaw, KUKA's A, B, C or
quaternions; other delimiters, no header, other column names; readings slightly past the URDF's
limits; predict/compensate in degrees; 1-based line numbers.

The other conventions are written by scipy.spatial.transform and Pinocchio (pin.rpy), not by the
package, and must give the same calibration as the rotation vectors to 1e-9."""

import csv
import json

import numpy as np
import pinocchio as pin
import pytest
import yaml
from scipy.spatial.transform import Rotation

from campaign.cli import main
from campaign.measure.csvio import read_measured_csv, write_measured_csv
from campaign.sim.truth import make_truth, random_joint_poses, synthesize

N_POSES = 100


def run_cli(*argv):
    return main([str(a) for a in argv])


@pytest.fixture(scope="module")
def rotvec_csv(tmp_path_factory, robot):
    path = tmp_path_factory.mktemp("conv") / "rotvec.csv"
    write_measured_csv(path, synthesize(make_truth(robot, seed=11), random_joint_poses(robot, N_POSES, seed=12),
                                        seed=13))
    return path


def read_rows(path):
    with open(path, newline="") as fh:
        rows = list(csv.reader(fh))
    return rows[0], rows[1:]


def convert(src, dst, columns, fn, *, scale_angles=1.0, scale_lengths=1.0):
    """Rewrite a rotation-vector CSV with the orientation columns ``columns`` = fn(Rotation) and
    optionally joints/angles and lengths scaled (degrees, mm)."""
    header, rows = read_rows(src)
    rot = [header.index(c) for c in ("rx", "ry", "rz")]
    out = []
    for r in rows:
        vals = fn(Rotation.from_rotvec([float(r[i]) for i in rot]))
        new = {h: r[k] for k, h in enumerate(header)}
        for h in header:
            if h.startswith("q") and h[1:].isdigit():
                new[h] = repr(float(new[h]) * scale_angles)
            if h in ("x", "y", "z"):
                new[h] = repr(float(new[h]) * scale_lengths)
        cells = [new[h] for h in header[:rot[0]]] + [repr(float(v) * (scale_angles if len(columns) == 3 else 1))
                                                     for v in vals]
        out.append(cells + [new[h] for h in header[rot[2] + 1:]])
    head = header[:rot[0]] + list(columns) + header[rot[2] + 1:]
    with open(dst, "w", newline="") as fh:
        csv.writer(fh).writerows([head] + out)
    return dst


def rpy_by_pinocchio(R: Rotation):
    return pin.rpy.matrixToRpy(R.as_matrix())  # R = Rz(y) Ry(p) Rx(r)


def calibration(run):
    params = yaml.safe_load((run / "calibration" / "params.yaml").read_text())
    m = json.loads((run / "calibration" / "metrics.json").read_text())
    return np.array(params["p_e_min_norm"]), m


@pytest.mark.parametrize("rotation, columns, fn, units", [
    ("rpy", ("rx", "ry", "rz"), rpy_by_pinocchio, ()),
    ("abc", ("a", "b", "c"), lambda R: R.as_euler("ZYX"), ()),
    ("abc", ("a", "b", "c"), lambda R: R.as_euler("ZYX"), ("deg", "mm")),  # a KUKA file: mm and degrees
    ("quat", ("qw", "qx", "qy", "qz"), lambda R: np.roll(R.as_quat(), 1), ()),
])
def test_other_rotation_readings_give_the_same_calibration(rotvec_csv, tmp_path, rotation, columns, fn, units):
    ref = tmp_path / "ref"
    assert run_cli("import", rotvec_csv, "--run", ref, "--quiet") == 0
    assert run_cli("calibrate", ref, "--no-ann", "--quiet", "--no-report") == 0
    deg, mm = "deg" in units, "mm" in units
    other = convert(rotvec_csv, tmp_path / f"{rotation}.csv", columns, fn,
                    scale_angles=180 / np.pi if deg else 1.0, scale_lengths=1e3 if mm else 1.0)
    run = tmp_path / rotation
    flags = ["--rotation", rotation] + (["--angle-unit", "deg"] if deg else []) + (["--length-unit", "mm"] if mm else [])
    assert run_cli("import", other, "--run", run, "--quiet", "--strict", *flags) == 0
    assert run_cli("calibrate", run, "--no-ann", "--quiet", "--no-report", "--strict") == 0
    (p_ref, m_ref), (p, m) = calibration(ref), calibration(run)
    np.testing.assert_allclose(p, p_ref, rtol=0, atol=1e-9)
    for stage in m_ref["order"]:
        for split in ("train", "test"):
            for block in ("position_mm", "orientation_mrad"):
                for k in ("max", "mean", "q90"):
                    assert abs(m["stages"][stage][split][block][k] - m_ref["stages"][stage][split][block][k]) < 1e-9


def test_rpy_read_as_rotation_vectors_is_named(rotvec_csv, tmp_path, capsys):
    rpy = convert(rotvec_csv, tmp_path / "rpy.csv", ("rx", "ry", "rz"), rpy_by_pinocchio)
    # norms above pi: the hint names the reading that fits, not degrees
    assert run_cli("import", rpy, "--run", tmp_path / "a", "--quiet") == 1
    err = capsys.readouterr().err
    assert "exceeds pi: not rotation vectors" in err and "--rotation rpy" in err and "--angle-unit deg" not in err
    # every norm below pi: the import goes through, and the warning names the reading
    header, rows = read_rows(rpy)
    rot = [header.index(c) for c in ("rx", "ry", "rz")]
    small = [r for r in rows if np.linalg.norm([float(r[i]) for i in rot]) < 3.0]
    assert len(small) > 50
    part = tmp_path / "rpy_small.csv"
    with open(part, "w", newline="") as fh:
        csv.writer(fh).writerows([header] + small)
    assert run_cli("import", part, "--run", tmp_path / "b", "--quiet") == 0
    (line,) = [ln for ln in capsys.readouterr().err.splitlines() if ln.startswith("warning:")]
    assert line.endswith("[rotation_reading]") and "read as rpy they agree" in line and "--rotation rpy" in line
    # calibrate cannot see the columns as written any more: it repeats the import's warning
    assert run_cli("calibrate", tmp_path / "b", "--no-ann", "--quiet", "--no-report") == 0
    lines = [ln for ln in capsys.readouterr().err.splitlines() if ln.startswith("warning:")]
    assert line in lines
    warned = json.loads((tmp_path / "b" / "calibration" / "metrics.json").read_text())["warnings"]
    assert "rotation_reading" in [w["code"] for w in warned]
    assert run_cli("import", part, "--run", tmp_path / "c", "--quiet", "--rotation", "rpy", "--strict") == 0


def test_kuka_columns_without_rotation_abc_are_named(rotvec_csv, tmp_path, capsys):
    abc = convert(rotvec_csv, tmp_path / "abc.csv", ("a", "b", "c"), lambda R: R.as_euler("ZYX"))
    assert run_cli("import", abc, "--run", tmp_path / "r", "--quiet") == 1
    err = capsys.readouterr().err
    assert "columns a,b,c look like KUKA's A, B, C" in err and "--rotation abc" in err
    assert not (tmp_path / "r" / "measurements.sqlite").exists()


def _rewrite(src, dst, sep, *, header=True, decimal_comma=False, pad=""):
    header_row, rows = read_rows(src)
    lines = ([sep.join(header_row)] if header else []) + [pad + sep.join(r) for r in rows]
    if decimal_comma:
        lines = [ln.replace(".", ",") for ln in lines]
    dst.write_text("\n".join(lines) + "\n")
    return dst


def test_delimiters_and_missing_headers_are_named_and_read(rotvec_csv, tmp_path, capsys):
    ref = read_measured_csv(rotvec_csv)
    semi = _rewrite(rotvec_csv, tmp_path / "semi.csv", ";")
    assert run_cli("import", semi, "--run", tmp_path / "a", "--quiet") == 1
    assert "line 1: not comma-separated: looks like ';'" in capsys.readouterr().err
    from campaign.measure.csvio import ImportOptions

    for sep, name, pad in ((";", ";", ""), ("\t", "tab", ""), ("   ", "space", "  ")):
        path = _rewrite(rotvec_csv, tmp_path / f"{name}.csv", sep, pad=pad)
        got = read_measured_csv(path, None, ImportOptions(delimiter=name))
        np.testing.assert_array_equal(got.q, ref.q)
        np.testing.assert_array_equal(got.T_IE, ref.T_IE)
    assert run_cli("import", tmp_path / "space.csv", "--run", tmp_path / "b", "--delimiter", "space",
                   "--quiet") == 0
    bare = _rewrite(rotvec_csv, tmp_path / "bare.csv", ",", header=False)
    assert run_cli("import", bare, "--run", tmp_path / "c", "--quiet") == 1
    assert "no header: line 1 holds numbers" in capsys.readouterr().err
    bare_space = _rewrite(rotvec_csv, tmp_path / "bare_space.csv", " ", header=False)
    assert run_cli("import", bare_space, "--run", tmp_path / "d", "--quiet") == 1
    err = capsys.readouterr().err
    assert "not comma-separated: looks like 'space' and no header" in err and "--delimiter 'space'" in err
    names = read_rows(rotvec_csv)[0]
    got = read_measured_csv(bare_space, None, ImportOptions(delimiter="space", header=tuple(names)))
    np.testing.assert_array_equal(got.q, ref.q)
    np.testing.assert_array_equal(got.T_IE, ref.T_IE)
    assert run_cli("import", bare, "--run", tmp_path / "d", "--header", ",".join(names), "--quiet") == 0
    assert run_cli("import", rotvec_csv, "--run", tmp_path / "d2", "--header", ",".join(names), "--quiet") == 1
    assert "line 1 is a header (pose_id, time_s, q1, q2, ...) and --header names the columns too" in \
        capsys.readouterr().err
    comma = _rewrite(rotvec_csv, tmp_path / "comma.csv", ";", decimal_comma=True)
    assert run_cli("import", comma, "--run", tmp_path / "e", "--delimiter", ";", "--quiet") == 1
    assert "line 2, column time_s: '0,0' is not a number (a decimal comma?" in capsys.readouterr().err


def test_line_numbers_are_the_files_own(rotvec_csv, tmp_path, capsys):
    header, rows = read_rows(rotvec_csv)
    rows[2][header.index("q4")] = "oops"  # the 4th line of the file: header, then rows 1, 2, 3
    path = tmp_path / "bad.csv"
    path.write_text("\n".join(";".join(r) for r in [header] + rows) + "\n")
    assert run_cli("import", path, "--run", tmp_path / "r", "--delimiter", ";", "--quiet") == 1
    assert "line 4, column q4: 'oops' is not a number" in capsys.readouterr().err
    rows[2][header.index("q4")] = "0.1"
    rows[5][header.index("q5")] = "1.9"  # outside q5's limit, on line 7
    path.write_text("\n".join(";".join(r) for r in [header] + rows) + "\n")
    assert run_cli("import", path, "--run", tmp_path / "r", "--delimiter", ";", "--quiet") == 1
    assert "line 7, column q5: 1.9 rad is outside the joint limit" in capsys.readouterr().err


def test_column_mapping_on_the_command_line_and_in_robot_yaml(robot, rotvec_csv, tmp_path, capsys):
    header, rows = read_rows(rotvec_csv)
    names = {"x": "X", "y": "Y", "z": "Z", "q1": "J1", "pose_id": "id"}
    path = tmp_path / "named.csv"
    with open(path, "w", newline="") as fh:
        csv.writer(fh).writerows([[names.get(h, h) for h in header]] + rows)
    assert run_cli("import", path, "--run", tmp_path / "a", "--quiet") == 1
    assert "missing column(s) q1 in the header" in capsys.readouterr().err  # pose_id is optional
    mapping = ",".join(f"{k}={v}" for k, v in names.items())
    assert run_cli("import", path, "--run", tmp_path / "b", "--columns", mapping, "--quiet") == 0
    assert run_cli("import", path, "--run", tmp_path / "c", "--columns", "x=NOPE", "--quiet") == 1
    assert "--columns names column(s) NOPE" in capsys.readouterr().err
    meta = tmp_path / "robot" / "robot.yaml"
    meta.parent.mkdir()
    doc = yaml.safe_load((robot.urdf_path.parent / "robot.yaml").read_text())
    doc.update(urdf=str(robot.urdf_path), columns=names)
    meta.write_text(yaml.safe_dump(doc))
    assert run_cli("import", path, "--run", tmp_path / "d", "--robot", meta, "--quiet") == 0
    ref = read_measured_csv(rotvec_csv)
    for run in ("b", "d"):
        assert run_cli("export", tmp_path / run, "--csv", tmp_path / f"{run}.csv") == 0
        got = read_measured_csv(tmp_path / f"{run}.csv")
        np.testing.assert_array_equal(got.q, ref.q)
        np.testing.assert_allclose(got.T_IE, ref.T_IE, rtol=0, atol=1e-14)  # via the log's rotation vectors


def test_limit_slack_accepts_tiago_torso_past_its_limit(tmp_path, capsys):
    from fcl_reference import erd_robot

    from campaign.model.robot import RobotModel

    urdf = erd_robot("tiago_description/robots/tiago.urdf")
    frames = ("--base-frame", "base_footprint", "--tool-frame", "arm_tool_link")
    tiago = RobotModel.load(urdf, base_frame="base_footprint", tool_frame="arm_tool_link")
    assert tiago.joint_names[0] == "torso_lift_joint" and tiago.q_upper[0] == pytest.approx(0.35)
    q = random_joint_poses(tiago, 60, seed=21)
    q[[4, 9, 30], 0] = [0.35012, 0.350184, 0.35005]  # real readings past the URDF's 0.35 m
    path = tmp_path / "tiago.csv"
    write_measured_csv(path, synthesize(make_truth(tiago, seed=22), q, seed=23))
    assert run_cli("import", path, "--run", tmp_path / "a", "--robot", urdf, *frames, "--quiet") == 1
    err = capsys.readouterr().err
    assert "line 6, column q1: 0.35012 m is outside the joint limit 0.35 m" in err and "--limit-slack" in err
    run = tmp_path / "b"
    assert run_cli("import", path, "--run", run, "--robot", urdf, *frames, "--limit-slack", "0.5", "--quiet") == 0
    out = capsys.readouterr().out
    assert "3 joint reading(s) past the URDF limits" in out and "line 11, q1 = 0.350184 m (limit 0.35 m)" in out
    assert run_cli("import", path, "--run", tmp_path / "c", "--robot", urdf, *frames, "--limit-slack", "0.1",
                   "--quiet") == 1  # 0.184 mm past: more than 0.1 mm
    assert run_cli("calibrate", run, "--no-ann", "--quiet", "--no-report") == 0


def test_predict_and_compensate_read_and_write_degrees(rotvec_csv, tmp_path, capsys):
    run = tmp_path / "run"
    assert run_cli("import", rotvec_csv, "--run", run, "--quiet") == 0
    assert run_cli("calibrate", run, "--no-ann", "--quiet", "--no-report") == 0
    header, rows = read_rows(rotvec_csv)
    qcols = [header.index(f"q{j}") for j in range(1, 7)]
    q = np.array([[float(r[i]) for i in qcols] for r in rows[:10]])
    for unit, qq in (("rad", q), ("deg", np.rad2deg(q))):
        lines = ["q1,q2,q3,q4,q5,q6"] + [",".join(repr(float(v)) for v in row) for row in qq]
        (tmp_path / f"q_{unit}.csv").write_text("\n".join(lines) + "\n")
        for cmd in ("predict", "compensate"):
            assert run_cli(cmd, run, "--csv", tmp_path / f"q_{unit}.csv", "--out", tmp_path / f"{cmd}_{unit}.csv",
                           "--angle-unit", unit) == 0
    for cmd in ("predict", "compensate"):
        h, a = read_rows(tmp_path / f"{cmd}_rad.csv")
        _, b = read_rows(tmp_path / f"{cmd}_deg.csv")
        a, b = np.array(a, dtype=float), np.array(b, dtype=float)
        angles = [k for k, name in enumerate(h) if name.startswith(("q", "dq"))]
        other = [k for k in range(len(h)) if k not in angles and not h[k].startswith("residual")]
        np.testing.assert_allclose(np.deg2rad(b[:, angles]), a[:, angles], rtol=0, atol=1e-9)
        np.testing.assert_allclose(b[:, other], a[:, other], rtol=0, atol=1e-9)
    np.testing.assert_allclose(np.deg2rad(np.array(read_rows(tmp_path / "predict_deg.csv")[1], dtype=float)[:, 1:7]),
                               q, rtol=0, atol=1e-12)
    lines = (tmp_path / "q_deg.csv").read_text().splitlines()
    cells = lines[3].split(",")
    cells[4] = "120.0"  # q5 beyond its ±98 deg limit, on the file's line 4
    lines[3] = ",".join(cells)
    (tmp_path / "bad.csv").write_text("\n".join(lines) + "\n")
    assert run_cli("predict", run, "--csv", tmp_path / "bad.csv", "--angle-unit", "deg") == 1
    assert "(read in deg): line 4, q5 = 2.0944 rad is outside the joint limit" in capsys.readouterr().err
