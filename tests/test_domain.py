"""Issue 30: what the data cannot tell. Identifiability on the measured poses (a joint that never
moved is named, --strict refuses), the calibrated domain (in_domain) and the uncertainty pose by
pose (sigma_mm) in every output. The simulator's truth is read only after the pipeline answered."""

import csv
import json
import shutil

import numpy as np
import pytest

from campaign.cli import main
from campaign.identify.domain import calibrated_domain, read_domain
from campaign.identify.identifiability import analyse, hold_unidentified, parameter_words
from campaign.identify.solver import CalibrationModel
from campaign.identify.uncertainty import model_uncertainty
from campaign.measure.csvio import write_measured_csv
from campaign.sim.truth import make_truth, random_joint_poses, synthesize

Q1_DEG = 17.2


def _rows(path):
    with open(path, newline="") as fh:
        return list(csv.DictReader(fh))


def _joint_csv(path, q):
    lines = ["pose_id,q1,q2,q3,q4,q5,q6"] + [f"{i}," + ",".join(repr(float(v)) for v in row) for i, row in enumerate(q)]
    path.write_text("\n".join(lines) + "\n")


@pytest.fixture(scope="module")
def still_run(tmp_path_factory, robot):
    """12 measured poses in which joint 1 never moved, imported and calibrated (the issue's case)."""
    d = tmp_path_factory.mktemp("still")
    truth = make_truth(robot, seed=3)
    q = random_joint_poses(robot, 12, seed=4)
    q[:, 0] = np.deg2rad(Q1_DEG)
    poses = synthesize(truth, q, seed=5)
    write_measured_csv(d / "m.csv", poses, robot)
    assert main(["import", str(d / "m.csv"), "--run", str(d / "run"), "--quiet"]) == 0
    return d, truth, poses


def test_a_joint_that_never_moved_is_named_and_strict_refuses(still_run, capsys):
    d, _, _ = still_run
    capsys.readouterr()
    assert main(["calibrate", str(d / "run"), "--no-ann", "--quiet", "--no-report", "--strict"]) == 1
    err = capsys.readouterr().err
    assert "unidentifiable" in err and "joint 1 never moved" in err and f"q1 = {Q1_DEG}°" in err
    assert not (d / "run" / "calibration" / "metrics.json").exists()  # nothing written
    assert main(["calibrate", str(d / "run"), "--no-ann", "--quiet", "--no-report"]) == 0
    out = capsys.readouterr()
    metrics = json.loads((d / "run" / "calibration" / "metrics.json").read_text())
    codes = [w["code"] for w in metrics["warnings"]]
    assert "unidentifiable" in codes
    msg = next(w["message"] for w in metrics["warnings"] if w["code"] == "unidentifiable")
    assert "joint 1 never moved" in msg and "held at their nominal value" in msg
    assert metrics["identifiability"]["rank"] < metrics["identifiability"]["n_unknowns"]
    assert metrics["identifiability"]["held_at"] == "nominal" and metrics["identifiability"]["held"]
    # never "identified ... condition number inf"
    line = next(x for x in out.out.splitlines() if x.startswith("identified"))
    assert "inf" not in line and "of 30 base parameters" in line


