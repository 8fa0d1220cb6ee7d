"""Where the driver expects each reflector: the ``aims`` of a measure request (docs/protocol.md).

The prediction is the nominal model's: the reflectors' centres in F_E carried by the nominal
forward kinematics at the commanded joints, then into the tracker frame F_L by the tracker's pose
T_LI, known from the base-frame set-up or, without one (``--frame tracker``), estimated by a
rigid fit of the centres measured so far to their nominal positions in F_I. Millimetres off
(the robot's errors), which is what a tracker needs to find its reflector.
"""

from __future__ import annotations

import numpy as np

from campaign.measure.reflectors import register_points, transform_points

#: the points an estimate of T_LI is fitted to must span at least this much in two directions (m)
MIN_SPREAD_M = 0.05
#: the most recent measured centres kept for the estimate
MAX_POINTS = 600


class AimPredictor:
    """Predicted centres in F_L of ``targets`` (reflectors at ``P_E`` (k, 3) m in the tool frame).

    T_LI: the tracker's pose of F_I (4, 4) from the set-up, or None to estimate it from
    :meth:`learn`. Calling it with q (N,) rad gives ((name, (x, y, z) m or None), ...), None
    before T_LI is known.
    """

    def __init__(self, robot, targets, P_E, T_LI=None):
        self.robot, self.targets = robot, tuple(targets)
        self.P_E = np.asarray(P_E, dtype=float).reshape(-1, 3)
        self.T_LI = None if T_LI is None else np.asarray(T_LI, dtype=float)
        self.fixed = T_LI is not None
        self._I: list = []
        self._L: list = []

    def _nominal_I(self, q) -> np.ndarray:
        from campaign.model.kinematics import forward

        return transform_points(forward(self.robot, np.asarray(q, dtype=float)[None])[0], self.P_E)

    def __call__(self, q) -> tuple:
        if self.T_LI is None:
            return tuple((t, None) for t in self.targets)
        P_L = transform_points(self.T_LI, self._nominal_I(q))
        return tuple((t, tuple(float(v) for v in p)) for t, p in zip(self.targets, P_L))

    def learn(self, q, P_L) -> None:
        """Add the centres measured at q ((k, 3) m in F_L, NaN rows for unseen ones) to the
        estimate of T_LI (nothing when T_LI came from the set-up)."""
        if self.fixed:
            return
        P_L = np.asarray(P_L, dtype=float).reshape(-1, 3)
        ok = np.isfinite(P_L).all(axis=1)
        self._I.extend(self._nominal_I(q)[ok])
        self._L.extend(P_L[ok])
        del self._I[:-MAX_POINTS], self._L[:-MAX_POINTS]
        A = np.array(self._I)
        if len(A) >= 3 and np.linalg.svd(A - A.mean(axis=0), compute_uv=False)[1] >= MIN_SPREAD_M:
            self.T_LI = register_points(A, np.array(self._L))
