"""The plan's path search (campaign.plan.pathsearch, campaign.plan.repair.PathFinder): a motion
that neither the straight line nor the lifted arm makes clear is found by a seeded RRT-Connect
search; a pose no motion reaches is dropped once the search's budget is spent. The tours are
re-checked from outside: Pinocchio places the URDF's collision geometry, python-fcl measures."""

import json

import numpy as np
import pytest
import yaml

from campaign.cli import main
from campaign.model.robot import RobotModel
from campaign.paths import DEFAULT_SCENE
from campaign.plan import pathsearch
from campaign.plan.checks import ClearanceChecker
from campaign.plan.repair import _via_path
from campaign.plan.scene import load_scene

from fcl_reference import FclReference, erd_robot

MOTION_CLEARANCE_M = 0.01


# --- the search alone, on a plane with a wall ------------------------------------------------------

def _wall_step(gap):
    """step_clear for points in the plane: a wall x = 0 (|x| < 0.2) with a gap |y| < ``gap``,
    sampled every 0.01 along a step; records every step asked."""
    asked = []

    def step_clear(a, b):
        asked.append((a.copy(), b.copy()))
        s = np.linspace(0.0, 1.0, int(np.ceil(np.max(np.abs(b - a)) / 0.01)) + 1)[:, None]
        p = a + s * (b - a)
        return not np.any((np.abs(p[:, 0]) < 0.2) & (np.abs(p[:, 1]) >= gap))

    return step_clear, asked


def test_rrt_connect_finds_a_path_through_the_gap_every_step_clear_and_seeded():
    step_clear, asked = _wall_step(0.3)
    a, b = np.array([-3.0, -3.0]), np.array([3.0, 3.0])
    found = pathsearch.rrt_connect(a, b, step_clear, np.random.default_rng(5), -np.full(2, 4.0), np.full(2, 4.0),
                                   step=0.5, budget=400)
    path = found.path
    assert path is not None and found.checks == len(asked) <= 400
    np.testing.assert_array_equal(path[0], a)
    np.testing.assert_array_equal(path[-1], b)
    assert np.all(np.max(np.abs(np.diff(path, axis=0)), axis=1) <= 0.5 + 1e-12)
    check, _ = _wall_step(0.3)
    assert all(check(p, q) for p, q in zip(path[:-1], path[1:]))
    crossing = np.flatnonzero(np.diff(np.sign(path[:, 0])))  # the path passes the wall in the gap
    assert len(crossing) and all(abs(path[k, 1]) < 0.3 + 0.5 for k in crossing)
    again = pathsearch.rrt_connect(a, b, _wall_step(0.3)[0], np.random.default_rng(5), -np.full(2, 4.0),
                                   np.full(2, 4.0), step=0.5, budget=400)
    np.testing.assert_array_equal(again.path, path)


def test_rrt_connect_gives_up_after_its_budget_when_no_path_exists():
    step_clear, asked = _wall_step(0.0)  # no gap
    found = pathsearch.rrt_connect(np.array([-3.0, 0]), np.array([3.0, 0]), step_clear, np.random.default_rng(1),
                                   -np.full(2, 4.0), np.full(2, 4.0), step=0.5, budget=150)
    assert found.path is None and found.checks == len(asked) == 150


def test_shortcut_keeps_the_ends_and_only_clear_motions():
    step_clear, _ = _wall_step(0.3)
    zigzag = np.array([[-3.0, -3], [-2, 0], [-1, 0.1], [0, 0.1], [1, 0.1], [2, -2], [3, -2]])

    def segments_clear(A, B):
        return np.array([step_clear(a, b) for a, b in zip(A, B)])

    short, calls = pathsearch.shortcut(zigzag, segments_clear)
    assert calls <= len(zigzag) - 2
    np.testing.assert_array_equal(short[[0, -1]], zigzag[[0, -1]])
    assert all(step_clear(p, q) for p, q in zip(short[:-1], short[1:]))
    # from (-3, -3) the lines to (3, -2), (2, -2), (1, 0.1) meet the wall at y -2.5, -2.4, -0.68 (the gap
    # is |y| < 0.3); the one to (0, 0.1) enters it at y -0.11; from there (3, -2) is clear (y -0.04 at x 0.2)
    np.testing.assert_array_equal(short, zigzag[[0, 3, 6]])