def test_predict_at_other_q1_is_outside_with_a_larger_sigma_and_strict_refuses(still_run, robot, tmp_path, capsys):
    d, truth, poses = still_run
    if not (d / "run" / "calibration" / "metrics.json").exists():
        assert main(["calibrate", str(d / "run"), "--no-ann", "--quiet", "--no-report"]) == 0
    q = np.repeat(poses.q[:1], 8, axis=0)
    q[4:, 0] = np.deg2rad([-60.0, -20.0, 60.0, 120.0])  # the first four at the trained q1: one training pose
    _joint_csv(tmp_path / "q.csv", q)
    capsys.readouterr()
    assert main(["predict", str(d / "run"), "--csv", str(tmp_path / "q.csv"), "--out", str(tmp_path / "p.csv")]) == 0
    said = capsys.readouterr().out
    rows = _rows(tmp_path / "p.csv")
    assert list(rows[0])[-2:] == ["in_domain", "sigma_mm"]
    inside = np.array([int(r["in_domain"]) for r in rows])
    sigma = np.array([float(r["sigma_mm"]) for r in rows])
    assert inside[:4].all() and not inside[4:].any()
    assert sigma[4:].min() > 20 * sigma[:4].max()
    assert "4 of 8 rows outside the calibrated domain" in said and "q1 beyond the training range: 4" in said
    # the truth, read after the pipeline answered: the predicted poses are off by more there
    T = np.array([[float(r[k]) for k in ("x", "y", "z")] for r in rows])
    err_mm = 1e3 * np.linalg.norm(T - truth.pose_in_measured_frame(q, poses.T_LI)[:, :3, 3], axis=1)
    assert err_mm[4:].mean() > 20 * err_mm[:4].mean()
    assert main(["predict", str(d / "run"), "--csv", str(tmp_path / "q.csv"), "--strict"]) == 1
    err = capsys.readouterr().err
    assert "outside the calibrated domain with --strict (pose_id 4 (q1 beyond the training range)" in err
    assert len(err.strip().splitlines()) == 1


def test_domain_json_carries_the_calibration_id(still_run):
    d, _, _ = still_run
    if not (d / "run" / "calibration" / "metrics.json").exists():
        assert main(["calibrate", str(d / "run"), "--no-ann", "--quiet", "--no-report"]) == 0
    metrics = json.loads((d / "run" / "calibration" / "metrics.json").read_text())
    folder = (d / "run" / "calibration").resolve()
    stored = read_domain(folder, metrics["calibration_id"])
    assert stored is not None and "geometric" in stored.uncertainty
    from campaign.errors import DataError

    with pytest.raises(DataError, match="domain.json: of calibration"):
        read_domain(folder, "another-id")


def test_a_partial_range_marks_poses_beyond_it_outside(robot):
    q = random_joint_poses(robot, 200, seed=1)
    half = robot.q_lower[1] + 0.5 * (robot.q_upper[1] - robot.q_lower[1])
    q[:, 1] = robot.q_lower[1] + 0.05 + (q[:, 1] - robot.q_lower[1] - 0.05) * (half - robot.q_lower[1]) / \
        (robot.q_upper[1] - robot.q_lower[1])
    dom = calibrated_domain(robot, q)
    fresh = random_joint_poses(robot, 1000, seed=2)
    beyond = fresh[fresh[:, 1] > q[:, 1].max() + 0.1 * (robot.q_upper[1] - robot.q_lower[1])]
    assert len(beyond) > 100 and not dom.contains(beyond).any()
    within = fresh[(fresh[:, 1] > q[:, 1].min()) & (fresh[:, 1] < q[:, 1].max())]
    assert dom.contains(within).mean() >= 0.95


def test_a_full_spread_campaign_keeps_fresh_poses_inside_with_sigma_near_the_true_error(runs_full):
    model, domain, unc, truth, T_LI, robot = runs_full
    fresh = random_joint_poses(robot, 1000, seed=77)
    assert domain.contains(fresh).mean() >= 0.95
    sigma = unc.sigma_m(robot, model.effect_set_, model.params_, model.effect_params_, fresh)
    true = np.linalg.norm(model.predict(fresh)[:, :3, 3] - truth.pose_in_measured_frame(fresh, T_LI)[:, :3, 3], axis=1)
    assert 0.5 <= sigma.mean() / true.mean() <= 2.0
    assert np.mean(true < 2 * sigma) >= 0.9


@pytest.fixture(scope="module")
def runs_full(robot):
    truth = make_truth(robot, seed=8)
    poses = synthesize(truth, random_joint_poses(robot, 150, seed=9), seed=10)
    model = CalibrationModel(robot=robot).fit(poses.q, poses.T_IE)
    unc = model_uncertainty(model)
    return model, calibrated_domain(robot, poses.q), unc, truth, poses.T_LI, robot


