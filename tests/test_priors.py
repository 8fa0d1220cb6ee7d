"""Issue 24: identification with priors (MAP), model choice by cross-validation, --fix, and the
expected held-out error. References: scipy.optimize.least_squares on the redundant model with the
same Gaussian prior as extra residuals; refits without each pose for the closed-form leave-one-out;
the simulator's truth only after the pipeline answered."""

import json

import numpy as np
import pytest
import scipy.optimize
import yaml

from campaign.cli import main
from campaign.errors import ConfigError
from campaign.identify.model_choice import CV_MAX_TRAIN_POSES, STRENGTHS, expected_heldout_mm, fit_model, \
    least_restrictive_within_se, \
    loo_position_errors
from campaign.identify.solver import CalibrationModel
from campaign.model.kinematics import forward, pose_error
from campaign.model.priors import DEFAULT_TOLERANCES, make_prior, parse_fix, resolve_fix
from campaign.model.robot import RobotModel
from campaign.sim.truth import make_truth, random_joint_poses, synthesize

SIG = np.array([1e-5] * 3 + [1e-4] * 3)  # row weights of the comparison (m, rad)
STRENGTH = 100.0  # strong enough that the prior moves the estimate by many σ


@pytest.fixture(scope="module")
def comau_map(robot):
    """12 COMAU poses, MAP at STRENGTH with fixed row weights, and the scipy reference on the
    redundant model (all 48 physical parameters, prior rows √s · p / σ_p)."""
    truth = make_truth(robot, seed=3)
    q = random_joint_poses(robot, 12, seed=4)
    T = synthesize(truth, q, seed=5).T_IE
    model = CalibrationModel(robot=robot, prior="tolerances", prior_strength=STRENGTH, estimate_noise=False,
                             sigma_position_m=SIG[0], sigma_orientation_rad=SIG[3]).fit(q, T)
    sd = make_prior(robot).sigma

    def residuals(p):
        r = pose_error(forward(robot, q, p), T) / SIG
        return np.concatenate([r.ravel(), np.sqrt(STRENGTH) * p / sd])

    ref = scipy.optimize.least_squares(residuals, np.zeros(robot.n_params), method="trf", xtol=1e-15, ftol=1e-15,
                                       gtol=1e-15)
    return model, ref


def test_map_agrees_with_scipy_least_squares_on_the_redundant_model(comau_map):
    model, ref = comau_map
    assert model.kind_ == "map" and len(model.unknown_names_) == 48
    np.testing.assert_allclose(model.physical_params_, ref.x, atol=1e-9)
    C = model.base_.combination
    assert np.max(np.abs(C @ ref.x - model.base_params_) / model.base_sigma_) < 1e-4
    # the prior matters here: least squares on the same data is many σ away
    lsq = CalibrationModel(robot=model.robot, estimate_noise=False).fit(*_data(model.robot))
    assert np.max(np.abs(lsq.base_params_ - model.base_params_) / model.base_sigma_) > 1.0


def _data(robot):
    truth = make_truth(robot, seed=3)
    q = random_joint_poses(robot, 12, seed=4)
    return q, synthesize(truth, q, seed=5).T_IE


def test_the_posterior_covariance_is_data_plus_prior_information_from_scipys_jacobian(comau_map):
    model, ref = comau_map
    n_data = ref.jac.shape[0] - model.robot.n_params
    Jd, Jp = ref.jac[:n_data], ref.jac[n_data:]
    cov = np.linalg.inv(Jd.T @ Jd / model.variance_factor_ + Jp.T @ Jp)
    sd = np.sqrt(np.diag(cov))
    np.testing.assert_allclose(model.sigma_[:48], sd, rtol=1e-3)
    np.testing.assert_allclose(model.correlation_[:48, :48], cov / np.outer(sd, sd), atol=2e-3)


