"""diagnose names the joints an effect acts on, makes every effect of the model earn its place,
tells time from pose, and stops at once on a noise-free cell (issue 31 parts 1, 2, 3, 7).

Each case hides a truth in a simulated campaign; the pipeline's answer is compared with it after
diagnose answered."""

import json

import numpy as np
import pytest
import yaml

from campaign.cli import main
from campaign.diagnose import diagnose
from campaign.diagnose.timing import rank_by_time_test, same_pose_visits, time_test
from campaign.effects import make_effect
from campaign.measure.drift import same_pose_groups
from campaign.measure.csvio import write_measured_csv
from campaign.model.robot import RobotModel
from campaign.run import RunFolder
from campaign.sim.truth import make_truth, random_joint_poses, synthesize
from test_diagnose_open_world import WarmUp, make_open_run


def test_a_compliant_joint_4_is_named_joint_compliance_of_joint_4_and_nothing_else(tmp_path, robot):
    run, _, _ = make_open_run(tmp_path, robot, [make_effect("joint_compliance:4", robot)], [2e-3], n=300)
    d = diagnose(run, folds=4)
    assert d.verdict == "joint_compliance" and d.verdict_spec == "joint_compliance:4", d.text()
    out = d.as_json()
    assert out["verdict_label"] == "joint_compliance of joint 4"
    assert out["config_line"] == "effects: [joint_compliance:4]"
    assert "verdict: add joint_compliance of joint 4" in d.text()
    best = out["ranking"][0]
    assert best["joints"] == [4] and best["joint_search"][0]["joints"] == [4]


def test_an_effect_that_does_not_earn_its_place_is_named_for_removal(tmp_path, robot):
    run, _, _ = make_open_run(tmp_path, robot, [make_effect("joint_compliance:4", robot)], [2e-3], n=300)
    d = diagnose(run, folds=4, effects="backlash:4,joint_compliance:2,4", candidates="ground_compliance")
    by = {(c.spec, c.joint): c for c in d.contributions}
    assert by[("joint_compliance:2,4", 4)].earns_place  # the true joint: taking it out doubles the error
    assert by[("joint_compliance:2,4", 4)].gain_mm > 5 * by[("joint_compliance:2,4", 4)].gain_se_mm
    assert not by[("backlash:4", None)].earns_place and not by[("joint_compliance:2,4", 2)].earns_place
    assert d.removal.spec == "backlash:4"
    assert d.effects_after_removal() == ("joint_compliance:2,4",)
    out = d.as_json()
    assert out["remove"]["effect"] == "backlash:4" and out["remove"]["effects_after"] == ["joint_compliance:2,4"]
    assert "take out backlash of joint 4" in d.text()


def test_the_contribution_matches_a_refit_without_the_effect(tmp_path, robot):
    """The linearised removal against a full refit of the model without the effect on the same folds."""
    from campaign.identify.solver import CalibrationModel

    run, _, _ = make_open_run(tmp_path, robot, [make_effect("joint_compliance:4", robot)], [2e-3], n=240)
    d = diagnose(run, folds=3, effects="joint_compliance:4", candidates="drift", structure=False)
    (c,) = d.contributions
    from campaign.measure.store import open_run

    with open_run(run) as store:
        poses = store.load_measured()
    ids = {int(p): i for i, p in enumerate(poses.pose_id)}
    errors = []
    for k, fold_ids in enumerate(d.fold_pose_ids):
        out = np.array([ids[p] for p in fold_ids])
        fit = np.array([ids[p] for j, f in enumerate(d.fold_pose_ids) if j != k for p in f])
        m = CalibrationModel(robot=robot).fit(poses.q[fit], poses.T_IE[fit])
        errors.append(np.linalg.norm(m.residuals(poses.q[out], poses.T_IE[out])[:, :3], axis=1) * 1e3)
    refit = float(np.concatenate(errors).mean())
    assert c.heldout_mean_position_mm_without == pytest.approx(refit, rel=0.03)


def test_two_effects_on_a_7_joint_arm_end_on_their_joints_alone(tmp_path):
    panda = RobotModel.load("panda")
    hidden = {"joint_compliance:4": [3e-3], "backlash:6": [1.5e-3]}
    truth = make_truth(panda, seed=2, effects=hidden)
    q = random_joint_poses(panda, 300, seed=4)
    index = np.concatenate([np.repeat(i, 3) if i % 20 == 0 else [i] for i in range(len(q))])
    poses = synthesize(truth, q[index], seed=5)
    write_measured_csv(tmp_path / "m.csv", poses)
    run = tmp_path / "run"
    assert main(["import", str(tmp_path / "m.csv"), "--run", str(run), "--robot", "panda"]) == 0
    folder = RunFolder(run)
    steps = []
    for _ in range(5):  # every round re-earns the model: take out before adding
        d = diagnose(run, folds=4, candidates="joint_compliance,backlash,ground_compliance,cyclic")
        if d.removal is not None:
            steps.append(f"-{d.removal.label}")
            folder.set_effects(d.effects_after_removal())
        elif d.verdict not in (None, "unexplained"):
            steps.append(f"+{d.verdict_spec}")
            folder.add_effects([d.verdict_spec])
        else:
            break
    assert d.verdict is None and sorted(folder.effects) == sorted(hidden), (steps, d.text())