def test_sigma_at_a_pose_is_the_least_squares_covariance_carried_to_the_tool_point(runs_full):
    model, _, unc, _, _, robot = runs_full
    q = random_joint_poses(robot, 5, seed=3)
    J = model.jacobian(q, model.predict(q))[:, :3, :]  # base-parameter columns, the fit's own covariance
    ref = np.sqrt(np.einsum("nij,jk,nik->n", J, model.covariance_, J))
    # the fit's covariance is at its variance factor; the uncertainty's at the final weights' own
    e = model.residual_at_fit_ / model.row_sigma_
    s2 = np.sum(e ** 2) / (model.n_equations_ - model.n_effective_)
    got = unc.sigma_m(robot, model.effect_set_, model.params_, model.effect_params_, q)
    assert np.allclose(got, ref * np.sqrt(s2 / model.variance_factor_), rtol=1e-3)


def test_a_wrist_that_barely_turned_is_named_barely_identified(robot):
    truth = make_truth(robot, seed=3)
    q = random_joint_poses(robot, 40, seed=4)
    q[:, 4] = np.deg2rad(17.2) + np.deg2rad(1.0) * (np.random.default_rng(1).uniform(size=40) - 0.5)
    poses = synthesize(truth, q, seed=5)
    m = CalibrationModel(robot=robot).fit(poses.q, poses.T_IE)
    ident = analyse(m, poses.q)
    assert ident.rank == ident.n_unknowns and ident.weak and not ident.unidentified
    text = " ".join(f.message for f in ident.findings(robot))
    assert "barely identified" in text and "joint 5 moved only 1.0°" in text


def test_a_least_squares_fit_holds_the_unidentified_directions_at_nominal(robot):
    truth = make_truth(robot, seed=3)
    q = random_joint_poses(robot, 40, seed=4)
    q[:, 5] = 0.3
    poses = synthesize(truth, q, seed=5)
    make = lambda **kw: CalibrationModel(robot=robot, **kw)  # noqa: E731
    first = make().fit(poses.q, poses.T_IE)
    assert not np.isfinite(first.condition_number_)
    model, ident = hold_unidentified(make, first, poses.q, poses.T_IE)
    assert len(ident.held) == ident.n_unknowns - ident.rank == 4
    assert np.isfinite(model.condition_number_)
    assert all(model.values_[n] == 0.0 for n in ident.held)
    # the same fit at the training poses: the held directions change nothing there
    assert np.allclose(model.residuals(poses.q, poses.T_IE), first.residuals(poses.q, poses.T_IE), atol=1e-9)
    assert [j for j, _, _ in ident.still] == [5]


def test_parameters_are_named_in_an_engineers_words(robot):
    assert parameter_words(robot, "pq1") == "joint 1's zero offset"
    assert parameter_words(robot, "pR_6E_x") == "the tool's rotation about its x axis"
    assert parameter_words(robot, "pR_12_y") == "joint 2's axis tilt about y"
    assert parameter_words(robot, "pL_I0_z", "tracker") == "the base's (the tracker's pose) position along z"


