"""Batched forward kinematics with the geometric error parameters (paper eqs. 5-13, generalised).

Parameter vector ``p_e`` (6N + 12,) for a chain of N moving joints (campaign.model.robot), six
entries per transform k of ``robot.transform_names`` (COMAU: I0, 01, .., 56, 6E; the 48 of
Table 2 in its order). Base, tool and revolute joints (eqs. 6-11):

    R̂_k = R̄_k R(pR_k_x, pR_k_y, c_k),   c_k = q_j + pq_j  or  pR_k_z,
    t̂_k = t̄_k + pL_k.

A prismatic joint j (names ``pL_k_x, pL_k_y, pR_k_z, pR_k_x, pR_k_y, pd<j>``):

    R̂_k = R̄_k R(pR_k_x, pR_k_y, pR_k_z),   t̂_k = t̄_k + R̄_k (pL_k_x, pL_k_y, 0) + R̂_k e_z (q_j + pd_j).

Optional joint twists ξ (n, N, 6) act right after each joint's motion: ``… A_j(q_j) exp(ξ_j) A_{j+1} …``.

Pose error (eq. 13): ``Δz = (t_model - t_meas, log(R_model R_measᵀ))``, position in m,
rotation vector in rad, both resolved in F_I.
"""

from __future__ import annotations

import numpy as np

from campaign.model.robot import TRANSFORM_NAMES, RobotModel
from campaign.model.rotations import (cardan_xyz, inverse_left_jacobian, matrix_to_rotvec, rot_x, rot_y,
                                      rotvec_to_matrix, skew)

N_PARAMS = 48

#: Poses evaluated together; bounds memory at about 2 kB a pose in the Jacobian.
CHUNK = 65536


def _make_names():
    names = []
    for k, tname in enumerate(TRANSFORM_NAMES):
        names += [f"pL_{tname}_x", f"pL_{tname}_y", f"pL_{tname}_z", f"pR_{tname}_x", f"pR_{tname}_y"]
        names.append(f"pq{k}" if 1 <= k <= 6 else f"pR_{tname}_z")
    return tuple(names)


#: Names of the 48 error parameters of the default COMAU, Table 2's order (any robot: robot.param_names).
PARAM_NAMES = _make_names()
#: SI unit of each parameter.
PARAM_UNITS = tuple("m" if n.startswith("pL") else "rad" for n in PARAM_NAMES)
#: Index of pq1..pq6 in ``p_e``.
JOINT_OFFSET_INDEX = tuple(6 * k + 5 for k in range(1, 7))


def _as_q(q, robot: RobotModel | None = None):
    N = robot.n_joints if robot is not None else 6
    q = np.asarray(q, dtype=float)
    if q.ndim == 1:
        q = q[None, :]
    if q.ndim != 2 or q.shape[1] != N:
        raise ValueError(f"q must have shape (n, {N}), got {q.shape}")
    return q


def _as_p(p_e, robot: RobotModel | None = None):
    n_params = robot.n_params if robot is not None else N_PARAMS
    if p_e is None:
        return np.zeros(n_params)
    p = np.asarray(p_e, dtype=float)
    if p.shape != (n_params,):
        raise ValueError(f"p_e must have shape ({n_params},), got {p.shape}")
    return p


def _as_twists(joint_twists, robot, n):
    if joint_twists is None:
        return None
    xi = np.asarray(joint_twists, dtype=float)
    if xi.shape != (n, robot.n_joints, 6):
        raise ValueError(f"joint_twists must have shape (n, N, 6) = ({n}, {robot.n_joints}, 6), got {xi.shape}")
    return xi


def se3_exp(xi):
    """Exponential of twists ``xi = (v, ω)`` (..., 6): rotations (..., 3, 3) and translations (..., 3)."""
    xi = np.asarray(xi, dtype=float)
    v, w = xi[..., :3], xi[..., 3:]
    R = rotvec_to_matrix(w)
    theta = np.linalg.norm(w, axis=-1)[..., None, None]
    K = skew(w)
    small = theta < 1e-6
    safe = np.where(small, 1.0, theta)
    b = np.where(small, 0.5 - theta**2 / 24.0, (1.0 - np.cos(safe)) / safe**2)
    c = np.where(small, 1.0 / 6.0 - theta**2 / 120.0, (safe - np.sin(safe)) / safe**3)
    V = np.eye(3) + b * K + c * (K @ K)
    return R, (V @ v[..., None])[..., 0]


