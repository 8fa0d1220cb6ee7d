import numpy as np
import pytest

from campaign.errors import NotFittedError
from campaign.identify.solver import CalibrationModel
from campaign.model.kinematics import forward, pose_error
from campaign.sim.truth import make_truth, random_joint_poses, synthesize


@pytest.fixture(scope="module")
def campaign_2000(robot):
    truth = make_truth(robot, seed=3)
    q = random_joint_poses(robot, 2000, seed=4)
    meas = synthesize(truth, q, seed=5)
    n_train = 1600
    model = CalibrationModel(robot=robot).fit(meas.q[:n_train], meas.T_IE[:n_train])
    return truth, meas, model, n_train


def test_every_base_parameter_is_recovered_within_3_sigma(campaign_2000):
    truth, meas, model, _ = campaign_2000
    expected = truth.expected_base_params(meas.T_LI)  # looked at only after the fit
    z = (model.base_params_ - expected) / model.base_sigma_
    assert np.all(np.abs(z) < 3.0), np.round(z, 2)


def test_heldout_error_is_within_1_5_of_the_noise_floor(campaign_2000):
    truth, meas, model, n = campaign_2000
    dz = model.residuals(meas.q[n:], meas.T_IE[n:])
    floor = pose_error(truth.pose_in_measured_frame(meas.q[n:], meas.T_LI), meas.T_IE[n:])
    mean = np.linalg.norm(dz[:, :3], axis=1).mean()
    mean_floor = np.linalg.norm(floor[:, :3], axis=1).mean()
    assert mean <= 1.5 * mean_floor
    nominal = np.linalg.norm(pose_error(forward(truth.robot, meas.q[n:]), meas.T_IE[n:])[:, :3], axis=1).mean()
    assert nominal > 50 * mean  # the errors were large before


def test_report_fields_are_present(campaign_2000):
    _, _, model, _ = campaign_2000
    assert model.base_sigma_.shape == (30,)
    assert np.all(model.base_sigma_ > 0)
    assert 1.0 < model.condition_number_ < 1e4
    assert model.n_iter_ >= 2
    assert all(abs(r) > 0.95 for _, _, r in model.correlated_pairs_)
    assert model.params_.shape == (48,)


def test_position_only_identification_recovers_positions(robot):
    truth = make_truth(robot, seed=8)
    q = random_joint_poses(robot, 800, seed=9)
    meas = synthesize(truth, q, seed=10)
    model = CalibrationModel(robot=robot, position_only=True).fit(meas.q[:600], meas.T_IE[:600])
    assert model.base_.n_base < 30
    dz = model.residuals(meas.q[600:], meas.T_IE[600:])
    assert np.linalg.norm(dz[:, :3], axis=1).mean() < 30e-6


def test_predict_before_fit_raises(robot):
    with pytest.raises(NotFittedError, match="fit"):
        CalibrationModel(robot=robot).predict(np.zeros((1, 6)))
