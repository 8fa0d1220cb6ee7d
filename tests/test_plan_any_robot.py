"""Issue 12, item 9: `campaign plan --robot` for arms that are not the COMAU: a 6R arm with z up
(UR10, URDF alone: the default reflector triad) and a 7R arm (Panda, with a robot.yaml naming its
reflectors and locked fingers), both from example-robot-data, whose collision geometry is STL
meshes (and, for the Panda's fingers, boxes). The plan's verdicts are re-checked from outside:
Pinocchio places the URDF's collision geometry (its own parser and forward kinematics), trimesh
loads the meshes, python-fcl measures the distances, and the cell is placed by hand."""

import json
import re
from pathlib import Path

import numpy as np
import pytest
import yaml

from campaign.cli import main
from campaign.errors import ConfigError
from campaign.model.kinematics import frames
from campaign.model.robot import RobotModel
from campaign.paths import DEFAULT_SCENE
from campaign.plan import checks
from campaign.plan.checks import ClearanceChecker
from campaign.plan.geometry import nominal_frames_entry_first, robot_primitives
from campaign.plan.grid import DEFAULT_GRID_SIZE, PAPER_CELLS, Grid, default_cells, iter_tool_points, tool_frames
from campaign.plan.repair import arm_joints, lift_posture
from campaign.plan.scene import load_scene

from fcl_reference import FclReference, erd_robot

CLEARANCE_M = 0.035


def _urdf(which):
    return erd_robot({"ur10": "ur_description/urdf/ur10_robot.urdf", "panda": "panda_description/urdf/panda.urdf"}[which])


PANDA_YAML = {
    "name": "panda", "tool_frame": "panda_hand",
    "locked_joints": {"panda_finger_joint1": 0.02, "panda_finger_joint2": 0.02},
    # three nests on a bracket beside the hand, facing the hand's +x
    "reflectors": [{"name": "a", "position_m": [0.05, 0.04, 0.02], "axis": [1, 0, 0], "half_angle_deg": 40},
                   {"name": "b", "position_m": [0.05, -0.04, 0.02], "axis": [1, 0, 0], "half_angle_deg": 40},
                   {"name": "c", "position_m": [0.05, 0.0, 0.06], "axis": [1, 0, 0], "half_angle_deg": 30}],
}


@pytest.fixture(scope="module")
def panda_yaml(tmp_path_factory):
    path = tmp_path_factory.mktemp("panda") / "robot.yaml"
    path.write_text(yaml.safe_dump({"urdf": str(_urdf("panda")), **PANDA_YAML}))
    return path


def _plan(tmp, robot_args, cells, extra=("--all",)):  # default: every suitable pose, the whole tour
    cfg = tmp / "campaign.yaml"
    cfg.write_text(yaml.safe_dump({"scene": str(DEFAULT_SCENE), "plan": {"grid_cells": cells, "motion_sample_deg": 2.0},
                                   "sim": {"noise_m": 0.0, "seed": 3}}))
    run = tmp / "run"
    assert main(["plan", "--config", str(cfg), "--run", str(run), "--quiet", *robot_args, *extra]) == 0
    return run


@pytest.fixture(scope="module")
def ur10_plan(tmp_path_factory):
    return _plan(tmp_path_factory.mktemp("ur10"), ["--robot", str(_urdf("ur10")), "--tool-frame", "tool0"],
                 [8, 6, 4, 5, 5, 4])


@pytest.fixture(scope="module")
def panda_plan(tmp_path_factory, panda_yaml):
    return _plan(tmp_path_factory.mktemp("panda_plan"), ["--robot", str(panda_yaml)], [6, 4, 5, 4, 5, 4, 3])


def _reference(robot):
    """The suitability criteria computed without the planner's code (tests/fcl_reference.py); the
    robot stands in the default cell where a z-up robot stands by the scene's rule, worked out
    here by hand: its gravity (-z) turned onto the cell's down (+y), a quarter turn about x."""
    assert np.array_equal(robot.T_root_base, np.eye(4))  # F_I is the URDF's root for both arms
    c, s = np.cos(np.pi / 2), np.sin(np.pi / 2)
    return FclReference(robot, DEFAULT_SCENE, np.array([[1, 0, 0, 0], [0, c, -s, 0], [0, s, c, 0], [0, 0, 0, 1.0]]))


def _read_poses(run):
    lines = (run / "plan" / "poses.csv").read_text().splitlines()
    data = np.array([[float(v) for v in line.split(",")] for line in lines[1:]])
    return lines[0], data[:, 0].astype(np.int64), data[:, 1:]