def _transform_rotations(robot: RobotModel, q, p):
    """Rotations R̂_k for each pose: list of N + 2 arrays (n, 3, 3) (or (3, 3) if constant)."""
    out = []
    N = robot.n_joints
    for k in range(N + 2):
        a, b, c = p[6 * k + 3], p[6 * k + 4], p[6 * k + 5]
        if 1 <= k <= N:
            if robot.joint_types[k - 1] == "prismatic":
                out.append(robot.R_nominal[k] @ cardan_xyz(a, b, p[6 * k + 2]))
            else:  # R̄_k Rx(a) Ry(b) is one matrix for all poses: only Rz(q + c) varies
                out.append(_times_rot_z(robot.R_nominal[k] @ rot_x(a) @ rot_y(b), q[:, k - 1] + c))
        else:
            out.append(robot.R_nominal[k] @ cardan_xyz(a, b, c))
    return out


def _times_rot_z(C, angle):
    """``C @ Rz(angle)`` for one C (3, 3) and angles (n,): (n, 3, 3), two columns mixed by cos and
    sin (a matmul per pose and the stacking of Rz cost several times more in the chain)."""
    c, s = np.cos(angle)[:, None], np.sin(angle)[:, None]
    out = np.empty((len(angle), 3, 3))
    out[:, :, 0] = c * C[:, 0] + s * C[:, 1]
    out[:, :, 1] = c * C[:, 1] - s * C[:, 0]
    out[:, :, 2] = C[:, 2]
    return out


def _translation(robot: RobotModel, k, p):
    """t̂_k (3,) in the parent model frame, before any prismatic motion."""
    if 1 <= k <= robot.n_joints and robot.joint_types[k - 1] == "prismatic":
        return robot.t_nominal[k] + robot.R_nominal[k] @ np.array([p[6 * k], p[6 * k + 1], 0.0])
    return robot.t_nominal[k] + p[6 * k : 6 * k + 3]


def _chain(robot: RobotModel, q, p, xi, *, keep: bool):
    """Walk the chain for poses q (m, N). Returns (R, t) of the tool and, with ``keep``,
    (R_after (m, K, 3, 3), t_after (m, K, 3), t_pre (m, K, 3)): each transform's frame after
    its motion (and twist), and its origin before the motion (where its parameter rotations act)."""
    m = q.shape[0]
    N = robot.n_joints
    K = N + 2
    Rk = _transform_rotations(robot, q, p)
    R = np.broadcast_to(np.eye(3), (m, 3, 3))
    t = np.zeros((m, 3))
    if keep:
        R_out = np.empty((m, K, 3, 3))
        t_out = np.empty((m, K, 3))
        t_pre = np.empty((m, K, 3))
    rot = xi_t = None
    if xi is not None:
        rot, xi_t = se3_exp(xi)
    for k in range(K):
        t = t + R @ _translation(robot, k, p)
        if keep:
            t_pre[:, k] = t
        R = R @ Rk[k]
        if 1 <= k <= N:
            if robot.joint_types[k - 1] == "prismatic":
                t = t + R[:, :, 2] * (q[:, k - 1] + p[6 * k + 5])[:, None]
            if xi is not None:
                t = t + (R @ xi_t[:, k - 1, :, None])[..., 0]
                R = R @ rot[:, k - 1]
        if keep:
            R_out[:, k] = R
            t_out[:, k] = t
    if keep:
        return R, t, (R_out, t_out, t_pre)
    return R, t, None


def frames(robot: RobotModel, q, p_e=None, *, joint_twists=None):
    """Poses of the model frames after each of the N + 2 transforms, in F_I.

    Returns ``(R, t)`` with ``R`` of shape (n, N + 2, 3, 3) and ``t`` (n, N + 2, 3): entry k is
    the frame *after* transform k (0 -> F_0, ..., N -> F_N, N + 1 -> F_E); for a moving joint
    the frame after its motion (and its twist, if ``joint_twists`` (n, N, 6) is given).
    Not chunked; use for moderate n.
    """
    q = _as_q(q, robot)
    p = _as_p(p_e, robot)
    _, _, (R_out, t_out, _) = _chain(robot, q, p, _as_twists(joint_twists, robot, len(q)), keep=True)
    return R_out, t_out