@pytest.mark.parametrize("prior", [None, "tolerances"])
def test_closed_form_leave_one_out_is_the_refit_without_each_pose(robot, prior):
    truth = make_truth(robot, seed=1, position_only=True)
    q = random_joint_poses(robot, 16, seed=2)
    T = synthesize(truth, q, seed=3).T_IE
    kw = {"robot": robot, "position_only": True, "estimate_noise": False, "prior": prior, "prior_strength": 10.0}
    full = CalibrationModel(**kw).fit(q, T)
    loo = loo_position_errors(full)
    for i in (0, 5, 11):
        keep = np.arange(len(q)) != i
        m = CalibrationModel(**kw).fit(q[keep], T[keep], init=full.values_)
        refit = np.linalg.norm(m.residuals(q[i:i + 1], T[i:i + 1])[0, :3])
        assert loo[i] == pytest.approx(refit, rel=2e-3), (i, loo[i], refit)


def test_auto_is_least_squares_without_cross_validation_from_300_training_poses(robot):
    truth = make_truth(robot, seed=2)
    q = random_joint_poses(robot, CV_MAX_TRAIN_POSES, seed=3)
    T = synthesize(truth, q, seed=4).T_IE

    def make(**kw):
        return CalibrationModel(robot=robot, **kw)

    chosen, choice = fit_model(make, q, T, model="auto")
    assert choice.choice == "lsq" and choice.candidates == [] and "300" in choice.reason
    np.testing.assert_array_equal(chosen.params_, make().fit(q, T).params_)


def test_fix_holds_a_group_and_a_value_and_names_what_matches_nothing(robot):
    fix = resolve_fix(robot, parse_fix("tool,pq2=0.001"))
    assert set(fix) == set(robot.param_names[-6:]) | {"pq2"} and fix["pq2"] == 0.001
    q, T = _data(robot)
    m = CalibrationModel(robot=robot, prior="tolerances", fixed=fix).fit(q, T)
    i = robot.param_names.index("pq2")
    assert m.physical_params_[i] == 0.001 and np.all(m.physical_params_[-6:] == 0.0)
    assert set(m.held_) == set(fix) and m.sigma_[i] == 0.0
    lsq = CalibrationModel(robot=robot, fixed=resolve_fix(robot, {"tool": None})).fit(q, T)
    # base parameters made of tool parameters alone are held at zero; the others stay free
    only_tool = [j for j in range(lsq.base_.n_base)
                 if not np.any(lsq.base_.combination[j, :-6])]
    assert only_tool and set(lsq.held_) == {lsq.base_.names[j] for j in only_tool}
    with pytest.raises(ConfigError, match=r"^--fix pX_9: no such parameter or group"):
        resolve_fix(robot, {"pX_9": None})
    with pytest.raises(ConfigError, match=r"^--fix pq2: the value must be a finite number"):
        parse_fix("pq2=abc")


def test_tolerances_come_from_robot_yaml_per_kind(tmp_path):
    import shutil

    from campaign.paths import DATA_DIR

    src = DATA_DIR / "robot_models" / "comau_racer5_080"
    shutil.copytree(src, tmp_path / "comau")
    meta = yaml.safe_load((tmp_path / "comau" / "robot.yaml").read_text())
    meta["tolerances"] = {"length_m": 2e-4, "tool_m": 5e-5}
    (tmp_path / "comau" / "robot.yaml").write_text(yaml.safe_dump(meta))
    robot = RobotModel.load(tmp_path / "comau" / "robot.yaml")
    sd = dict(zip(robot.param_names, make_prior(robot).sigma))
    assert sd["pL_12_x"] == 2e-4 and sd["pL_6E_z"] == 5e-5 and sd["pL_I0_x"] == DEFAULT_TOLERANCES["base_m"]
    assert sd["pq3"] == DEFAULT_TOLERANCES["joint_offset_rad"] and sd["pR_23_x"] == DEFAULT_TOLERANCES["angle_rad"]
    meta["tolerances"] = {"length_mm": 0.2}
    (tmp_path / "comau" / "robot.yaml").write_text(yaml.safe_dump(meta))
    with pytest.raises(ConfigError, match=r"robot.yaml: tolerances.length_mm is not a kind"):
        make_prior(RobotModel.load(tmp_path / "comau" / "robot.yaml"))


