"""The design knows what the tour can reach (issue 22, item 1: campaign.plan.region): a UR10 on its
pedestal, whose joint 2 pointing the upper arm into the pedestal splits the suitable poses into
sets no motion joins, gets a short campaign chosen among the poses of one set, toured whole in
one round; the summary says how many suitable poses lie outside and which joint keeps them out.
Checked from outside: Pinocchio places the URDF's collision geometry, python-fcl measures."""

import json

import numpy as np
import pytest
import yaml

from campaign.cli import main
from campaign.model.robot import RobotModel
from campaign.paths import DEFAULT_SCENE
from campaign.plan.checks import ClearanceChecker
from campaign.plan.grid import Grid
from campaign.plan.scene import load_scene

from fcl_reference import FclReference, erd_robot

MOTION_CLEARANCE_M = 0.01
#: the UR10 stands upright in the default cell: its z (up) along the cell's -y, a quarter turn about x
UR10_IN_CELL = np.array([[1.0, 0, 0, 0], [0, 0, -1, 0], [0, 1, 0, 0], [0, 0, 0, 1]])
UR10 = "ur_description/urdf/ur10_robot.urdf"
CELLS = [7, 9, 5, 4, 4, 4]


def _side(q):
    """Which range of joint 2 a joint vector lies in (between the postures pointing the upper arm into the pedestal)."""
    return int(np.digitize(q[1], [-1.5 * np.pi, 0.5 * np.pi]))


def _rows(run, name):
    lines = (run / "plan" / name).read_text().splitlines()[1:]
    return [line.split(",", 1) for line in lines if line.strip()]


@pytest.fixture(scope="module")
def selected(tmp_path_factory):
    tmp = tmp_path_factory.mktemp("ur10_region")
    (tmp / "campaign.yaml").write_text(yaml.safe_dump({
        "scene": str(DEFAULT_SCENE), "plan": {"grid_cells": CELLS, "motion_sample_deg": 2.0}}))
    run = tmp / "run"
    assert main(["plan", "--config", str(tmp / "campaign.yaml"), "--run", str(run), "--quiet",
                 "--robot", str(erd_robot(UR10)), "--tool-frame", "tool0",
                 "--select", "12", "--validation", "0.5"]) == 0
    poses = [(int(p), np.array([float(v) for v in r.split(",")])) for p, r in _rows(run, "poses.csv")]
    vias = {}
    for p, r in _rows(run, "vias.csv"):
        vias.setdefault(int(p), []).append(np.array([float(v) for v in r.split(",")]))
    return run, poses, vias, json.loads((run / "plan" / "summary.json").read_text())


def test_the_chosen_poses_are_toured_in_one_round_and_the_summary_names_joint_2(selected, capsys):
    run, poses, _, s = selected
    rep, reach = s["selection"]["replacement"], s["reachable"]
    assert rep["rounds"] == 1 and rep["dropped_per_round"] == [0] and s["tour"]["dropped"] == 0
    assert s["selection"]["selected"] == s["selection"]["chosen"] == 12
    assert reach["chosen_among"] == "reachable"
    assert reach["inside"] + reach["outside"] == reach["suitable"] == s["suitable"]
    assert 0 < reach["outside"] < reach["inside"]
    assert sum(reach["outside_by_barrier"].values()) == reach["outside"]
    assert all("2" in key.split("joint", 1)[1] for key in reach["outside_by_barrier"])  # joint 2 blocks every one
    # every toured pose on one side of joint 2's pedestal posture
    assert len({_side(q) for _, q in poses}) == 1


def test_the_poses_outside_lie_beyond_joint_2_and_the_motion_there_collides_in_the_reference(selected):
    """The reachable set from the library (the same grid and cell): the suitable poses inside lie on
    the tour's side of joint 2, those outside on another; the straight motion from the nearest inside
    pose to an outside one passes a posture the reference finds closer than the motion clearance."""
    from campaign.plan.pipeline import suitable_poses
    from campaign.plan.region import reachable_region

    run, poses, _, s = selected
    robot = RobotModel.load(erd_robot(UR10), tool_frame="tool0").with_default_reflectors()
    scene = load_scene(DEFAULT_SCENE).placed(robot)
    grid = Grid.for_robot(robot, CELLS)
    suitable = suitable_poses(robot, scene, grid, 0.035)
    checker = ClearanceChecker(robot, scene, 0.035)
    region = reachable_region(robot, checker, grid, suitable, np.deg2rad(2.0), MOTION_CLEARANCE_M)
    assert int(region.inside.sum()) == s["reachable"]["inside"]
    Q = grid.q(suitable)
    toured_side = _side(poses[0][1])
    assert all(_side(q) == toured_side for q in Q[region.inside])
    assert all(_side(q) != toured_side for q in Q[~region.inside])
    # the closest pair across: its straight motion collides in the reference
    qi, qo = Q[region.inside], Q[~region.inside]
    d = np.max(np.abs(qi[:, None, :] - qo[None, :, :]), axis=2)
    i, o = np.unravel_index(np.argmin(d), d.shape)
    ref = FclReference(robot, DEFAULT_SCENE, UR10_IN_CELL)
    pairs = ref.pairs(checker)
    k = int(np.ceil(np.max(np.abs(qo[o] - qi[i])) / np.deg2rad(2.0)))
    assert min(ref.min_clearance(qi[i] + (j / k) * (qo[o] - qi[i]), pairs) for j in range(1, k)) < MOTION_CLEARANCE_M


def test_every_pose_and_motion_of_the_tour_keeps_its_clearance_in_the_reference(selected):
    run, poses, vias, s = selected
    robot = RobotModel.load(erd_robot(UR10), tool_frame="tool0")
    ref = FclReference(robot, DEFAULT_SCENE, UR10_IN_CELL)
    pairs = ref.pairs(ClearanceChecker(robot, load_scene(DEFAULT_SCENE).placed(robot), 0.035))
    assert min(ref.min_clearance(q, pairs) for _, q in poses) >= 0.035
    step = np.deg2rad(2.0)
    samples = []
    for (_, a), (p, b) in zip(poses[:-1], poses[1:]):
        path = [a, *vias.get(p, []), b]
        samples += vias.get(p, [])
        for u, v in zip(path[:-1], path[1:]):
            k = int(np.ceil(np.max(np.abs(v - u)) / step))
            samples += [u + (j / k) * (v - u) for j in range(1, k)]
    rng = np.random.default_rng(5)
    picked = [samples[i] for i in rng.choice(len(samples), min(80, len(samples)), replace=False)]
    assert min(ref.min_clearance(q, pairs) for q in picked) >= MOTION_CLEARANCE_M