def test_sampling_box_is_half_a_turn_beyond_the_two_poses_within_the_limits():
    ur10 = RobotModel.load(_urdf("ur10"), tool_frame="tool0")
    a = np.array([0.0, -6.0, 1.0, 5.0, 0, 0])
    b = np.array([1.0, -5.0, -1.0, 6.0, 0, 0])
    lo, hi = pathsearch.sampling_box(ur10, a, b)
    np.testing.assert_allclose(lo, [-np.pi, -2 * np.pi, -np.pi, 5.0 - np.pi, -np.pi, -np.pi])
    np.testing.assert_allclose(hi, [1.0 + np.pi, -5.0 + np.pi, np.pi, 2 * np.pi, np.pi, np.pi])


# --- a reference outside the planner --------------------------------------------------------------

def _urdf(which):
    return erd_robot({"ur10": "ur_description/urdf/ur10_robot.urdf"}[which])


def _motion_samples(path, step):
    """The samples the plan checks along each straight motion of ``path``, ≤ step apart (ends excluded)."""
    out = []
    for a, b in zip(path[:-1], path[1:]):
        k = int(np.ceil(np.max(np.abs(b - a)) / step))
        out += [a + (i / k) * (b - a) for i in range(1, k)]
    return out


def _read(run):
    def rows(name):
        lines = (run / "plan" / name).read_text().splitlines()[1:]
        return [line.split(",", 1) for line in lines if line.strip()]

    poses = [(int(p), np.array([float(v) for v in r.split(",")])) for p, r in rows("poses.csv")]
    vias = {}
    for p, r in rows("vias.csv"):
        vias.setdefault(int(p), []).append(np.array([float(v) for v in r.split(",")]))
    dropped = [(int(p), r) for p, r in rows("dropped.csv")]
    return poses, vias, dropped, json.loads((run / "plan" / "summary.json").read_text())


# --- the COMAU under a low ceiling: the lifted arm always collides, a searched path does not ------

@pytest.fixture(scope="module")
def ceiling(tmp_path_factory):
    tmp = tmp_path_factory.mktemp("ceiling")
    scene = yaml.safe_load(DEFAULT_SCENE.read_text())
    scene["obstacles"] += [
        # over the robot, 1.10 m above its base: the upright arm reaches 1.17 m
        {"name": "ceiling", "box": {"center_m": [0.0, -1.15, 0.0], "size_m": [1.6, 0.1, 1.6]}},
    ]
    (tmp / "cell.yaml").write_text(yaml.safe_dump(scene))
    (tmp / "campaign.yaml").write_text(yaml.safe_dump({
        "scene": "cell.yaml", "plan": {"grid_cells": [6, 5, 5, 4, 3, 3], "motion_clearance_m": MOTION_CLEARANCE_M}}))
    run = tmp / "run"
    assert main(["plan", "--config", str(tmp / "campaign.yaml"), "--run", str(run), "--all", "--quiet"]) == 0
    return run, tmp / "cell.yaml"


def test_under_a_ceiling_every_pose_is_toured_through_searched_paths(ceiling):
    run, cell = ceiling
    robot = RobotModel.load()
    poses, vias, dropped, s = _read(run)
    ref = FclReference(robot, cell, np.eye(4))
    pairs = ref.pairs(ClearanceChecker(robot, load_scene(cell).placed(robot), 0.035))
    assert dropped == [] and s["tour"]["dropped"] == 0 and len(poses) == s["suitable"] > 20
    assert s["tour"]["via_poses"] == sum(len(v) for v in vias.values()) > 0
    assert s["tour"]["path_search"]["motions"] > 0
    # every motion that needed vias is clear at every sample the plan checks, in the reference;
    # its straight motion was not, nor was the lifted arm (its via postures reach into the ceiling)
    step = np.deg2rad(1.0)
    ids = [p for p, _ in poses]
    Q = [q for _, q in poses]
    for k in range(1, len(ids)):
        if ids[k] not in vias:
            continue
        path = [Q[k - 1], *vias[ids[k]], Q[k]]
        assert min(ref.min_clearance(v, pairs) for v in _via_path(robot, Q[k - 1], Q[k])[1:3]) < MOTION_CLEARANCE_M
        assert all(ref.min_clearance(v, pairs) >= MOTION_CLEARANCE_M for v in vias[ids[k]])
        assert min(ref.min_clearance(q, pairs) for q in _motion_samples(path, step)) >= MOTION_CLEARANCE_M, ids[k]
        assert min(ref.min_clearance(q, pairs) for q in _motion_samples([Q[k - 1], Q[k]], step)) < MOTION_CLEARANCE_M


