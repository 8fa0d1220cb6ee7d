"""The train/test split of a run (80/20, seeded), shared by every stage, and the folds of its
cross-validations.

The rules for small campaigns (issue 12: real campaigns bring 30-300 poses), in one place:

* **Test split.** From :data:`EXACT_SPLIT_BELOW` distinct poses on, each pose's side follows from
  a hash of its id alone (about 20 %; a resumed or extended run keeps every pose on its side).
  Below that, exactly ``max(1, round(0.2 n))`` poses are tested: the ones with the smallest hash.
  The hash alone would test 6 ± 2 of 30 poses, and none at all of 10 poses one time in nine;
  with the exact count the training count, and with it whether the base parameters are
  identifiable, follows from the number of poses (:func:`poses_for_training`).
* **Folds** (:func:`choose_folds`): leave-one-out below :data:`LOO_BELOW_TRAIN_POSES` distinct
  training poses, :data:`DEFAULT_FOLDS`-fold from there on, or the number asked for
  (``--folds K``). Leave-one-out fits each fold on every training pose but one, so a campaign
  just above the identifiable count can still be cross-validated (5 folds would fit on 80 %);
  at 60 poses the two differ by about 1 % in the held-out error of a 30-parameter model and
  leave-one-out costs 12 times the fits.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

SPLIT_SEED = 20200101
TEST_FRACTION = 0.2
#: fewer distinct poses than this: the test set is exactly round(TEST_FRACTION · n) of them
EXACT_SPLIT_BELOW = 100
#: fewer distinct training poses than this: leave-one-out folds
LOO_BELOW_TRAIN_POSES = 60
#: folds from LOO_BELOW_TRAIN_POSES training poses on
DEFAULT_FOLDS = 5


def _hash_uniform(pose_id, seed: int) -> np.ndarray:
    """A fixed, well-mixed number in [0, 1) per pose id: splitmix64 of (id ^ seed)."""
    pose_id = np.asarray(pose_id, dtype=np.uint64)
    with np.errstate(over="ignore"):
        z = pose_id ^ np.uint64(seed)
        z = z + np.uint64(0x9E3779B97F4A7C15)
        z = (z ^ (z >> np.uint64(30))) * np.uint64(0xBF58476D1CE4E5B9)
        z = (z ^ (z >> np.uint64(27))) * np.uint64(0x94D049BB133111EB)
        z = z ^ (z >> np.uint64(31))
    return (z >> np.uint64(11)).astype(np.float64) / float(1 << 53)


def train_test_split(pose_id, *, seed: int = SPLIT_SEED, test_fraction: float = TEST_FRACTION):
    """Boolean mask ``is_test`` (n,) for poses with these ids, by the hash alone.

    A pose's side depends only on its id and the seed, not on which other poses are
    present, so a resumed or extended run keeps every earlier pose on its side.
    """
    return _hash_uniform(pose_id, seed) < test_fraction


def n_test_poses(n: int) -> int:
    """Test poses of a campaign of ``n`` distinct poses below EXACT_SPLIT_BELOW: max(1, round(0.2 n))."""
    return max(1, int(round(TEST_FRACTION * n))) if n else 0


def campaign_split(pose_id) -> np.ndarray:
    """Boolean mask ``is_test`` (n,) of the 80/20 split: the hash split from EXACT_SPLIT_BELOW
    distinct poses on, else exactly :func:`n_test_poses` of them (those of smallest hash). Equal
    ids (a pose and its repeats, already mapped to one id) lie on one side."""
    pose_id = np.asarray(pose_id, dtype=np.int64)
    ids, inverse = np.unique(pose_id, return_inverse=True)
    if len(ids) >= EXACT_SPLIT_BELOW:
        return train_test_split(pose_id)
    u = _hash_uniform(ids, SPLIT_SEED)
    test = np.zeros(len(ids), dtype=bool)
    test[np.argsort(u, kind="stable")[:n_test_poses(len(ids))]] = True
    return test[inverse.reshape(-1)]


def poses_for_training(n_train: int) -> int:
    """The fewest distinct poses whose 80/20 split leaves ``n_train`` training poses."""
    n = n_train
    while n - (n_test_poses(n) if n < EXACT_SPLIT_BELOW else int(round(TEST_FRACTION * n))) < n_train:
        n += 1
    return n


@dataclass(frozen=True)
class FoldRule:
    """How a cross-validation on ``n_poses`` distinct training poses is folded: ``k`` folds,
    ``asked`` when the user gave ``--folds``."""

    k: int
    n_poses: int
    asked: bool = False

    @property
    def leave_one_out(self) -> bool:
        return self.k == self.n_poses

    @property
    def fit_poses(self) -> int:
        """Training poses of the smallest fold fit (the largest fold held out)."""
        return self.n_poses - -(-self.n_poses // self.k)

    def reason(self) -> str:
        """Why these folds: ``leave-one-out: fewer than 60 training poses``, ``5-fold: 60 training
        poses or more`` or ``--folds K``."""
        if self.asked:
            return f"--folds {self.k}" + (", leave-one-out" if self.leave_one_out else "")
        if self.leave_one_out:
            return f"leave-one-out: fewer than {LOO_BELOW_TRAIN_POSES} training poses"
        return f"{self.k}-fold: {LOO_BELOW_TRAIN_POSES} training poses or more"

    def text(self) -> str:
        """``24 folds of 24 training poses (leave-one-out: fewer than 60 training poses)``."""
        return f"{self.k} folds of {self.n_poses} training poses ({self.reason()})"

    def as_json(self) -> dict:
        return {"folds": self.k, "leave_one_out": self.leave_one_out, "training_poses": self.n_poses,
                "rule": self.reason()}


def choose_folds(n_poses: int, folds: int | None = None) -> FoldRule:
    """The folds of a cross-validation on ``n_poses`` distinct training poses: ``folds`` when
    given (2 ≤ folds ≤ n_poses, else ConfigError naming ``--folds``), else leave-one-out below
    LOO_BELOW_TRAIN_POSES poses and DEFAULT_FOLDS from there on."""
    from campaign.errors import ConfigError

    if folds is None:
        return FoldRule(n_poses if n_poses < LOO_BELOW_TRAIN_POSES else DEFAULT_FOLDS, n_poses)
    if isinstance(folds, bool) or not isinstance(folds, (int, np.integer)) or folds < 2:
        raise ConfigError(f"--folds must be an integer >= 2 (cross-validation needs two folds), got {folds!r}")
    if folds > n_poses:
        raise ConfigError(f"--folds {folds}: only {n_poses} training poses (leave-one-out is --folds {n_poses}; "
                          "without --folds the folds are chosen from the data)")
    return FoldRule(int(folds), n_poses, asked=True)


def validation_file(run_dir):
    """``RUN/plan/validation.csv``, the plan's validation poses (may not exist)."""
    from pathlib import Path

    return Path(run_dir) / "plan" / "validation.csv"