@pytest.mark.parametrize("which", ["ur10", "panda"])
def test_accepted_poses_are_clear_visible_and_rejected_ones_really_fail(which, request):
    run = request.getfixturevalue(f"{which}_plan")
    cfg = yaml.safe_load((run / "campaign.yaml").read_text())
    robot = RobotModel.load(cfg["robot"], tool_frame=cfg.get("tool_frame")).with_default_reflectors()
    s = json.loads((run / "plan" / "summary.json").read_text())
    head, ids, Q = _read_poses(run)
    assert head == "pose_id," + ",".join(f"q{j}" for j in range(1, robot.n_joints + 1))
    assert s["candidates"] == int(np.prod(cfg["plan"]["grid_cells"])) == Grid.for_robot(robot, s["grid_cells"]).size
    assert s["suitable"] > 20 and s["tour"]["poses"] + s["tour"]["dropped"] == s["suitable"] == len(ids) + s["tour"]["dropped"]
    assert any(p.kind == "mesh" for p in robot_primitives(robot))
    grid = Grid.for_robot(robot, s["grid_cells"])
    np.testing.assert_allclose(Q, grid.q(ids), atol=1e-12)
    ref = _reference(robot)
    checker = ClearanceChecker(robot, load_scene(DEFAULT_SCENE).placed(robot), CLEARANCE_M)
    pairs = ref.pairs(checker)
    rng = np.random.default_rng(7)
    for q in Q[rng.choice(len(Q), size=min(25, len(Q)), replace=False)]:
        assert ref.min_clearance(q, pairs) >= CLEARANCE_M
        assert ref.visible(q, robot.reflectors)
    # rejected poses: out of a cone, out of sight or too close; the plan's bounds are conservative
    # (a few good poses may be rejected), never the other way round. Most candidates fail a cone:
    # those that the reference sees, the plan rejected for their clearance (or, conservatively, a
    # beam), so they are checked for a collision.
    rejected = np.setdiff1d(rng.choice(grid.size, 1500, replace=False), ids)
    seen = [i for i in rejected if ref.visible(grid.q([i])[0], robot.reflectors)]
    dropped = {int(line.split(",")[0]) for line in (run / "plan" / "dropped.csv").read_text().splitlines()[1:]}
    good = [i for i in seen if i not in dropped and ref.min_clearance(grid.q([i])[0], pairs) >= CLEARANCE_M]
    assert len(seen) >= 5 and s["removed_by_filter"]["clearance_fcl"] > 0
    assert len(good) <= 3, (good, len(seen))


def test_the_tour_motions_keep_the_motion_clearance_in_the_reference(ur10_plan):
    cfg = yaml.safe_load((ur10_plan / "campaign.yaml").read_text())
    robot = RobotModel.load(cfg["robot"], tool_frame=cfg["tool_frame"]).with_default_reflectors()
    _, ids, Q = _read_poses(ur10_plan)
    ref = _reference(robot)
    checker = ClearanceChecker(robot, load_scene(DEFAULT_SCENE).placed(robot), CLEARANCE_M)
    pairs = ref.pairs(checker)
    vias = {}
    for line in (ur10_plan / "plan" / "vias.csv").read_text().splitlines()[1:]:
        c = [float(v) for v in line.split(",")]
        vias.setdefault(int(c[0]), []).append(c[1:])
    path = [Q[0]]
    for pid, q in zip(ids[1:], Q[1:]):
        path += [np.array(v) for v in vias.get(int(pid), [])] + [q]
    # the samples the plan checks (plan.motion_sample_deg apart along each straight joint motion),
    # a random 60 of them re-checked
    step = np.deg2rad(cfg["plan"]["motion_sample_deg"])
    samples = []
    for a, b in zip(path[:-1], path[1:]):
        k = int(np.ceil(np.max(np.abs(b - a)) / step))
        samples += [a + (i / k) * (b - a) for i in range(1, k)]
    rng = np.random.default_rng(4)
    worst = min(ref.min_clearance(samples[i], pairs) for i in rng.choice(len(samples), 60, replace=False))
    assert worst >= cfg["plan"]["motion_clearance_m"]


