"""Rotation conventions, batched over leading axes.

Conventions (see README, "Conventions"):

* ``cardan_xyz(a, b, c) = Rx(a) @ Ry(b) @ Rz(c)``: the paper's R(alpha, beta, gamma).
* URDF ``rpy = (r, p, y)`` means ``Rz(y) @ Ry(p) @ Rx(r)`` (fixed axes x, then y, then z).
* KUKA's ``A, B, C`` mean ``Rz(A) @ Ry(B) @ Rx(C)``: URDF's rpy with roll C, pitch B, yaw A.
* Quaternions ``(w, x, y, z)``, scalar first.
* Orientation errors are rotation vectors (axis * angle, rad).

Every function accepts arrays with arbitrary leading shape; angles in rad.
"""

from __future__ import annotations

import numpy as np

from campaign.tolerances import SMALL_ANGLE


def rot_x(a):
    """Rotation matrices about x, shape ``a.shape + (3, 3)``."""
    a = np.asarray(a, dtype=float)
    c, s = np.cos(a), np.sin(a)
    o, z = np.ones_like(a), np.zeros_like(a)
    return np.stack([o, z, z, z, c, -s, z, s, c], axis=-1).reshape(a.shape + (3, 3))


def rot_y(a):
    """Rotation matrices about y, shape ``a.shape + (3, 3)``."""
    a = np.asarray(a, dtype=float)
    c, s = np.cos(a), np.sin(a)
    o, z = np.ones_like(a), np.zeros_like(a)
    return np.stack([c, z, s, z, o, z, -s, z, c], axis=-1).reshape(a.shape + (3, 3))


def rot_z(a):
    """Rotation matrices about z, shape ``a.shape + (3, 3)``."""
    a = np.asarray(a, dtype=float)
    c, s = np.cos(a), np.sin(a)
    o, z = np.ones_like(a), np.zeros_like(a)
    return np.stack([c, -s, z, s, c, z, z, z, o], axis=-1).reshape(a.shape + (3, 3))


def cardan_xyz(a, b, c):
    """The paper's Cardan angles: ``Rx(a) Ry(b) Rz(c)`` (intrinsic x-y-z)."""
    return rot_x(a) @ rot_y(b) @ rot_z(c)


def urdf_rpy(r, p, y):
    """URDF's fixed-axis roll-pitch-yaw: ``Rz(y) Ry(p) Rx(r)``."""
    return rot_z(y) @ rot_y(p) @ rot_x(r)


def kuka_abc(a, b, c):
    """KUKA's A, B, C: ``Rz(a) Ry(b) Rx(c)`` (= ``urdf_rpy(c, b, a)``)."""
    return rot_z(a) @ rot_y(b) @ rot_x(c)


def quaternion_to_matrix(q_wxyz):
    """Unit quaternions ``(..., 4)`` (w, x, y, z; normalised here) to matrices ``(..., 3, 3)``."""
    q = np.asarray(q_wxyz, dtype=float)
    q = q / np.linalg.norm(q, axis=-1, keepdims=True)
    w, x, y, z = q[..., 0], q[..., 1], q[..., 2], q[..., 3]
    return np.stack([1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y),
                     2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x),
                     2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)],
                    axis=-1).reshape(q.shape[:-1] + (3, 3))


def cardan_xyz_from_matrix(R):
    """Inverse of :func:`cardan_xyz`; returns ``(..., 3)`` with ``b`` in [-pi/2, pi/2].

    At the singularity ``|b| = pi/2`` the split between ``a`` and ``c`` is not unique;
    ``c = 0`` is returned then.
    """
    R = np.asarray(R, dtype=float)
    # R = Rx(a)Ry(b)Rz(c): R[0,2] = sin b, R[1,2] = -sin a cos b, R[2,2] = cos a cos b,
    # R[0,1] = -cos b sin c, R[0,0] = cos b cos c
    sb = np.clip(R[..., 0, 2], -1.0, 1.0)
    b = np.arcsin(sb)
    cb = np.cos(b)
    regular = cb > 1e-9
    a = np.where(regular, np.arctan2(-R[..., 1, 2], R[..., 2, 2]), np.arctan2(R[..., 2, 1], R[..., 1, 1]))
    c = np.where(regular, np.arctan2(-R[..., 0, 1], R[..., 0, 0]), 0.0)
    return np.stack([a, b, c], axis=-1)


