"""Issue 29, items 11-19, checked from outside: variants of the rough edges a user hits with
files of their own (a raw-reflector file given back to predict, a planned run's file without
pose_id, a file of another robot, a blank line before the header). References: files written
in the test itself (synth's seeded data, read back with numpy)."""

import csv

import numpy as np
import pytest

from campaign.cli import main


def _read(path):
    with open(path, newline="") as fh:
        rows = list(csv.reader(fh))
    return rows[0], np.array([[float(c) if c else np.nan for c in r] for r in rows[1:]])


def _write(path, header, values):
    with open(path, "w", newline="") as fh:
        w = csv.writer(fh)
        w.writerow(header)
        w.writerows([["" if np.isnan(v) else repr(float(v)) for v in row] for row in values])


@pytest.fixture(scope="module")
def markers_ur10(tmp_path_factory):
    """A UR10 raw-reflector run (a reflector missed now and then: empty cells), calibrated."""
    tmp = tmp_path_factory.mktemp("markers")
    src = tmp / "m.csv"
    assert main(["synth", "--csv", str(src), "--robot", "ur10", "--poses", "50", "--seed", "4", "--kind", "markers",
                 "--miss-rate", "0.1"]) == 0
    run = tmp / "run"
    assert main(["import", str(src), "--run", str(run), "--robot", "ur10", "--markers",
                 str(tmp / "m.markers.yaml"), "--quiet"]) == 0
    assert main(["calibrate", str(run), "--no-ann", "--no-report", "--quiet"]) == 0
    return run, src


@pytest.mark.parametrize("cmd", ["predict", "compensate"])
def test_the_measured_file_itself_is_read_by_predict_its_empty_reflector_cells_unread(markers_ur10, tmp_path,
                                                                                     capsys, cmd):
    run, src = markers_ur10
    header, values = _read(src)
    assert np.isnan(values).any()  # the missed reflectors
    joints = ["pose_id"] + [f"q{j}" for j in range(1, 7)]
    _write(tmp_path / "joints.csv", joints, values[:, [header.index(h) for h in joints]])
    labelled = tmp_path / "labelled.csv"  # and a text label beside them
    with open(src) as fh, open(labelled, "w") as out:
        for k, line in enumerate(fh):
            out.write(("label," if k == 0 else f"P{k},") + line)
    outs = []
    for k, path in enumerate((tmp_path / "joints.csv", src, labelled)):
        outs.append(tmp_path / f"out{k}.csv")
        assert main([cmd, str(run), "--csv", str(path), "--out", str(outs[-1])]) == 0, capsys.readouterr().err
    first = _read(outs[0])[1]
    assert len(first) == len(values)
    for out in outs[1:]:
        np.testing.assert_array_equal(_read(out)[1], first)