def test_the_expected_heldout_error_matches_the_measured_one_on_average(robot):
    """The posterior and the fit's noise predict the held-out mean position error of a 40-pose
    campaign: measured / expected over five seeds averages 1 within 10 %."""
    ratios = []
    for seed in range(5):
        truth = make_truth(robot, seed=seed, position_only=True)
        q = random_joint_poses(robot, 40, seed=seed + 10)
        T = synthesize(truth, q, seed=seed + 20).T_IE
        tr, te = np.arange(40) < 32, np.arange(40) >= 32
        m, _ = fit_model(lambda **kw: CalibrationModel(robot=robot, position_only=True, **kw), q[tr], T[tr])
        measured = 1e3 * np.mean(np.linalg.norm(m.residuals(q[te], T[te])[:, :3], axis=1))
        ratios.append(measured / expected_heldout_mm(m, q[te]))
    assert 0.9 < np.mean(ratios) < 1.1, ratios


def test_calibrate_model_map_with_fix_reports_the_choice_curve_and_what_was_held(tmp_path, capsys):
    csv = tmp_path / "c.csv"
    assert main(["synth", "--csv", str(csv), "--poses", "30", "--seed", "2", "--kind", "point"]) == 0
    run = tmp_path / "run"
    assert main(["import", str(csv), "--run", str(run), "--quiet"]) == 0
    capsys.readouterr()
    assert main(["calibrate", str(run), "--no-ann", "--quiet", "--fix", "pX_1"]) == 1
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "--fix pX_1: no such parameter or group" in err[0]
    assert not (run / "calibration").exists()
    assert main(["calibrate", str(run), "--no-ann", "--quiet", "--model", "map", "--fix", "tool"]) == 0
    out = capsys.readouterr().out
    model = json.loads((run / "calibration" / "metrics.json").read_text())["model"]
    assert model["choice"] == "map" and model["asked"] == "map" and model["kind"] == "map"
    assert [c["strength"] for c in model["cv_curve"]] == list(STRENGTHS)
    assert model["strength"] == min(model["cv_curve"], key=lambda c: c["cv_mean_position_mm"])["strength"]
    assert sorted(model["fixed"]) == sorted(RobotModel.load().param_names[-6:])
    assert model["expected_heldout_mean_position_mm"] > 0 and model["measured_heldout_mean_position_mm"] > 0
    assert "model: map" in out and "held (--fix): pL_6E_x = 0" in out
    page = (run / "calibration" / "report.html").read_text()
    assert "<h2>Model choice</h2>" in page and "leave-one-out mean on the training poses (mm)" in page


def test_plan_select_is_bayesian_d_optimal_the_design_starts_from_the_prior_precision(robot):
    """`plan --select` maximises log det of the poses' information plus the prior's precision
    (campaign.model.priors.unknowns_precision, in the design's column scale)."""
    from campaign.model.base_params import base_parameters
    from campaign.model.priors import unknowns_precision
    from campaign.plan.selection import RIDGE, Design, information_model, select

    q = random_joint_poses(robot, 200, seed=0)
    info = information_model(robot, q, priors=True)
    # the precision by hand: (C Σ Cᵀ)⁻¹ of the base parameters from the tolerances, per kind
    base = base_parameters(robot)
    sd = make_prior(robot).sigma
    np.testing.assert_allclose(info.prior_precision, np.linalg.inv((base.combination * sd**2) @ base.combination.T),
                               rtol=1e-6, atol=1e-6 * np.abs(info.prior_precision).max())
    P = info.prior_precision / np.outer(info.scale, info.scale)
    sel = select(info, 12)
    d = Design(info, "D")
    for j in sel.index:
        d.add(j)
    expected = np.linalg.slogdet(info.information(sel.index) + P + RIDGE * np.eye(info.n_unknowns))[1]
    assert d.criterion_value() == pytest.approx(expected, abs=1e-6)
    assert information_model(robot, q).prior_precision is None
    np.testing.assert_array_equal(unknowns_precision(base, make_prior(robot)), info.prior_precision)


