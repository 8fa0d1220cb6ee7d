"""Small helpers shared by pose-map effects."""

from __future__ import annotations

import numpy as np

from campaign.model.rotations import rotvec_to_matrix


def rotate_about(T, rotvec, pivot):
    """Rotate poses T (n, 4, 4) by rotation vectors (n, 3) rad about pivot points (3,) or (n, 3) m."""
    R = rotvec_to_matrix(rotvec)
    out = np.array(T, dtype=float, copy=True)
    out[:, :3, :3] = R @ out[:, :3, :3]
    rel = out[:, :3, 3] - pivot
    out[:, :3, 3] = pivot + (R @ rel[..., None])[..., 0]
    return out


def translate(T, dt):
    """Shift poses T (n, 4, 4) by dt (n, 3) m in F_I."""
    out = np.array(T, dtype=float, copy=True)
    out[:, :3, 3] += dt
    return out
