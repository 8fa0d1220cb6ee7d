"""Two joint-indexed effects on one joint (issue 31): the leading candidate keeps a joint only when
it fits it better than every other joint-indexed candidate on that joint; when the poses cannot
tell them apart, neither is named for it and auto measures poses that separate them.

Each case hides a truth in simulated measurements; the truth is compared only after diagnose answered."""

import numpy as np
import pytest

from campaign.cli import main
from campaign.diagnose import diagnose
from campaign.diagnose.joints import Rival, contested_joints, shared_joint_rivals
from campaign.measure.csvio import write_measured_csv
from campaign.model.robot import RobotModel
from campaign.run import RunFolder
from campaign.sim.truth import make_truth, random_joint_poses, synthesize


def _run(tmp_path, robot_name, hidden, n, seed=3):
    robot = RobotModel.load(robot_name)
    truth = make_truth(robot, seed=seed, effects=hidden)
    q = random_joint_poses(robot, n, seed=seed + 1)
    index = np.concatenate([np.repeat(i, 3) if i % 20 == 0 else [i] for i in range(n)])
    write_measured_csv(tmp_path / "m.csv", synthesize(truth, q[index], seed=seed + 2))
    run = tmp_path / "run"
    assert main(["import", str(tmp_path / "m.csv"), "--run", str(run), "--robot", robot_name]) == 0
    return run


def test_backlash_of_panda_joint_6_is_not_read_as_compliance_of_joint_6(tmp_path):
    """Compliance of joint 4 and backlash of joint 6 hidden: compliance alone, searched over the
    joints, takes joint 6 too (its gravity torque of 1-2.5 N·m makes backlash's tanh nearly linear);
    given the rival on joint 6, the verdict is compliance of joint 4 alone, then backlash of joint 6."""
    run = _run(tmp_path, "panda", {"joint_compliance:4": [1e-4], "backlash:6": [1e-3]}, n=120)
    d = diagnose(run, folds=4, candidates="joint_compliance,backlash")
    assert d.verdict_spec == "joint_compliance:4", d.text()
    first = d.ranking[0]
    six = [r for r in first.rivals if r.joint == 6]
    assert [(r.own, r.rival, r.outcome) for r in six] == [("joint_compliance:6", "backlash:6", "rival")]
    assert first.joint_steps[-1].joints == (4, 6)  # the search alone took joint 6
    # what decides, against full refits on the same folds (the candidate fits start from the geometric
    # model's Jacobian: each mean is a few µm high, their difference within a few per cent)
    refit = _refit_mean(run, d, ["joint_compliance:4,6"]) - _refit_mean(run, d, ["joint_compliance:4", "backlash:6"])
    assert six[0].own_mm - six[0].rival_mm == pytest.approx(refit, rel=0.1)
    assert "backlash of joint 6 rather than joint_compliance of joint 6" in d.text()
    RunFolder(run).add_effects([d.verdict_spec])
    d2 = diagnose(run, folds=4, candidates="joint_compliance,backlash")
    assert d2.verdict_spec == "backlash:6", d2.text()
    assert d2.as_json()["indistinguishable"] == []


def test_a_joint_of_the_model_that_another_effect_fits_better_is_replaced(tmp_path):
    """The model holds compliance of joints 4 and 6 (as a search over compliance alone finds it);
    each of its joints earns its place, but backlash in the place of joint 6's compliance fits the
    held-out poses better: diagnose says replace it, auto's decision does."""
    from campaign.auto import Limits, decide
    from test_auto import _StubLoop, _round

    run = _run(tmp_path, "panda", {"joint_compliance:4": [1e-4], "backlash:6": [1e-3]}, n=120)
    RunFolder(run).set_effects(["joint_compliance:4,6"])
    d = diagnose(run, folds=4, candidates="joint_compliance,backlash")
    assert d.swap is not None, d.text()
    rival, after = d.swap
    assert (rival.own, rival.rival, rival.outcome) == ("joint_compliance:6", "backlash:6", "rival")
    assert tuple(after) == ("joint_compliance:4", "backlash:6")
    assert d.removal is None  # joint 6's compliance does earn its place: removal alone would keep it
    assert [r.outcome for r in d.model_rivals if r.joint == 4] == ["own"]
    out = d.as_json()
    assert out["replace"]["effects_after"] == ["joint_compliance:4", "backlash:6"]
    assert "replace joint_compliance of joint 6 by backlash of joint 6" in d.text()
    got = decide(d, _round(), [], Limits(312, None, None), _StubLoop())
    assert got.kind == "remove_effect" and got.effects == ("joint_compliance:4", "backlash:6")
    back = _round().__class__(**{**_round().__dict__, "effects": ("backlash:6", "joint_compliance:4")})
    assert decide(d, _round(), [back], Limits(312, None, None), _StubLoop()).kind != "remove_effect"  # no way back
    assert rival.rival_mm == pytest.approx(_refit_mean(run, d, ["joint_compliance:4", "backlash:6"]), rel=0.03)


