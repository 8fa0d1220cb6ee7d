"""The pieces that keep `campaign plan` fast (issue 22) give the answers of the slow ways: the grid's
frames built block by block, the convex hull's bound and the remembered verdicts, the prediction
on a sample."""

import numpy as np
import pytest

from campaign.model.robot import RobotModel
from campaign.paths import DEFAULT_SCENE
from campaign.plan.checks import ClearanceChecker
from campaign.plan.geometry import nominal_frames, nominal_frames_entry_first, robot_primitives
from campaign.plan.grid import Grid, _descend, _descend_blocks
from campaign.plan.scene import load_scene

from fcl_reference import erd_robot


@pytest.fixture(scope="module")
def ur10():
    urdf = erd_robot("ur_description/urdf/ur10_robot.urdf")
    return RobotModel.load(urdf, tool_frame="tool0").with_default_reflectors()


def test_frames_built_block_by_block_equal_the_whole_descent_for_any_block_size(ur10):
    grid = Grid.for_robot(ur10, (5, 4, 3, 4, 3, 2))
    R, t = _descend(ur10, grid, 5)
    for rows in (1, 7, 50, 240, 10_000):
        blocks = list(_descend_blocks(ur10, grid, 5, max_rows=rows))
        assert max(len(b[0]) for b in blocks) <= max(rows, 3 * 4 * 3)  # one value of q1 spans 144 at most
        np.testing.assert_array_equal(np.concatenate([b[0] for b in blocks]), R)
        np.testing.assert_array_equal(np.concatenate([b[1] for b in blocks]), t)


def test_a_mesh_hull_is_never_farther_than_the_mesh_and_the_verdicts_match_the_triangles(ur10):
    """At random postures: each mesh pair's hull distance from FCL, and the least distance of their
    pieces' hulls, less the slack allowed for GJK's error, is at most its triangle distance, and
    the checker's verdict per posture (hulls, pieces, remembered verdicts) equals the one from
    triangle distances alone (with the closed-mesh inside test) at the clearance."""
    from campaign.plan.checks import HULL_SLACK_M, HULL_SLACK_REL

    scene = load_scene(DEFAULT_SCENE).placed(ur10)
    checker = ClearanceChecker(ur10, scene, 0.035)
    rng = np.random.default_rng(11)
    q = rng.uniform(ur10.q_lower, ur10.q_upper, size=(40, ur10.n_joints))
    q = np.concatenate([q, q[:15]])  # the same postures again: answered from memory
    R, t = nominal_frames_entry_first(ur10, q)
    got = checker.clear_entry_first(R, t)
    expected = []
    for k in range(len(q)):
        checker._place(R[..., k], t[..., k])
        for i, j in checker.self_pairs:
            if checker.hull_objs[i] is not checker.robot_objs[i] and checker.hull_objs[j] is not checker.robot_objs[j]:
                h = checker._dist(checker.hull_objs[i], checker.hull_objs[j])  # -1: in contact
                mesh = max(checker._dist(checker.robot_objs[i], checker.robot_objs[j]), 0)
                assert max(h, 0) * (1 - HULL_SLACK_REL) - HULL_SLACK_M <= mesh
                pieces = min(checker._dist(x, y) for x in checker.piece_objs[i] for y in checker.piece_objs[j])
                assert max(pieces, 0) * (1 - HULL_SLACK_REL) - HULL_SLACK_M <= mesh
        for i, j in checker.scene_pairs:
            if checker.hull_objs[i] is not checker.robot_objs[i]:
                h = checker._dist(checker.hull_objs[i], checker.scene_objs[j])
                assert max(h, 0) * (1 - HULL_SLACK_REL) - HULL_SLACK_M <= max(
                    checker._dist(checker.robot_objs[i], checker.scene_objs[j]), 0)
        d_scene = [checker._dist_scene(i, j) for i, j in checker.scene_pairs]
        d_self = [checker._dist_self(i, j) for i, j in checker.self_pairs]
        expected.append(min(d_scene + d_self) >= 0.035)
    np.testing.assert_array_equal(got, expected)
    assert 0 < got.sum() < len(got)
    assert any(p.mesh is not None for p in robot_primitives(ur10))


