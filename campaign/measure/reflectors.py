"""From laser-tracker points to poses.

* :func:`frame_from_setup_points` — ``T_LI`` from the base-frame set-up points (the origin
  of F_I, a point on its x axis and a point on its y axis, measured in F_L), as in the paper.
* :func:`kabsch` — the least-squares rigid transform that maps points given in one frame
  onto the same points measured in another (Kabsch / Horn), batched.
* :func:`pose_from_reflectors` — the pose of F_E in F_I from the three reflectors.
"""

from __future__ import annotations

import numpy as np

from campaign.errors import DataError
from campaign.tolerances import (POINT_REGISTRATION_MAX_STEPS, POINT_REGISTRATION_RCOND, POINT_REGISTRATION_STEP_TOL_M,
                                 SETUP_POINT_MIN_SEPARATION_M)


def frame_from_setup_points(origin_L, x_point_L, y_point_L) -> np.ndarray:
    """``T_LI`` (4, 4): pose of F_I in F_L from three points measured in F_L (m).

    x_I points from the origin to ``x_point``; y_I is the part of (``y_point`` − origin)
    orthogonal to x_I; z_I = x_I × y_I.
    """
    o = np.asarray(origin_L, dtype=float)
    px = np.asarray(x_point_L, dtype=float) - o
    py = np.asarray(y_point_L, dtype=float) - o
    nx = np.linalg.norm(px)
    if nx < SETUP_POINT_MIN_SEPARATION_M:
        raise DataError(f"set-up points: the x point is {nx * 1e3:.3f} mm from the origin "
                        f"(need >= {SETUP_POINT_MIN_SEPARATION_M * 1e3:g} mm)")
    x = px / nx
    y = py - (py @ x) * x
    ny = np.linalg.norm(y)
    if ny < SETUP_POINT_MIN_SEPARATION_M:
        raise DataError("set-up points: the y point is (nearly) on the x axis")
    y = y / ny
    z = np.cross(x, y)
    T = np.eye(4)
    T[:3, :3] = np.stack([x, y, z], axis=1)
    T[:3, 3] = o
    return T


def invert(T) -> np.ndarray:
    """Inverse of homogeneous transforms (..., 4, 4)."""
    T = np.asarray(T, dtype=float)
    out = np.zeros_like(T)
    Rt = np.swapaxes(T[..., :3, :3], -1, -2)
    out[..., :3, :3] = Rt
    out[..., :3, 3] = -(Rt @ T[..., :3, 3, None])[..., 0]
    out[..., 3, 3] = 1.0
    return out


def transform_points(T, P) -> np.ndarray:
    """Apply transforms (..., 4, 4) to points (..., k, 3)."""
    T = np.asarray(T, dtype=float)
    P = np.asarray(P, dtype=float)
    return P @ np.swapaxes(T[..., :3, :3], -1, -2) + T[..., None, :3, 3]


def kabsch(P_local, P_world) -> np.ndarray:
    """Rigid transforms T (n, 4, 4) minimising Σ‖T·p_local − p_world‖².

    P_local: (k, 3) points in the body frame (same for all n); P_world: (n, k, 3).
    """
    A = np.asarray(P_local, dtype=float)
    B = np.asarray(P_world, dtype=float)
    if B.ndim == 2:
        B = B[None]
    ca = A.mean(axis=0)
    cb = B.mean(axis=1)
    H = np.einsum("ki,nkj->nij", A - ca, B - cb[:, None, :])
    U, _, Vt = np.linalg.svd(H)
    d = np.sign(np.linalg.det(np.swapaxes(Vt, -1, -2) @ np.swapaxes(U, -1, -2)))
    D = np.zeros((B.shape[0], 3, 3))
    D[:, 0, 0] = 1.0
    D[:, 1, 1] = 1.0
    D[:, 2, 2] = d
    R = np.swapaxes(Vt, -1, -2) @ D @ np.swapaxes(U, -1, -2)
    T = np.zeros((B.shape[0], 4, 4))
    T[:, :3, :3] = R
    T[:, :3, 3] = cb - (R @ ca)
    T[:, 3, 3] = 1.0
    return T


def pose_from_reflectors(T_LI, reflectors_in_E, reflectors_in_L):
    """Pose of F_E in F_I, (n, 4, 4), and the fit residual RMS per pose (n,), m.

    T_LI: (4, 4) pose of F_I in F_L; reflectors_in_E: (3, 3) nominal centres in F_E;
    reflectors_in_L: (n, 3, 3) measured centres in F_L.
    """
    P_L = np.asarray(reflectors_in_L, dtype=float)
    if P_L.ndim == 2:
        P_L = P_L[None]
    P_I = transform_points(invert(T_LI), P_L)
    T_IE = kabsch(reflectors_in_E, P_I)
    fitted = transform_points(T_IE, np.broadcast_to(reflectors_in_E, P_I.shape))
    rms = np.sqrt(np.mean(np.sum((fitted - P_I) ** 2, axis=-1), axis=-1))
    return T_IE, rms