def test_collision_geometry_sits_on_the_chain_where_pinocchio_puts_it(panda_yaml):
    robot = RobotModel.load(panda_yaml)
    ref = _reference(robot)
    rng = np.random.default_rng(2)
    prims = robot_primitives(robot)
    assert {p.kind for p in prims} == {"mesh", "box"} and len(prims) == len(ref.links) == 17
    index = ref.index_of(prims)
    for q in rng.uniform(robot.q_lower, robot.q_upper, size=(4, 7)):
        ref.place(q)
        R, t = frames(robot, q[None])
        for p, k in zip(prims, index):
            T_ref = ref.gdata.oMg[k].homogeneous  # in the URDF's root, F_I of the Panda
            T = np.eye(4)
            T[:3, :3], T[:3, 3] = R[0, p.frame], t[0, p.frame]
            T = T @ p.T
            if p.kind == "mesh":  # the mesh's own frame: its box frame times the box's pose in it
                import trimesh

                v = trimesh.load(ref.gmodel.geometryObjects[k].meshPath, force="mesh").vertices
                mine = p.mesh.vertices @ T[:3, :3].T + T[:3, 3]
                theirs = v @ T_ref[:3, :3].T + T_ref[:3, 3]
                np.testing.assert_allclose(mine, theirs, atol=1e-9)
            else:
                np.testing.assert_allclose(T, T_ref, atol=1e-12)


def test_n_joint_grid_is_the_product_of_its_cells_and_follows_pinocchio(panda_yaml):
    import pinocchio as pin

    robot = RobotModel.load(panda_yaml)
    cells = (3, 2, 3, 2, 2, 3, 2)
    g = Grid.for_robot(robot, cells)
    assert g.size == int(np.prod(cells)) == 432
    idx = np.arange(g.size)
    np.testing.assert_array_equal(np.ravel_multi_index(g.cell_indices(idx).T, g.cells), idx)
    R, t = tool_frames(robot, g)
    model = robot.pinocchio_model
    data = model.createData()
    fid = model.getFrameId(robot.tool_frame)
    for i in (0, 1, 77, 431):
        pin.framesForwardKinematics(model, data, robot.pinocchio_q(g.q([i]))[0])
        np.testing.assert_allclose(R[i], data.oMf[fid].rotation, atol=1e-12)
        np.testing.assert_allclose(t[i], data.oMf[fid].translation, atol=1e-12)
    points = robot.reflector_positions_in_E
    axes = np.array([r.axis_in_E for r in robot.reflectors])
    blocks = list(iter_tool_points(robot, g, points, axes, chunk=5))
    P = np.concatenate([b[1] for b in blocks])
    np.testing.assert_allclose(P, np.einsum("nij,rj->nri", R, points) + t[:, None], atol=1e-12)
    Re, te = nominal_frames_entry_first(robot, g.q(idx[:50]))
    Rf, tf = frames(robot, g.q(idx[:50]))
    np.testing.assert_allclose(np.moveaxis(Re, -1, 0), Rf, atol=1e-14)
    np.testing.assert_allclose(np.moveaxis(te, -1, 0), tf, atol=1e-14)
    # the COMAU's default grid is the paper's; a 7R arm's about a million candidates, every joint >= 2 cells
    assert default_cells(RobotModel.load()) == PAPER_CELLS and Grid.for_robot(RobotModel.load()).size == 1_428_000
    default = default_cells(robot)
    assert len(default) == 7 and min(default) >= 2
    assert 0.5 * DEFAULT_GRID_SIZE <= np.prod(default) <= DEFAULT_GRID_SIZE


def test_the_lifted_arm_is_the_highest_flange_over_the_45_degree_postures():
    import itertools

    import pinocchio as pin

    robot = RobotModel.load(_urdf("panda"), tool_frame="panda_hand")
    arm = arm_joints(7)
    assert arm.tolist() == [1, 2, 3]
    model = robot.pinocchio_model
    data = model.createData()
    flange = model.getFrameId("panda_link7")

    def height(values):
        q = np.clip(np.zeros(7), robot.q_lower, robot.q_upper)
        q[arm] = values
        pin.framesForwardKinematics(model, data, q)
        return data.oMf[flange].translation[2]  # z up, gravity -z

    grid = [np.arange(-8, 9) * np.pi / 4 for _ in arm]
    allowed = [v[(v >= robot.q_lower[j]) & (v <= robot.q_upper[j])] for v, j in zip(grid, arm)]
    best = max(height(np.array(c)) for c in itertools.product(*allowed))
    assert height(lift_posture(robot)) == pytest.approx(best, abs=1e-12)
    comau = RobotModel.load()
    assert lift_posture(comau).tolist() == [0.0, -np.pi / 2]  # the arm upright, as it always was


