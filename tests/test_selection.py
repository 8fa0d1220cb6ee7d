"""Optimal pose selection (issue 14): the design's algebra, its prediction, and `plan --select`."""

import json

import numpy as np
import pytest

from campaign.cli import main
from campaign.measure.reflectors import pose_from_reflectors, transform_points
from campaign.model.kinematics import forward, pose_error
from campaign.plan import selection as S
from campaign.sim.truth import make_truth, random_joint_poses, synthesize


@pytest.fixture(scope="module")
def candidates(robot):
    return random_joint_poses(robot, 300, seed=7)


@pytest.fixture(scope="module")
def info(robot, candidates):
    return S.information_model(robot, candidates)


def test_rank_six_updates_equal_the_direct_inverse_and_log_det(info):
    d = S.Design(info, "D")
    rng = np.random.default_rng(0)
    picks = rng.choice(info.n_candidates, 40, replace=False)
    for j in picks:
        d.add(j)
    d.remove(picks[3])
    kept = np.delete(picks, 3)
    M = info.information(kept) + S.RIDGE * np.eye(info.n_unknowns)
    assert d.criterion_value() == pytest.approx(np.linalg.slogdet(M)[1], rel=1e-9)
    G = info.blocks @ np.linalg.inv(M) @ np.swapaxes(info.blocks, 1, 2)
    np.testing.assert_allclose(d.G, G, atol=1e-8 * np.abs(G).max())
    # the gain of adding a candidate is the change of log det (matrix determinant lemma)
    j = int(rng.integers(info.n_candidates))
    M2 = M + info.blocks[j].T @ info.blocks[j]
    assert d.gains()[j] == pytest.approx(np.linalg.slogdet(M2)[1] - np.linalg.slogdet(M)[1], rel=1e-8)


def test_d_optimal_beats_every_random_subset_on_log_det_and_exchanges_never_lose(info):
    greedy = S.select(info, 20, exchange=False)
    best = S.select(info, 20)
    rng = np.random.default_rng(1)
    random = [S.log_det(info, rng.choice(info.n_candidates, 20, replace=False)) for _ in range(50)]
    assert greedy.log_det > max(random)
    assert best.log_det >= greedy.log_det - 1e-9
    assert len(set(best.index.tolist())) == 20


def test_a_and_i_criteria_lower_their_own_trace_below_d_and_random(info):
    W = S.position_weight(info)
    n = 20
    rng = np.random.default_rng(2)

    def trace(idx, weight):
        Minv = np.linalg.inv(info.information(idx))
        return np.trace(Minv if weight is None else weight @ Minv)

    for crit, weight in (("A", None), ("I", W)):
        sel = S.select(info, n, criterion=crit)
        t = trace(sel.index, weight)
        assert t < trace(S.select(info, n).index, weight)
        assert t < min(trace(rng.choice(info.n_candidates, n, replace=False), weight) for _ in range(20))


def test_kabsch_pose_noise_equals_monte_carlo_of_the_three_reflectors(robot, candidates):
    q = candidates[:3]
    cov = S.reflector_pose_noise(robot, q, 1e-5)
    T = forward(robot, q)
    P = transform_points(T, np.broadcast_to(robot.reflector_positions_in_E, (3, 3, 3)))
    rng = np.random.default_rng(3)
    draws = []
    for _ in range(4000):
        Tm, _ = pose_from_reflectors(np.eye(4), robot.reflector_positions_in_E, P + rng.normal(0, 1e-5, P.shape))
        draws.append(pose_error(Tm, T))
    d = np.array(draws)  # (draws, 3, 6)
    for k in range(3):
        emp = np.cov(d[:, k].T)
        np.testing.assert_allclose(np.sqrt(np.diag(emp)), np.sqrt(np.diag(cov[k])), rtol=0.06)


