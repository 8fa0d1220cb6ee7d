"""CalibrationModel.fit as named steps: each step callable on its own, and the steps composed by
hand give the fit's own answer."""

import numpy as np
import pytest

from campaign.identify import solver
from campaign.identify.solver import CalibrationModel
from campaign.sim.truth import make_truth, random_joint_poses, synthesize


@pytest.fixture(scope="module")
def poses(robot):
    truth = make_truth(robot, seed=21)
    return synthesize(truth, random_joint_poses(robot, 60, seed=22), seed=23)


def _by_hand(model, poses):
    q, T, ctx = model.check_data(poses.q, poses.T_IE, None)
    unknowns = model.choose_unknowns()
    layout = model.row_layout(q, T)
    x, mu, held = model.start_values(unknowns)
    problem = solver.FitProblem(model, q, T, ctx, layout, unknowns.r)
    free = model.free_unknowns(problem, x, held, unknowns, layout.sigma)
    prior = solver._PriorTerm(np.zeros((len(free), len(free))), mu[free], False, free)
    fit = solver.iterate(problem, x, free, prior, layout, max_iter=50, estimate_noise=True)
    return fit, solver.posterior(problem, fit, free, prior, layout, unknowns,
                                 effective_unknowns=model._effective_unknowns)


def test_the_steps_composed_by_hand_give_the_fits_values_and_covariance(robot, poses):
    fitted = CalibrationModel(robot=robot).fit(poses.q, poses.T_IE)
    fit, post = _by_hand(CalibrationModel(robot=robot), poses)
    assert np.array_equal(fit.x, fitted.x_)
    assert np.array_equal(post.covariance, fitted.covariance_)
    assert fit.n_iter == fitted.n_iter_


def test_least_squares_covariance_is_the_inverse_normal_matrix_times_the_variance_factor(robot, poses):
    model = CalibrationModel(robot=robot, estimate_noise=False).fit(poses.q, poses.T_IE)
    J = model.jacobian(poses.q, poses.T_IE)[:, :6, :] / model.row_sigma_[None, :, None]
    A = J.reshape(-1, J.shape[-1])
    e = (model.residuals(poses.q, poses.T_IE) / model.row_sigma_).reshape(-1)
    s2 = float(e @ e) / (A.shape[0] - A.shape[1])
    ref = np.linalg.inv(A.T @ A) * s2
    assert np.allclose(model.covariance_, ref, rtol=1e-6, atol=1e-6 * np.abs(ref).max())


def test_variance_components_give_each_block_its_rms_over_its_rows_less_their_leverage(rng):
    res = np.concatenate([rng.normal(0, 2e-5, (40, 3)), rng.normal(0, 3e-4, (40, 3))], axis=1)
    layout = solver.RowLayout(rows=slice(0, 6), mask=np.ones((40, 6)), sigma=np.full(6, 1.0),
                              blocks=[np.arange(3), np.arange(3, 6)], measured=None)
    J = rng.normal(size=(40, 6, 12))
    J[:, 3:, :8] = 0.0  # eight unknowns the second block does not see
    h = solver.row_leverage(J, np.zeros((12, 12)))
    Q, _ = np.linalg.qr(J.reshape(240, 12))  # the hat matrix's diagonal, independently
    assert np.allclose(h.reshape(-1), np.sum(Q ** 2, axis=1)) and h.sum() == pytest.approx(12)
    got = solver.variance_components(res, layout.sigma, layout, h)
    assert h[:, :3].sum() > 8  # the first block carries more than its equal share of the unknowns
    assert np.allclose(got[:3], np.sqrt(np.sum(res[:, :3] ** 2) / (120 - h[:, :3].sum())))
    assert np.allclose(got[3:], np.sqrt(np.sum(res[:, 3:] ** 2) / (120 - h[:, 3:].sum())))


def test_start_values_take_init_by_name_and_hold_dropped_unknowns_at_zero(robot, poses):
    model = CalibrationModel(robot=robot)
    model.check_data(poses.q, poses.T_IE, None)
    unknowns = model.choose_unknowns()
    model.drop = (unknowns.names[1],)
    x, _, held = model.start_values(unknowns, init={unknowns.names[0]: 1e-3, unknowns.names[1]: 2e-3})
    assert x[0] == 1e-3 and x[1] == 0.0 and held[1] and not held[0]
