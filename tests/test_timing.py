"""Motion timing (campaign.plan.timing): Ruckig's durations against a hand-derived closed form."""

import numpy as np
import pytest

from campaign.errors import ConfigError
from campaign.plan.grid import PAPER_CELLS, Grid
from campaign.plan.timing import GridTimes, joint_min_time, path_time, rest_to_rest_time, ruckig_trajectory
from campaign.plan.tour import segment_samples


def closed_form_time(d, v, a, j):
    """Minimum rest-to-rest time of one axis over distance d ≥ 0 under limits v, a, j, derived
    by hand from the symmetric seven-phase jerk-limited profile (accelerate, cruise, brake).

    Accelerating from rest to a peak velocity vp takes t(vp) = vp/a + a/j when the acceleration
    limit is reached (vp ≥ a²/j), else 2·sqrt(vp/j); it covers vp·t(vp)/2. With a cruise phase,
    vp = v; without, vp solves d = vp·t(vp)."""
    t_acc = v / a + a / j if v >= a * a / j else 2.0 * np.sqrt(v / j)
    d_acc = v * t_acc / 2.0
    if d >= 2 * d_acc:
        return 2 * t_acc + (d - 2 * d_acc) / v
    # full acceleration phase: d = vp (vp/a + a/j)  →  vp² / a + vp a / j − d = 0
    vp = 0.5 * a * (-a / j + np.sqrt((a / j) ** 2 + 4 * d / a))
    if vp >= a * a / j:
        return 2 * (vp / a + a / j)
    # triangular acceleration: d = 2 vp sqrt(vp/j)  →  vp = (d sqrt(j) / 2)^(2/3)
    vp = (d * np.sqrt(j) / 2.0) ** (2.0 / 3.0)
    return 4.0 * np.sqrt(vp / j)


def test_the_closed_form_on_a_hand_computed_move():
    # v = 1, a = 2, j = 10: t_acc = 0.5 + 0.2 = 0.7 s covering 0.35 rad; 2 rad → 1.4 s + 1.3 rad at 1 rad/s
    assert closed_form_time(2.0, 1.0, 2.0, 10.0) == pytest.approx(2.7, abs=1e-12)


@pytest.mark.parametrize("v, a, j", [(1.0, 2.0, 10.0),  # all three regimes
                                     (1.0, 5.0, 10.0),  # v < a²/j: the acceleration limit is never reached
                                     (3.5, 12.0, 60.0)])
def test_ruckig_one_axis_time_equals_the_closed_form_in_every_regime(v, a, j):
    d = np.concatenate([[0.0, 1e-6], np.geomspace(1e-4, 10.0, 60)])
    ref = np.array([closed_form_time(x, v, a, j) for x in d])
    np.testing.assert_allclose(joint_min_time(d, v, a, j), ref, rtol=1e-9, atol=1e-12)
    np.testing.assert_allclose(joint_min_time(-d, v, a, j), ref, rtol=1e-9, atol=1e-12)


def test_move_time_is_the_slowest_joints_closed_form_and_the_motion_a_straight_joint_line(robot, rng):
    qa = rng.uniform(robot.q_lower, robot.q_upper, size=(30, 6))
    qb = rng.uniform(robot.q_lower, robot.q_upper, size=(30, 6))
    ref = np.array([max(closed_form_time(abs(b[i] - a[i]), robot.max_velocity[i], robot.max_acceleration[i],
                                         robot.max_jerk[i]) for i in range(6)) for a, b in zip(qa, qb)])
    t = rest_to_rest_time(robot, qa, qb)
    assert t.shape == (30,)
    np.testing.assert_allclose(t, ref, rtol=1e-9)
    assert path_time(robot, np.stack([qa[0], qb[0], qa[1]])) == pytest.approx(
        ref[0] + max(closed_form_time(abs(qa[1][i] - qb[0][i]), robot.max_velocity[i], robot.max_acceleration[i],
                                      robot.max_jerk[i]) for i in range(6)), rel=1e-9)
    for a, b, t_ab in zip(qa[:10], qb[:10], t[:10]):
        duration, traj = ruckig_trajectory(robot, a, b)
        assert duration == pytest.approx(t_ab, abs=1e-12)
        for s in np.linspace(0, duration, 7):
            lam = (np.array(traj.at_time(s)[0]) - a) / (b - a)
            assert np.ptp(lam) < 1e-8  # every joint at the same fraction of its way
    samples = segment_samples(np.zeros(6), np.full(6, 0.5), np.deg2rad(1.0))
    assert np.max(np.abs(np.diff(samples, axis=0))) <= np.deg2rad(1.0) + 1e-12


def test_grid_lookup_times_equal_ruckig_on_grid_poses(robot, rng):
    g = Grid.for_robot(robot, PAPER_CELLS)
    times = GridTimes(robot, g)
    idx = rng.choice(g.size, 40, replace=False)
    A, B = g.cell_indices(idx[:20]), g.cell_indices(idx[20:])
    np.testing.assert_allclose(times.pair(A, B), rest_to_rest_time(robot, g.q(idx[:20]), g.q(idx[20:])), rtol=1e-12)


def test_limits_that_cannot_time_a_move_are_one_config_error():
    with pytest.raises(ConfigError, match="max_jerk must be finite and positive"):
        joint_min_time([0.1], 1.0, 2.0, 0.0)