def test_the_searched_paths_are_the_same_when_planned_again(ceiling, tmp_path):
    run, cell = ceiling
    again = tmp_path / "again"
    assert main(["plan", "--config", str(cell.parent / "campaign.yaml"), "--run", str(again), "--all", "--quiet"]) == 0
    for name in ("poses.csv", "vias.csv", "dropped.csv"):
        assert (again / "plan" / name).read_bytes() == (run / "plan" / name).read_bytes(), name


# --- a UR10 on the pedestal: three ranges of joint 2 that no motion joins --------------------------

#: the UR10 stands upright in the default cell: its z (up) along the cell's -y, a quarter turn about x
UR10_IN_CELL = np.array([[1.0, 0, 0, 0], [0, 0, -1, 0], [0, 1, 0, 0], [0, 0, 0, 1]])


@pytest.fixture(scope="module")
def ur10_run(tmp_path_factory):
    tmp = tmp_path_factory.mktemp("ur10_search")
    (tmp / "campaign.yaml").write_text(yaml.safe_dump({
        "scene": str(DEFAULT_SCENE), "plan": {"grid_cells": [7, 9, 5, 4, 4, 4], "motion_sample_deg": 2.0}}))
    run = tmp / "run"
    assert main(["plan", "--config", str(tmp / "campaign.yaml"), "--run", str(run), "--quiet", "--all",
                 "--robot", str(_urdf("ur10")), "--tool-frame", "tool0"]) == 0
    return run


def test_ur10_drops_only_the_poses_beyond_the_arm_pointing_into_the_pedestal(ur10_run):
    """Joint 2 at +90° (or -270°) points the upper arm down into the pedestal whatever joint 1 does:
    no motion passes it, so the poses on the other side of it cannot be reached from the tour's.
    Every suitable pose on the tour's side is toured (before the path search the plan dropped 81
    of these 168 suitable poses, 17 of them on the tour's side); the others are dropped, the
    search giving up within its budget."""
    robot = RobotModel.load(_urdf("ur10"), tool_frame="tool0")
    poses, vias, dropped, s = _read(ur10_run)
    ref = FclReference(robot, DEFAULT_SCENE, UR10_IN_CELL)
    upper_arm = ref.links.index("upper_arm_link")
    for q2 in np.pi / 2 + np.deg2rad([-2, -1, 0, 1, 2]):
        for q1 in np.deg2rad(np.arange(0, 360)):
            assert ref.link_to(np.array([q1, q2, 0, 0, 0, 0]), upper_arm, "pedestal") < MOTION_CLEARANCE_M
    side = lambda q: int(np.digitize(q[1], [-1.5 * np.pi, 0.5 * np.pi]))  # noqa: E731
    toured = {side(q) for _, q in poses}
    assert len(toured) == 1
    from campaign.plan.grid import Grid

    grid = Grid.for_robot(robot, s["grid_cells"])
    q_dropped = grid.q([p for p, _ in dropped])
    assert len(dropped) == s["tour"]["dropped"] == s["suitable"] - len(poses) > 0
    assert all(side(q) not in toured for q in q_dropped)
    assert len(poses) > s["suitable"] / 2  # the larger side is toured
    budget = f"after a path search of {pathsearch.BUDGET} checked steps"
    assert all(budget in r or "which it did not reach either" in r or "that no path search reached" in r
               for _, r in dropped)
    gave_up = sum(budget in r for _, r in dropped)
    search = s["tour"]["path_search"]
    assert 1 <= gave_up <= search["motions"] and search["checks"] <= search["motions"] * (2 * pathsearch.BUDGET + 2)


def test_ur10_tour_keeps_the_motion_clearance_in_the_reference(ur10_run):
    robot = RobotModel.load(_urdf("ur10"), tool_frame="tool0")
    poses, vias, _, _ = _read(ur10_run)
    ref = FclReference(robot, DEFAULT_SCENE, UR10_IN_CELL)
    pairs = ref.pairs(ClearanceChecker(robot, load_scene(DEFAULT_SCENE).placed(robot), 0.035))
    step = np.deg2rad(2.0)
    repaired, straight = [], []
    for (_, a), (p, b) in zip(poses[:-1], poses[1:]):
        if p in vias:
            repaired += _motion_samples([a, *vias[p], b], step) + vias[p]
        else:
            straight += _motion_samples([a, b], step)
    assert len(vias) > 0
    rng = np.random.default_rng(3)
    picked = [repaired[i] for i in rng.choice(len(repaired), min(150, len(repaired)), replace=False)]
    picked += [straight[i] for i in rng.choice(len(straight), 60, replace=False)]
    assert min(ref.min_clearance(q, pairs) for q in picked) >= MOTION_CLEARANCE_M