def test_export_and_compensate_append_the_columns_and_the_export_reads_back(still_run, tmp_path, capsys):
    d, _, poses = still_run
    if not (d / "run" / "calibration" / "metrics.json").exists():
        assert main(["calibrate", str(d / "run"), "--no-ann", "--quiet", "--no-report"]) == 0
    assert main(["export", str(d / "run"), "--csv", str(tmp_path / "x.csv")]) == 0
    rows = _rows(tmp_path / "x.csv")
    assert list(rows[0])[:14] == ["pose_id", "time_s", "q1", "q2", "q3", "q4", "q5", "q6", "x", "y", "z", "rx", "ry",
                                  "rz"]
    assert list(rows[0])[-2:] == ["in_domain", "sigma_mm"] and all(r["in_domain"] == "1" for r in rows)
    assert main(["import", str(tmp_path / "x.csv"), "--run", str(tmp_path / "again"), "--quiet"]) == 0
    from campaign.measure.store import open_run

    with open_run(tmp_path / "again") as store:
        assert not set(store.load_measured().context) & {"in_domain", "sigma_mm"}
    _joint_csv(tmp_path / "q.csv", poses.q[:3])
    assert main(["compensate", str(d / "run"), "--csv", str(tmp_path / "q.csv"), "--out", str(tmp_path / "c.csv")]) == 0
    head = list(_rows(tmp_path / "c.csv")[0])
    assert head[-4:] == ["converged", "within_limits", "in_domain", "sigma_mm"]


def test_two_reflectors_seen_name_the_unobserved_tool_rotation(robot):
    truth = make_truth(robot, seed=3)
    q = random_joint_poses(robot, 60, seed=4)
    poses = synthesize(truth, q, seed=5)
    pts = np.array([[0.05, 0, 0], [0, 0.05, 0], [0, 0, 0.05]])
    P = np.einsum("nij,kj->nki", poses.T_IE[:, :3, :3], pts) + poses.T_IE[:, None, :3, 3]
    P[:, 2] = np.nan  # the third reflector never seen
    make = lambda **kw: CalibrationModel(robot=robot, points=pts, **kw)  # noqa: E731
    model, ident = hold_unidentified(make, make().fit(q, P), q, P)
    assert ident.n_unknowns - ident.rank == 1 and np.isfinite(model.condition_number_)
    msg = ident.findings(robot)[0].message
    assert "rotation about their line is not observed" in msg and "the tool's rotation about its" in msg


def test_with_a_noise_floor_sigma_covers_an_unmodelled_effect_and_without_one_says_so(robot):
    from campaign.effects.base import make_effect

    c = make_effect("ground_compliance", robot).typical_params(0)
    truth = make_truth(robot, seed=3, effects={"ground_compliance": c})
    q = random_joint_poses(robot, 120, seed=4)
    poses = synthesize(truth, q, seed=5)
    model = CalibrationModel(robot=robot).fit(q, poses.T_IE)  # geometric only: the compliance is unmodelled
    # the floor as repeats would measure it: the noise alone, per axis at the tool point
    noise = poses.T_IE[:, :3, 3] - truth.pose_in_measured_frame(q, poses.T_LI)[:, :3, 3]
    floor = {"sigma_position_mm": list(1e3 * noise.std(axis=0)), "relative_uncertainty": 0.1}
    with_floor, without = model_uncertainty(model, floor), model_uncertainty(model)
    assert "parameter uncertainty only (no noise floor" in without.basis
    assert with_floor.systematic_sigma_m > 0 and "beyond the noise floor" in with_floor.basis
    fresh = random_joint_poses(robot, 400, seed=9)
    true = np.linalg.norm(model.predict(fresh)[:, :3, 3] - truth.pose_in_measured_frame(fresh, poses.T_LI)[:, :3, 3],
                          axis=1)
    sigma = with_floor.sigma_m(robot, model.effect_set_, model.params_, model.effect_params_, fresh)
    assert 0.5 <= sigma.mean() / true.mean() <= 2.0 and np.mean(true < 2 * sigma) >= 0.9
    # a geometric truth at the floor adds nothing
    geo = synthesize(make_truth(robot, seed=3), q, seed=5)
    m0 = CalibrationModel(robot=robot).fit(q, geo.T_IE)
    assert model_uncertainty(m0, floor).systematic_sigma_m == 0.0