def urdf_rpy_from_matrix(R):
    """Inverse of :func:`urdf_rpy`; returns ``(..., 3)`` rpy with pitch in [-pi/2, pi/2]."""
    R = np.asarray(R, dtype=float)
    # R = Rz(y)Ry(p)Rx(r): R[2,0] = -sin p, R[2,1] = cos p sin r, R[2,2] = cos p cos r,
    # R[1,0] = sin y cos p, R[0,0] = cos y cos p
    sp = np.clip(-R[..., 2, 0], -1.0, 1.0)
    p = np.arcsin(sp)
    regular = np.cos(p) > 1e-9
    r = np.where(regular, np.arctan2(R[..., 2, 1], R[..., 2, 2]), np.arctan2(-R[..., 1, 2], R[..., 1, 1]))
    y = np.where(regular, np.arctan2(R[..., 1, 0], R[..., 0, 0]), 0.0)
    return np.stack([r, p, y], axis=-1)


def cardan_to_rpy(abc):
    """Convert Cardan x-y-z angles ``(..., 3)`` to URDF rpy describing the same rotation."""
    abc = np.asarray(abc, dtype=float)
    return urdf_rpy_from_matrix(cardan_xyz(abc[..., 0], abc[..., 1], abc[..., 2]))


def rpy_to_cardan(rpy):
    """Convert URDF rpy ``(..., 3)`` to Cardan x-y-z angles describing the same rotation."""
    rpy = np.asarray(rpy, dtype=float)
    return cardan_xyz_from_matrix(urdf_rpy(rpy[..., 0], rpy[..., 1], rpy[..., 2]))


def skew(v):
    """Skew-symmetric matrices ``[v]x`` of shape ``(..., 3, 3)``."""
    v = np.asarray(v, dtype=float)
    z = np.zeros(v.shape[:-1])
    x, y, w = v[..., 0], v[..., 1], v[..., 2]
    return np.stack([z, -w, y, w, z, -x, -y, x, z], axis=-1).reshape(v.shape[:-1] + (3, 3))


def rotvec_to_matrix(phi):
    """Rodrigues: rotation vectors ``(..., 3)`` (rad) to matrices ``(..., 3, 3)``."""
    phi = np.asarray(phi, dtype=float)
    theta = np.linalg.norm(phi, axis=-1)[..., None, None]
    K = skew(phi)
    small = theta < SMALL_ANGLE
    safe = np.where(small, 1.0, theta)
    a = np.where(small, 1.0 - theta**2 / 6.0, np.sin(safe) / safe)
    b = np.where(small, 0.5 - theta**2 / 24.0, (1.0 - np.cos(safe)) / safe**2)
    return np.eye(3) + a * K + b * (K @ K)


def matrix_to_rotvec(R):
    """Logarithm of SO(3): matrices ``(..., 3, 3)`` to rotation vectors ``(..., 3)`` (rad).

    Accurate over the whole range, including angles near pi, where the axis is taken
    from the symmetric part of R.
    """
    R = np.asarray(R, dtype=float)
    tr = np.trace(R, axis1=-2, axis2=-1)
    cos_t = np.clip((tr - 1.0) / 2.0, -1.0, 1.0)
    w = np.stack([R[..., 2, 1] - R[..., 1, 2], R[..., 0, 2] - R[..., 2, 0], R[..., 1, 0] - R[..., 0, 1]], axis=-1)
    sin_t = 0.5 * np.linalg.norm(w, axis=-1)
    theta = np.arctan2(sin_t, cos_t)
    small = theta < SMALL_ANGLE
    near_pi = cos_t < -0.99
    safe_sin = np.where(small | near_pi, 1.0, np.sin(theta))
    factor = np.where(small, 0.5 + theta**2 / 12.0, 0.5 * theta / safe_sin)
    out = factor[..., None] * w
    if np.any(near_pi):
        Rp = R[near_pi]
        th = theta[near_pi]
        S = 0.5 * (Rp + np.swapaxes(Rp, -1, -2)) - np.cos(th)[..., None, None] * np.eye(3)
        S = S / (1.0 - np.cos(th))[..., None, None]  # = a a^T
        idx = np.argmax(np.diagonal(S, axis1=-2, axis2=-1), axis=-1)
        col = np.take_along_axis(S, idx[..., None, None].repeat(3, axis=-2), axis=-1)[..., 0]
        axis = col / np.linalg.norm(col, axis=-1, keepdims=True)
        wp = w[near_pi]
        sign = np.where(np.sum(axis * wp, axis=-1) < 0.0, -1.0, 1.0)
        out[near_pi] = (sign * th)[..., None] * axis
    return out