def test_time_ranked_first_by_the_tour_is_dropped_when_the_same_poses_do_not_move():
    rng = np.random.default_rng(0)
    q = rng.uniform(-1, 1, (40, 6))
    t = np.arange(40) * 60.0
    again = np.concatenate([q[:10], q[:10] + np.r_[np.zeros(5), 1e-6]])  # an hour later, the last joint 1 µrad on
    centres = rng.uniform(-1, 1, (10, 3))
    xyz = np.r_[centres, centres] + rng.normal(0, 1e-5, (20, 3))
    times = np.concatenate([t[:10], t[:10] + 3600.0])
    group = same_pose_groups(again)
    assert len(same_pose_visits(group, times)) == 10
    still = time_test(xyz, group, times, np.full(3, 1e-5))
    assert still.poses == 10 and still.dof == 30 and not still.moved
    moved = time_test(xyz + np.r_[np.zeros((10, 3)), np.full((10, 3), 5e-5)], group, times, np.full(3, 1e-5))
    assert moved.moved and moved.p_value < 1e-6
    assert rank_by_time_test(["time_s", "q2", "q3"], still) == ["q2", "q3"]
    assert rank_by_time_test(["q2", "time_s"], moved) == ["time_s", "q2"]
    assert rank_by_time_test(["time_s", "q2"], None) == ["time_s", "q2"]


def test_time_test_statistic_is_chi2_under_no_motion():
    """Pure noise: the p-values of many independent tests are uniform (KS test)."""
    from scipy import stats

    rng = np.random.default_rng(1)
    q = np.repeat(rng.uniform(-1, 1, (8, 6)), 4, axis=0)
    t = np.tile([0.0, 10.0, 4000.0, 8000.0], 8)  # two back-to-back readings, then two visits later
    group = same_pose_groups(q)
    ps = [time_test(rng.normal(0, 2e-5, (32, 3)), group, t, np.full(3, 2e-5)).p_value for _ in range(300)]
    assert stats.kstest(ps, "uniform").pvalue > 0.01


def test_warm_up_keeps_time_first_and_diagnosis_json_records_the_test(tmp_path, robot):
    run, _, _ = make_open_run(tmp_path, robot, [WarmUp(robot)], [1.5e-4], n=300)
    # 15 early poses measured again at the end of the campaign (as auto does): the same joints
    from campaign.measure.store import open_run

    with open_run(run) as store:
        p = store.load_measured()
    base = make_truth(robot, seed=3)
    from campaign.effects.base import EffectSet

    truth = base.__class__(base.robot, base.p_e, base.T_LI, base.noise_m, base.resolution_m,
                           EffectSet((WarmUp(robot),)), np.array([1.5e-4]))
    again = synthesize(truth, p.q[20:35], seed=9, time_s=p.time_s[-1] + 60.0 + 20.0 * np.arange(15))
    merged = type(p)(np.r_[p.pose_id, p.pose_id[20:35] + 10 ** 9], np.r_[p.time_s, again.time_s],
                     np.r_[p.q, again.q], np.r_[p.T_IE, again.T_IE], {}, p.T_LI)
    write_measured_csv(tmp_path / "all.csv", merged)
    run2 = tmp_path / "run2"
    assert main(["import", str(tmp_path / "all.csv"), "--run", str(run2)]) == 0
    assert main(["diagnose", str(run2), "--json", "--folds", "3", "--candidates", "drift"]) == 0
    out = json.loads((run2 / "diagnose" / "diagnosis.json").read_text())
    assert out["unexplained"]["depends_on"][0] == "time_s", out["unexplained"]
    tt = out["time_test"]
    assert tt["moved"] and tt["poses_used"] == 15 and tt["p_value"] < 0.01 and tt["statistic"] > tt["dof"]


def test_a_noise_free_cell_stops_at_once_with_a_clear_line(tmp_path, robot):
    truth = make_truth(robot, seed=4, noise_m=0.0, resolution_m=0.0)
    q = random_joint_poses(robot, 120, seed=4)
    index = np.concatenate([np.repeat(i, 2) if i % 10 == 0 else [i] for i in range(len(q))])
    write_measured_csv(tmp_path / "m.csv", synthesize(truth, q[index], seed=5))
    run = tmp_path / "run"
    assert main(["import", str(tmp_path / "m.csv"), "--run", str(run)]) == 0
    d = diagnose(run, folds=3)
    assert d.round_off and d.verdict is None and d.at_floor and d.structure is None and not d.ranking
    assert d.heldout_mean_position_mm < 1e-6
    assert "noise-free measurements, and the model fits them to round-off" in d.text()
    assert not d.worth_a_round


def test_time_test_counts_the_floors_own_sampling_error():
    """σ estimated from 9 back-to-back differences each time: with the F distribution the p-values of
    a pose that does not move stay uniform; read as a known σ they would call it moving far too often."""
    from scipy import stats

    rng = np.random.default_rng(2)
    q = np.repeat(rng.uniform(-1, 1, (1, 6)), 10, axis=0)
    t = np.arange(10) * 400.0  # ten visits of one reference pose (drift checks)
    group = same_pose_groups(q)
    p_f, p_chi2 = [], []
    for _ in range(400):
        sigma_hat = np.sqrt(np.mean(rng.normal(0, 6e-6, (9, 3)) ** 2 * 2 / 2, axis=0))  # 9 differences / √2
        xyz = rng.normal(0, 6e-6, (10, 3))
        p_f.append(time_test(xyz, group, t, sigma_hat, sigma_dof=27).p_value)
        p_chi2.append(time_test(xyz, group, t, sigma_hat).p_value)
    assert stats.kstest(p_f, "uniform").pvalue > 0.01
    assert np.mean(np.array(p_chi2) < 0.01) > 3 * np.mean(np.array(p_f) < 0.01) + 0.01
