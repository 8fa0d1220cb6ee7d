"""The folds against the test set (campaign.diagnose.testset).

A run whose training poses hold joint 5 at two values (as an optimal design does) while its test
poses spread it, and whose truth hides a run-out of joint 5 (written here): on the folds the model
is at the noise (the geometry absorbs any function of two values), on the test set it is not.
Diagnose must not say "at the measurement noise": it names q5 as the joint the training poses do
not vary. Without the hidden effect the same design passes the check. The truth's parameters are
only compared with nothing: the test asserts what the pipeline says about its own data.
"""

import json

import numpy as np
import pytest
import yaml

from campaign.cli import main
from campaign.diagnose import diagnose
from campaign.diagnose.testset import check_test_set, joint_coverage
from campaign.effects import Effect
from campaign.effects.base import EffectSet
from campaign.identify.split import train_test_split
from campaign.measure.csvio import write_measured_csv
from campaign.sim.truth import make_truth, random_joint_poses, synthesize


class WristRunout(Effect):
    """joint 5's axis tilts about y of its frame by a sin(q5) + b cos(q5)."""

    name = "wrist_runout_test"
    param_names = ("a", "b")
    param_units = ("rad", "rad")

    def joint_twist(self, params, q, context):
        xi = np.zeros((len(q), q.shape[1], 6))
        xi[:, 4, 4] = params[0] * np.sin(q[:, 4]) + params[1] * np.cos(q[:, 4])
        return xi


def two_valued_run(tmp_path, robot, effects=(), theta=(), n=260, seed=5):
    """A run of ``n`` poses whose training poses have q5 = ±0.85 rad and whose test poses spread it."""
    base = make_truth(robot, seed=seed)
    truth = base.__class__(base.robot, base.p_e, base.T_LI, base.noise_m, base.resolution_m,
                           EffectSet(tuple(effects)), np.asarray(theta, dtype=float))
    q = random_joint_poses(robot, n, seed=seed + 1)
    ids = synthesize(truth, q, seed=seed + 2).pose_id  # the ids do not depend on q
    train = ~train_test_split(ids)
    rng = np.random.default_rng(seed + 3)
    q[train, 4] = rng.choice([-0.85, 0.85], int(train.sum()))
    q[~train, 4] = rng.uniform(-0.85, 0.85, int((~train).sum()))
    poses = synthesize(truth, q, seed=seed + 2)
    csv = tmp_path / "m.csv"
    write_measured_csv(csv, poses)
    run = tmp_path / "run"
    assert main(["import", str(csv), "--run", str(run)]) == 0
    # the floor from the tracker's stated noise (the test's own statement of its tracker)
    (run / "campaign.yaml").write_text(yaml.safe_dump({"tracker": {"noise_m": 1e-5}}))
    return run


def test_the_check_itself_on_known_numbers():
    rng = np.random.default_rng(0)
    folds = np.abs(rng.normal(0.01, 0.003, 160))
    q_tr = np.column_stack([rng.uniform(-1, 1, 160), rng.choice([-0.8, 0.8], 160)])
    q_te = np.column_stack([rng.uniform(-1, 1, 30), rng.uniform(-0.8, 0.8, 30)])
    bad = check_test_set(np.abs(rng.normal(0.05, 0.02, 30)), folds, q_tr, q_te)
    assert not bad.holds and bad.ratio > 3 and bad.p_value < 1e-6
    assert bad.sparse_joints == ["q2"]  # q1 spread over its range: covered
    cov = {c.joint: c for c in joint_coverage(q_tr, q_te)}
    assert cov["q2"].distinct == 2 and 0.15 < cov["q2"].gap_share < 0.35  # uniform over ±0.8 to ±0.8: 0.25 median
    assert cov["q1"].gap_share < 0.02
    good = check_test_set(np.abs(rng.normal(0.01, 0.003, 30)), folds, q_tr, q_te)
    assert good.holds, good.text()
    # materially worse but not significantly (3 poses), and significantly but not materially
    assert check_test_set([0.02, 0.01, 0.03], folds, q_tr, q_te[:3]).holds
    assert check_test_set(folds * 1.2, folds, q_tr, q_tr).holds
    assert check_test_set([0.05, 0.06], folds, q_tr, q_te[:2]) is None


def test_an_error_the_training_poses_cannot_vary_is_not_called_the_noise(tmp_path, robot):
    run = two_valued_run(tmp_path, robot, [WristRunout(robot)], [1.5e-3, -1.0e-3])
    d = diagnose(run, folds=4, candidates="joint_compliance,cyclic")
    t = d.test_set
    assert t is not None and not t.holds, d.text()
    assert t.sparse_joints == ["q5"], d.text()
    assert not d.at_floor and d.verdict == "unexplained", d.text()
    assert "at the measurement noise" not in d.text()
    assert "q5" in d.text().splitlines()[-2]
    out = d.as_json()["test_set"]
    assert out["holds"] is False and out["sparse_joints"][0]["joint"] == "q5"
    assert out["sparse_joints"][0]["distinct_training_values"] == 2
    assert out["ratio_to_folds"] == pytest.approx(out["mean_position_mm"] / out["folds_mean_position_mm"])


def test_the_same_design_without_the_error_passes(tmp_path, robot, capsys):
    run = two_valued_run(tmp_path, robot)
    capsys.readouterr()
    assert main(["diagnose", str(run), "--json", "--folds", "4", "--candidates", "joint_compliance"]) == 0
    out = json.loads(capsys.readouterr().out)
    assert out["test_set"]["holds"] is True, out["test_set"]
    assert out["at_noise_floor"] is True and out["verdict"] is None