def test_a_z_up_robot_stands_upright_in_the_default_cell_and_robot_base_places_it(tmp_path):
    ur10 = RobotModel.load(_urdf("ur10"), tool_frame="tool0")
    scene = load_scene(DEFAULT_SCENE)
    placed = scene.placed(ur10)
    # a quarter turn about x: the UR10's z (up) along the cell's -y (up), its gravity along +y (down)
    np.testing.assert_allclose(placed.T_cell_I, [[1, 0, 0, 0], [0, 0, -1, 0], [0, 1, 0, 0], [0, 0, 0, 1.0]], atol=1e-15)
    # the tracker, 3 m in front (+z) and 0.55 m up (-y) in the cell, is 3 m along +y and 0.55 m up (+z) of the UR10
    np.testing.assert_allclose(placed.tracker_position, [0.0, 3.0, 0.55], atol=1e-12)
    assert load_scene(DEFAULT_SCENE).placed(RobotModel.load()).T_cell_I.tolist() == np.eye(4).tolist()
    doc = yaml.safe_load(DEFAULT_SCENE.read_text())
    doc["robot_base"] = {"position_m": [0.1, -0.2, 0.3], "rotation_cardan_deg": [90, 0, 90]}
    (tmp_path / "cell.yaml").write_text(yaml.safe_dump(doc))
    moved = load_scene(tmp_path / "cell.yaml").placed(ur10)
    from campaign.model.rotations import cardan_xyz

    np.testing.assert_allclose(moved.T_cell_I[:3, :3], cardan_xyz(np.pi / 2, 0, np.pi / 2), atol=1e-15)
    world = moved.T_cell_I @ np.append(moved.tracker_position, 1.0)
    np.testing.assert_allclose(world[:3], scene.tracker_position, atol=1e-12)
    doc["robot_base"] = {"tilt": 3}
    (tmp_path / "bad.yaml").write_text(yaml.safe_dump(doc))
    with pytest.raises(ConfigError, match=r"robot_base: unknown key 'tilt'"):
        load_scene(tmp_path / "bad.yaml")


_TINY = """<robot name="tiny">
  <link name="base"/>
  <joint name="j1" type="revolute"><parent link="base"/><child link="l1"/><axis xyz="0 0 1"/>
    <limit lower="-3" upper="3" velocity="1" effort="1"/></joint>
  <link name="l1"><collision><geometry>{geometry}</geometry></collision></link>
  <joint name="j2" type="revolute"><parent link="l1"/><child link="tool"/><origin xyz="0 0 0.5"/><axis xyz="0 1 0"/>
    <limit lower="-3" upper="3" velocity="1" effort="1"/></joint>
  <link name="tool"/>
</robot>
"""


@pytest.mark.parametrize("geometry, message", [
    ('<mesh filename="package://nowhere/arm.stl"/>', r"link 'l1': collision mesh 'package://nowhere/arm\.stl' not found"),
    ('<mesh filename="broken.stl"/>', r"link 'l1': collision mesh .*broken\.stl is not a readable mesh"),
    ("<heightfield/>", r"link 'l1': collision geometry <heightfield> is not supported by the planner"),
])
def test_geometry_the_planner_cannot_check_is_one_line_and_exit_1(tmp_path, capsys, geometry, message):
    (tmp_path / "broken.stl").write_text("solid nothing here\nthis is not an stl\n")
    urdf = tmp_path / "tiny.urdf"
    urdf.write_text(_TINY.format(geometry=geometry))
    run = tmp_path / "run"
    assert main(["plan", "--robot", str(urdf), "--run", str(run), "--quiet"]) == 1
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and str(urdf) in err[0], err
    assert re.search(message, err[0]), err[0]
    assert not run.exists()


_KINDS = """<robot name="kinds">
  <link name="base"><collision><origin xyz="0 0 0.6"/><geometry><mesh filename="ball.dae" scale="0.5 0.5 0.5"/></geometry>
    </collision></link>
  <joint name="j1" type="revolute"><parent link="base"/><child link="l1"/><axis xyz="0 0 1"/>
    <limit lower="-3" upper="3" velocity="1" effort="1"/></joint>
  <link name="l1"><collision><origin xyz="0.3 0 0.1" rpy="0 1.5707963267948966 0"/>
    <geometry><capsule radius="0.03" length="0.4"/></geometry></collision></link>
  <joint name="j2" type="prismatic"><parent link="l1"/><child link="l2"/><axis xyz="0 0 1"/>
    <limit lower="0" upper="1" velocity="1" effort="1"/></joint>
  <link name="l2"><collision><geometry><sphere radius="0.02"/></geometry></collision>
    <collision><origin xyz="0.1 0 0"/><geometry><cylinder radius="0.02" length="0.1"/></geometry></collision></link>
  <joint name="j3" type="revolute"><parent link="l2"/><child link="tool"/><origin xyz="0 0 0.05"/><axis xyz="1 0 0"/>
    <limit lower="-3" upper="3" velocity="1" effort="1"/></joint>
  <link name="tool"><collision><geometry><mesh filename="block.stl"/></geometry></collision></link>
</robot>
"""


