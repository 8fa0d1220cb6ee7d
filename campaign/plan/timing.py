"""Motion timing: how long the robot takes between two poses, computed by Ruckig.

Every motion of a campaign is a rest-to-rest, time-optimal, jerk-limited move under the
robot's per-joint limits (``max_velocity`` rad/s, ``max_acceleration`` rad/s², ``max_jerk``
rad/s³ from robot.yaml). Its duration is what Ruckig computes for that move
(:func:`rest_to_rest_time`, :func:`path_time`: the plan's motion time, the simulated cell's
clock). With phase synchronisation every joint follows the same normalised profile, so the
motion is a straight line in joint space (tour.py samples it as one for the collision check)
and its duration is the largest of the joints' single-axis minimum times.

That last fact makes the tour ordering cheap: the time between two grid poses is the maximum
over joints of a per-joint table indexed by the cell difference (:class:`GridTimes`). The
tables hold the closed form of the one-axis profile (:func:`joint_min_time`), which equals
Ruckig's one-axis duration to the last bit or one (tests/test_timing.py, every regime); it is
kept for the tables because the ordering breaks ties between equally short tours by those
values, and Ruckig's 1-ulp differences would reorder a few equal-time neighbours of the
published demo's tour (and with them the neural network's cross-validation folds). Ruckig's
calculation costs about 6 µs a move, so the final tour's path time (about 10,000 moves on
the default cell) takes well under a second.
"""

from __future__ import annotations

import numpy as np

from campaign.errors import ConfigError


def _limits(robot):
    """(v, a, j) per joint, each (N,), from the robot's description."""
    return (np.asarray(robot.max_velocity, dtype=float), np.asarray(robot.max_acceleration, dtype=float),
            np.asarray(robot.max_jerk, dtype=float))


class _Ruckig:
    """One reusable Ruckig instance with its input and output buffers for ``dofs`` axes."""

    def __init__(self, v, a, j, synchronization="phase"):
        from ruckig import InputParameter, Ruckig, Synchronization, Trajectory

        v, a, j = (np.atleast_1d(np.asarray(x, dtype=float)) for x in (v, a, j))
        for name, x in (("max_velocity", v), ("max_acceleration", a), ("max_jerk", j)):
            if not np.all(np.isfinite(x) & (x > 0)):
                raise ConfigError(f"robot {name} must be finite and positive for the motion timing, got {x.tolist()}")
        self.dofs = len(v)
        self.otg = Ruckig(self.dofs)
        self.inp = InputParameter(self.dofs)
        self.inp.max_velocity = v.tolist()
        self.inp.max_acceleration = a.tolist()
        self.inp.max_jerk = j.tolist()
        self.inp.synchronization = {"phase": Synchronization.Phase, "time": Synchronization.Time}[synchronization]
        self.traj = Trajectory(self.dofs)
        self._ok = None

    def duration(self, qa, qb) -> float:
        """Duration (s) of the rest-to-rest move qa → qb (lists of ``dofs`` floats, rad)."""
        from ruckig import Result

        self.inp.current_position = qa
        self.inp.target_position = qb
        res = self.otg.calculate(self.inp, self.traj)
        if res not in (Result.Working, Result.Finished):
            raise ConfigError(f"ruckig could not time the move {qa} -> {qb}: {res}")
        return self.traj.duration


def ruckig_trajectory(robot, qa, qb):
    """Ruckig's time-optimal, phase-synchronised rest-to-rest trajectory qa → qb (N,) rad.

    Returns (duration s, ruckig.Trajectory) — the trajectory's ``at_time(t)`` gives the
    position, velocity and acceleration at time t."""
    r = _Ruckig(*_limits(robot))
    duration = r.duration([float(x) for x in qa], [float(x) for x in qb])
    return duration, r.traj


