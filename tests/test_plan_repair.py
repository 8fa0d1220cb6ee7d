"""The plan's repair of colliding motions: via postures that lift the arm, else a searched path
(campaign.plan.pathsearch; a pose is dropped only when the search's budget is spent: tests/
test_plan_search.py). A cell with two posts beside the robot (straight joint motions sweep
through them) and a partial ceiling (the lifted arm hits it on one side) takes both paths."""

import json

import numpy as np
import pytest
import yaml

from campaign.cli import main
from campaign.model.kinematics import frames
from campaign.paths import DEFAULT_SCENE
from campaign.plan.checks import ExactChecker
from campaign.plan.repair import _via_path
from campaign.plan.scene import load_scene
from campaign.plan.tour import segment_samples

MOTION_CLEARANCE_M = 0.01


@pytest.fixture(scope="module")
def repaired(tmp_path_factory):
    tmp = tmp_path_factory.mktemp("repair")
    scene = yaml.safe_load(DEFAULT_SCENE.read_text())
    scene["obstacles"] += [
        {"name": "post_right", "cylinder": {"center_m": [0.5, 0.0, 0.0], "radius_m": 0.05, "height_m": 1.4, "axis": "y"}},
        {"name": "post_left", "cylinder": {"center_m": [-0.5, 0.0, 0.2], "radius_m": 0.08, "height_m": 1.4, "axis": "y"}},
        {"name": "ceiling_left", "box": {"center_m": [-0.8, -0.9, 0.0], "size_m": [0.8, 0.1, 1.6]}},
    ]
    (tmp / "cell.yaml").write_text(yaml.safe_dump(scene))
    (tmp / "campaign.yaml").write_text(yaml.safe_dump({
        "scene": "cell.yaml", "plan": {"grid_cells": [6, 5, 5, 4, 3, 3], "motion_clearance_m": MOTION_CLEARANCE_M}}))
    run = tmp / "run"
    assert main(["plan", "--config", str(tmp / "campaign.yaml"), "--run", str(run), "--all", "--quiet"]) == 0
    return run, load_scene(tmp / "cell.yaml")


def read_csv(path):
    lines = path.read_text().splitlines()[1:]
    return [line.split(",") for line in lines if line.strip()]


def min_clearance(robot, checker, a, b):
    """Smallest exact distance robot-scene / robot-robot (m) along the straight joint motion a → b."""
    R, t = frames(robot, segment_samples(a, b, np.deg2rad(1.0)))
    return min(checker.clearance.exact_min_distance(R[k], t[k]) for k in range(len(R)))


def test_both_repairs_happen_and_the_counts_add_up(repaired, robot):
    run, _ = repaired
    s = json.loads((run / "plan" / "summary.json").read_text())
    rows = read_csv(run / "plan" / "poses.csv")
    poses = [int(r[0]) for r in rows]
    Q = {int(r[0]): np.array([float(v) for v in r[1:]]) for r in rows}
    dropped = read_csv(run / "plan" / "dropped.csv")
    vias = read_csv(run / "plan" / "vias.csv")
    assert s["tour"]["via_poses"] == len(vias) > 0
    assert s["tour"]["dropped"] == len(dropped) == 0  # the search reaches what the lifted arm does not
    assert s["tour"]["poses"] == len(poses) == s["suitable"]
    assert {int(r[0]) for r in vias} <= set(poses)
    by_pose = {}
    for r in vias:
        by_pose.setdefault(int(r[0]), []).append(np.array([float(v) for v in r[1:]]))
    lifted = other = 0
    for k in range(1, len(poses)):
        if poses[k] in by_pose:
            path = _via_path(robot, Q[poses[k - 1]], Q[poses[k]])
            if len(by_pose[poses[k]]) == 2 and np.array_equal(np.array(by_pose[poses[k]]), path[1:3]):
                lifted += 1
            else:
                other += 1
    assert lifted > 0 and other > 0


def test_the_repaired_tour_is_collision_free_and_every_via_was_needed(repaired, robot):
    run, scene = repaired
    checker = ExactChecker(robot, scene, MOTION_CLEARANCE_M)
    rows = read_csv(run / "plan" / "poses.csv")
    ids = [int(r[0]) for r in rows]
    Q = np.array([[float(v) for v in r[1:]] for r in rows])
    vias = {}
    for r in read_csv(run / "plan" / "vias.csv"):
        vias.setdefault(int(r[0]), []).append(np.array([float(v) for v in r[1:]]))
    needed = 0
    for k in range(1, len(ids)):
        path = [Q[k - 1], *vias.get(ids[k], []), Q[k]]
        for a, b in zip(path[:-1], path[1:]):
            assert min_clearance(robot, checker, a, b) >= MOTION_CLEARANCE_M, f"motion to pose {ids[k]} collides"
        if ids[k] in vias:  # the straight motion it replaces does not keep the clearance
            assert min_clearance(robot, checker, Q[k - 1], Q[k]) < MOTION_CLEARANCE_M
            needed += 1
    assert needed == len(vias) > 0