def test_predicted_error_against_the_truth_matches_the_real_identification_within_20_percent(robot, candidates, info):
    """Monte-Carlo of the real pipeline (reflector noise → Kabsch → CalibrationModel) on one design."""
    from campaign.identify.solver import CalibrationModel

    sel = S.select(info, 25)
    pred = S.predict_accuracy(info, sel.index)
    truth = make_truth(robot, seed=4)
    q = candidates[sel.index]
    errs, held = [], []
    for seed in range(12):
        meas = synthesize(truth, q, seed=100 + seed)
        model = CalibrationModel(robot=robot).fit(meas.q, meas.T_IE)
        # the truth as seen in this campaign's set-up frame, at every candidate
        T_true = truth.pose_in_measured_frame(candidates, meas.T_LI)
        errs.append(np.mean(np.linalg.norm(pose_error(model.predict(candidates), T_true)[:, :3], axis=1)))
        other = synthesize(truth, candidates, seed=500 + seed)
        T_other = truth.pose_in_measured_frame(candidates, meas.T_LI) @ np.linalg.inv(
            truth.pose_in_measured_frame(candidates, other.T_LI)) @ other.T_IE
        held.append(np.mean(np.linalg.norm(pose_error(model.predict(candidates), T_other)[:, :3], axis=1)))
    assert np.mean(errs) * 1e3 == pytest.approx(pred.model_position_mm, rel=0.2)
    assert np.mean(held) * 1e3 == pytest.approx(pred.heldout_position_mm, rel=0.2)


def test_smallest_design_reaching_a_target_is_the_first_greedy_prefix_that_does(info):
    full = S.select(info, 60, exchange=False).index
    target = S.predict_accuracy(info, full[:30]).model_position_mm * 1.0001
    n, sel, pred = S.smallest_reaching(info, target, max_n=60)
    assert pred.model_position_mm <= target
    assert S.predict_accuracy(info, full[: n - 1]).model_position_mm > target
    assert n <= 30


def test_repeats_are_measured_back_to_back_with_their_own_ids():
    """Issue 20: the copies of a repeated pose one tour pose apart (p, a, p', b, p''), not
    spread over the tour, so that their differences are the noise and not the drift."""
    choice = S.CampaignChoice(np.array([5, 7, 9]), np.array([11]), np.array([105, 119]), 3, None, {})
    tour = np.arange(100, 120)
    order = choice.with_repeats(tour)
    extra = order[order >= S.REPEAT_ID_STRIDE]
    assert sorted(extra.tolist()) == sorted([105 + S.REPEAT_ID_STRIDE, 119 + S.REPEAT_ID_STRIDE,
                                             105 + 2 * S.REPEAT_ID_STRIDE, 119 + 2 * S.REPEAT_ID_STRIDE])
    np.testing.assert_array_equal(order[order < S.REPEAT_ID_STRIDE], tour)  # the tour itself unchanged
    at = np.flatnonzero(S.base_pose_id(order) == 105)
    np.testing.assert_array_equal(np.diff(at), [2, 2])  # one tour pose between successive measurements
    np.testing.assert_array_equal(order[at[0]:at[-1] + 1], [105, 106, 105 + S.REPEAT_ID_STRIDE, 107,
                                                            105 + 2 * S.REPEAT_ID_STRIDE])
    # the tour's last pose: its repeats follow it directly
    np.testing.assert_array_equal(order[-3:], [119, 119 + S.REPEAT_ID_STRIDE, 119 + 2 * S.REPEAT_ID_STRIDE])
    layout = S.repeats_in_tour(order)
    assert layout["poses"] == 2 and layout["measurements"] == {"105": 3, "119": 3} and layout["max_steps_between"] == 2


@pytest.fixture(scope="module")
def selected_run(tmp_path_factory):
    run = tmp_path_factory.mktemp("select") / "run"
    assert main(["plan", "--run", str(run), "--grid-scale", "0.6", "--select", "12", "--quiet"]) == 0
    return run


def _read_csv(path):
    lines = path.read_text().splitlines()
    return lines[0], [[float(v) for v in ln.split(",")] for ln in lines[1:] if ln]


