"""Motion timing (campaign.plan.timing): Ruckig's durations, and the closed form the ordering's tables use."""

import numpy as np
import pytest

from campaign.errors import ConfigError
from campaign.plan.grid import PAPER_CELLS, Grid
from campaign.plan.timing import (GridTimes, joint_min_time, path_time, rest_to_rest_time, ruckig_joint_time,
                                  ruckig_trajectory)
from campaign.plan.tour import segment_samples


def test_the_closed_form_on_a_hand_computed_move():
    # v = 1, a = 2, j = 10: t_acc = 0.5 + 0.2 = 0.7 s covering 0.35 rad; 2 rad → 1.4 s + 1.3 rad at 1 rad/s
    assert joint_min_time(np.array([2.0]), 1.0, 2.0, 10.0)[0] == pytest.approx(2.7, abs=1e-12)
    assert ruckig_joint_time(np.array([2.0]), 1.0, 2.0, 10.0)[0] == pytest.approx(2.7, abs=1e-12)


@pytest.mark.parametrize("v, a, j", [(1.0, 2.0, 10.0),  # all three regimes
                                     (1.0, 5.0, 10.0),  # v < a²/j: the acceleration limit is never reached
                                     (3.5, 12.0, 60.0)])
def test_the_closed_form_equals_ruckigs_one_axis_time_in_every_regime(v, a, j):
    d = np.concatenate([[0.0, 1e-6], np.geomspace(1e-4, 10.0, 60)])
    ref = ruckig_joint_time(d, v, a, j)
    np.testing.assert_allclose(joint_min_time(d, v, a, j), ref, rtol=1e-12, atol=1e-15)
    np.testing.assert_allclose(joint_min_time(-d, v, a, j), ref, rtol=1e-12, atol=1e-15)
    # the distances span the regimes: below the triangular-acceleration limit 2a³/j², and cruising
    d_acc = v * (v / a + a / j if v >= a * a / j else 2 * np.sqrt(v / j)) / 2
    assert np.sum(d < min(2 * a ** 3 / j ** 2, 2 * d_acc)) > 5 and np.sum(d > 2 * d_acc) > 5


def test_move_time_is_the_slowest_joints_closed_form_and_the_motion_a_straight_joint_line(robot, rng):
    qa = rng.uniform(robot.q_lower, robot.q_upper, size=(30, 6))
    qb = rng.uniform(robot.q_lower, robot.q_upper, size=(30, 6))
    ref = np.max([joint_min_time(np.abs(qb[:, i] - qa[:, i]), robot.max_velocity[i], robot.max_acceleration[i],
                                 robot.max_jerk[i]) for i in range(6)], axis=0)
    t = rest_to_rest_time(robot, qa, qb)
    assert t.shape == (30,)
    np.testing.assert_allclose(t, ref, rtol=1e-9)
    assert path_time(robot, np.stack([qa[0], qb[0], qa[1]])) == pytest.approx(
        ref[0] + rest_to_rest_time(robot, qb[0], qa[1]), rel=1e-12)
    for a, b, t_ab in zip(qa[:10], qb[:10], t[:10]):
        duration, traj = ruckig_trajectory(robot, a, b)
        assert duration == pytest.approx(t_ab, abs=1e-12)
        for s in np.linspace(0, duration, 7):
            lam = (np.array(traj.at_time(s)[0]) - a) / (b - a)
            assert np.ptp(lam) < 1e-8  # every joint at the same fraction of its way
    samples = segment_samples(np.zeros(6), np.full(6, 0.5), np.deg2rad(1.0))
    assert np.max(np.abs(np.diff(samples, axis=0))) <= np.deg2rad(1.0) + 1e-12


def test_the_orderings_grid_lookup_times_equal_ruckig_on_grid_poses(robot, rng):
    g = Grid.for_robot(robot, PAPER_CELLS)
    times = GridTimes(robot, g)
    idx = rng.choice(g.size, 40, replace=False)
    A, B = g.cell_indices(idx[:20]), g.cell_indices(idx[20:])
    np.testing.assert_allclose(times.pair(A, B), rest_to_rest_time(robot, g.q(idx[:20]), g.q(idx[20:])), rtol=1e-12)


def test_limits_that_cannot_time_a_move_are_one_config_error():
    with pytest.raises(ConfigError, match="max_jerk must be finite and positive"):
        ruckig_joint_time([0.1], 1.0, 2.0, 0.0)