@pytest.fixture(scope="module")
def kinds_robot(tmp_path_factory):
    """A made-up chain with every kind of collision geometry: a closed DAE mesh (scaled) on the base,
    a capsule, a prismatic joint carrying a sphere and a cylinder, an STL mesh on the tool."""
    import trimesh

    tmp = tmp_path_factory.mktemp("kinds")
    (tmp / "ball.dae").write_bytes(trimesh.exchange.dae.export_collada(trimesh.creation.icosphere(2, radius=0.4)))
    trimesh.creation.box((0.08, 0.05, 0.03)).export(tmp / "block.stl")
    (tmp / "kinds.urdf").write_text(_KINDS)
    return RobotModel.load(tmp / "kinds.urdf", tool_frame="tool")


@pytest.mark.parametrize("clearance", [0.01, 0.035, 0.1])
def test_sphere_bounds_never_clear_a_pair_that_fcl_finds_closer_for_every_kind(kinds_robot, clearance):
    robot = kinds_robot
    prims = robot_primitives(robot)
    assert [p.kind for p in prims] == ["mesh", "capsule", "sphere", "cylinder", "mesh"]
    checker = ClearanceChecker(robot, load_scene(DEFAULT_SCENE).placed(robot), 0.035)
    q = np.random.default_rng(5).uniform(robot.q_lower, robot.q_upper, size=(150, 3))
    R, t = frames(robot, q)
    Re, te = nominal_frames_entry_first(robot, q)
    np.testing.assert_allclose(np.moveaxis(te, -1, 0), t, atol=1e-14)  # the prismatic joint too
    need_scene, need_self = checker.undecided_pairs(Re, te, clearance)
    for k in range(len(q)):
        d_scene, d_self = checker.pair_distances(R[k], t[k])
        assert np.all(d_scene[~need_scene[:, k]] >= clearance)
        assert np.all(d_self[~need_self[:, k]] >= clearance)
    if clearance <= 0.035:  # the bounds decide most pairs (this arm is small: within 10 cm of itself often)
        assert need_self.mean() < 0.5 and need_scene.mean() < 0.5


def test_meshes_load_scaled_and_a_shape_inside_a_closed_mesh_touches_it(kinds_robot):
    import fcl
    import trimesh

    robot = kinds_robot
    ball = robot_primitives(robot)[0]
    v = trimesh.load(robot.urdf_path.parent / "ball.dae", force="mesh").vertices * 0.5 + [0, 0, 0.6]
    np.testing.assert_allclose(ball.mesh.vertices @ ball.T[:3, :3].T + ball.T[:3, 3], v, atol=1e-12)
    checker = ClearanceChecker(robot, load_scene(DEFAULT_SCENE).placed(robot), 0.035)
    sphere, cylinder = 2, 3
    assert (0, sphere) in checker.self_pairs and (0, cylinder) in checker.self_pairs
    R, t = frames(robot, np.array([[0.0, 0.6, 0.0]]))  # the sphere at the ball's centre, 2 cm in a 20 cm ball
    ball_mesh = trimesh.Trimesh(v, trimesh.load(robot.urdf_path.parent / "ball.dae", force="mesh").faces)
    _, to_surface, _ = trimesh.proximity.closest_point(ball_mesh, t[0, 2][None])
    shell = fcl.BVHModel()
    shell.beginModel(len(v), len(ball_mesh.faces))
    shell.addSubModel(v, np.asarray(ball_mesh.faces, dtype=np.int32))
    shell.endModel()
    surfaces = fcl.distance(fcl.CollisionObject(shell, fcl.Transform()),
                            fcl.CollisionObject(fcl.Sphere(0.02), fcl.Transform(np.eye(3), t[0, 2])),
                            fcl.DistanceRequest(), fcl.DistanceResult())
    assert surfaces == pytest.approx(to_surface[0] - 0.02, abs=1e-6)  # FCL sees only the triangles
    assert ball_mesh.contains(t[0, 2][None])[0]
    d_scene, d_self = checker.pair_distances(R[0], t[0])
    assert d_self[checker.self_pairs.index((0, sphere))] == 0.0 == d_self[checker.self_pairs.index((0, cylinder))]
    assert not checker.clear(R, t)[0]
    R, t = frames(robot, np.array([[0.0, 0.95, 0.0]]))  # above the ball: apart by 0.95 - 0.6 - 0.2 - 0.02 m
    d_scene, d_self = checker.pair_distances(R[0], t[0])
    _, gap, _ = trimesh.proximity.closest_point(ball_mesh, t[0, 2][None])
    assert d_self[checker.self_pairs.index((0, sphere))] == pytest.approx(gap[0] - 0.02, abs=1e-6)
    assert gap[0] == pytest.approx(0.95 - 0.6 - 0.2, abs=1e-6)  # the ball's top is a vertex