def test_the_prediction_on_its_sample_is_within_2_percent_of_the_prediction_over_every_pose(ur10):
    from campaign.plan import selection as S

    rng = np.random.default_rng(4)
    q = rng.uniform(np.maximum(ur10.q_lower, -np.pi), np.minimum(ur10.q_upper, np.pi), size=(6000, ur10.n_joints))
    info = S.information_model(ur10, q)
    design = S.select(info, 40, exchange=False).index
    ev, sample = S.evaluation_sample(info, design, pilot=500)
    assert sample["of"] == 6000 and sample["poses"] == len(ev) < 6000 and sample["relative_half_width"] == 0.02
    assert len(ev) >= (1.96 * sample["pilot_coefficient_of_variation"] / 0.02) ** 2 - 1
    full, part = S.predict_accuracy(info, design), S.predict_accuracy(info, design, ev)
    for key in ("model_position_mm", "model_orientation_mrad", "heldout_position_mm"):
        assert getattr(part, key) == pytest.approx(getattr(full, key), rel=0.02), key
    assert "random sample" in S.sample_text(sample) and "±2 %" in S.sample_text(sample)


def test_the_greedy_tour_with_neighbour_lists_is_the_greedy_tour_without(ur10):
    from campaign.plan.timing import GridTimes
    from campaign.plan.tour import nearest_neighbour, neighbour_lists

    grid = Grid.for_robot(ur10)
    times = GridTimes(ur10, grid)
    rng = np.random.default_rng(8)
    for n in (300, 3000):
        C = grid.cell_indices(rng.choice(grid.size, n, replace=False))
        C[1] = C[0]  # ties in travel time
        np.testing.assert_array_equal(nearest_neighbour(times, C, 5, neighbour_lists(times, C, 8)),
                                      nearest_neighbour(times, C, 5))


def test_a_mesh_read_from_the_cache_is_the_mesh_parsed_and_a_bad_cache_entry_is_parsed_again(tmp_path, monkeypatch):
    import campaign.plan.geometry as G

    path = str(erd_robot("ur_description/meshes/ur10/collision/forearm.stl").resolve())
    monkeypatch.setenv("CAMPAIGN_CACHE_DIR", str(tmp_path))
    G._load_mesh.cache_clear()
    parsed = G._load_mesh(path, (1.0, 1.0, 1.0), 0)
    assert len(list((tmp_path / "meshes").glob("*.npz"))) == 1
    G._load_mesh.cache_clear()
    cached = G._load_mesh(path, (1.0, 1.0, 1.0), 0)
    for a, b in zip(parsed, cached):
        np.testing.assert_array_equal(a, b)
    next((tmp_path / "meshes").glob("*.npz")).write_bytes(b"not a cache entry")
    G._load_mesh.cache_clear()
    again = G._load_mesh(path, (1.0, 1.0, 1.0), 0)
    np.testing.assert_array_equal(again[0], parsed[0])
    G._load_mesh.cache_clear()
    scaled = G._load_mesh(path, (2.0, 2.0, 2.0), 0)  # another scale: another entry
    np.testing.assert_allclose(scaled[3], 2 * parsed[3], rtol=1e-9)
    G._load_mesh.cache_clear()


def test_the_pairs_always_near_read_from_the_cache_are_those_found_and_a_bad_entry_is_found_again(ur10, tmp_path,
                                                                                                   monkeypatch):
    monkeypatch.setenv("CAMPAIGN_CACHE_DIR", str(tmp_path))
    scene = load_scene(DEFAULT_SCENE).placed(ur10)
    found = ClearanceChecker(ur10, scene, 0.035)
    entries = list((tmp_path / "pairs").glob("*.json"))
    assert len(entries) == 1 and found.disabled_pairs  # the UR10 has pairs always in contact
    cached = ClearanceChecker(ur10, scene, 0.035)
    assert (cached.self_pairs, cached.disabled_pairs) == (found.self_pairs, found.disabled_pairs)
    entries[0].write_text('{"always": [true]}')
    again = ClearanceChecker(ur10, scene, 0.035)
    assert (again.self_pairs, again.disabled_pairs) == (found.self_pairs, found.disabled_pairs)
    other = ClearanceChecker(ur10, scene, 0.02)  # another clearance: another entry
    assert len(list((tmp_path / "pairs").glob("*.json"))) == 2 and other.clearance == 0.02


