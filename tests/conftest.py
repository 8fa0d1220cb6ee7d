import os
import sqlite3
from pathlib import Path

# one BLAS thread: the tests' matrices are small, and on a shared 2-core machine OpenBLAS's
# threads spin against each other (measured: the effect tests 553 s -> 145 s)
os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")

import numpy as np  # noqa: E402
import pytest  # noqa: E402
import yaml  # noqa: E402

os.environ.setdefault("MPLBACKEND", "Agg")


@pytest.fixture(scope="session")
def robot():
    from campaign.model.robot import RobotModel

    return RobotModel.load()


@pytest.fixture(scope="session")
def base(robot):
    from campaign.model.base_params import base_parameters

    return base_parameters(robot)


@pytest.fixture
def rng():
    return np.random.default_rng(12345)


class SimRuns:
    """Run folders for the simulated cell: a random plan (pose ids 1000, 1001, ...) and a
    campaign.yaml with short timeouts; what a run stored; the cell processes of a run."""

    def __init__(self, tmp_path, robot):
        self.tmp_path, self.robot = tmp_path, robot

    def make(self, n=60, seed=0, sim=None, run=None, name="run") -> Path:
        from campaign.paths import DEFAULT_SCENE
        from campaign.sim.truth import random_joint_poses

        run_dir = self.tmp_path / name
        (run_dir / "plan").mkdir(parents=True)
        q = random_joint_poses(self.robot, n, seed=seed)
        lines = ["pose_id,q1,q2,q3,q4,q5,q6"] + [f"{1000 + i}," + ",".join(repr(float(v)) for v in q[i])
                                                for i in range(n)]
        (run_dir / "plan" / "poses.csv").write_text("\n".join(lines) + "\n")
        cfg = {"robot": "comau_racer5_080", "scene": str(DEFAULT_SCENE),
               "run": {"timeout_s": 0.5, "retries": 3, "backoff_s": 0.01, "drift_check_every": 20, **(run or {})},
               "sim": {"seed": seed, "time_factor": 0.0, **(sim or {})}}
        (run_dir / "campaign.yaml").write_text(yaml.safe_dump(cfg))
        return run_dir

    @staticmethod
    def stored(run_dir) -> list:
        """[(pose_id, status, reason), ...] of the run's log, by pose id."""
        with sqlite3.connect(Path(run_dir) / "measurements.sqlite") as db:
            return db.execute("SELECT pose_id, status, reason FROM poses ORDER BY pose_id").fetchall()

    @staticmethod
    def cell_pids(run_dir) -> list:
        """Process ids of simulated cells serving ``run_dir``."""
        pids = []
        for d in Path("/proc").iterdir():
            if d.name.isdigit():
                try:
                    cmd = (d / "cmdline").read_bytes().replace(b"\0", b" ").decode()
                except OSError:
                    continue
                if "campaign.sim.cell" in cmd and str(run_dir) in cmd:
                    pids.append(int(d.name))
        return pids


@pytest.fixture
def runs(tmp_path, robot):
    """A :class:`SimRuns` in this test's tmp_path."""
    return SimRuns(tmp_path, robot)


class MeasuredRuns:
    """Run folders imported (`campaign import`) from a synthetic campaign of the default robot:
    ``make(n, seed, q, name)`` -> (run folder, truth, the measured poses)."""

    def __init__(self, tmp_path, robot):
        self.tmp_path, self.robot = tmp_path, robot

    def make(self, n=60, seed=1, q=None, name="run"):
        from campaign.cli import main
        from campaign.measure.csvio import write_measured_csv
        from campaign.sim.truth import make_truth, random_joint_poses, synthesize

        truth = make_truth(self.robot, seed=seed)
        q = random_joint_poses(self.robot, n, seed=seed) if q is None else q
        poses = synthesize(truth, q, seed=seed + 1)
        self.tmp_path.mkdir(parents=True, exist_ok=True)
        csv = self.tmp_path / f"{name}.csv"
        write_measured_csv(csv, poses)
        run = self.tmp_path / name
        assert main(["import", str(csv), "--run", str(run)]) == 0
        return run, truth, poses


@pytest.fixture
def measured(tmp_path, robot):
    """A :class:`MeasuredRuns` in this test's tmp_path."""
    return MeasuredRuns(tmp_path, robot)


@pytest.fixture(scope="session")
def erd():
    """Path to a file of the test extra example-robot-data (skips when it is not installed)."""
    from importlib import metadata

    def path(rel):
        try:
            dist = metadata.distribution("example-robot-data")
        except metadata.PackageNotFoundError:
            pytest.skip("example-robot-data (test extra) is not installed")
        return str(Path(dist.locate_file("cmeel.prefix/share/example-robot-data/robots")) / rel)

    return path