def test_plan_then_run_in_the_simulated_cell_for_the_panda(tmp_path, panda_yaml):
    """`campaign plan --robot panda/robot.yaml --select` then `campaign run --sim`: the simulated
    cell measures the Panda's own three reflectors; the stored poses equal the truth's."""
    from campaign.effects.base import effect_context
    from campaign.measure.store import open_run
    from campaign.sim.truth import read_truth

    run = _plan(tmp_path, ["--robot", str(panda_yaml)], [6, 4, 5, 4, 5, 4, 3], ["--select", "12", "--validation", "0.5"])
    cfg = yaml.safe_load((run / "campaign.yaml").read_text())
    assert Path(cfg["robot"]) == panda_yaml.resolve() and cfg["plan"]["grid_cells"] == [6, 4, 5, 4, 5, 4, 3]
    _, ids, Q = _read_poses(run)
    assert main(["run", str(run), "--sim", "--quiet"]) == 0
    robot = RobotModel.load(panda_yaml)
    with open_run(run) as store:
        poses = store.load_measured()
    assert len(poses) == len(ids) and poses.q.shape[1] == 7
    truth = read_truth(run / "sim" / "truth.yaml", robot)  # only now, after the run
    T_true = truth.pose(poses.q, effect_context(poses.context, poses.time_s))
    assert np.max(np.abs(T_true[:, :3, 3] - poses.xyz)) < 1e-9
    assert np.max(np.abs(T_true[:, :3, :3] - poses.T_IE[:, :3, :3])) < 1e-9


def test_the_robot_named_in_campaign_yaml_is_planned_for_and_recorded(tmp_path, panda_yaml):
    cfg = tmp_path / "campaign.yaml"
    cfg.write_text(yaml.safe_dump({"robot": str(panda_yaml), "plan": {"grid_cells": [3, 3, 3, 2, 3, 3, 3]}}))
    run = tmp_path / "run"
    assert main(["plan", "--config", str(cfg), "--run", str(run), "--quiet"]) == 0
    s = json.loads((run / "plan" / "summary.json").read_text())
    assert s["robot"] == "panda" and s["tool_frame"] == "panda_hand" and s["reflectors"] == ["a", "b", "c"]
    recorded = yaml.safe_load((run / "campaign.yaml").read_text())
    assert Path(recorded["robot"]) == panda_yaml.resolve() and recorded["plan"]["grid_cells"] == [3, 3, 3, 2, 3, 3, 3]
    assert s["candidates"] == 3 ** 6 * 2


@pytest.mark.parametrize("args, message", [
    (["--robot", "{tmp}/nowhere.urdf"], r"robot '.*nowhere\.urdf': neither a URDF file"),
    (["--robot", "{ur10}", "--tool-frame", "flange"], r"tool frame 'flange' is not a link of ur10_robot\.urdf"),
    (["--robot", "{one}", "--select", "9"], r"--select 9: 29 unknowns need at least 10 poses \(3 equations each\)"),
    (["--robot", "{ur10}", "--tool-frame", "tool0", "--config", "{tmp}/upside.yaml"], r"down must not be zero"),
])
def test_bad_robot_or_cell_for_another_robot_is_one_line_and_exit_1(tmp_path, capsys, args, message):
    (tmp_path / "one.yaml").write_text(yaml.safe_dump({"urdf": str(_urdf("panda")), "tool_frame": "panda_hand",
                                                       "reflectors": [{"name": "m1", "position_m": [0, 0, 0.12]}]}))
    doc = yaml.safe_load(DEFAULT_SCENE.read_text())
    doc["down"] = [0, 0, 0]
    (tmp_path / "cell.yaml").write_text(yaml.safe_dump(doc))
    (tmp_path / "upside.yaml").write_text(yaml.safe_dump({"scene": "cell.yaml"}))
    subs = {"tmp": str(tmp_path), "ur10": str(_urdf("ur10")), "one": str(tmp_path / "one.yaml")}
    run = tmp_path / "run"
    assert main(["plan", "--run", str(run), "--quiet", *[a.format(**subs) for a in args]]) == 1
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and re.search(message, err[0]), err
    assert not run.exists()