def joint_min_time(d, v, a, j):
    """Minimum rest-to-rest time (s) of one axis moving distances |d| (rad, any shape) under the
    limits v (rad/s), a (rad/s²), j (rad/s³): the closed form of the symmetric jerk-limited
    profile (equal to Ruckig's one-axis duration, :func:`ruckig_joint_time`). Vectorised.

    Accelerating from rest to a peak velocity vp takes t(vp) = vp/a + a/j when the acceleration
    limit is reached (vp ≥ a²/j), else 2·sqrt(vp/j), and covers vp·t(vp)/2; with a cruise phase
    vp = v, without one vp solves d = vp·t(vp).
    """
    d = np.abs(np.asarray(d, dtype=float))
    t_acc = v / a + a / j if v >= a * a / j else 2.0 * np.sqrt(v / j)
    d_acc = v * t_acc / 2.0  # distance of a full acceleration phase up to v
    cruise = d >= 2 * d_acc
    out = np.empty_like(d)
    out[cruise] = 2 * t_acc + (d[cruise] - 2 * d_acc) / v
    ds = d[~cruise]
    vp = 0.5 * a * (-a / j + np.sqrt((a / j) ** 2 + 4 * ds / a))  # d = vp (vp/a + a/j)
    full_acc = vp >= a * a / j
    vp_tri = (ds * np.sqrt(j) / 2.0) ** (2.0 / 3.0)  # triangular acceleration: d = 2 vp sqrt(vp/j)
    out[~cruise] = np.where(full_acc, 2 * (vp / a + a / j), 4.0 * np.sqrt(vp_tri / j))
    return out


def ruckig_joint_time(d, v, a, j):
    """Ruckig's minimum rest-to-rest time (s) of one axis over distances |d| (rad, any shape)."""
    d = np.abs(np.asarray(d, dtype=float))
    r = _Ruckig(v, a, j)
    return np.array([r.duration([0.0], [x]) for x in d.reshape(-1).tolist()]).reshape(d.shape)


def rest_to_rest_time(robot, qa, qb):
    """Synchronised rest-to-rest duration (s), shape (…,), between joint vectors qa, qb (…, N) rad."""
    qa, qb = np.broadcast_arrays(np.asarray(qa, dtype=float), np.asarray(qb, dtype=float))
    shape = qa.shape[:-1]
    r = _Ruckig(*_limits(robot))
    A, B = qa.reshape(-1, qa.shape[-1]).tolist(), qb.reshape(-1, qb.shape[-1]).tolist()
    return np.array([r.duration(a, b) for a, b in zip(A, B)], dtype=float).reshape(shape)


def path_time(robot, Q) -> float:
    """Total travel time (s) of a path through joint vectors Q (n, N) rad, resting at each."""
    if len(Q) < 2:
        return 0.0
    Q = np.asarray(Q, dtype=float)
    return float(np.sum(rest_to_rest_time(robot, Q[:-1], Q[1:])))


class GridTimes:
    """Travel times between grid poses by lookup, for the tour ordering: for grid poses, |Δq_i|
    is a whole number of cells, so each joint's time is a table (:func:`joint_min_time`)
    indexed by the cell difference, and a move's time is the largest of its joints' entries."""

    def __init__(self, robot, grid):
        v, a, j = _limits(robot)
        self.lut = [joint_min_time(np.arange(grid.cells[i]) * grid.step[i], v[i], a[i], j[i])
                    for i in range(len(grid.cells))]

    def from_one(self, c, C):
        """Times (m,) s from cell vector c (N,) to cell vectors C (m, N)."""
        t = self.lut[0][np.abs(C[:, 0] - c[0])]
        for i in range(1, len(self.lut)):
            t = np.maximum(t, self.lut[i][np.abs(C[:, i] - c[i])])
        return t

    def pair(self, A, B):
        """Times (…,) s between cell vectors A and B (…, N)."""
        d = np.abs(A - B)
        t = self.lut[0][d[..., 0]]
        for i in range(1, len(self.lut)):
            t = np.maximum(t, self.lut[i][d[..., i]])
        return t