# --- a chosen campaign is toured as chosen: the poses a tour drops are replaced ------------------

def _plan_ur10_select(tmp, *extra):
    (tmp / "campaign.yaml").write_text(yaml.safe_dump({
        "scene": str(DEFAULT_SCENE), "plan": {"grid_cells": [7, 9, 5, 4, 4, 4], "motion_sample_deg": 2.0}}))
    run = tmp / "run"
    assert main(["plan", "--config", str(tmp / "campaign.yaml"), "--run", str(run), "--quiet",
                 "--robot", str(_urdf("ur10")), "--tool-frame", "tool0", *extra]) == 0
    return run


def _toured_counts(run):
    poses, _, dropped, s = _read(run)
    base = {p % 1_000_000_000 for p, _ in poses}
    validation = {int(v) for v in (run / "plan" / "validation.csv").read_text().split()[1:]}
    return poses, dropped, s, base - validation, validation


def test_select_replaces_the_poses_its_first_tour_dropped(tmp_path, capsys):
    run = _plan_ur10_select(tmp_path, "--select", "12", "--validation", "0.5", "--choose-among", "suitable")
    poses, dropped, s, selected, validation = _toured_counts(run)
    rep = s["selection"]["replacement"]
    assert rep["dropped_per_round"][0] > 0 and rep["dropped_per_round"][-1] == 0 == len(dropped) == s["tour"]["dropped"]
    assert rep["rounds"] == len(rep["dropped_per_round"]) >= 2 and rep["why_short"] is None
    assert len(selected) == s["selection"]["selected"] == s["selection"]["chosen"] == 12
    assert len(validation) == s["selection"]["validation"] == 30
    assert len(poses) == 12 + 30 + (s["selection"]["repeat_times"] - 1) * s["selection"]["repeated_poses"] == s["tour"]["poses"]
    side = {int(np.digitize(q[1], [-1.5 * np.pi, 0.5 * np.pi])) for _, q in poses}
    assert len(side) == 1  # one side of the pedestal (test_ur10_drops_only_the_poses_beyond...)
    out = capsys.readouterr().out
    assert f"replaced {rep['replaced']} chosen poses that no collision-free motion reached, choosing {rep['rounds']} times\n" in out


def test_select_more_than_the_tour_can_reach_says_why_and_predicts_for_the_toured(tmp_path, capsys):
    from campaign.plan.grid import Grid
    from campaign.plan.selection import evaluation_sample, information_model, predict_accuracy

    run = _plan_ur10_select(tmp_path, "--select", "110", "--validation", "0.1", "--repeats", "0")
    poses, dropped, s, selected, validation = _toured_counts(run)
    sel = s["selection"]
    assert "cannot select 110 of" in sel["replacement"]["why_short"] and len(dropped) > 0
    assert sel["chosen"] == 110 > sel["selected"] == len(selected) and sel["validation"] == len(validation)
    out = capsys.readouterr().out
    assert f"{110 - len(selected)} chosen poses not toured: choosing again without the" in out
    assert f": {len(selected)} of the 110 poses chosen toured, {len(validation)} random validation poses added" in out
    # the prediction is for the selected poses toured, over every suitable pose
    from campaign.plan.pipeline import suitable_poses

    robot = RobotModel.load(_urdf("ur10"), tool_frame="tool0").with_default_reflectors()
    grid = Grid.for_robot(robot, s["grid_cells"])
    suitable = suitable_poses(robot, load_scene(DEFAULT_SCENE).placed(robot), grid, 0.035)
    assert len(suitable) == s["suitable"]
    info = information_model(robot, grid.q(suitable), noise_m=sel["tracker_noise_m"])
    train = np.flatnonzero(np.isin(suitable, sorted(selected)))
    expected = predict_accuracy(info, train, evaluation_sample(info, train)[0])
    assert sel["predicted"]["for"] == "the chosen poses the tour keeps"
    assert sel["predicted"]["model_position_mm"] == pytest.approx(expected.model_position_mm, rel=1e-9)
    assert sel["predicted"]["heldout_position_mm"] == pytest.approx(expected.heldout_position_mm, rel=1e-9)
