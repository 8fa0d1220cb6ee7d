"""Joint (gear and drive) compliance under the arm's own weight."""

from __future__ import annotations

import numpy as np

from campaign.effects.gravity import gravity_torques, loaded_joints
from campaign.effects.base import Effect, check_effect_joints, register


@register
class JointCompliance(Effect):
    """Δq_i = c_i · τ_i, with τ the gravity torque (N·m) from the URDF's inertias (Pinocchio).

    ``joints`` (1-based, any of the robot's): by default those with a gravity torque worth
    identifying (:func:`~campaign.effects.gravity.loaded_joints`; the COMAU's 2, 3 and 5: joint 1's
    axis is vertical, the torques of its joints 4 and 6 are tiny), each with a compliance c_i
    (rad/(N·m)).
    """

    name = "joint_compliance"
    description = "joint compliance: Δq_i = c_i · τ_gravity,i(q)"

    def __init__(self, robot, joints=None):
        super().__init__(robot)
        self.joints = check_effect_joints(loaded_joints(robot) if joints is None else joints, robot, self.name)
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
