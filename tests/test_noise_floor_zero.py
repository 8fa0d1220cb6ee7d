"""A run measured with exactly zero tracker noise: the floor is 0, said as such, never divided by.

model_to_noise is then null in JSON (no ratio to a zero floor exists; ``inf`` is not JSON),
diagnose and calibrate state the floor without crashing, and a correct model sits at the floor
(its held-out error is the fit's round-off), while a model that misses an effect does not.
"""

import json

import numpy as np
import pytest
import yaml

from campaign.cli import main
from campaign.diagnose import diagnose
from campaign.identify.calibrate import calibrate
from campaign.measure.csvio import write_measured_csv
from campaign.measure.floor import floor_from_repeats, ratio_to_floor, times_the_noise
from campaign.sim.truth import make_truth, random_joint_poses, synthesize


def noise_free_run(tmp_path, robot, effects=None, n=150, bursts=10, repeats=3):
    """An imported run from a tracker without noise or rounding; ``bursts`` poses measured
    ``repeats`` times back to back."""
    truth = make_truth(robot, seed=11, noise_m=0.0, resolution_m=0.0, effects=effects)
    q = random_joint_poses(robot, n, seed=12)
    index = np.concatenate([np.repeat(i, repeats if i < bursts else 1) for i in range(n)])
    poses = synthesize(truth, q[index], seed=13)
    tmp_path.mkdir(parents=True, exist_ok=True)
    write_measured_csv(tmp_path / "m.csv", poses)
    run = tmp_path / "run"
    assert main(["import", str(tmp_path / "m.csv"), "--run", str(run)]) == 0
    return run, poses


def test_identical_repeats_give_a_floor_of_zero_and_no_ratio():
    q = np.repeat(np.array([[0.1, 0.2, 0.3, 0.4, 0.5, 0.6], [0.6, 0.5, 0.4, 0.3, 0.2, 0.1]]), 4, axis=0)
    xyz = np.repeat(np.array([[0.5, 0.1, 0.2], [0.4, 0.3, 0.1]]), 4, axis=0)
    floor = floor_from_repeats(xyz, q)
    assert floor.source == "repeats" and floor.known and floor.dof == 6
    assert floor.mean_position_mm == 0.0 and np.all(floor.sigma_position_m == 0.0)
    assert floor.ratio(0.01) is None and ratio_to_floor(0.01, None) is None
    assert ratio_to_floor(0.02, 0.01) == pytest.approx(2.0)
    assert times_the_noise(0.01, 0.0) == "(the measurement noise is 0: no ratio to it)"
    assert times_the_noise(0.02, 0.01) == "= 2.0× the measurement noise"
    json.dumps(floor.as_json(), allow_nan=False)


def test_diagnose_and_calibrate_of_a_noise_free_run_state_the_zero_floor(tmp_path, robot, capsys):
    run, _ = noise_free_run(tmp_path / "clean", robot)
    d = diagnose(run, folds=3, candidates="drift,joint_compliance")
    assert d.floor.source == "repeats" and d.floor.mean_position_mm == 0.0
    assert d.model_to_noise is None
    # the geometric model represents this truth exactly: held-out error at round-off
    assert d.heldout_mean_position_mm < 1e-6 and d.at_floor is True
    assert d.verdict is None, d.text()
    text = d.text()
    assert "(the measurement noise is 0: no ratio to it)" in text and "noise floor: 0.0000 mm" in text
    out = json.loads(json.dumps(d.as_json(), allow_nan=False))
    assert out["noise_floor_mm"] == 0.0 and out["model_to_noise"] is None and out["at_noise_floor"] is True
    capsys.readouterr()
    assert main(["diagnose", str(run), "--json", "--folds", "3", "--candidates", "drift", "--no-report"]) == 0
    assert json.loads(capsys.readouterr().out)["model_to_noise"] is None

    result = calibrate(run, ann=False)
    assert result.metrics["noise_floor"]["mean_position_mm"] == 0.0
    assert "geometric: test set (" in result.floor_line() and "held-out poses): mean 0.0000 mm (the measurement noise is 0: no ratio to it)" in result.floor_line()


def test_a_model_that_misses_an_effect_is_not_at_a_zero_floor(tmp_path, robot):
    from campaign.effects import make_effect

    theta = make_effect("ground_compliance", robot).typical_params(2)
    run, _ = noise_free_run(tmp_path / "tilt", robot, effects={"ground_compliance": theta})
    d = diagnose(run, folds=3, candidates="ground_compliance,drift")
    assert d.floor.mean_position_mm == 0.0 and d.model_to_noise is None
    assert d.at_floor is False and d.heldout_mean_position_mm > 0.01
    assert d.verdict == "ground_compliance", d.text()
    assert json.loads(json.dumps(d.as_json(), allow_nan=False))["model_to_noise"] is None
    (run / "campaign.yaml").write_text(yaml.safe_dump({**yaml.safe_load((run / "campaign.yaml").read_text()),
                                                       "effects": ["ground_compliance"]}))
    d = diagnose(run, folds=3, candidates="drift")
    assert d.at_floor is True and d.verdict is None, d.text()
