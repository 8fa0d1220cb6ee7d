"""Inverse kinematics of any pose map: joint vectors q with ``pose(q) = T_target``.

One solver for every model a command inverts: the nominal chain (the ISO 9283 test poses),
a calibrated stage with its effects and network (`campaign compensate`). Levenberg-Marquardt
per pose, batched over poses; the Jacobian by central differences of ``pose``, so whatever the
map contains is inverted exactly.
"""

from __future__ import annotations

from typing import Callable

import numpy as np

from campaign.model.kinematics import forward, pose_error


def solve_pose(pose: Callable, T_target, q_start, *, rows: Callable | None = None, tol_m: float = 1e-9,
               tol_rad: float = 1e-8, max_iter: int = 50, step_rad: float = 1e-6, max_step_rad: float = 0.1):
    """Joint vectors q (n, N) with ``pose(q) ≈ T_target`` (n, 4, 4), iterated from q_start (n, N).

    pose(q, idx) → (m, 4, 4): the pose of the tool for joint vectors q (m, N) of the poses ``idx``
    (m,) (so a map with per-pose context takes its rows). A Newton step where the Jacobian is well
    conditioned, damped near a singularity, steps of at most ``max_step_rad``. Returns (q,
    residual (n, 6) = pose_error(pose(q), T_target) in m and rad, converged (n,) bool).
    """
    T_target = np.asarray(T_target, dtype=float).reshape(-1, 4, 4)
    q = np.array(q_start, dtype=float).reshape(len(T_target), -1)
    everyone = np.arange(len(q))
    lam = np.full(len(q), 1e-9)
    r = pose_error(pose(q, everyone), T_target)

    def done(res):
        return (np.linalg.norm(res[:, :3], axis=1) <= tol_m) & (np.linalg.norm(res[:, 3:], axis=1) <= tol_rad)

    N = q.shape[1]
    for _ in range(max_iter):
        idx = np.flatnonzero(~done(r))
        if len(idx) == 0:
            break
        J = np.empty((len(idx), 6, N))
        for j in range(N):
            dq = np.zeros(N)
            dq[j] = step_rad
            r_plus = pose_error(pose(q[idx] + dq, idx), T_target[idx])
            r_minus = pose_error(pose(q[idx] - dq, idx), T_target[idx])
            J[:, :, j] = (r_plus - r_minus) / (2 * step_rad)
        JtJ = np.einsum("nki,nkj->nij", J, J)
        g = np.einsum("nki,nk->ni", J, r[idx])
        damping = lam[idx, None, None] * (np.eye(N) * np.einsum("nii->ni", JtJ)[:, None, :] + 1e-12 * np.eye(N))
        step = -np.linalg.solve(JtJ + damping, g[:, :, None])[:, :, 0]
        big = np.abs(step).max(axis=1) > max_step_rad
        step[big] *= (max_step_rad / np.abs(step[big]).max(axis=1))[:, None]
        r_new = pose_error(pose(q[idx] + step, idx), T_target[idx])
        better = np.sum(r_new ** 2, axis=1) < np.sum(r[idx] ** 2, axis=1)
        q[idx[better]] += step[better]
        r[idx[better]] = r_new[better]
        lam[idx] = np.where(better, np.maximum(lam[idx] / 10, 1e-12), lam[idx] * 10)
    converged = (np.linalg.norm(r[:, :3], axis=1) <= 10 * tol_m) & (np.linalg.norm(r[:, 3:], axis=1) <= 10 * tol_rad)
    return q, r, converged


def nominal_ik(robot, T_target, q_start, **kw):
    """:func:`solve_pose` for the nominal chain of ``robot`` (its tool frame E in F_I)."""
    return solve_pose(lambda q, idx: forward(robot, q), T_target, q_start, **kw)
