"""Does the model hold on the test set? The folds against the poses calibrate keeps apart.

Diagnose judges the current model on held-out folds of the training poses. The training poses are
the most informative ones, and an optimal design puts a joint at the ends of its range: a wrist
joint may take two values on every training pose. An error that depends on that joint's interior
values then hides from every fold (any function of two values is an offset the geometry absorbs)
and shows only on poses where the joint sits elsewhere, such as the plan's random validation
poses. This module compares the current model's test-set errors with the folds' and names the
joints whose test values lie far from every training value, so that "at the measurement noise"
is never said of a model whose own test set says otherwise.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy import stats

from campaign.tolerances import TEST_SET_ALPHA, TEST_SET_GAP_SHARE, TEST_SET_MARGIN


@dataclass(frozen=True)
class JointCoverage:
    """How the training poses cover one joint where the test poses are: ``distinct`` training
    values (to 1 mrad), and the test poses' median distance to the nearest training value, as a
    share of the joint's range over both sets."""

    joint: str
    distinct: int
    gap_share: float

    def text(self) -> str:
        return (f"{self.joint} at {self.distinct} value{'s' if self.distinct != 1 else ''} (the test poses lie a "
                f"median {100 * self.gap_share:.0f} % of its range from them)")


@dataclass(frozen=True)
class TestSetCheck:
    """The current model's mean position error on the test set against the folds' held-out mean
    (one-sided Welch t on the per-pose errors), and the joints the training poses leave sparse."""

    n_test: int
    mean_mm: float
    folds_mean_mm: float
    p_value: float
    sparse: tuple  # JointCoverage of the joints whose test values the training poses do not reach

    @property
    def ratio(self) -> float:
        return self.mean_mm / self.folds_mean_mm if self.folds_mean_mm > 0 else float("inf")

    @property
    def holds(self) -> bool:
        """False when the test set is significantly (TEST_SET_ALPHA) and materially (TEST_SET_MARGIN)
        worse than the folds: the folds' figure does not describe the model beyond the training poses."""
        return not (self.p_value < TEST_SET_ALPHA and self.ratio > 1.0 + TEST_SET_MARGIN)

    @property
    def sparse_joints(self) -> list:
        return [c.joint for c in self.sparse]

    def text(self) -> str:
        head = (f"test set: mean {self.mean_mm:.4f} mm on {self.n_test} poses, {self.ratio:.2f}× the folds' "
                f"{self.folds_mean_mm:.4f} mm (one-sided p = {self.p_value:.2g})")
        if self.holds:
            return head + ": the folds' figure holds on it"
        where = ("; the training poses hold " + ", ".join(c.text() for c in self.sparse)) if self.sparse else ""
        return (head + ": the model does not hold on the test poses, whatever the folds say" + where
                + " — an error that depends on what the training poses do not vary is invisible to the folds")

    def as_json(self) -> dict:
        return {"n_poses": self.n_test, "mean_position_mm": self.mean_mm, "folds_mean_position_mm": self.folds_mean_mm,
                "ratio_to_folds": self.ratio, "p_value": self.p_value, "holds": self.holds,
                "sparse_joints": [{"joint": c.joint, "distinct_training_values": c.distinct,
                                   "test_gap_share_of_range": c.gap_share} for c in self.sparse]}


def joint_coverage(q_train, q_test) -> list:
    """Every joint's :class:`JointCoverage` of the test poses by the training poses."""
    out = []
    for j in range(q_train.shape[1]):
        tr, te = np.asarray(q_train[:, j], dtype=float), np.asarray(q_test[:, j], dtype=float)
        span = float(max(tr.max(), te.max()) - min(tr.min(), te.min()))
        values = np.unique(np.round(tr, 3))
        gap = np.min(np.abs(te[:, None] - values[None, :]), axis=1)
        out.append(JointCoverage(f"q{j + 1}", int(len(values)), float(np.median(gap) / span) if span > 0 else 0.0))
    return out


def check_test_set(errors_test_mm, errors_folds_mm, q_train, q_test) -> TestSetCheck | None:
    """The check from the current model's per-pose position errors on the test set and on the
    held-out folds (mm), and the joint angles of both; None with fewer than 3 test poses."""
    e_t = np.asarray(errors_test_mm, dtype=float)
    e_f = np.asarray(errors_folds_mm, dtype=float)
    e_t, e_f = e_t[np.isfinite(e_t)], e_f[np.isfinite(e_f)]
    if len(e_t) < 3 or len(e_f) < 3:
        return None
    p = float(stats.ttest_ind(e_t, e_f, equal_var=False, alternative="greater").pvalue)
    p = 1.0 if not np.isfinite(p) else p
    sparse = tuple(c for c in joint_coverage(q_train, q_test) if c.gap_share > TEST_SET_GAP_SHARE)
    return TestSetCheck(len(e_t), float(e_t.mean()), float(e_f.mean()), p, sparse)