def test_the_frame_spheres_decide_what_the_primitive_spheres_did_and_clear_no_pair_the_reference_finds_near():
    """TIAGo: 41 meshes on the gripper's frame. The frame level (one sphere per frame around its
    primitives, pairs of two frames decided together) leaves undecided exactly the pairs the
    primitive spheres left without it; a pair it clears is at least the clearance apart in the
    Pinocchio + FCL reference."""
    from fcl_reference import FclReference

    robot = RobotModel.load(erd_robot("tiago_description/robots/tiago.urdf"), tool_frame="arm_tool_link",
                            base_frame="base_footprint")
    checker = ClearanceChecker(robot, load_scene(DEFAULT_SCENE).placed(robot), 0.035)
    q = np.random.default_rng(3).uniform(robot.q_lower, robot.q_upper, size=(300, robot.n_joints))
    R, t = nominal_frames_entry_first(robot, q)
    need_scene, need_self = checker.undecided_pairs(R, t, 0.035)
    frame_radius = checker._frame_radius
    checker._frame_radius = np.full_like(frame_radius, np.inf)  # every frame pair undecided: no frame level
    try:
        without_scene, without_self = checker.undecided_pairs(R, t, 0.035)
    finally:
        checker._frame_radius = frame_radius
    np.testing.assert_array_equal(need_self, without_self)
    np.testing.assert_array_equal(need_scene, without_scene)
    ref = FclReference(robot, DEFAULT_SCENE, np.eye(4))  # pairs of links: where the robot stands does not matter
    pairs = ref.pairs(checker)
    rng = np.random.default_rng(4)
    nearest = np.inf
    for k in rng.choice(len(q), 6, replace=False):
        ref.place(q[k])
        for m in rng.choice(np.flatnonzero(~need_self[:, k]), 60, replace=False):
            nearest = min(nearest, ref.dist(ref.objs[pairs[m][0]], ref.objs[pairs[m][1]]))
    assert 0.035 <= nearest < 0.5
    assert len(checker.prims) > 60 and 0 < need_self.mean() < 0.05


def test_inside_a_closed_mesh_by_its_hull_first_is_inside_by_the_rays_alone():
    """MeshShape.contains answers points outside the convex hull's planes without casting rays:
    the same answers as trimesh's ray test for every point, on the closed meshes of a TIAGo."""
    robot = RobotModel.load(erd_robot("tiago_description/robots/tiago.urdf"), tool_frame="arm_tool_link",
                            base_frame="base_footprint")
    closed = [p for p in robot_primitives(robot) if p.mesh is not None and p.mesh.watertight]
    assert len(closed) >= 3
    rng = np.random.default_rng(6)
    inside = 0
    for p in closed[:8]:
        pts = rng.uniform(-0.6, 0.6, size=(400, 3)) * np.asarray(p.size)
        got = p.mesh.contains(pts)
        np.testing.assert_array_equal(got, p.mesh.trimesh.contains(pts))
        inside += got.sum()
    assert inside > 50


def test_a_pairs_distance_changes_along_a_motion_by_at_most_its_speed_in_the_reference():
    """TIAGo (a prismatic torso, 41 meshes on the gripper): along straight joint motions, the
    distance of a link to an obstacle and of two links, in the Pinocchio + FCL reference, moves
    from its value at either end pose by at most the pair's speed (campaign.plan.repair.pair_speeds)
    times the motion's parameter from that end; a pair no joint of the motion moves keeps it."""
    from fcl_reference import FclReference

    from campaign.plan.repair import pair_speeds

    robot = RobotModel.load(erd_robot("tiago_description/robots/tiago.urdf"), tool_frame="arm_tool_link",
                            base_frame="base_footprint")
    scene = load_scene(DEFAULT_SCENE).placed(robot)
    checker = ClearanceChecker(robot, scene, 0.035)
    ref = FclReference(robot, DEFAULT_SCENE, scene.T_cell_I)
    index = ref.index_of(checker.prims)
    rng = np.random.default_rng(5)
    s = np.linspace(0.0, 1.0, 9)
    slack, compared, kept = [], 0, 0
    for motion in range(4):
        qa = rng.uniform(robot.q_lower, robot.q_upper)
        qb = np.clip(qa + rng.uniform(-0.6, 0.6, robot.n_joints), robot.q_lower, robot.q_upper)
        if motion == 3:
            qb[:-2] = qa[:-2]  # the wrist alone: the pairs before it do not move against each other
        scene_speed, self_speed = (v[..., 0] for v in pair_speeds(robot, (qb - qa)[None]))
        scene_pairs = [checker.scene_pairs[m] for m in rng.choice(len(checker.scene_pairs), 20, replace=False)]
        self_pairs = [checker.self_pairs[m] for m in rng.choice(len(checker.self_pairs), 40, replace=False)]
        d = np.empty((len(s), len(scene_pairs) + len(self_pairs)))
        for k, sk in enumerate(s):
            ref.place(qa + sk * (qb - qa))
            d[k] = [ref.dist(ref.objs[index[i]], ref.obstacles[j]) for i, j in scene_pairs] + \
                   [ref.dist(ref.objs[index[i]], ref.objs[index[j]]) for i, j in self_pairs]
        speed = np.array([scene_speed[checker.prims[i].frame] for i, _ in scene_pairs] +
                         [self_speed[checker.prims[i].frame, checker.prims[j].frame] for i, j in self_pairs])
        apart = np.all(d > 0, axis=0)  # FCL's distance of shapes that overlap is not their depth
        for end, u in ((0, s), (-1, 1.0 - s)):
            slack.append((speed * u[:, None] - np.abs(d - d[end]))[:, apart])
        compared += int(apart.sum())
        still = apart & (speed == 0)
        kept += int(still.sum())
        np.testing.assert_allclose(d[:, still], np.broadcast_to(d[0, still], d[:, still].shape), atol=1e-9)
    assert np.concatenate([x.ravel() for x in slack]).min() >= -1e-9
    assert compared >= 150 and kept >= 5


