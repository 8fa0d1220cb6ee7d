"""Batched forward kinematics with the paper's 48 geometric error parameters.

Parameter vector ``p_e`` (48,), ordered as Table 2: for each transform
k in (I0, 01, 12, 23, 34, 45, 56, 6E) the six entries
``pL_k_x, pL_k_y, pL_k_z`` (m), ``pR_k_x, pR_k_y`` (rad) and a third rotation,
``pR_k_z`` for I0 and 6E, ``pq<i>`` for the joint transforms (rad), so that (eqs. 6-11)

    R̂_k = R̄_k R(pR_k_x, pR_k_y, c_k),   c_k = q_i + pq_i  or  pR_k_z,
    t̂_k = t̄_k + pL_k.

Pose error (eq. 13): ``Δz = (t_model - t_meas, log(R_model R_measᵀ))``, position in m,
rotation vector in rad, both resolved in F_I.
"""

from __future__ import annotations

import numpy as np

from campaign.model.robot import TRANSFORM_NAMES, RobotModel
from campaign.model.rotations import cardan_xyz, inverse_left_jacobian, matrix_to_rotvec, rot_x, rot_y

N_PARAMS = 48

#: Poses evaluated together; bounds memory at about 2 kB a pose in the Jacobian.
CHUNK = 65536


def _make_names():
    names = []
    for k, tname in enumerate(TRANSFORM_NAMES):
        names += [f"pL_{tname}_x", f"pL_{tname}_y", f"pL_{tname}_z", f"pR_{tname}_x", f"pR_{tname}_y"]
        names.append(f"pq{k}" if 1 <= k <= 6 else f"pR_{tname}_z")
    return tuple(names)


#: Names of the 48 error parameters, Table 2's order.
PARAM_NAMES = _make_names()
#: SI unit of each parameter.
PARAM_UNITS = tuple("m" if n.startswith("pL") else "rad" for n in PARAM_NAMES)
#: Index of pq1..pq6 in ``p_e``.
JOINT_OFFSET_INDEX = tuple(6 * k + 5 for k in range(1, 7))


def _as_q(q):
    q = np.asarray(q, dtype=float)
    if q.ndim == 1:
        q = q[None, :]
    if q.ndim != 2 or q.shape[1] != 6:
        raise ValueError(f"q must have shape (n, 6), got {q.shape}")
    return q


def _as_p(p_e):
    if p_e is None:
        return np.zeros(N_PARAMS)
    p = np.asarray(p_e, dtype=float)
    if p.shape != (N_PARAMS,):
        raise ValueError(f"p_e must have shape (48,), got {p.shape}")
    return p


def _transform_rotations(robot: RobotModel, q, p):
    """Rotations R̂_k for each pose: list of 8 arrays (n, 3, 3) (or (3, 3) if constant)."""
    out = []
    for k in range(8):
        a, b, c = p[6 * k + 3], p[6 * k + 4], p[6 * k + 5]
        if 1 <= k <= 6:
            out.append(robot.R_nominal[k] @ cardan_xyz(a, b, q[:, k - 1] + c))
        else:
            out.append(robot.R_nominal[k] @ cardan_xyz(a, b, c))
    return out


def frames(robot: RobotModel, q, p_e=None):
    """Poses of frames 0..6 and E in F_I for each joint vector.

    Returns ``(R, t)`` with ``R`` of shape (n, 8, 3, 3) and ``t`` (n, 8, 3): entry k is
    the frame *after* transform k (0 -> F_0, ..., 7 -> F_E). Not chunked; use for
    moderate n.
    """
    q = _as_q(q)
    p = _as_p(p_e)
    n = q.shape[0]
    Rk = _transform_rotations(robot, q, p)
    R_out = np.empty((n, 8, 3, 3))
    t_out = np.empty((n, 8, 3))
    R = np.broadcast_to(np.eye(3), (n, 3, 3))
    t = np.zeros((n, 3))
    for k in range(8):
        tk = robot.t_nominal[k] + p[6 * k : 6 * k + 3]
        t = t + R @ tk
        R = R @ Rk[k]
        R_out[:, k] = R
        t_out[:, k] = t
    return R_out, t_out


