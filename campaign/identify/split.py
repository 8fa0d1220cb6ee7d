"""The fixed train/test split of a run (80/20, seeded), shared by every stage."""

from __future__ import annotations

import numpy as np

SPLIT_SEED = 20200101
TEST_FRACTION = 0.2


def train_test_split(pose_id, *, seed: int = SPLIT_SEED, test_fraction: float = TEST_FRACTION):
    """Boolean mask ``is_test`` (n,) for poses with these ids.

    A pose's side depends only on its id and the seed, not on which other poses are
    present, so a resumed or extended run keeps every earlier pose on its side.
    """
    pose_id = np.asarray(pose_id, dtype=np.uint64)
    # splitmix64 of (id ^ seed): a fixed, well-mixed hash per pose
    with np.errstate(over="ignore"):
        z = pose_id ^ np.uint64(seed)
        z = z + np.uint64(0x9E3779B97F4A7C15)
        z = (z ^ (z >> np.uint64(30))) * np.uint64(0xBF58476D1CE4E5B9)
        z = (z ^ (z >> np.uint64(27))) * np.uint64(0x94D049BB133111EB)
        z = z ^ (z >> np.uint64(31))
    u = (z >> np.uint64(11)).astype(np.float64) / float(1 << 53)
    return u < test_fraction


def run_split(run_dir, pose_id):
    """Boolean mask ``is_test`` (n,) for a run's measured poses.

    A plan that chose its poses (`campaign plan --select/--budget/--target-mm`) drew validation
    poses at random from the suitable set and listed them in ``RUN/plan/validation.csv``
    (``pose_id``): they are the test set, so the accuracy claim comes from poses the design did
    not choose. Otherwise the fixed 80/20 split, where a repeated measurement (pose id
    ``p + r·10⁹``, when the plan wrote RUN/plan/repeats.csv) lies on the side of the pose ``p``
    it repeats.
    """
    from pathlib import Path

    from campaign.errors import DataError
    from campaign.plan.selection import base_pose_id

    pose_id = np.asarray(pose_id, dtype=np.int64)
    path = Path(run_dir) / "plan" / "validation.csv"
    if not path.is_file():
        if (Path(run_dir) / "plan" / "repeats.csv").is_file():
            return train_test_split(base_pose_id(pose_id))
        return train_test_split(pose_id)
    lines = [ln.strip() for ln in path.read_text().splitlines() if ln.strip()]
    if not lines or lines[0] != "pose_id":
        raise DataError(f"{path}: header must be pose_id")
    try:
        ids = np.array([int(ln) for ln in lines[1:]], dtype=np.int64)
    except ValueError:
        raise DataError(f"{path}: pose ids must be integers") from None
    return np.isin(pose_id, ids)