def test_an_effect_declares_its_prior_and_map_fits_it_with_the_geometry(robot):
    from campaign.effects.base import make_effect
    from campaign.effects.joint_compliance import JointCompliance
    from campaign.model.priors import EFFECT_PRIOR_TYPICAL_FACTOR
    from campaign.sim.truth import synthetic_campaign

    class Stiff(JointCompliance):
        prior_sigma = (1e-6, 2e-6, 3e-6)

    typical = np.abs(make_effect("joint_compliance", robot).typical_params(0))
    np.testing.assert_allclose(make_prior(robot, [make_effect("joint_compliance", robot)]).effect_sigma,
                               EFFECT_PRIOR_TYPICAL_FACTOR * typical)
    np.testing.assert_array_equal(make_prior(robot, [Stiff(robot)]).effect_sigma, [1e-6, 2e-6, 3e-6])
    poses, truth = synthetic_campaign(robot, 30, seed=1, hidden=("joint_compliance",))
    tight = CalibrationModel(robot=robot, effects=[Stiff(robot)], prior="tolerances").fit(poses.q, poses.T_IE)
    loose = CalibrationModel(robot=robot, effects=["joint_compliance"], prior="tolerances").fit(poses.q, poses.T_IE)
    # truth only now: the loose prior recovers the compliance, the tight one holds it near zero
    assert np.all(np.abs(loose.effect_params_ - truth.theta) < 3 * loose.effect_sigma_)
    assert np.all(loose.effect_sigma_ < 0.3 * np.abs(truth.theta))
    # the posterior is never wider than the prior; where the data know c5 worse than the tight
    # prior does, the prior pulls it towards zero
    assert np.all(tight.effect_sigma_ <= np.array([1e-6, 2e-6, 3e-6]))
    assert tight.effect_sigma_[2] < 0.6 * loose.effect_sigma_[2]
    assert abs(tight.effect_params_[2]) < 0.5 * abs(loose.effect_params_[2])


def test_map_on_the_base_parameters_agrees_with_scipy_on_the_redundant_model_seen_through_them(robot):
    """``physical=False`` (what `calibrate --model map|auto` fits): the prior on every physical
    parameter, the data through the base parameters ``C p`` alone; scipy minimises the same over
    all 48 parameters, so its physical split is the prior's conditional mean."""
    q, T = _data(robot)
    model = CalibrationModel(robot=robot, prior="tolerances", prior_strength=STRENGTH, physical=False,
                             estimate_noise=False, sigma_position_m=SIG[0], sigma_orientation_rad=SIG[3]).fit(q, T)
    sd, C = make_prior(robot).sigma, model.base_.combination

    def residuals(p):
        r = pose_error(forward(robot, q, model.base_.expand(C @ p)), T) / SIG
        return np.concatenate([r.ravel(), np.sqrt(STRENGTH) * p / sd])

    ref = scipy.optimize.least_squares(residuals, np.zeros(robot.n_params), method="trf", xtol=1e-15, ftol=1e-15,
                                       gtol=1e-15)
    assert np.max(np.abs(C @ ref.x - model.base_params_) / model.base_sigma_) < 1e-4
    np.testing.assert_allclose(model.physical_params_, ref.x, atol=1e-9)


def test_auto_takes_the_least_restrictive_candidate_within_two_standard_errors_of_the_best():
    """Per-pose CV errors of three candidates on 8 poses, least restrictive first: the second is
    lower than the first on every pose, the third lower than the second on average by less than
    two standard errors of their paired differences."""
    first = np.full(8, 3.0)
    second = first - np.array([0.5] * 7 + [0.3])
    third = second - np.array([0.4, -0.2, 0.4, -0.2, 0.4, -0.2, 0.4, -0.2])

    def gain_in_se(a, b):
        d = a - b
        return np.mean(d) / (np.std(d, ddof=1) / np.sqrt(len(d)))

    assert np.mean(third) < np.mean(second) < np.mean(first)
    assert gain_in_se(second, third) < 2 < gain_in_se(first, third)
    assert least_restrictive_within_se([first, second, third]) == 1
    assert least_restrictive_within_se([first, second, third], n_se=0.0) == 2
    assert least_restrictive_within_se([first, third, second]) == 1
    assert least_restrictive_within_se([first]) == 0
