"""The solver's extension point: any Effect plugs in without changing the solver."""

import numpy as np

from campaign.effects.base import Effect, EffectSet, model_pose
from campaign.identify.solver import CalibrationModel
from campaign.model.kinematics import pose_error
from campaign.model.rotations import rotvec_to_matrix
from campaign.sim.truth import make_truth, random_joint_poses, synthesize


class SineJoint2(Effect):
    """Test effect: Δq2 = a·sin(2 q2) (a transmission harmonic)."""

    name = "test_sine_joint2"
    param_names = ("a",)
    param_units = ("rad",)

    def joint_offset(self, params, q, context):
        dq = np.zeros_like(q)
        dq[:, 1] = params[0] * np.sin(2 * q[:, 1])
        return dq


class TiltAboutPivot(Effect):
    """Test effect: the whole arm tilts about x_I by b·(x-coordinate of the tool), pivot at (0, 0.1, 0)."""

    name = "test_tilt"
    param_names = ("b",)
    param_units = ("rad/m",)

    def pose_map(self, params, T, q, context):
        angle = params[0] * T[:, 0, 3]
        R = rotvec_to_matrix(np.stack([angle, 0 * angle, 0 * angle], axis=1))
        pivot = np.array([0.0, 0.1, 0.0])
        out = T.copy()
        out[:, :3, :3] = R @ T[:, :3, :3]
        out[:, :3, 3] = pivot + (R @ (T[:, :3, 3] - pivot)[..., None])[..., 0]
        return out


class CopyOfJoint2Offset(Effect):
    """Test effect that the geometric parameters fully absorb: a constant Δq2."""

    name = "test_constant_q2"
    param_names = ("c",)
    param_units = ("rad",)

    def joint_offset(self, params, q, context):
        dq = np.zeros_like(q)
        dq[:, 1] = params[0]
        return dq


def test_combined_jacobian_matches_central_differences(robot, rng):
    truth = make_truth(robot, seed=1)
    q = random_joint_poses(robot, 6, seed=2)
    T_meas = truth.pose(q)
    effects = [SineJoint2(robot), TiltAboutPivot(robot)]
    q_fit = random_joint_poses(robot, 60, seed=4)
    model = CalibrationModel(robot=robot, effects=effects, max_iter=2).fit(q_fit, truth.pose(q_fit))
    r = model.base_.n_base
    x = rng.normal(0, 1e-3, r + 2)
    J = model.jacobian(q, T_meas, base_params=x[:r], effect_params=x[r:])
    effect_set = EffectSet(tuple(effects))
    h = 1e-7
    J_fd = np.empty_like(J)
    for j in range(r + 2):
        d = np.zeros(r + 2)
        d[j] = h
        xp, xm = x + d, x - d
        fp = pose_error(model_pose(robot, q, model.base_.expand(xp[:r]), effect_set, xp[r:]), T_meas)
        fm = pose_error(model_pose(robot, q, model.base_.expand(xm[:r]), effect_set, xm[r:]), T_meas)
        J_fd[:, :, j] = (fp - fm) / (2 * h)
    np.testing.assert_allclose(J, J_fd, atol=2e-6)


def test_hidden_custom_effects_are_identified_jointly(robot):
    truth = make_truth(robot, seed=4)
    effects = EffectSet((SineJoint2(robot), TiltAboutPivot(robot)))
    hidden = np.array([4e-4, 2e-3])
    truth = truth.__class__(truth.robot, truth.p_e, truth.T_LI, truth.noise_m, truth.resolution_m, effects, hidden)
    q = random_joint_poses(robot, 1500, seed=5)
    meas = synthesize(truth, q, seed=6)
    model = CalibrationModel(robot=robot, effects=list(effects.effects)).fit(meas.q, meas.T_IE)
    z = (model.effect_params_ - hidden) / model.effect_sigma_
    assert np.all(np.abs(z) < 4), (model.effect_params_, model.effect_sigma_)
    assert model.absorbed_ == []


def test_an_effect_the_geometry_absorbs_is_reported_not_fitted(robot):
    truth = make_truth(robot, seed=4)
    q = random_joint_poses(robot, 300, seed=5)
    meas = synthesize(truth, q, seed=6)
    model = CalibrationModel(robot=robot, effects=[CopyOfJoint2Offset(robot)]).fit(meas.q, meas.T_IE)
    assert [model.unknown_names_[i] for i in model.absorbed_] == ["test_constant_q2.c"]
    assert model.effect_params_[0] == 0.0
