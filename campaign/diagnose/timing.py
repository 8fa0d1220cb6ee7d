"""Time told from pose: do the same poses, measured at different times, move?

The model-free test ranks its inputs by permutation importance, and a campaign's tour orders
its poses, so time (and a temperature that follows it) stands in for the joints the tour
sweeps. Whenever time or temperature ranks among the inputs, this test decides: the poses the
run measured more than once, at times further apart than
:data:`campaign.tolerances.REPEAT_CLOSE_S` (repeats spread over the campaign, poses measured
again by `auto`, the driver's drift checks: :func:`campaign.measure.drift.drift_readings`), compared
with the noise of readings close in time.

Statistic: the measurements of one pose form *visits* (readings closer in time than
REPEAT_CLOSE_S, e.g. back-to-back repeats); with visit means x̄_v of n_v readings, the overall
mean x̄ and the floor's σ per coordinate, ``Σ_v n_v Σ_c ((x̄_v,c − x̄_c) / σ_c)²`` follows
χ²(3 (V − 1)) per pose when the pose does not move and σ is known (a stated noise; a floor from
repeats is itself estimated: each coordinate's statistic over its degrees of freedom then follows
an F distribution, the three p-values combined by Fisher's method) (the drift checks' readings are the reference
pose's). Drift checks stored as distances only add the last one's d from the reference's first
reading: d² / (2 σ̄²) ~ χ²(3). The p-value is of the summed statistic. None without such poses or
without a floor.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy import stats

from campaign.tolerances import REPEAT_CLOSE_S

#: the inputs a time test speaks for
TIME_INPUTS = ("time_s", "temperature_c")
#: a test that finds no movement takes time out of the inputs only if it would have seen, with at
#: least this probability, the change over time the flexible regressor predicts at its readings
MIN_POWER = 0.5


@dataclass(frozen=True)
class TimeTest:
    """The same poses at different times against the noise: chi² ``statistic`` with ``dof``,
    ``p_value``; ``poses`` distinct poses with ``readings`` readings in ``visits`` visits, over
    ``span_h`` hours; ``drift_checks``: the drift check's distances used (0 or 1); ``sigma_dof``:
    the floor's degrees of freedom per coordinate (0: a stated noise)."""

    statistic: float
    dof: int
    p_value: float
    poses: int
    readings: int
    visits: int
    span_h: float
    drift_checks: int
    alpha: float
    sigma_dof: int = 0
    #: the probability that the test sees the change over time the flexible regressor predicts at
    #: these readings (None: not asked); below MIN_POWER a test that finds no movement says nothing
    power: float | None = None

    @property
    def conclusive(self) -> bool:
        """Moved, or had the power to see the change the regressor predicts (MIN_POWER; unknown: yes)."""
        return self.moved or self.power is None or self.power >= MIN_POWER

    @property
    def moved(self) -> bool:
        """The poses moved over time beyond the noise (p < alpha)."""
        return self.p_value < self.alpha

    def as_json(self) -> dict:
        return {"statistic": self.statistic, "dof": self.dof, "p_value": self.p_value, "poses_used": self.poses,
                "readings": self.readings, "visits": self.visits, "span_h": self.span_h,
                "drift_checks": self.drift_checks, "alpha": self.alpha, "moved": self.moved,
                "floor_dof": self.sigma_dof, "power": self.power}

    def text(self) -> str:
        what = (f"{self.poses} pose{'' if self.poses == 1 else 's'} measured again over {self.span_h:.2g} h ({self.readings} readings"
                + (", the drift check" if self.drift_checks else "") + ")")
        if self.moved:
            return f"time test: {what} moved beyond the noise (χ² {self.statistic:.1f} on {self.dof}, p = {self.p_value:.2g})"
        if not self.conclusive:
            return (f"time test: {what} did not move beyond the noise (χ² {self.statistic:.1f} on {self.dof}, "
                    f"p = {self.p_value:.2g}), but would have seen the change over time the regressor finds with "
                    f"probability {self.power:.2f} only: it does not decide")
        return (f"time test: {what} did not move beyond the noise (χ² {self.statistic:.1f} on {self.dof}, "
                f"p = {self.p_value:.2g}): time stands in for the poses the tour sweeps")