def not_the_plans(run_dir, pose_id) -> str | None:
    """The sentence saying that none of the measured pose ids is one of the run's plan
    (RUN/plan/poses.csv), whose validation poses then cannot be told: the test set is the 80/20
    split (a file of the user's own ids imported into a planned run); None when some are, or
    without a plan."""
    from pathlib import Path

    path = Path(run_dir) / "plan" / "poses.csv"
    if not path.is_file() or not validation_file(run_dir).is_file():
        return None
    with open(path) as fh:
        next(fh, None)
        planned = np.array([int(float(ln.split(",", 1)[0])) for ln in fh if ln.strip()], dtype=np.int64)
    if np.isin(np.asarray(pose_id, dtype=np.int64), planned).any():
        return None
    return (f"none of the {len(np.unique(pose_id))} measured pose ids is one of the plan's ({path}): its validation "
            "poses cannot be told, the test set is the 80/20 split (a file without pose_id imported into the "
            "planned run finds the plan's poses by their joints)")


def run_split(run_dir, pose_id):
    """Boolean mask ``is_test`` (n,) for a run's measured poses.

    A plan that chose its poses (`campaign plan --select/--budget/--target-mm`, and the default
    short campaign) drew validation poses at random from the suitable set and listed them in
    ``RUN/plan/validation.csv`` (``pose_id``): they are the test set, so the accuracy claim comes
    from poses the design did not choose. Otherwise (or when no measured id is the plan's:
    :func:`not_the_plans`) the 80/20 split (:func:`campaign_split`),
    where a repeated measurement (pose id ``p + r·10⁹``, when the plan wrote RUN/plan/repeats.csv)
    lies on the side of the pose ``p`` it repeats.
    """
    from pathlib import Path

    from campaign.errors import DataError
    from campaign.plan.selection import base_pose_id

    pose_id = np.asarray(pose_id, dtype=np.int64)
    path = validation_file(run_dir)
    if not path.is_file() or not_the_plans(run_dir, pose_id):
        if (Path(run_dir) / "plan" / "repeats.csv").is_file():
            return campaign_split(base_pose_id(pose_id))
        return campaign_split(pose_id)
    lines = [ln.strip() for ln in path.read_text().splitlines() if ln.strip()]
    if not lines or lines[0] != "pose_id":
        raise DataError(f"{path}: header must be pose_id")
    try:
        ids = np.array([int(ln) for ln in lines[1:]], dtype=np.int64)
    except ValueError:
        raise DataError(f"{path}: pose ids must be integers") from None
    return np.isin(pose_id, ids)