def inverse_left_jacobian(phi):
    """Inverse of SO(3)'s left Jacobian, ``(..., 3, 3)``.

    If ``R = exp(phi)`` and R is perturbed on the left, ``R' = exp(w) R``, then
    ``log(R') = phi + J_l^{-1}(phi) w + O(|w|^2)``.
    """
    phi = np.asarray(phi, dtype=float)
    theta = np.linalg.norm(phi, axis=-1)[..., None, None]
    K = skew(phi)
    small = theta < 1e-4
    safe = np.where(small, 1.0, theta)
    c = np.where(
        small,
        1.0 / 12.0 + theta**2 / 720.0,
        1.0 / safe**2 - (1.0 + np.cos(safe)) / (2.0 * safe * np.sin(safe)),
    )
    return np.eye(3) - 0.5 * K + c * (K @ K)


def matrix_to_quaternion(R):
    """Unit quaternions ``(..., 4)`` (w, x, y, z; w >= 0) of rotation matrices ``(..., 3, 3)``,
    the inverse of :func:`quaternion_to_matrix` (Shepperd's method: the largest of the four
    squared components is taken first, so no division by a small number)."""
    R = np.asarray(R, dtype=float)
    tr = np.trace(R, axis1=-2, axis2=-1)
    d = np.stack([tr, R[..., 0, 0], R[..., 1, 1], R[..., 2, 2]], axis=-1)
    k = np.argmax(d, axis=-1)
    out = np.empty(R.shape[:-2] + (4,))
    s = np.sqrt(np.maximum(1.0 + 2.0 * np.take_along_axis(d, k[..., None], -1)[..., 0] - tr, 1e-300)) * 2
    w = np.where(k == 0, s / 4, 0)
    m = k == 0
    out[m] = np.stack([w[m], (R[..., 2, 1] - R[..., 1, 2])[m] / s[m], (R[..., 0, 2] - R[..., 2, 0])[m] / s[m],
                       (R[..., 1, 0] - R[..., 0, 1])[m] / s[m]], axis=-1)
    m = k == 1
    out[m] = np.stack([(R[..., 2, 1] - R[..., 1, 2])[m] / s[m], s[m] / 4, (R[..., 0, 1] + R[..., 1, 0])[m] / s[m],
                       (R[..., 0, 2] + R[..., 2, 0])[m] / s[m]], axis=-1)
    m = k == 2
    out[m] = np.stack([(R[..., 0, 2] - R[..., 2, 0])[m] / s[m], (R[..., 0, 1] + R[..., 1, 0])[m] / s[m], s[m] / 4,
                       (R[..., 1, 2] + R[..., 2, 1])[m] / s[m]], axis=-1)
    m = k == 3
    out[m] = np.stack([(R[..., 1, 0] - R[..., 0, 1])[m] / s[m], (R[..., 0, 2] + R[..., 2, 0])[m] / s[m],
                       (R[..., 1, 2] + R[..., 2, 1])[m] / s[m], s[m] / 4], axis=-1)
    return out * np.where(out[..., :1] < 0, -1.0, 1.0)


def zyz(a, b, c):
    """Z-Y-Z Euler angles (COMAU's POS): ``Rz(a) Ry(b) Rz(c)``."""
    return rot_z(a) @ rot_y(b) @ rot_z(c)


def zyz_from_matrix(R):
    """Inverse of :func:`zyz`; returns ``(..., 3)`` with ``b`` in [0, pi] (``c = 0`` where b is 0 or pi)."""
    R = np.asarray(R, dtype=float)
    b = np.arccos(np.clip(R[..., 2, 2], -1.0, 1.0))
    regular = np.sin(b) > 1e-9
    a = np.where(regular, np.arctan2(R[..., 1, 2], R[..., 0, 2]), np.arctan2(R[..., 1, 0], R[..., 0, 0]))
    c = np.where(regular, np.arctan2(R[..., 2, 1], -R[..., 2, 0]), 0.0)
    return np.stack([a, b, c], axis=-1)