def test_a_map_fit_holds_the_unidentified_directions_at_the_prior_and_says_so(still_run, tmp_path, capsys):
    d, _, _ = still_run
    run = tmp_path / "run"
    shutil.copytree(d / "run", run, ignore=shutil.ignore_patterns("calibration*"))
    capsys.readouterr()
    assert main(["calibrate", str(run), "--no-ann", "--quiet", "--no-report", "--model", "map"]) == 0
    out = capsys.readouterr()
    metrics = json.loads((run / "calibration" / "metrics.json").read_text())
    assert metrics["identifiability"]["held_at"] == "prior"
    msg = next(w["message"] for w in metrics["warnings"] if w["code"] == "unidentifiable")
    assert "joint 1 never moved" in msg and "at their prior" in msg
    line = next(x for x in out.out.splitlines() if x.startswith("estimated"))
    assert "inf" not in line and "4 direction(s) of them from the prior alone" in line


def test_a_grid_plan_with_repeats_keeps_poses_between_its_nodes_inside(robot):
    rng = np.random.default_rng(3)
    levels = np.linspace(0.1, 0.9, 5)  # each joint on 5 values of its range, as a plan's grid
    q = robot.q_lower + levels[rng.integers(0, 5, size=(300, robot.n_joints))] * (robot.q_upper - robot.q_lower)
    q = np.concatenate([q, q[:40]])  # repeats: identical joint vectors
    dom = calibrated_domain(robot, q)
    lo = robot.q_lower + 0.12 * (robot.q_upper - robot.q_lower)
    hi = robot.q_upper - 0.12 * (robot.q_upper - robot.q_lower)
    between = rng.uniform(lo, hi, size=(500, robot.n_joints))
    assert dom.contains(between).mean() >= 0.95


def test_the_poses_between_a_d_optimal_plans_extremes_are_inside(robot):
    rng = np.random.default_rng(4)
    span = robot.q_upper - robot.q_lower
    extreme = rng.uniform(0.0, 0.15, size=(200, robot.n_joints))  # each joint near one of its limits
    q = np.where(rng.uniform(size=extreme.shape) < 0.5, robot.q_lower + 0.05 * span + extreme * span,
                 robot.q_upper - 0.05 * span - extreme * span)
    dom = calibrated_domain(robot, q)
    interior = rng.uniform(robot.q_lower + 0.3 * span, robot.q_upper - 0.3 * span, size=(500, robot.n_joints))
    assert dom.contains(interior).mean() >= 0.95


def test_a_fold_ensembles_rows_add_the_spread_of_its_members(robot, tmp_path, capsys):
    from campaign.identify.use import CalibratedRobot

    from campaign.effects import make_effect
    from campaign.sim.truth import hidden_effect_params

    # something for the network to learn (compliant joints): a network with no significant held-out
    # gain is switched off and has no members (campaign.ann.gain)
    compliance = make_effect("joint_compliance", robot)
    truth = make_truth(robot, seed=7, effects={"joint_compliance": hidden_effect_params(compliance, 7)})
    poses = synthesize(truth, random_joint_poses(robot, 300, seed=8), seed=9)
    write_measured_csv(tmp_path / "m.csv", poses, robot)
    run = tmp_path / "run"
    assert main(["import", str(tmp_path / "m.csv"), "--run", str(run), "--quiet"]) == 0
    assert main(["calibrate", str(run), "--ann", "--ann-solver", "adam", "--sizes", "8x8", "--folds", "3",
                 "--epochs", "100", "--quiet", "--no-report"]) == 0
    assert not json.loads((run / "calibration" / "metrics.json").read_text())["ann_gain"]["geometric+ann"]["switched_off"]
    q = random_joint_poses(robot, 6, seed=10)
    _joint_csv(tmp_path / "q.csv", q)
    capsys.readouterr()
    assert main(["predict", str(run), "--csv", str(tmp_path / "q.csv"), "--out", str(tmp_path / "p.csv")]) == 0
    assert "spread of the network's 3 cross-validation members" in capsys.readouterr().out
    got = np.array([float(r["sigma_mm"]) for r in _rows(tmp_path / "p.csv")])
    # by hand: the physical model's sigma and the members' sample covariance at each pose
    physical = CalibratedRobot(run, stage="geometric").sigma_mm(q)
    members = CalibratedRobot(run).network.predict_members(q)[:, :, :3]
    spread = np.sqrt(np.sum(np.var(members, axis=0, ddof=1), axis=1)) * 1e3
    assert members.shape[0] == 3 and np.all(spread > 0)
    assert np.allclose(got, np.sqrt(physical ** 2 + spread ** 2), rtol=1e-3)
    on_nominal = CalibratedRobot(run, stage="ann")  # the network on the nominal model: its spread alone
    m0 = on_nominal.network.predict_members(q)[:, :, :3]
    assert np.allclose(on_nominal.sigma_mm(q), np.sqrt(np.sum(np.var(m0, axis=0, ddof=1), axis=1)) * 1e3, rtol=1e-9)