def forward(robot: RobotModel, q, p_e=None, *, chunk: int = CHUNK, joint_twists=None):
    """``T_IE(q, p_e)`` for an array of joint vectors.

    q: (n, N) rad (m for prismatic joints); p_e: (6N + 12,) or None for the nominal model;
    joint_twists: optional (n, N, 6) twists (v [m], ω [rad]) applied right after each moving
    joint's motion, in its frame: ``T = … A_j(q_j) exp(ξ_j) A_{j+1} …``.
    Returns (n, 4, 4) homogeneous transforms (m). Memory is bounded by ``chunk``.
    """
    q = _as_q(q, robot)
    p = _as_p(p_e, robot)
    n = q.shape[0]
    xi = _as_twists(joint_twists, robot, n)
    T = np.zeros((n, 4, 4))
    T[:, 3, 3] = 1.0
    for s in range(0, n, chunk):
        R, t, _ = _chain(robot, q[s : s + chunk], p, None if xi is None else xi[s : s + chunk], keep=False)
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


def error_jacobian(robot: RobotModel, q, p_e=None, T_meas=None, *, chunk: int = CHUNK, joint_twists=None):
    """Analytic ``∂Δz/∂p_e`` for each pose: (n, 6, 6N + 12).

    Rows 0-2 are ∂t_IE/∂p (m per unit). Rows 3-5 are the derivative of the rotation-vector
    error: if ``T_meas`` is given, ``J_l⁻¹(Δφ) ω`` (exact); without it, the spatial
    angular velocity ω itself (exact at Δφ = 0). The zero-offset columns (``pq<j>``,
    ``pd<j>``) are also ∂Δz/∂q_j. ``joint_twists`` as in :func:`forward`.

    The array is a view of a parameter-major buffer (6N + 12, 6, n): each column is written in
    contiguous runs over the poses, and taking some columns (the base parameters) copies runs.
    """
    q = _as_q(q, robot)
    p = _as_p(p_e, robot)
    n = q.shape[0]
    N = robot.n_joints
    xi = _as_twists(joint_twists, robot, n)
    Jp = np.zeros((robot.n_params, 6, n))
    ey, ez = np.eye(3)[1], np.eye(3)[2]
    for s in range(0, n, chunk):
        qs = q[s : s + chunk]
        m = qs.shape[0]
        e = s + m
        _, _, (R_after, t_after, t_pre) = _chain(robot, qs, p, None if xi is None else xi[s : s + chunk], keep=True)
        tE = t_after[:, N + 1]
        for k in range(N + 2):
            a, b = p[6 * k + 3], p[6 * k + 4]
            if k == 0:
                R_before = np.broadcast_to(np.eye(3), (m, 3, 3))
                RbN = np.broadcast_to(robot.R_nominal[0], (m, 3, 3))
            else:
                R_before = R_after[:, k - 1]
                RbN = R_before @ robot.R_nominal[k]
            prismatic = 1 <= k <= N and robot.joint_types[k - 1] == "prismatic"
            lever = (tE - t_pre[:, k]).T  # (3, m): from frame k's origin before its motion to the tool
            w_a = RbN[:, :, 0].T
            w_b = (RbN @ (rot_x(a) @ ey)).T
            w_c = (RbN @ (rot_x(a) @ rot_y(b) @ ez)).T
            Jk = Jp[6 * k : 6 * k + 6, :, s:e]
            if prismatic:
                # translations perpendicular to the axis in the joint's nominal frame, then the
                # rotation about the axis, a, b, and the zero offset along the axis
                Jk[0:2, 0:3] = RbN[:, :, 0:2].transpose(2, 1, 0)
                Jk[5, 0:3] = w_c
                cols = ((2, w_c), (3, w_a), (4, w_b))
            else:
                Jk[0:3, 0:3] = R_before.transpose(2, 1, 0)  # translations: along the parent's axes
                cols = ((3, w_a), (4, w_b), (5, w_c))
            for col, w in cols:  # a rotation w about frame k's origin moves the tool by w × lever
                Jk[col, 0] = w[1] * lever[2] - w[2] * lever[1]
                Jk[col, 1] = w[2] * lever[0] - w[0] * lever[2]
                Jk[col, 2] = w[0] * lever[1] - w[1] * lever[0]
                Jk[col, 3:6] = w
        if T_meas is not None:
            Tm = np.asarray(T_meas, dtype=float)[s:e]
            dphi = matrix_to_rotvec(R_after[:, N + 1] @ np.swapaxes(Tm[:, :3, :3], -1, -2))
            L = inverse_left_jacobian(dphi).transpose(1, 2, 0)  # (3, 3, m)
            W = Jp[:, 3:6, s:e].copy()
            for i in range(3):
                Jp[:, 3 + i, s:e] = L[i, 0] * W[:, 0] + L[i, 1] * W[:, 1] + L[i, 2] * W[:, 2]
    return Jp.transpose(2, 1, 0)