def test_a_one_reflector_robot_gets_the_short_campaign_by_default_and_a_selection_on_request(tmp_path):
    """One reflector: each pose measures its position (3 equations), and the selection weighs
    exactly that; the default plan is the short campaign (120 poses, validation, repeats), not
    every suitable pose; `--select` chooses the number asked."""
    (tmp_path / "one.yaml").write_text(yaml.safe_dump({"urdf": str(_urdf("panda")), "tool_frame": "panda_hand",
                                                       "reflectors": [{"name": "m1", "position_m": [0, 0, 0.12]}]}))
    cells = [6, 4, 5, 4, 5, 4, 3]
    (tmp_path / "default").mkdir()
    (tmp_path / "chosen").mkdir()
    default = _plan(tmp_path / "default", ["--robot", str(tmp_path / "one.yaml")], cells, ())
    s = json.loads((default / "plan" / "summary.json").read_text())
    assert s["campaign"]["kind"] == "short" and s["campaign"]["mode"] == "default" and s["suitable"] > 150
    sel = s["selection"]
    assert (sel["selected"], sel["validation"], sel["repeated_poses"]) == (120, 30, 3)
    assert sel["measured"]["kind"] == "points" and sel["measured"]["equations_per_pose"] == 3
    assert sel["predicted"]["model_orientation_mrad"] is None
    assert 0 < sel["predicted"]["model_position_mm"] < sel["predicted"]["heldout_position_mm"]
    _, ids, _ = _read_poses(default)
    assert len(ids) == 120 + 30 + 3 * (sel["repeat_times"] - 1) - s["tour"]["dropped"]
    chosen = _plan(tmp_path / "chosen", ["--robot", str(tmp_path / "one.yaml")], cells, ("--select", "15"))
    s = json.loads((chosen / "plan" / "summary.json").read_text())
    assert s["selection"]["selected"] == 15 and s["selection"]["n_unknowns"] == 29


def test_a_move_of_another_joint_count_says_how_many_and_six_stay_as_they_were():
    from campaign.errors import ProtocolError
    from campaign.measure import protocol as P

    seven = P.Move(3, tuple(0.1 * k for k in range(7)))
    body = P.encode(seven)[4:]
    assert json.loads(body)["joints"] == 7 and P.decode(body) == seven
    assert P.decode(P.encode(P.Reached(3, (0.2,) * 7, 1.5))[4:]) == P.Reached(3, (0.2,) * 7, 1.5)
    assert "joints" not in json.loads(P.encode(P.Move(3, (0.1,) * 6))[4:])
    with pytest.raises(ProtocolError, match=r"'q' must be a list of 7 numbers"):
        P.decode(b'{"type": "move", "id": 1, "joints": 7, "q": [0, 0, 0, 0, 0, 0]}')
    with pytest.raises(ProtocolError, match=r"field 'joints' must be an integer in 1\.\.32"):
        P.decode(b'{"type": "move", "id": 1, "joints": 0, "q": []}')


def test_campaign_sim_serves_the_robot_the_run_records_and_refuses_another(tmp_path, capsys, panda_yaml):
    """`campaign sim --run RUN` for a run planned for the Panda serves the Panda (not the default
    robot): a driver measures 7-joint poses through its ports; `--robot` naming another robot
    than the run records is one line, exit 1, and the run folder is left as it was."""
    import os
    import signal
    import subprocess
    import sys

    from campaign.measure.store import open_run

    run = _plan(tmp_path, ["--robot", str(panda_yaml)], [3, 3, 3, 2, 3, 3, 3], ["--select", "12", "--validation", "0.5"])
    before = sorted(p.name for p in run.iterdir())
    assert main(["sim", "--run", str(run), "--robot", str(_urdf("ur10")), "--tool-frame", "tool0"]) == 1
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and re.search(r"records robot .*panda.*simulate that one", err[0]), err
    assert sorted(p.name for p in run.iterdir()) == before
    env = {**os.environ, "PYTHONPATH": str(Path(__file__).resolve().parents[1])}
    cell = subprocess.Popen([sys.executable, "-m", "campaign.cli", "sim", "--run", str(run)],
                            stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, env=env)
    try:
        line = cell.stdout.readline()
        assert "panda" in line, line + cell.stderr.read()
        ports = dict(re.findall(r"(controller|tracker) 127\.0\.0\.1:(\d+)", line))
        assert main(["run", str(run), "--controller", f"127.0.0.1:{ports['controller']}",
                     "--tracker", f"127.0.0.1:{ports['tracker']}", "--quiet"]) == 0
    finally:
        cell.send_signal(signal.SIGINT)
        cell.wait(timeout=30)
    with open_run(run) as store:
        poses = store.load_measured()
    _, ids, _ = _read_poses(run)
    assert len(poses) == len(ids) and poses.q.shape[1] == 7