def _refit_mean(run, d, effects) -> float:
    """Held-out mean position error (mm) of a full refit of the model with ``effects`` on the
    diagnosis's folds: the reference for the first-order swap."""
    from campaign.identify.solver import CalibrationModel
    from campaign.measure.store import open_run

    with open_run(run) as store:
        poses = store.load_measured()
    robot = RunFolder(run).robot()
    ids = {int(p): i for i, p in enumerate(poses.pose_id)}
    errors = []
    for k, fold_ids in enumerate(d.fold_pose_ids):
        out = np.array([ids[p] for p in fold_ids])
        fit = np.array([ids[p] for j, f in enumerate(d.fold_pose_ids) if j != k for p in f])
        m = CalibrationModel(robot=robot, effects=effects).fit(poses.q[fit], poses.T_IE[fit])
        errors.append(np.linalg.norm(m.residuals(poses.q[out], poses.T_IE[out])[:, :3], axis=1) * 1e3)
    return float(np.concatenate(errors).mean())


def test_two_effects_the_poses_cannot_tell_apart_are_named_together_and_neither_is_the_verdict(tmp_path):
    """Backlash of the COMAU's joint 6, whose gravity torque (< 0.3 N·m) keeps tanh linear: it is
    compliance of joint 6 on any poses; diagnose says so instead of picking one."""
    run = _run(tmp_path, "comau_racer5_080", {"backlash:6": [2e-2]}, n=100)
    d = diagnose(run, folds=4, candidates="joint_compliance,backlash")
    assert d.verdict_spec is None or 6 not in (d.ranking[0].joints or ()), d.text()
    pairs = d.as_json()["indistinguishable"]
    assert [sorted(p["effects"]) for p in pairs] == [["backlash:6", "joint_compliance:6"]], d.text()
    assert "are indistinguishable on these poses" in d.text()


def test_a_rival_keeps_a_joint_only_beyond_two_standard_errors():
    """The comparison itself on numbers written here: the candidate's per-pose errors against the
    rival's, paired."""
    rng = np.random.default_rng(0)
    own = 1.0 + rng.normal(0, 0.1, 200)

    def score_with(rest, rival):
        if rival.endswith(":4"):  # joint 4 given to a rival: 0.5 worse on every pose
            assert rest == "joint_compliance:6"
            return own + 0.5
        assert rest == "joint_compliance:4"
        return own - {"backlash:6": 0.05, "cyclic:6": 0.0}[rival]  # backlash 0.05 lower on every pose

    found = shared_joint_rivals("joint_compliance:4,6", own, ["backlash", "cyclic", "joint_compliance"], score_with)
    assert [(r.joint, r.rival, r.outcome) for r in found] == [
        (4, "backlash:4", "own"), (4, "cyclic:4", "own"), (6, "backlash:6", "rival"), (6, "cyclic:6", "indistinguishable")]
    assert contested_joints(found) == (6,)
    se = 0.01
    assert Rival(6, "a:6", "b:6", 1.0, 1.0 + 2.1 * se, se).outcome == "own"
    assert Rival(6, "a:6", "b:6", 1.0, 1.0 + 1.9 * se, se).outcome == "indistinguishable"


def test_auto_stops_naming_both_when_poses_chosen_to_separate_them_did_not():
    from campaign.auto import Decision, Limits, decide
    from test_auto import _StubLoop, _diagnosis, _round

    d = _diagnosis("unexplained", significant=False)
    d.indistinguishable = (Rival(6, "joint_compliance:6", "backlash:6", 0.10, 0.10, 0.01),)
    separate = [_round(decision_kind="design")] * 2
    separate = [r.__class__(**{**r.__dict__, "decision": Decision("design", "", reason="separate")}) for r in separate]
    got = decide(d, _round(), separate, Limits(312, None, None), _StubLoop(30))
    assert got.kind == "stop" and got.reason == "indistinguishable"
    assert "joint_compliance of joint 6 and backlash of joint 6 are indistinguishable" in got.text