def test_plan_select_writes_the_design_validation_and_repeats(selected_run):
    s = json.loads((selected_run / "plan" / "summary.json").read_text())
    sel = s["selection"]
    assert sel["selected"] == 12 and sel["validation"] == 30 and sel["repeated_poses"] == 3
    header, rows = _read_csv(selected_run / "plan" / "poses.csv")
    assert header == "pose_id,q1,q2,q3,q4,q5,q6"
    ids = np.array([r[0] for r in rows], dtype=np.int64)
    assert len(ids) == len(set(ids)) == 12 + 30 + 3 * (S.REPEAT_TIMES - 1) - s["tour"]["dropped"]
    _, val = _read_csv(selected_run / "plan" / "validation.csv")
    assert set(int(v[0]) for v in val) <= set(ids.tolist())
    _, reps = _read_csv(selected_run / "plan" / "repeats.csv")
    q_of = {int(r[0]): r[1:] for r in rows}
    for pid, orig in reps:
        assert q_of[int(pid)] == q_of[int(orig)]  # identical joint vectors
    assert sel["predicted"]["heldout_position_mm"] > sel["predicted"]["noise_position_mm"] > 0
    assert s["estimated_campaign"]["total_s"] < 3600


def test_the_default_plan_is_the_short_campaign_and_all_plans_every_suitable_pose(tmp_path):
    short, full = tmp_path / "short", tmp_path / "full"
    assert main(["plan", "--run", str(short), "--grid-scale", "0.6", "--quiet"]) == 0
    assert main(["plan", "--run", str(full), "--grid-scale", "0.6", "--all", "--quiet"]) == 0
    s = json.loads((short / "plan" / "summary.json").read_text())
    f = json.loads((full / "plan" / "summary.json").read_text())
    assert s["campaign"]["mode"] == "default" and s["selection"]["select"] == S.DEFAULT_SELECT == 120
    assert (s["selection"]["selected"], s["selection"]["validation"], s["selection"]["repeated_poses"]) == (120, 30, 3)
    _, rows = _read_csv(short / "plan" / "poses.csv")
    assert len(rows) == 120 + 30 + 3 * (S.REPEAT_TIMES - 1) - s["tour"]["dropped"]
    assert (short / "plan" / "validation.csv").is_file()
    assert f["campaign"]["kind"] == "all" and "selection" not in f and not (full / "plan" / "validation.csv").exists()
    _, rows = _read_csv(full / "plan" / "poses.csv")
    assert len(rows) + f["tour"]["dropped"] == f["suitable"] == s["suitable"] > 150
    assert s["estimated_campaign"]["total_s"] < 0.5 * f["estimated_campaign"]["total_s"]


def test_a_cell_with_fewer_suitable_poses_than_the_short_campaign_plans_them_all(tmp_path):
    run = tmp_path / "run"
    assert main(["plan", "--run", str(run), "--grid-scale", "0.4", "--quiet"]) == 0
    s = json.loads((run / "plan" / "summary.json").read_text())
    assert s["suitable"] < 150 and s["campaign"]["mode"] == "all_few" and "selection" not in s
    assert s["tour"]["poses"] + s["tour"]["dropped"] == s["suitable"]


def test_the_predicted_accuracy_takes_the_tracker_noise_from_campaign_yaml(tmp_path, selected_run):
    """Twice the stated noise: the noise alone predicts exactly twice the error, and the model's
    predicted errors about twice (the estimator's covariance scales with σ²; the Bayesian design
    weighs the tolerances' prior against an information that falls with σ², so on 12 poses it
    may choose a few others: within 10 %). The same σ, the same plan, byte for byte."""
    (tmp_path / "campaign.yaml").write_text("tracker: {noise_m: 2.0e-05}\n")
    run = tmp_path / "run"
    assert main(["plan", "--config", str(tmp_path / "campaign.yaml"), "--run", str(run), "--grid-scale", "0.6",
                 "--select", "12", "--quiet"]) == 0
    a = json.loads((selected_run / "plan" / "summary.json").read_text())["selection"]
    b = json.loads((run / "plan" / "summary.json").read_text())["selection"]
    assert (a["tracker_noise_m"], b["tracker_noise_m"]) == (S.TRACKER_NOISE_M, 2e-5)
    assert b["predicted"]["noise_position_mm"] == pytest.approx(2 * a["predicted"]["noise_position_mm"], rel=1e-6)
    for key in ("model_position_mm", "heldout_position_mm", "model_orientation_mrad"):
        assert b["predicted"][key] == pytest.approx(2 * a["predicted"][key], rel=0.10), key
    (tmp_path / "same.yaml").write_text(f"tracker: {{noise_m: {S.TRACKER_NOISE_M:.6e}}}\n")
    same = tmp_path / "same"
    assert main(["plan", "--config", str(tmp_path / "same.yaml"), "--run", str(same), "--grid-scale", "0.6",
                 "--select", "12", "--quiet"]) == 0
    assert (same / "plan" / "poses.csv").read_text() == (selected_run / "plan" / "poses.csv").read_text()


