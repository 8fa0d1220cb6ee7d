"""What a fit keeps for its callers (diagnose's folds and candidates), against independent references:
the residual at the fit, the derivative in the joint offsets (central differences of the model), and
a refit started at the optimum that takes no step."""

import numpy as np
import pytest

from campaign.identify.solver import CalibrationModel
from campaign.model.kinematics import forward, pose_error
from campaign.sim.truth import make_truth, random_joint_poses, synthesize


@pytest.fixture(scope="module")
def fitted(robot):
    truth = make_truth(robot, seed=11)
    q = random_joint_poses(robot, 120, seed=12)
    poses = synthesize(truth, q, seed=13)
    return CalibrationModel(robot=robot).fit(poses.q, poses.T_IE), poses


def test_residual_at_fit_is_the_fitted_models_residual(fitted):
    model, poses = fitted
    assert np.array_equal(model.residual_at_fit_, model.residuals(poses.q, poses.T_IE))


def test_joint_jacobian_at_fit_equals_central_differences_in_each_joint(robot, fitted):
    model, poses = fitted
    step = 1e-6
    for j in range(robot.n_joints):
        dq = np.zeros_like(poses.q)
        dq[:, j] = step
        ref = (pose_error(forward(robot, poses.q + dq, model.params_), poses.T_IE)
               - pose_error(forward(robot, poses.q - dq, model.params_), poses.T_IE)) / (2 * step)
        got = model.joint_jacobian_at_fit_[:, :, j]
        assert np.max(np.abs(got - ref)) < 1e-8 * np.max(np.abs(ref)), j


def test_a_refit_started_at_the_optimum_takes_no_step(robot, fitted):
    _, poses = fitted
    kw = dict(robot=robot, estimate_noise=False, sigma_position_m=1e-5, sigma_orientation_rad=1e-4)
    model = CalibrationModel(**kw).fit(poses.q, poses.T_IE)  # fixed weights: its values are the optimum
    assert model.n_iter_ > 1
    refit = CalibrationModel(**kw).fit(poses.q, poses.T_IE, base=model.base_, init=model.values_,
                                       init_jacobian=model.jacobian_at_fit_)
    assert refit.n_iter_ == 0
    assert np.array_equal(refit.x_, model.x_)