def test_a_prismatic_joint_that_never_moved_is_named_in_mm():
    from importlib import metadata

    from campaign.model.robot import RobotModel

    try:
        metadata.distribution("example-robot-data")
    except metadata.PackageNotFoundError:
        pytest.skip("example-robot-data (test extra) is not installed")
    robot = RobotModel.load("tiago")  # a prismatic torso, then 7 revolute joints
    q = random_joint_poses(robot, 80, seed=2)
    q[:, 0] = 0.2
    poses = synthesize(make_truth(robot, seed=1), q, seed=3)
    make = lambda **kw: CalibrationModel(robot=robot, **kw)  # noqa: E731
    model, ident = hold_unidentified(make, make().fit(q, poses.T_IE), q, poses.T_IE)
    msg = ident.findings(robot)[0].message
    assert msg.startswith("joint 1 never moved (q1 = 200.0 mm in all 80 training poses): its length offset and axis "
                          "direction cannot be identified")
    assert np.isfinite(model.condition_number_) and ident.held


def test_eight_poses_with_a_still_wrist_give_sigma_near_the_true_error_at_other_q6(robot, tmp_path, capsys):
    """Six training poses: the fit passes through its positions (noise 0.02 µm) and leave-one-out picks
    a MAP prior at strength 0.001. The directions the data do not see were dropped from the covariance
    (sigma_mm 0.03 mm at other q6 where the model was 1-2 mm off, 0 at training poses); at 31 times
    the tolerances they said 100 mm. They keep the tolerances."""
    truth = make_truth(robot, seed=3)
    q = random_joint_poses(robot, 8, seed=4)
    q[:, 5] = q[0, 5]
    poses = synthesize(truth, q, seed=5)
    write_measured_csv(tmp_path / "m.csv", poses, robot)
    assert main(["import", str(tmp_path / "m.csv"), "--run", str(tmp_path / "run"), "--quiet"]) == 0
    assert main(["calibrate", str(tmp_path / "run"), "--no-ann", "--quiet", "--no-report"]) == 0
    qq = np.repeat(q[:1], 7, axis=0)
    qq[1:, 5] = np.deg2rad([-150.0, -100.0, 0.0, 50.0, 100.0, 150.0])
    _joint_csv(tmp_path / "q.csv", qq)
    capsys.readouterr()
    assert main(["predict", str(tmp_path / "run"), "--csv", str(tmp_path / "q.csv"), "--out", str(tmp_path / "p.csv")]) == 0
    rows = _rows(tmp_path / "p.csv")
    sigma = np.array([float(r["sigma_mm"]) for r in rows])
    P = np.array([[float(r[k]) for k in "xyz"] for r in rows])
    err = 1e3 * np.linalg.norm(P - truth.pose_in_measured_frame(qq, poses.T_LI)[:, :3, 3], axis=1)
    assert sigma[0] > 0.2 * err[0] and sigma[1:].min() > 10 * sigma[0]
    assert 0.5 <= sigma[1:].mean() / err[1:].mean() <= 4.0