def forward(robot: RobotModel, q, p_e=None, *, chunk: int = CHUNK):
    """``T_IE(q, p_e)`` for an array of joint vectors.

    q: (n, 6) rad; p_e: (48,) or None for the nominal model.
    Returns (n, 4, 4) homogeneous transforms (m). Memory is bounded by ``chunk``.
    """
    q = _as_q(q)
    p = _as_p(p_e)
    n = q.shape[0]
    T = np.zeros((n, 4, 4))
    T[:, 3, 3] = 1.0
    for s in range(0, n, chunk):
        qs = q[s : s + chunk]
        Rk = _transform_rotations(robot, qs, p)
        R = np.broadcast_to(np.eye(3), (qs.shape[0], 3, 3))
        t = np.zeros((qs.shape[0], 3))
        for k in range(8):
            t = t + R @ (robot.t_nominal[k] + p[6 * k : 6 * k + 3])
            R = R @ Rk[k]
        T[s : s + chunk, :3, :3] = R
        T[s : s + chunk, :3, 3] = t
    return T


def pose_error(T_model, T_meas):
    """Δz of eq. (13): (n, 6) = (t_model - t_meas [m], log(R_model R_measᵀ) [rad])."""
    T_model = np.asarray(T_model, dtype=float)
    T_meas = np.asarray(T_meas, dtype=float)
    dt = T_model[..., :3, 3] - T_meas[..., :3, 3]
    dphi = matrix_to_rotvec(T_model[..., :3, :3] @ np.swapaxes(T_meas[..., :3, :3], -1, -2))
    return np.concatenate([dt, dphi], axis=-1)


def error_jacobian(robot: RobotModel, q, p_e=None, T_meas=None, *, chunk: int = CHUNK):
    """Analytic ``∂Δz/∂p_e`` for each pose: (n, 6, 48).

    Rows 0-2 are ∂t_IE/∂p (m per unit). Rows 3-5 are the derivative of the rotation-vector
    error: if ``T_meas`` is given, ``J_l⁻¹(Δφ) ω`` (exact); without it, the spatial
    angular velocity ω itself (exact at Δφ = 0).
    """
    q = _as_q(q)
    p = _as_p(p_e)
    n = q.shape[0]
    J = np.empty((n, 6, N_PARAMS))
    ex, ey, ez = np.eye(3)
    for s in range(0, n, chunk):
        qs = q[s : s + chunk]
        m = qs.shape[0]
        R_after, t_after = frames(robot, qs, p)
        tE = t_after[:, 7]
        Js = J[s : s + chunk]
        for k in range(8):
            if k == 0:
                R_before = np.broadcast_to(np.eye(3), (m, 3, 3))
            else:
                R_before = R_after[:, k - 1]
            ok = t_after[:, k]  # origin of frame k in F_I
            # translations: along the parent's axes
            Js[:, 0:3, 6 * k : 6 * k + 3] = R_before
            Js[:, 3:6, 6 * k : 6 * k + 3] = 0.0
            a, b = p[6 * k + 3], p[6 * k + 4]
            RbN = R_before @ robot.R_nominal[k]
            w_a = RbN @ ex
            w_b = RbN @ (rot_x(a) @ ey)
            w_c = RbN @ (rot_x(a) @ rot_y(b) @ ez)
            lever = tE - ok
            for col, w in ((3, w_a), (4, w_b), (5, w_c)):
                w = np.broadcast_to(w, (m, 3))
                Js[:, 0:3, 6 * k + col] = np.cross(w, lever)
                Js[:, 3:6, 6 * k + col] = w
        if T_meas is not None:
            Tm = np.asarray(T_meas, dtype=float)[s : s + chunk]
            R_model = R_after[:, 7]
            dphi = matrix_to_rotvec(R_model @ np.swapaxes(Tm[:, :3, :3], -1, -2))
            Js[:, 3:6, :] = inverse_left_jacobian(dphi) @ Js[:, 3:6, :]
    return J
