"""The compliant ground of the paper's set-up: the whole robot tilts under its own weight."""

from __future__ import annotations

import numpy as np

from campaign.effects.gravity import gravity_vector, horizontal_axes, overturning_moment
from campaign.effects._maps import rotate_about, translate
from campaign.effects.base import Effect, register


@register
class GroundCompliance(Effect):
    """Base tilt proportional to the overturning moment M (N·m) of the arm's and payload's weight.

    The robot stands on an elastic structure; the weight's moment about the base axis tilts
    it about the two horizontal axes h_1, h_2 of F_I (perpendicular to the robot model's
    gravity; for the COMAU, whose gravity is along −y, F_I's x and z) through a pivot at
    height y_p below the base on the vertical u = −g/|g|:

        δφ = k_1 (M·h_1) h_1 + k_2 (M·h_2) h_2            (rad)
        T' = rotation by δφ about the pivot −y_p u

    The pivot height y_p is unknown in general. To keep the model linear in its parameters,
    the pivot enters through ``s_i = k_i y_p`` (rotation about F_I's origin plus the shift
    (s_1 (M·h_1) h_1 + s_2 (M·h_2) h_2) × u); y_p = s/k when k is well determined.
    Parameters are named after the axes (COMAU: k_x, k_z, s_x, s_z).
    Context: ``payload_kg`` (optional) adds a payload's weight at the tool point.
    """

    name = "ground_compliance"
    description = "elastic ground: base tilt proportional to the overturning moment of the robot's weight"

    def __init__(self, robot):
        super().__init__(robot)
        self.axes, labels = horizontal_axes(robot)
        self.up = -gravity_vector(robot) / np.linalg.norm(gravity_vector(robot))
        self.param_names = tuple(f"k_{a}" for a in labels) + tuple(f"s_{a}" for a in labels)
        self.param_units = ("rad/(N·m)",) * 2 + ("m·rad/(N·m)",) * 2

    def _moment(self, T, q, context):
        payload = context.get("payload_kg") if context else None
        return overturning_moment(self.robot, q, payload, T[:, :3, 3] if payload is not None else None)

    def pose_map(self, params, T, q, context):
        k1, k2, s1, s2 = params
        m = self._moment(T, q, context) @ self.axes.T  # (n, 2): moment about h_1, h_2
        dphi = (k1 * m[:, :1]) * self.axes[0] + (k2 * m[:, 1:]) * self.axes[1]
        out = rotate_about(T, dphi, np.zeros(3))
        # rotation about −y_p u = rotation about the origin, then a shift −δφ × (−y_p u) = (s·M) × u
        shift = np.cross((s1 * m[:, :1]) * self.axes[0] + (s2 * m[:, 1:]) * self.axes[1], self.up)
        return translate(out, shift)

    def typical_params(self, seed=0):
        """A wooden structure under a 32 kg arm: ~0.3-0.6 mrad at 50 N·m, pivot 0.4 m below the base."""
        rng = np.random.default_rng(seed)
        k = rng.uniform(6e-6, 1.2e-5, 2) * rng.choice([-1, 1], 2)
        pivot_y_m = 0.4
        return np.array([k[0], k[1], k[0] * pivot_y_m, k[1] * pivot_y_m])