def test_a_domain_json_of_another_shape_is_one_line_never_a_silent_in_domain(still_run, tmp_path, capsys):
    """A domain.json whose joints list lost one (or whose poses were of another count) was reshaped into
    other training poses and answered in_domain silently (11 of 12 rows outside); another stage's
    parameters gave a traceback."""
    d, _, poses = still_run
    if not (d / "run" / "calibration" / "metrics.json").exists():
        assert main(["calibrate", str(d / "run"), "--no-ann", "--quiet", "--no-report"]) == 0
    _joint_csv(tmp_path / "q.csv", poses.q[:3])
    good = json.loads((d / "run" / "calibration" / "domain.json").read_text())
    for breaks, says in [(lambda x: x["domain"].update(joints=x["domain"]["joints"][:5]), "the domain has 5 joints"),
                         (lambda x: x["domain"].update(n_train=7), "the domain says 7 poses of 6 joints"),
                         (lambda x: x["uncertainty"]["geometric"].update(
                             names=x["uncertainty"]["geometric"]["names"][::-1]), "not of COMAU")]:
        run = tmp_path / f"run{len(says)}"
        shutil.copytree(d / "run", run, symlinks=True)
        bad = json.loads(json.dumps(good))
        breaks(bad)
        (run / "calibration" / "domain.json").write_text(json.dumps(bad))
        capsys.readouterr()
        assert main(["predict", str(run), "--csv", str(tmp_path / "q.csv")]) == 1
        err = capsys.readouterr().err.strip()
        assert says in err and "domain.json" in err and len(err.splitlines()) == 1


def test_joints_that_moved_only_together_are_named_and_poses_off_their_relation_are_outside(robot):
    """q2 + q3 held at one value over 30 poses: the warning named parameters but not the joints, and
    poses at other sums were inside (4 of 6, the model 0.5-1.6 mm off there)."""
    truth = make_truth(robot, seed=3)
    q = random_joint_poses(robot, 30, seed=4)
    total = q[0, 1] + q[0, 2]
    q[:, 2] = np.clip(total - q[:, 1], robot.q_lower[2] + 0.05, robot.q_upper[2] - 0.05)
    q[:, 1] = total - q[:, 2]
    poses = synthesize(truth, q, seed=5)
    model = CalibrationModel(robot=robot).fit(q, poses.T_IE)
    msg = " ".join(f.message for f in analyse(model, q).findings(robot))
    assert f"q2 + q3 = {np.degrees(total):.1f}° in all 30 training poses" in msg
    dom = calibrated_domain(robot, q)
    other = np.repeat(q[:1], 4, axis=0)
    other[:, 1] += np.deg2rad([-20.0, -5.0, 5.0, 20.0])  # within q2's training range, the sum changed
    assert dom.within_ranges(other).all() and not dom.contains(other).any()
    along = np.repeat(q[:1], 4, axis=0)
    along[:, 1] += np.deg2rad([-20.0, -5.0, 5.0, 20.0])
    along[:, 2] -= np.deg2rad([-20.0, -5.0, 5.0, 20.0])  # the sum kept
    assert dom.keeps_relations(along).all()
    assert "off the relation q2 + q3 constant" in dom.why_outside(other, [f"q{j}" for j in range(1, 7)])[0]
    assert calibrated_domain(robot, q[:10]).relations  # from N + 4 training poses on (12 measured)
    fresh = random_joint_poses(robot, 500, seed=9)  # a campaign spread over every joint keeps no relation
    assert calibrated_domain(robot, random_joint_poses(robot, 12, seed=2)).keeps_relations(fresh).all()