def test_a_pair_that_each_fits_a_small_part_of_an_unexplained_error_is_not_the_question():
    """A cable's wind-up (q1 squared, outside the catalogue; the lead's held-out truth, seed 1): the
    regressor explains 74 % of the held-out 0.0675 mm, cyclic and backlash of joint 1 each about 6 %
    and indistinguishable. auto spent two rounds separating them and stopped "indistinguishable",
    offering either; the pair is not worth poses, the verdict is unexplained."""
    from types import SimpleNamespace

    from campaign.auto import Decision, Limits, decide
    from campaign.auto.decisions import worth_separating
    from test_auto import _StubLoop, _diagnosis, _round

    d = _diagnosis("unexplained", depends_on=["q1", "q2"], significant=True)
    d.heldout_mean_position_mm = 0.0675
    d.structure = SimpleNamespace(heldout_gain=0.74, after=np.full(10, 0.0175))
    d.indistinguishable = (Rival(1, "cyclic:1", "backlash:1", 0.0632, 0.0644, 0.00085),
                           Rival(1, "cyclic:1", "joint_compliance:1", 0.0632, 0.0644, 0.00085))
    assert worth_separating(d) == ()
    separate = [_round(decision_kind="design")] * 2
    separate = [r.__class__(**{**r.__dict__, "decision": Decision("design", "", reason="separate")}) for r in separate]
    for rounds in ([], separate):  # no room left: the stop names the limit, not the pair
        got = decide(d, _round(depends_on=("q1", "q2")), rounds, Limits(312, None, None), _StubLoop())
        assert got.kind == "stop" and got.reason not in ("separate", "indistinguishable"), got
    # the same pair fitting most of what the regressor finds is the question
    d.indistinguishable = (Rival(1, "cyclic:1", "backlash:1", 0.020, 0.0205, 0.00085),)
    assert len(worth_separating(d)) == 1
    got = decide(d, _round(depends_on=("q1", "q2")), separate, Limits(312, None, None), _StubLoop(30))
    assert got.reason == "indistinguishable" and got.text.count("[cyclic:1]") == 1, got


def test_auto_measures_poses_that_separate_an_indistinguishable_pair(tmp_path):
    """The separating round on a real plan: poses the plan lacks where compliance and backlash of
    the COMAU's joint 5 differ most, i.e. where its gravity torque bends tanh; with them the share
    of backlash's shape that compliance cannot take grows more than with as many random poses."""
    from types import SimpleNamespace

    from campaign.auto import Limits, decide
    from campaign.effects.gravity import gravity_torques
    from campaign.measure.driver import read_plan
    from campaign.plan.extend import plan_space
    from test_auto import _diagnosis, _round

    run = tmp_path / "r"
    assert main(["plan", "--run", str(run), "--grid-scale", "0.6", "--select", "30", "--quiet"]) == 0
    space = plan_space(RunFolder(run))
    ids, Q, _ = read_plan(run)
    loop = SimpleNamespace(space=space, room=lambda n: (min(n, 12), None), training=lambda: (ids, np.zeros(len(ids))),
                           planned=lambda: (ids, Q), design_effects=lambda: ())
    d = _diagnosis("unexplained", significant=False)
    d.indistinguishable = (Rival(5, "joint_compliance:5", "backlash:5", 0.10, 0.10, 0.01),)
    got = decide(d, _round(), [], Limits(312, None, None), loop)
    assert got.kind == "design" and got.reason == "separate" and len(got.pose_ids) == 12, got
    assert not set(got.pose_ids) & set(map(int, ids)) and set(got.pose_ids) <= set(map(int, space.suitable))

    def bend(q):  # the share of backlash's shape on joint 5 that compliance's cannot take
        t = gravity_torques(space.robot, q)[:, 4]
        b = np.tanh(t)
        return float(np.linalg.norm(b - t * (t @ b) / (t @ t)) / np.linalg.norm(b))

    free = np.setdiff1d(space.suitable, ids)
    random = np.random.default_rng(0).choice(free, 12, replace=False)
    chosen = bend(np.concatenate([Q, space.grid.q(np.array(got.pose_ids))]))
    assert chosen > 1.1 * bend(np.concatenate([Q, space.grid.q(random)])) and chosen > 1.1 * bend(Q)


def test_a_cyclic_effect_that_beats_the_regressor_leads_whatever_input_it_ranks_first():
    """Cyclic of joint 4 moves the tool by a lever that turns with q5, which the regressor ranks
    first (bench_explain cyclic_joint_4, seed 2: held-out 0.026 mm, cyclic of joint 4 0.0098, the
    regressor 0.023): the candidate's own fit decides. One that fits a small part (cyclic of joint 1,
    6 % of a run-out of joint 4 that the regressor finds 24 % of) still does not."""
    from types import SimpleNamespace

    from campaign.diagnose.engine import leads_to

    cyclic4 = SimpleNamespace(effect="cyclic", joints=(4,), heldout_mean_position_mm_after=0.0098)
    assert leads_to(cyclic4, ["q5", "q3"], 0.023)
    assert not leads_to(cyclic4, ["q5", "q3"]) and not leads_to(cyclic4, ["q5", "q3"], 0.015)
    cyclic1 = SimpleNamespace(effect="cyclic", joints=(1,), heldout_mean_position_mm_after=0.94)
    assert not leads_to(cyclic1, ["q4", "q1"], 0.76) and leads_to(cyclic1, ["q1", "q4"], 0.76)