def test_the_motion_check_with_the_end_poses_bound_gives_the_verdicts_of_the_check_without(ur10):
    """Motions between poses clear by the pose clearance (35 mm), checked at 10 mm: the pairs the
    end poses bound are skipped, the verdicts are those of checking every pair at every sample
    (colliding motions among them)."""
    from campaign.plan.repair import check_segments

    scene = load_scene(DEFAULT_SCENE).placed(ur10)
    checker = ClearanceChecker(ur10, scene, 0.035)
    q = np.random.default_rng(6).uniform(ur10.q_lower, ur10.q_upper, size=(400, ur10.n_joints))
    q = q[checker.clear(*nominal_frames(ur10, q))][:80]
    near = np.clip(q + np.random.default_rng(7).uniform(-0.3, 0.3, q.shape), ur10.q_lower, ur10.q_upper)
    near = near[checker.clear(*nominal_frames(ur10, near))]
    Q_from = np.concatenate([q[:40], near[: len(near) // 2]])
    Q_to = np.concatenate([q[40:80], q[: len(near) // 2]])
    step = np.deg2rad(1.0)
    bounded = check_segments(ur10, checker, Q_from, Q_to, step, 0.01, ends_clearance=0.035)
    checker._memo.clear()
    plain = check_segments(ur10, checker, Q_from, Q_to, step, 0.01)
    np.testing.assert_array_equal(bounded, plain)
    assert 5 <= (~plain).sum() <= len(plain) - 5


def test_inside_a_closed_mesh_by_the_cells_of_a_point_far_from_its_surface_is_inside_by_its_rays(ur10):
    """A point known to keep a distance from a closed mesh's surface is inside it as its cell's
    centre is (cells of half that distance, remembered): for points at least that far from the
    surface (trimesh's distance to the nearest point), the answer of the rays cast from the point
    itself; points of nearby poses share cells."""
    checker = ClearanceChecker(ur10, load_scene(DEFAULT_SCENE).placed(ur10), 0.035)
    closed = [i for i, p in enumerate(checker.prims) if p.mesh is not None and p.mesh.watertight]
    R, t = nominal_frames(ur10, np.zeros((1, ur10.n_joints)))
    checker._place(R[0], t[0])
    rng = np.random.default_rng(8)
    compared = inside = 0
    for i in closed[:3]:
        p = checker.prims[i]
        local = rng.uniform(-0.6, 0.6, size=(400, 3)) * np.asarray(p.size)
        local = np.concatenate([local, local + rng.uniform(-1e-3, 1e-3, local.shape)])  # nearby poses' points
        far_by = np.abs(p.mesh.trimesh.nearest.signed_distance(local))
        Rw, tw = checker._world[i]
        for apart in (0.01, 0.035):
            far = far_by >= apart
            got = [checker._inside(i, Rw @ x + tw, apart) for x in local[far]]
            np.testing.assert_array_equal(got, p.mesh.contains(local[far]))
            compared += int(far.sum())
            inside += int(np.sum(got))
    assert compared >= 1000 and inside >= 100
    assert len(checker._inside_cells) < 0.75 * compared