def test_beams_the_link_boxes_stop_are_decided_on_the_shapes_as_the_reference_sees_them():
    """The SO-ARM100 with its tool frame at the wrist: the wrist's bounding box holds a reflector
    of the default triad in every pose, its mesh does not. Poses the boxes reject are decided on
    the links' shapes: those accepted so are visible in the Pinocchio + FCL reference, those still
    rejected are not."""
    robot = RobotModel.load(erd_robot("so_arm_description/urdf/so100.urdf"), tool_frame="gripper").with_default_reflectors()
    scene = load_scene(DEFAULT_SCENE).placed(robot)
    q = np.random.default_rng(8).uniform(robot.q_lower, robot.q_upper, size=(20_000, robot.n_joints))
    R, t = frames(robot, q)
    E = robot.n_joints + 1
    P, A = checks.reflector_geometry(robot, R[:, E], t[:, E])
    seen = checks.range_ok(scene, P) & checks.cone_ok(robot, scene, P, A) & checks.scene_line_of_sight_ok(scene, P)
    boxed = checks.robot_line_of_sight_ok(robot, scene, P, R, t)
    assert seen.sum() > 500 and not (seen & boxed).any()  # the boxes alone leave nothing
    k = np.random.default_rng(9).choice(np.flatnonzero(seen), 80, replace=False)
    decided = ClearanceChecker(robot, scene, CLEARANCE_M).beams_clear(R[k], t[k], P[k])
    ref = _reference(robot)
    visible = np.array([ref.visible(qk, robot.reflectors) for qk in q[k]])
    np.testing.assert_array_equal(decided, visible)
    assert 5 <= decided.sum() < len(k)


def test_no_suitable_pose_says_in_one_line_which_link_hides_the_reflectors_and_what_to_change(tmp_path, capsys):
    """TALOS's arm with its tool frame at the last joint: the forearm's mesh hides a reflector of
    the default triad in every pose the tracker could see (the reference sees none either)."""
    urdf = erd_robot("talos_data/robots/talos_left_arm.urdf")
    assert main(["plan", "--robot", str(urdf), "--tool-frame", "arm_left_7_link", "--grid-scale", "0.3",
                 "--run", str(tmp_path / "run"), "--quiet"]) == 1
    err = capsys.readouterr().err.strip()
    assert len(err.splitlines()) == 1 and "no suitable pose among" in err
    assert "link 'arm_left_5_link' hides reflector" in err and "--tool-frame" in err and "robot.yaml" in err
    robot = RobotModel.load(urdf, tool_frame="arm_left_7_link").with_default_reflectors()
    ref = FclReference(robot, DEFAULT_SCENE, load_scene(DEFAULT_SCENE).placed(robot).T_cell_I)
    scene = load_scene(DEFAULT_SCENE).placed(robot)
    q = np.random.default_rng(2).uniform(robot.q_lower, robot.q_upper, size=(5000, robot.n_joints))
    R, t = frames(robot, q)
    P, A = checks.reflector_geometry(robot, R[:, -1], t[:, -1])
    seen = q[checks.range_ok(scene, P) & checks.cone_ok(robot, scene, P, A) & checks.scene_line_of_sight_ok(scene, P)]
    assert len(seen) >= 60 and not any(ref.visible(qk, robot.reflectors) for qk in seen[:60])


def test_when_the_link_boxes_leave_too_few_poses_the_plan_decides_their_beams_on_the_shapes():
    """The SO-ARM100 above: its links' boxes hide every pose; the filter then decides the beams they
    stopped on the shapes and says so; the poses it keeps are visible and clear in the reference."""
    from campaign.plan.pipeline import _filter_grid

    robot = RobotModel.load(erd_robot("so_arm_description/urdf/so100.urdf"), tool_frame="gripper").with_default_reflectors()
    grid = Grid.for_robot(robot, (8, 7, 7, 7, 10))
    suitable, counts, checker = _filter_grid(robot, load_scene(DEFAULT_SCENE).placed(robot), grid, CLEARANCE_M, False)
    exact = counts["line_of_sight_exact"]
    assert 0 < exact["seen"] < exact["poses"] and "left 0 suitable poses" in exact["why"]
    assert len(suitable) >= 20 and counts["suitable"] == len(suitable)
    ref = _reference(robot)
    pairs = ref.pairs(checker)
    for q in grid.q(np.random.default_rng(1).choice(suitable, 20, replace=False)):
        assert ref.visible(q, robot.reflectors) and ref.min_clearance(q, pairs) >= CLEARANCE_M
