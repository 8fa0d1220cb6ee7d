"""The measuring instrument itself: a scale error of the laser tracker."""

from __future__ import annotations

import numpy as np

from campaign.effects.base import Effect, register


@register
class TrackerScale(Effect):
    """Distances measured by the tracker are (1 + κ) times the true ones (wavelength or
    temperature compensation error). In F_I the tool position scales about the tracker:

        t' = t + κ (t − o_L),   o_L the tracker's origin in F_I.

    For a fixed tracker the constant part −κ o_L and the scale of the arm's lengths are both
    spanned by the geometric parameters, so the identification reports κ as absorbed: a
    scale error of the instrument is indistinguishable from a length error of the robot
    unless the tracker moves between poses (then pass ``tracker_x_m``, ``tracker_y_m``,
    ``tracker_z_m`` as per-pose context).
    """

    name = "tracker"
    description = "tracker scale error: measured distances scaled by (1 + κ)"
    param_names = ("kappa",)
    param_units = ("1",)

    def pose_map(self, params, T, q, context):
        out = np.array(T, dtype=float, copy=True)
        origin = np.zeros((len(T), 3))
        if context and "tracker_x_m" in context:
            origin = np.stack([np.asarray(context[f"tracker_{a}_m"], dtype=float) for a in "xyz"], axis=1)
        out[:, :3, 3] += params[0] * (out[:, :3, 3] - origin)
        return out

    def typical_params(self, seed=0):
        """5 ppm, a poorly compensated air temperature."""
        return np.array([5e-6])
