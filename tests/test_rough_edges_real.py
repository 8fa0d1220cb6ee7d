"""Real files as they come (issue 29, items 11-16): what a user at the command line hit with
FIGAROH's and a FANUC cell's files, each a working result or one clear line. References: files
written in the test itself (synth's seeded data, read back independently with numpy)."""

import csv
import json
import re

import numpy as np
import pytest
import yaml

from campaign.cli import main


def _synth(tmp_path, name, *args):
    out = tmp_path / f"{name}.csv"
    assert main(["synth", "--csv", str(out), *args]) == 0
    return out


def _read(path):
    with open(path, newline="") as fh:
        rows = list(csv.reader(fh))
    return rows[0], np.array([[float(c) if c else np.nan for c in r] for r in rows[1:]])


def _write(path, header, values):
    with open(path, "w", newline="") as fh:
        w = csv.writer(fh)
        w.writerow(header)
        w.writerows([[repr(float(v)) for v in row] for row in values])


def test_a_file_without_pose_id_is_imported_with_its_rows_numbered_and_says_so(tmp_path, capsys):
    src = _synth(tmp_path, "ur10", "--robot", "ur10", "--poses", "30", "--seed", "2")
    header, values = _read(src)
    _write(tmp_path / "noid.csv", header[1:], values[:, 1:])  # FIGAROH's files have no pose_id
    capsys.readouterr()
    assert main(["import", str(tmp_path / "noid.csv"), "--run", str(tmp_path / "run"), "--robot", "ur10",
                 "--quiet"]) == 0
    out = capsys.readouterr().out
    assert "no pose_id column: the 30 rows are numbered 0..29 in file order" in out
    assert main(["export", str(tmp_path / "run"), "--csv", str(tmp_path / "back.csv")]) == 0
    back_header, back = _read(tmp_path / "back.csv")
    assert back_header == header
    np.testing.assert_array_equal(back[:, 0], np.arange(30))
    np.testing.assert_allclose(back[:, 1:], values[:, 1:], rtol=0, atol=1e-12)


@pytest.fixture(scope="module")
def named_ur10(tmp_path_factory):
    """A UR10 run imported from a file with its own column names (robot.yaml's ``columns:``),
    calibrated; the joints of the file, as written."""
    from campaign.model.robot import RobotModel

    tmp = tmp_path_factory.mktemp("named")
    src = _synth(tmp, "ur10", "--robot", "ur10", "--poses", "60", "--seed", "3")
    header, values = _read(src)
    names = {"pose_id": "id", **{f"q{j}": f"J{j}" for j in range(1, 7)}, "x": "X", "y": "Y", "z": "Z"}
    _write(tmp / "named.csv", [names.get(h, h) for h in header], values)
    ur10 = RobotModel.load("ur10")
    meta = tmp / "ur10" / "robot.yaml"
    meta.parent.mkdir()
    meta.write_text(yaml.safe_dump({"urdf": str(ur10.urdf_path), "tool_frame": "tool0", "columns": names}))
    run = tmp / "run"
    assert main(["import", str(tmp / "named.csv"), "--run", str(run), "--robot", str(meta), "--quiet"]) == 0
    assert main(["calibrate", str(run), "--no-ann", "--no-report", "--quiet"]) == 0
    return run, values[:, [header.index(f"q{j}") for j in range(1, 7)]]


@pytest.mark.parametrize("cmd", ["predict", "compensate"])
def test_predict_and_compensate_read_the_files_own_column_names_as_import_does(named_ur10, tmp_path, capsys, cmd):
    run, q = named_ur10
    q = q[:8]
    _write(tmp_path / "plain.csv", [f"q{j}" for j in range(1, 7)], q)
    _write(tmp_path / "yaml.csv", [f"J{j}" for j in range(1, 7)], q)  # robot.yaml's names, no x,y,z here
    _write(tmp_path / "flag.csv", [f"A{j}" for j in range(1, 7)], q)
    out = {name: ["--out", str(tmp_path / f"{name}_out.csv")] for name in ("plain", "yaml", "flag")}
    assert main([cmd, str(run), "--csv", str(tmp_path / "plain.csv"), *out["plain"]]) == 0
    assert main([cmd, str(run), "--csv", str(tmp_path / "yaml.csv"), *out["yaml"]]) == 0
    assert main([cmd, str(run), "--csv", str(tmp_path / "flag.csv"), *out["flag"]]) == 1
    assert "column(s) J1, J2, J3, J4, J5, J6, which the header does not have" in capsys.readouterr().err
    assert main([cmd, str(run), "--csv", str(tmp_path / "flag.csv"), *out["flag"],
                 "--columns", ",".join(f"q{j}=A{j}" for j in range(1, 7))]) == 0
    ref_header, ref = _read(tmp_path / "plain_out.csv")
    for name in ("yaml", "flag"):
        got_header, got = _read(tmp_path / f"{name}_out.csv")
        assert got_header == ref_header
        np.testing.assert_array_equal(got, ref)
    if cmd == "predict":  # the joints read are the file's
        np.testing.assert_allclose(ref[:, 1:7], q, rtol=0, atol=1e-12)


def test_a_near_miss_column_name_points_to_columns_and_an_empty_file_names_the_header(tmp_path, capsys):
    src = _synth(tmp_path, "ur10", "--robot", "ur10", "--poses", "5", "--seed", "4")
    header, values = _read(src)
    _write(tmp_path / "near.csv", [{"q1": "Q1", "q2": "q_2"}.get(h, h) for h in header], values)
    assert main(["import", str(tmp_path / "near.csv"), "--run", str(tmp_path / "a"), "--robot", "ur10"]) == 1
    assert "missing column(s) q1, q2 in the header (the file's own names: --columns q1=Q1,q2=q_2" \
        in capsys.readouterr().err
    (tmp_path / "empty.csv").write_text("")
    assert main(["import", str(tmp_path / "empty.csv"), "--run", str(tmp_path / "b"), "--robot", "ur10"]) == 1
    assert "empty file (expected header [pose_id,][time_s,]q1,...,q6, then x,y,z,rx,ry,rz" in capsys.readouterr().err
