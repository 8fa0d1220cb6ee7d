"""ISO 9283 pose accuracy and pose repeatability from measured poses (ISO 9283:1998, 7.2).

For one test pose measured n times with attained positions x_i (m) and orientations R_i, and the
commanded pose (x_c, R_c):

- pose accuracy AP: the distance of the barycentre from the command,
  ``AP_P = ‖x̄ − x_c‖`` with components ``AP_x, AP_y, AP_z``; in orientation
  ``AP_a, AP_b, AP_c`` = the mean of the attained orientation's deviation from the command about
  the base frame's x, y, z axes (the rotation vector of R_i R_cᵀ: the standard's angle
  differences for the small deviations of a robot);
- pose repeatability ``RP_l = l̄ + 3 S_l`` with ``l_i = ‖x_i − x̄‖``, ``S_l`` the sample standard
  deviation (n − 1) of the l_i; in orientation ``RP_a = 3 S_a`` (likewise b, c) about the mean.
"""

from __future__ import annotations

from dataclasses import asdict, dataclass

import numpy as np

from campaign.model.rotations import matrix_to_rotvec


@dataclass(frozen=True)
class PoseFigures:
    """The figures of one test pose, mm and mrad (orientation None where it was not measured)."""

    n_cycles: int
    AP_p_mm: float
    AP_x_mm: float
    AP_y_mm: float
    AP_z_mm: float
    RP_l_mm: float
    l_mean_mm: float
    S_l_mm: float
    AP_a_mrad: float | None = None
    AP_b_mrad: float | None = None
    AP_c_mrad: float | None = None
    RP_a_mrad: float | None = None
    RP_b_mrad: float | None = None
    RP_c_mrad: float | None = None

    def as_dict(self) -> dict:
        return asdict(self)


def pose_figures(T_attained, T_command, *, orientation: bool = True) -> PoseFigures:
    """Figures of one pose from its attained poses T_attained (n, 4, 4) and its command (4, 4), m.

    orientation: whether T_attained's rotations were measured (not for one-reflector data)."""
    T = np.asarray(T_attained, dtype=float)
    n = len(T)
    if n < 2:
        raise ValueError(f"ISO 9283 needs at least 2 cycles of a pose, got {n}")
    x = T[:, :3, 3]
    x_bar = x.mean(axis=0)
    ap = x_bar - np.asarray(T_command, dtype=float)[:3, 3]
    l = np.linalg.norm(x - x_bar, axis=1)
    S_l = float(np.std(l, ddof=1))
    out = dict(n_cycles=n, AP_p_mm=1e3 * float(np.linalg.norm(ap)), AP_x_mm=1e3 * float(ap[0]),
               AP_y_mm=1e3 * float(ap[1]), AP_z_mm=1e3 * float(ap[2]), RP_l_mm=1e3 * float(l.mean() + 3 * S_l),
               l_mean_mm=1e3 * float(l.mean()), S_l_mm=1e3 * S_l)
    if orientation:
        R_c = np.asarray(T_command, dtype=float)[:3, :3]
        e = matrix_to_rotvec(T[:, :3, :3] @ R_c.T)  # (n, 3) rad, about F_I's axes
        mean, S = e.mean(axis=0), e.std(axis=0, ddof=1)
        out.update({f"AP_{c}_mrad": 1e3 * float(mean[k]) for k, c in enumerate("abc")})
        out.update({f"RP_{c}_mrad": 3e3 * float(S[k]) for k, c in enumerate("abc")})
    return PoseFigures(**out)
