"""The compliant ground of the paper's set-up: the whole robot tilts under its own weight."""

from __future__ import annotations

import numpy as np

from campaign.effects._gravity import overturning_moment
from campaign.effects._maps import rotate_about, translate
from campaign.effects.base import Effect, register


@register
class GroundCompliance(Effect):
    """Base tilt proportional to the overturning moment M (N·m) of the arm's and payload's weight.

    The robot stands on an elastic structure; the weight's moment about the base axis tilts
    it about the two horizontal axes of F_I (x and z) through a pivot below the base:

        δφ_x = k_x M_x,   δφ_z = k_z M_z             (rad)
        T' = rotation by δφ about the pivot (0, y_p, 0)

    The pivot height y_p is unknown in general. To keep the model linear in its parameters,
    the pivot enters through ``s_x = k_x y_p`` and ``s_z = k_z y_p`` (rotation about F_I's origin
    plus the shift −δφ × (0, y_p, 0)); y_p = s/k when k is well determined.
    Context: ``payload_kg`` (optional) adds a payload's weight at the tool point.
    """

    name = "ground_compliance"
    description = "elastic ground: base tilt proportional to the overturning moment of the robot's weight"
    param_names = ("k_x", "k_z", "s_x", "s_z")
    param_units = ("rad/(N·m)", "rad/(N·m)", "m·rad/(N·m)", "m·rad/(N·m)")

    def _moment(self, T, q, context):
        payload = context.get("payload_kg") if context else None
        return overturning_moment(self.robot, q, payload, T[:, :3, 3] if payload is not None else None)

    def pose_map(self, params, T, q, context):
        k_x, k_z, s_x, s_z = params
        M = self._moment(T, q, context)
        dphi = np.zeros((len(T), 3))
        dphi[:, 0] = k_x * M[:, 0]
        dphi[:, 2] = k_z * M[:, 2]
        out = rotate_about(T, dphi, np.zeros(3))
        # rotation about (0, y_p, 0) = rotation about the origin, then shift by -δφ × (0, y_p, 0)
        shift = np.zeros((len(T), 3))
        shift[:, 0] = s_z * M[:, 2]
        shift[:, 2] = -s_x * M[:, 0]
        return translate(out, shift)

    def typical_params(self, seed=0):
        """A wooden structure under a 32 kg arm: ~0.3-0.6 mrad at 50 N·m, pivot 0.4 m below the base."""
        rng = np.random.default_rng(seed)
        k = rng.uniform(6e-6, 1.2e-5, 2) * rng.choice([-1, 1], 2)
        pivot_y_m = 0.4
        return np.array([k[0], k[1], k[0] * pivot_y_m, k[1] * pivot_y_m])
