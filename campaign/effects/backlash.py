"""Backlash of the gears, taken up on the side the gravity torque pushes."""

from __future__ import annotations

import numpy as np

from campaign.effects.gravity import gravity_torques, loaded_joints
from campaign.effects.base import Effect, check_effect_joints, register

#: torque (N·m) over which the backlash is taken up: a smooth sign, differentiable for the solver
TAKE_UP_TORQUE_NM = 1.0


@register
class Backlash(Effect):
    """Δq_i = β_i · tanh(τ_i / 1 N·m): half the backlash, signed by the gravity torque.

    ``joints`` (1-based): by default those with a gravity torque worth identifying
    (:func:`~campaign.effects.gravity.loaded_joints`; a vertical joint 1 carries none). When the per-pose
    context has ``approach_sign_q<i>`` (±1, the direction of the last motion of joint i),
    that sign is used instead of the torque's.
    """

    name = "backlash"
    description = "backlash: an offset ±β_i signed by the gravity torque (or the approach direction)"

    def __init__(self, robot, joints=None):
        super().__init__(robot)
        self.joints = check_effect_joints(loaded_joints(robot) if joints is None else joints, robot, self.name)
        self.param_names = tuple(f"beta{j}" for j in self.joints)
        self.param_units = ("rad",) * len(self.joints)

    def joint_offset(self, params, q, context):
        tau = gravity_torques(self.robot, q)
        dq = np.zeros_like(q, dtype=float)
        for b, j in zip(params, self.joints):
            key = f"approach_sign_q{j}"
            if context and key in context:
                s = np.sign(np.asarray(context[key], dtype=float))
            else:
                s = np.tanh(tau[:, j - 1] / TAKE_UP_TORQUE_NM)
            dq[:, j - 1] = b * s
        return dq

    def typical_params(self, seed=0):
        """Half-backlash of 50-150 µrad."""
        rng = np.random.default_rng(seed + 53)
        return rng.uniform(5e-5, 1.5e-4, len(self.joints))
