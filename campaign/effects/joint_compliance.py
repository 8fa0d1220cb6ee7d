"""Joint (gear and drive) compliance under the arm's own weight."""

from __future__ import annotations

import numpy as np

from campaign.effects.gravity import gravity_torques
from campaign.effects.base import Effect, register

#: joints whose gravity torque is large enough to identify a compliance (1-based)
DEFAULT_JOINTS = (2, 3, 5)


@register
class JointCompliance(Effect):
    """Δq_i = c_i · τ_i, with τ the gravity torque (N·m) from the URDF's inertias (Pinocchio).

    Joint 1's axis is vertical (τ_1 = 0) and the torques of joints 4 and 6 are tiny, so by
    default only joints 2, 3 and 5 carry a compliance c_i (rad/(N·m)).
    """

    name = "joint_compliance"
    description = "joint compliance: Δq_i = c_i · τ_gravity,i(q)"

    def __init__(self, robot, joints=DEFAULT_JOINTS):
        super().__init__(robot)
        self.joints = tuple(int(j) for j in joints)
        if any(j < 1 or j > 6 for j in self.joints):
            raise ValueError(f"joints must be in 1..6, got {self.joints}")
        self.param_names = tuple(f"c{j}" for j in self.joints)
        self.param_units = ("rad/(N·m)",) * len(self.joints)

    def joint_offset(self, params, q, context):
        tau = gravity_torques(self.robot, q)
        dq = np.zeros_like(q, dtype=float)
        for c, j in zip(params, self.joints):
            dq[:, j - 1] = c * tau[:, j - 1]
        return dq

    def typical_params(self, seed=0):
        """Compliances of a small 6-axis arm's harmonic drives: 2-8e-5 rad/(N·m) (~0.1-0.5 mm at the tool)."""
        rng = np.random.default_rng(seed + 11)
        return rng.uniform(2e-5, 8e-5, len(self.joints))