def fit_markers(P_local, P_world):
    """Rigid fits of a reflector set to measurements where some reflectors may be missing.

    P_local: (k, 3) nominal centres in the body frame; P_world: (n, k, 3), NaN rows where the
    tracker missed a reflector. Returns (T (n, 4, 4), rms (n,) m); both NaN for a pose with
    fewer than three reflectors seen. Poses are fitted together per pattern of seen reflectors.
    """
    A = np.asarray(P_local, dtype=float)
    B = np.asarray(P_world, dtype=float)
    n = B.shape[0]
    seen = ~np.isnan(B).any(axis=2)
    T = np.full((n, 4, 4), np.nan)
    rms = np.full(n, np.nan)
    patterns, inverse = np.unique(seen, axis=0, return_inverse=True)
    for p, mask in enumerate(patterns):
        if mask.sum() < 3:
            continue
        rows = np.flatnonzero(inverse.reshape(-1) == p)
        Ts = kabsch(A[mask], B[rows][:, mask])
        fitted = transform_points(Ts, np.broadcast_to(A[mask], (len(rows), int(mask.sum()), 3)))
        T[rows] = Ts
        rms[rows] = np.sqrt(np.mean(np.sum((fitted - B[rows][:, mask]) ** 2, axis=-1), axis=-1))
    return T, rms


def register_points(P_model, P_measured) -> np.ndarray:
    """Closed-form rigid registration (Kabsch/Umeyama without scale): T (4, 4) minimising
    Σ‖T·p_model − p_measured‖² over corresponding points (n, 3), m."""
    A = np.asarray(P_model, dtype=float)
    B = np.asarray(P_measured, dtype=float)
    ok = np.isfinite(A).all(axis=1) & np.isfinite(B).all(axis=1)
    if ok.sum() < 3:
        raise DataError(f"registration to the tracker's frame needs 3 measured points, got {int(ok.sum())}")
    return kabsch(A[ok], B[ok][None])[0]


def register_measured_point(T_model, P_measured, *, tracker: bool = True):
    """Where an undeclared reflector sits on the tool, with the tracker's pose: (T (4, 4), p (3,))
    minimising Σ‖T·(R_i p + t_i) − y_i‖² over the poses T_model (n, 4, 4) of the tool frame and the
    measured points P_measured (n, 3), m (rows with a missing value are left out). ``tracker``
    False: the points are in the model's own frame, T is the identity and p a linear least-squares
    fit. :func:`register_measured_points` for one point."""
    T, p = register_measured_points(T_model, np.asarray(P_measured, dtype=float)[:, None, :], tracker=tracker)
    return T, p[0]


def register_measured_points(T_model, P_measured, *, tracker: bool = True):
    """Where k reflectors sit on the tool, with the tracker's pose: (T (4, 4), p (k, 3)) minimising
    Σ‖T·(R_i p_j + t_i) − y_ij‖² over the poses T_model (n, 4, 4) of the tool frame and the measured
    points P_measured (n, k, 3), m (a reflector not seen: NaN, left out). ``tracker`` False: T is
    the identity and each p_j a linear least-squares fit. Alternates the closed-form registration
    of every seen point and each point's linear least squares (each step lowers the sum); a
    point's directions the tool's orientations do not determine stay at 0."""
    T_model = np.asarray(T_model, dtype=float)
    Y = np.asarray(P_measured, dtype=float)
    seen = np.isfinite(Y).all(axis=2) & np.isfinite(T_model[:, :3, 3]).all(axis=1)[:, None]
    if seen.sum() < 3:
        raise DataError(f"registration of the measured point needs 3 measured points, got {int(seen.sum())}")
    R, t = T_model[:, :3, :3], T_model[:, :3, 3]
    T, p = np.eye(4), np.zeros((Y.shape[1], 3))

    def registered(p):
        X = np.einsum("nij,kj->nki", R, p) + t[:, None, :]
        return kabsch(X[seen], Y[seen][None])[0]

    for _ in range(POINT_REGISTRATION_MAX_STEPS):
        if tracker:
            T = registered(p)
        p_new = p.copy()
        for j in range(Y.shape[1]):
            s = seen[:, j]
            if not s.any():
                continue
            A = np.einsum("ij,njk->nik", T[:3, :3], R[s]).reshape(-1, 3)
            b = (Y[s, j] - t[s] @ T[:3, :3].T - T[:3, 3]).reshape(-1)
            p_new[j] = np.linalg.lstsq(A, b, rcond=POINT_REGISTRATION_RCOND)[0]
        step = float(np.linalg.norm(p_new - p))
        p = p_new
        if step < POINT_REGISTRATION_STEP_TOL_M:
            break
    if tracker:
        T = registered(p)
    return T, p