def test_two_reflectors_warn_that_the_tool_origin_is_unseen_and_sigma_carries_its_tolerance(robot):
    """Two reflectors declared (a base set of their own, so no direction is unidentified among it):
    no warning, strict passed, and sigma_mm at the tool origin was 0.007 mm where the model was 0.08 mm
    off. Three reflectors add nothing."""
    truth = make_truth(robot, seed=3)
    q = random_joint_poses(robot, 40, seed=4)
    poses = synthesize(truth, q, seed=5)
    pts = np.array([[0.05, 0, 0], [0, 0.05, 0], [0, 0, 0.05]])
    P = np.einsum("nij,kj->nki", poses.T_IE[:, :3, :3], pts) + poses.T_IE[:, None, :3, 3]
    fresh = random_joint_poses(robot, 200, seed=9)
    true_T = truth.pose_in_measured_frame(fresh, poses.T_LI)
    out = {}
    for k in (2, 3):
        make = lambda **kw: CalibrationModel(robot=robot, points=pts[:k], **kw)  # noqa: E731
        model, ident = hold_unidentified(make, make().fit(q, P[:, :k]), q, P[:, :k])
        unc = model_uncertainty(model)
        sigma = unc.sigma_m(robot, model.effect_set_, model.params_, model.effect_params_, fresh)
        err = np.linalg.norm(model.predict(fresh)[:, :3, 3] - true_T[:, :3, 3], axis=1)
        out[k] = (" ".join(f.message for f in ident.findings(robot)), sigma.mean() / err.mean())
    assert "the tool frame's origin moves along what they do not see (the tool's rotation about" in out[2][0]
    assert out[2][1] >= 1.0 and "origin moves" not in out[3][0] and 0.5 <= out[3][1] <= 2.0


def test_one_reflector_says_the_tool_orientation_is_not_observed(robot):
    """Positions only: nothing said that predict's rx, ry, rz are the nominal tool's; --strict passed."""
    truth = make_truth(robot, seed=3)
    q = random_joint_poses(robot, 30, seed=4)
    poses = synthesize(truth, q, seed=5)
    msgs = {}
    for position_only in (True, False):
        make = lambda **kw: CalibrationModel(robot=robot, position_only=position_only, **kw)  # noqa: E731
        _, ident = hold_unidentified(make, make().fit(q, poses.T_IE), q, poses.T_IE)
        msgs[position_only] = " ".join(f.message for f in ident.findings(robot))
    assert "the tool's orientation is not observed" in msgs[True] and "rx, ry, rz" in msgs[True]
    assert msgs[False] == ""


def test_compensate_strict_says_why_each_command_is_outside(still_run, tmp_path, capsys):
    """compensate --strict named the pose ids only; predict --strict said why."""
    d, _, poses = still_run
    if not (d / "run" / "calibration" / "metrics.json").exists():
        assert main(["calibrate", str(d / "run"), "--no-ann", "--quiet", "--no-report"]) == 0
    q = np.repeat(poses.q[:1], 2, axis=0)
    q[1, 0] = np.deg2rad(90.0)
    _joint_csv(tmp_path / "q.csv", q)
    capsys.readouterr()
    assert main(["compensate", str(d / "run"), "--csv", str(tmp_path / "q.csv"), "--strict"]) == 1
    err = capsys.readouterr().err.strip()
    assert "(pose_id 1 (q1 beyond the training range)): nothing written" in err and len(err.splitlines()) == 1


def test_export_of_a_calibration_before_domain_json_says_it_has_no_columns_not_empty_ones(still_run, tmp_path, capsys):
    """It said 'no in_domain, sigma_mm columns: ... in_domain and sigma_mm left empty' (both at once)."""
    d, _, _ = still_run
    if not (d / "run" / "calibration" / "metrics.json").exists():
        assert main(["calibrate", str(d / "run"), "--no-ann", "--quiet", "--no-report"]) == 0
    old = tmp_path / "old"
    shutil.copytree(d / "run", old, symlinks=True)
    (old / "calibration" / "domain.json").unlink()
    capsys.readouterr()
    assert main(["export", str(old), "--csv", str(tmp_path / "e.csv")]) == 0
    said = capsys.readouterr().out
    assert "no in_domain, sigma_mm columns: no calibrated domain" in said and "left empty" not in said
    assert list(_rows(tmp_path / "e.csv")[0])[-1] == "rz"