def same_pose_visits(group, time_s) -> list:
    """For each pose measured at different times: a list of index arrays, one per visit
    (readings at most REPEAT_CLOSE_S apart), in time order; group (n,) the pose of each reading
    (:func:`campaign.measure.drift.same_pose_groups`), time_s (n,) s."""
    group = np.asarray(group)
    t = np.asarray(time_s, dtype=float)
    if len(group) < 2 or not np.isfinite(t).all():
        return []
    out = []
    for g in np.unique(group):
        idx = np.flatnonzero(group == g)
        if len(idx) < 2:
            continue
        idx = idx[np.argsort(t[idx], kind="stable")]
        cuts = np.flatnonzero(np.diff(t[idx]) > REPEAT_CLOSE_S) + 1
        visits = np.split(idx, cuts)
        if len(visits) >= 2:
            out.append(visits)
    return out


def time_test(xyz, group, time_s, sigma_position_m, *, sigma_dof: int = 0, drift_check_m=None,
              alpha: float = 0.01) -> TimeTest | None:
    """The test of the module docstring on measured positions xyz (n, 3) m of the poses ``group``
    (n,) (one label a pose: the reference pose's drift checks among its readings) at times time_s
    (n,) s, with the floor's σ (3,) m per coordinate, estimated on ``sigma_dof`` degrees of freedom
    (0: known, a stated noise; else the statistic over its degrees of freedom is F-distributed, the
    floor's own sampling error counted: 9 back-to-back differences leave σ uncertain by a quarter);
    ``drift_check_m``: drift checks stored as
    distances only (m, from the reference's first reading, in time order; the last is used). None
    when no pose was measured at two times and no drift check exists, or without σ."""
    if sigma_position_m is None:
        return None
    sigma = np.asarray(sigma_position_m, dtype=float).reshape(3)
    if not np.all(sigma > 0):
        return None
    xyz = np.asarray(xyz, dtype=float)
    t = np.asarray(time_s, dtype=float)
    chi2, dof, readings, visits, poses, t_lo, t_hi = np.zeros(3), 0, 0, 0, 0, np.inf, -np.inf
    for pose in same_pose_visits(group, t):
        means = np.array([xyz[v].mean(axis=0) for v in pose])
        n_v = np.array([len(v) for v in pose], dtype=float)
        centre = (n_v[:, None] * means).sum(axis=0) / n_v.sum()
        chi2 += np.sum(n_v[:, None] * ((means - centre) / sigma) ** 2, axis=0)
        dof += len(pose) - 1  # per coordinate
        readings += int(n_v.sum())
        visits += len(pose)
        poses += 1
        t_lo, t_hi = min(t_lo, t[pose[0][0]]), max(t_hi, t[pose[-1][-1]])
    checks = 0
    if drift_check_m:  # a distance: its square spread evenly over the three coordinates
        d = float(drift_check_m[-1])
        chi2 += d ** 2 / (2.0 * float(np.mean(sigma ** 2))) / 3.0
        dof += 1
        checks = 1
    if dof == 0:
        return None
    span_h = float(t_hi - t_lo) / 3600.0 if poses else 0.0
    return TimeTest(float(chi2.sum()), int(3 * dof), _p_value(chi2, dof, sigma_dof), poses, readings, visits, span_h,
                    checks, float(alpha), int(sigma_dof))


def _p_value(chi2, dof: int, sigma_dof: int) -> float:
    """p of the per-coordinate statistics chi2 (3,) on ``dof`` each: χ²(3 dof) of their sum for a
    known σ; for σ estimated on ``sigma_dof`` (pooled over the three coordinates), each coordinate's
    ratio is F(dof, sigma_dof / 3) and the three p-values are combined by Fisher's method."""
    if sigma_dof <= 0:
        return float(stats.chi2.sf(float(chi2.sum()), 3 * dof))
    p = stats.f.sf(chi2 / dof, dof, max(sigma_dof / 3.0, 1.0))
    return float(stats.chi2.sf(-2.0 * float(np.sum(np.log(np.maximum(p, 1e-300)))), 6))


def rank_by_time_test(depends_on, test: TimeTest | None) -> list:
    """The inputs ranked by the time test: time and temperature first when the same poses moved
    over time (time alone when the flexible regressor ranked neither: the test itself found the
    error depends on time), taken out when they did not (time then stands in for the poses), as
    they were when there is no test or one too weak to see what the regressor predicts
    (:attr:`TimeTest.conclusive`)."""
    depends_on = list(depends_on)
    if test is None or not test.conclusive:
        return depends_on
    timed = [i for i in depends_on if i in TIME_INPUTS]
    rest = [i for i in depends_on if i not in TIME_INPUTS]
    return (timed or ["time_s"]) + rest if test.moved else rest
