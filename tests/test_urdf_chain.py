"""campaign.model.urdf_chain reads a URDF's chain as yourdfpy does (the reference), without
importing yourdfpy: every joint's type, links, origin, axis, limits and mimic, on every URDF at
hand (the embedded COMAU, example-robot-data's arms and more), and `campaign calibrate` imports
neither yourdfpy nor torch."""

import subprocess
import sys
from importlib import metadata
from pathlib import Path

import numpy as np
import pytest

from campaign.model.urdf_chain import read_chain
from campaign.paths import DEFAULT_CONFIG


def _urdfs():
    out = sorted((Path(DEFAULT_CONFIG).parent / "robot_models").glob("*/*.urdf"))
    try:
        share = Path(metadata.distribution("example-robot-data").locate_file("cmeel.prefix/share/example-robot-data"))
        out += sorted(share.glob("robots/*/urdf/*.urdf"))
    except metadata.PackageNotFoundError:
        pass
    return out


URDFS = _urdfs()


@pytest.mark.parametrize("path", URDFS, ids=[f"{p.parent.parent.name}/{p.name}" for p in URDFS])
def test_the_chain_reads_as_yourdfpy_reads_it(path):
    import yourdfpy

    try:
        ref = yourdfpy.URDF.load(str(path), load_meshes=False, build_scene_graph=False,
                                 build_collision_scene_graph=False).robot
    except Exception as exc:  # noqa: BLE001 - a file yourdfpy cannot read is not a reference
        pytest.skip(f"yourdfpy cannot read it: {exc.__class__.__name__}")
    ours = read_chain(path).robot
    assert ours.name == ref.name
    assert [lk.name for lk in ours.links] == [lk.name for lk in ref.links]
    assert len(ours.joints) == len(ref.joints)
    for a, b in zip(ours.joints, ref.joints):
        assert (a.name, a.type, a.parent, a.child) == (b.name, b.type, b.parent, b.child)
        if b.origin is None:
            assert a.origin is None
        else:
            np.testing.assert_allclose(a.origin, b.origin, rtol=0, atol=1e-15)
        np.testing.assert_array_equal(a.axis, b.axis)
        assert (a.limit is None) == (b.limit is None)
        if b.limit is not None:
            for k in ("effort", "velocity", "lower", "upper"):
                assert getattr(a.limit, k) == getattr(b.limit, k), (a.name, k)
        assert (a.mimic is None) == (b.mimic is None)
        if b.mimic is not None:
            assert (a.mimic.joint, a.mimic.multiplier, a.mimic.offset) == (b.mimic.joint, b.mimic.multiplier,
                                                                         b.mimic.offset)


def test_help_calibrate_and_diagnose_import_only_what_they_use(tmp_path):
    """`campaign --help` imports no numpy, scipy, torch or matplotlib; `calibrate --no-ann` no
    torch, no yourdfpy and no matplotlib; `diagnose` (with its report) no matplotlib (issue 22)."""
    from campaign.cli import main
    from campaign.measure.csvio import write_measured_csv
    from campaign.model.robot import RobotModel
    from campaign.sim.truth import make_truth, random_joint_poses, synthesize

    robot = RobotModel.load()
    poses = synthesize(make_truth(robot, seed=1), random_joint_poses(robot, 60, seed=2), seed=3)
    write_measured_csv(tmp_path / "m.csv", poses)
    assert main(["import", str(tmp_path / "m.csv"), "--run", str(tmp_path / "run"), "--quiet"]) == 0
    heavy = "('numpy', 'scipy', 'torch', 'matplotlib', 'yourdfpy', 'trimesh')"
    probe = ("import sys; from campaign.cli import main; rc = main(sys.argv[1:]); "
             f"print(rc, sorted(m for m in {heavy} if m in sys.modules))")
    out = subprocess.run([sys.executable, "-c", probe, "--help"], capture_output=True, text=True, cwd=tmp_path)
    assert out.stdout.strip().splitlines()[-1] == "0 []", out.stdout[-300:]
    out = subprocess.run([sys.executable, "-c", probe, "calibrate", str(tmp_path / "run"), "--no-ann", "--quiet"],
                         capture_output=True, text=True, cwd=tmp_path)
    last = out.stdout.strip().splitlines()[-1]
    assert last.startswith("0 [") and "numpy" in last, last
    for module in ("torch", "yourdfpy", "matplotlib"):  # the report's figures are SVG written from numpy
        assert module not in last, last
    out = subprocess.run([sys.executable, "-c", probe, "diagnose", str(tmp_path / "run"), "--folds", "3",
                          "--candidates", "drift"], capture_output=True, text=True, cwd=tmp_path)
    last = out.stdout.strip().splitlines()[-1]
    assert last.startswith("0 [") and "matplotlib" not in last, last  # so are the diagnose report's
    assert (tmp_path / "run" / "diagnose" / "report.html").is_file()
