"""Cyclic transmission errors of the gears: harmonics of the joint angles."""

from __future__ import annotations

import numpy as np

from campaign.effects.base import Effect, check_effect_joints, register
from campaign.effects.gravity import lever_joints


@register
class Cyclic(Effect):
    """Δq_i = Σ_k a_ik sin(k q_i) + b_ik cos(k q_i), for the chosen joints and harmonics k.

    Default: harmonics 1 and 2 on the three joints with the longest levers to the tool
    (:func:`~campaign.effects.gravity.lever_joints`; the COMAU's 1, 2 and 3).
    """

    name = "cyclic"
    description = "cyclic transmission error: harmonics sin/cos(k·q_i) of the joint angles"

    def __init__(self, robot, joints=None, harmonics=(1, 2)):
        super().__init__(robot)
        self.joints = check_effect_joints(lever_joints(robot) if joints is None else joints, robot, self.name)
        self.harmonics = tuple(int(k) for k in harmonics)
        names = []
        for j in self.joints:
            for k in self.harmonics:
                names += [f"a{j}_{k}", f"b{j}_{k}"]
        self.param_names = tuple(names)
        self.param_units = ("rad",) * len(names)

    def joint_offset(self, params, q, context):
        dq = np.zeros_like(q, dtype=float)
        i = 0
        for j in self.joints:
            x = q[:, j - 1]
            for k in self.harmonics:
                dq[:, j - 1] += params[i] * np.sin(k * x) + params[i + 1] * np.cos(k * x)
                i += 2
        return dq

    def typical_params(self, seed=0):
        """Amplitudes of 50-150 µrad (a few arc-seconds to half an arc-minute)."""
        rng = np.random.default_rng(seed + 41)
        return rng.uniform(5e-5, 1.5e-4, self.n_params) * rng.choice([-1, 1], self.n_params)