def test_calibrate_tests_on_the_plans_validation_poses(selected_run):
    from campaign.identify.split import run_split

    _, rows = _read_csv(selected_run / "plan" / "poses.csv")
    _, val = _read_csv(selected_run / "plan" / "validation.csv")
    ids = np.array([r[0] for r in rows], dtype=np.int64)
    is_test = run_split(selected_run, ids)
    assert set(ids[is_test].tolist()) == set(int(v[0]) for v in val)


def test_a_plan_of_every_pose_removes_a_previous_validation_list(tmp_path, selected_run):
    import shutil

    run = tmp_path / "run"
    shutil.copytree(selected_run, run)
    assert main(["plan", "--run", str(run), "--grid-scale", "0.4", "--all", "--quiet"]) == 0
    assert not (run / "plan" / "validation.csv").exists()


@pytest.mark.parametrize("argv, message", [
    (["--select", "3"], "at least 5 poses"),
    (["--select", "12", "--for-effects", "thermal"], "known only when measuring"),
    (["--select", "12", "--for-effects", "nonsense"], "unknown effect 'nonsense'"),
    (["--budget", "0.001"], "too short"),
    (["--all", "--for-effects", "ground_compliance"], "--all measures every suitable pose"),
    (["--all", "--repeats", "2"], "--all measures every suitable pose"),
])
def test_bad_selection_requests_get_one_line(tmp_path, capsys, argv, message):
    assert main(["plan", "--run", str(tmp_path / "r"), "--grid-scale", "0.4", "--quiet", *argv]) == 1
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and message in err[0]


def test_budget_plan_fits_its_hours(tmp_path):
    run = tmp_path / "run"
    assert main(["plan", "--run", str(run), "--grid-scale", "0.6", "--budget", "0.4", "--quiet"]) == 0
    s = json.loads((run / "plan" / "summary.json").read_text())
    assert s["estimated_campaign"]["total_s"] <= 0.4 * 3600 * 1.02
    assert s["selection"]["selected"] >= 5


def test_a_small_campaign_is_tested_on_its_validation_poses_and_trains_no_network(tmp_path, selected_run, capsys):
    import shutil

    run = tmp_path / "run"
    shutil.copytree(selected_run, run)
    assert main(["run", str(run), "--sim", "--quiet"]) == 0
    capsys.readouterr()
    assert main(["calibrate", str(run), "--quiet"]) == 0
    out = capsys.readouterr().out
    assert "no neural compensator" in out and "below the 250" in out
    m = json.loads((run / "calibration" / "metrics.json").read_text())
    assert m["order"] == ["nominal", "geometric"]
    _, val = _read_csv(run / "plan" / "validation.csv")
    assert m["stages"]["geometric"]["test"]["n_poses"] == len(val)
    assert m["stages"]["geometric"]["train"]["n_poses"] == 12 + 3 * (S.REPEAT_TIMES - 1)


def test_plan_target_mm_picks_a_campaign_predicted_to_reach_it(tmp_path):
    run = tmp_path / "run"
    assert main(["plan", "--run", str(run), "--grid-scale", "0.6", "--target-mm", "0.004", "--quiet"]) == 0
    sel = json.loads((run / "plan" / "summary.json").read_text())["selection"]
    assert sel["target_mm"] == 0.004
    assert sel["predicted"]["model_position_mm"] <= 0.004
    assert 5 <= sel["selected"] < 200
