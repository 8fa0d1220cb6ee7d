"""User effects (files and entry points), the joint_twist hook, gravity from the robot model,
and the noise floor's sources — each against an independent computation."""

import dataclasses
import importlib
import textwrap

import numpy as np
import pytest
import yaml

from campaign.cli import main
from campaign.diagnose.engine import candidate_specs
from campaign.effects import Effect, make_effect
from campaign.effects.base import EffectSet, effect_name, model_pose
from campaign.errors import ConfigError
from campaign.identify.calibrate import configured_effects
from campaign.measure.csvio import write_measured_csv
from campaign.measure.floor import floor_from_repeats, floor_from_stated, noise_floor
from campaign.measure.store import open_run
from campaign.model.kinematics import forward, frames, pose_error
from campaign.model.rotations import rotvec_to_matrix, skew
from campaign.sim.truth import make_truth, random_joint_poses, synthesize

EFFECT_SOURCE = '''
import numpy as np

from campaign.effects import Effect


class Sag(Effect):
    """The tool sags along gravity by s times the horizontal reach."""

    name = "sag"
    description = "tool sag proportional to the reach"
    param_names = ("s",)
    param_units = ("1",)

    def pose_map(self, params, T, q, context):
        out = np.array(T, dtype=float, copy=True)
        out[:, 1, 3] += params[0] * np.hypot(T[:, 0, 3], T[:, 2, 3])
        return out
'''


def imported_run(tmp_path, robot, n=60, seed=1, q=None):
    truth = make_truth(robot, seed=seed)
    q = random_joint_poses(robot, n, seed=seed) if q is None else q
    poses = synthesize(truth, q, seed=seed + 1)
    tmp_path.mkdir(parents=True, exist_ok=True)
    write_measured_csv(tmp_path / "m.csv", poses)
    run = tmp_path / "run"
    assert main(["import", str(tmp_path / "m.csv"), "--run", str(run)]) == 0
    return run, truth, poses


# -- user effect files and entry points ------------------------------------------------------------

def test_a_file_effect_is_found_relative_to_the_runs_campaign_yaml(tmp_path, robot):
    run, _, poses = imported_run(tmp_path, robot)
    (run / "effects").mkdir()
    (run / "effects" / "sag.py").write_text(EFFECT_SOURCE)
    cfg = yaml.safe_load((run / "campaign.yaml").read_text())
    cfg["effects"] = ["effects/sag.py:Sag", "drift"]
    (run / "campaign.yaml").write_text(yaml.safe_dump(cfg))
    specs = configured_effects(run)
    assert specs[0] == f"{(run / 'effects' / 'sag.py').resolve()}:Sag" and specs[1] == "drift"
    e = make_effect(specs[0], robot)
    assert e.name == effect_name(specs[0]) == "sag" and e.spec == specs[0]
    T = forward(robot, poses.q[:4])
    reach = np.hypot(T[:, 0, 3], T[:, 2, 3])
    np.testing.assert_allclose(e.pose_map(np.array([1e-3]), T, poses.q[:4], {})[:, 1, 3], T[:, 1, 3] + 1e-3 * reach)


@pytest.mark.parametrize("body, spec, message", [
    (None, "missing.py:Sag", "no such file"),
    (EFFECT_SOURCE, "eff.py:Nope", "defines no class 'Nope'"),
    ("class Sag:\n    name = 'sag'\n", "eff.py:Sag", "is not a subclass of campaign.effects.Effect"),
    ("def broken(:\n", "eff.py:Sag", "failed to load \\(SyntaxError"),
    (EFFECT_SOURCE.replace('name = "sag"', 'name = ""'), "eff.py:Sag", "sets no `name`"),
    (None, "no_such_effect", "unknown effect 'no_such_effect'"),
])
def test_a_bad_user_effect_is_one_line_naming_it(tmp_path, robot, body, spec, message, capsys):
    if body is not None:
        (tmp_path / "eff.py").write_text(body)
    with pytest.raises(ConfigError, match=message):
        make_effect(str(tmp_path / spec) if ".py:" in spec else spec, robot)
    run, _, _ = imported_run(tmp_path / "r", robot, n=30)
    capsys.readouterr()
    assert main(["calibrate", str(run), "--no-ann", "--effects", str(tmp_path / spec) if ".py:" in spec else spec]) == 1
    err = capsys.readouterr().err.strip()
    assert len(err.splitlines()) == 1 and "Traceback" not in err and spec.split(":")[-1].split(".")[0] in err
    assert not (run / "calibration").exists()


def test_an_installed_entry_point_is_a_candidate_and_can_be_named(tmp_path, robot, monkeypatch):
    site = tmp_path / "site"
    (site / "campaign_test_sag-0.1.dist-info").mkdir(parents=True)
    (site / "campaign_test_sag-0.1.dist-info" / "METADATA").write_text(
        "Metadata-Version: 2.1\nName: campaign-test-sag\nVersion: 0.1\n")
    (site / "campaign_test_sag-0.1.dist-info" / "entry_points.txt").write_text(
        "[campaign.effects]\nsag = campaign_test_sag:Sag\n")
    (site / "campaign_test_sag.py").write_text(EFFECT_SOURCE)
    monkeypatch.syspath_prepend(str(site))
    importlib.invalidate_caches()
    e = make_effect("sag", robot)
    assert e.name == "sag" and type(e).__module__ == "campaign_test_sag"
    assert "sag" in candidate_specs(None, (), tmp_path)
    assert "sag" not in candidate_specs(None, ("sag",), tmp_path)


# -- the joint_twist hook --------------------------------------------------------------------------

def reference_twisted_chain(robot, q, twists):
    """T = G_1 … G_N F_E with G_j = F_j exp(ξ_j) F_j⁻¹ from the twist-free frames (an independent
    composition of the same chain: ``… A_j exp(ξ_j) A_{j+1} …``)."""
    R, t = frames(robot, q)
    n = len(q)
    P = np.broadcast_to(np.eye(4), (n, 4, 4)).copy()
    for j, k in enumerate(robot.joint_frame_index):
        v, w = twists[:, j, :3], twists[:, j, 3:]
        th = np.linalg.norm(w, axis=1)[:, None, None]
        W = skew(w)
        V = np.eye(3) + (1 - np.cos(th)) / th ** 2 * W + (th - np.sin(th)) / th ** 3 * (W @ W)
        E = np.zeros((n, 4, 4))
        E[:, :3, :3], E[:, :3, 3], E[:, 3, 3] = rotvec_to_matrix(w), (V @ v[..., None])[..., 0], 1.0
        F = np.zeros((n, 4, 4))
        F[:, :3, :3], F[:, :3, 3], F[:, 3, 3] = R[:, k], t[:, k], 1.0
        P = P @ F @ E @ np.linalg.inv(F)
    T = np.zeros((n, 4, 4))
    T[:, :3, :3], T[:, :3, 3], T[:, 3, 3] = R[:, -1], t[:, -1], 1.0
    return P @ T


class RandomTwists(Effect):
    name = "test_random_twists"
    param_names = ("scale",)
    param_units = ("1",)

    def __init__(self, robot, xi):
        super().__init__(robot)
        self.xi = xi

    def joint_twist(self, params, q, context):
        return params[0] * self.xi


def test_joint_twists_act_right_after_their_joint(robot, rng):
    q = random_joint_poses(robot, 20, seed=3)
    xi = rng.normal(0, 1e-3, (20, robot.n_joints, 6))
    T = model_pose(robot, q, effects=EffectSet((RandomTwists(robot, xi),)), theta=np.array([1.0]))
    np.testing.assert_allclose(T, reference_twisted_chain(robot, q, xi), atol=1e-12)
    # a rotation about joint j's own axis (z after its motion) is a change of q_j
    for j in range(robot.n_joints):
        xi_z = np.zeros_like(xi)
        xi_z[:, j, 5] = 2e-3
        dq = np.zeros_like(q)
        dq[:, j] = 2e-3
        T_z = model_pose(robot, q, effects=EffectSet((RandomTwists(robot, xi_z),)), theta=np.array([1.0]))
        np.testing.assert_allclose(T_z, forward(robot, q + dq), atol=1e-12)
    # a translation in joint j's frame is the next transform's translation parameter pL
    xi_v = np.zeros_like(xi)
    xi_v[:, 2, :3] = [1e-3, -2e-3, 5e-4]
    p_e = np.zeros(robot.n_params)
    k = robot.param_names.index("pL_34_x") if "pL_34_x" in robot.param_names else 18
    p_e[k : k + 3] = [1e-3, -2e-3, 5e-4]
    T_v = model_pose(robot, q, effects=EffectSet((RandomTwists(robot, xi_v),)), theta=np.array([1.0]))
    np.testing.assert_allclose(T_v, forward(robot, q, p_e), atol=1e-12)


# -- gravity from the robot model -----------------------------------------------------------------

def old_ground_compliance(robot, params, T, q):
    """The effect as it was before gravity came from the model: tilt about F_I's x and z."""
    from campaign.effects.gravity import overturning_moment

    k_x, k_z, s_x, s_z = params
    M = overturning_moment(robot, q)
    dphi = np.zeros((len(T), 3))
    dphi[:, 0], dphi[:, 2] = k_x * M[:, 0], k_z * M[:, 2]
    R = rotvec_to_matrix(dphi)
    out = T.copy()
    out[:, :3, :3] = R @ T[:, :3, :3]
    out[:, :3, 3] = (R @ T[:, :3, 3][..., None])[..., 0]
    out[:, 0, 3] += s_z * M[:, 2]
    out[:, 2, 3] += -s_x * M[:, 0]
    return out


def test_ground_compliance_of_the_comau_is_unchanged(robot):
    e = make_effect("ground_compliance", robot)
    assert e.param_names == ("k_x", "k_z", "s_x", "s_z")
    q = random_joint_poses(robot, 30, seed=5)
    T = forward(robot, q)
    th = e.typical_params(3)
    np.testing.assert_allclose(e.pose_map(th, T, q, {}), old_ground_compliance(robot, th, T, q), atol=1e-14)


def test_the_tilt_is_about_the_horizontal_axes_of_the_models_gravity(robot):
    upright = dataclasses.replace(robot, gravity_in_I=np.array([0.0, 0.0, -9.81]))
    e = make_effect("ground_compliance", upright)
    assert e.param_names == ("k_x", "k_y", "s_x", "s_y")
    q = random_joint_poses(robot, 30, seed=6)
    T = forward(robot, q)
    T2 = e.pose_map(np.array([1e-5, -2e-5, 0.0, 0.0]), T, q, {})
    dphi = pose_error(T2, T)[:, 3:]
    assert np.max(np.abs(dphi[:, 2])) < 1e-15 and np.max(np.abs(dphi[:, :2])) > 1e-5


def test_the_overturning_moment_equals_the_urdf_link_masses_by_hand(robot):
    """Σ m_i (c_i − its vertical projection) × m_i g over the URDF's links (yourdfpy transforms),
    against the Pinocchio centre of mass the effects use."""
    from campaign.effects.gravity import gravity_vector, overturning_moment

    q = random_joint_poses(robot, 5, seed=7)
    g = gravity_vector(robot)
    up = -g / np.linalg.norm(g)
    urdf = robot.urdf
    expected = []
    for qi in q:
        urdf.update_cfg(dict(zip(robot.joint_names, qi)))
        M = np.zeros(3)
        for name, link in urdf.link_map.items():
            if link.inertial is None or link.inertial.mass == 0:
                continue
            c = (urdf.get_transform(name, urdf.base_link) @ link.inertial.origin)[:3, 3]
            lever = c - (c @ up) * up
            M += np.cross(lever, link.inertial.mass * g)
        expected.append(M)
    np.testing.assert_allclose(overturning_moment(robot, q), expected, rtol=1e-9, atol=1e-9)


# -- the noise floor's sources ---------------------------------------------------------------------

def test_the_floor_from_drift_checks_when_nothing_is_repeated(tmp_path, robot):
    run, truth, poses = imported_run(tmp_path, robot, n=40)
    rng = np.random.default_rng(0)
    sigma = 6e-6  # of the measured tool position, per coordinate
    drift = np.linalg.norm(rng.normal(0, sigma, (400, 3)) - rng.normal(0, sigma, (400, 3)), axis=1)
    with open_run(run) as store:
        for d in drift:
            store.add_event("drift_check", {"reference_pose_id": 1, "drift_mm": d * 1e3, "over_threshold": False})
    floor = noise_floor(run, poses, robot)
    assert floor.source == "repeats" and "400 drift-check" in floor.detail
    assert floor.mean_position_mm == pytest.approx(sigma * 2 * np.sqrt(2 / np.pi) * 1e3, rel=0.06)


def test_the_floor_from_repeats_is_the_noise_of_the_true_robot(robot):
    truth = make_truth(robot, seed=2)
    q = random_joint_poses(robot, 300, seed=3)
    q = np.concatenate([q, np.repeat(q[:100], 3, axis=0)])
    poses = synthesize(truth, q, seed=4)
    floor = floor_from_repeats(poses.xyz, poses.q, time_s=poses.time_s)
    # only now the truth: the mean position error of the noise alone
    true_mm = np.linalg.norm(pose_error(truth.pose_of(poses), poses.T_IE)[:, :3], axis=1).mean() * 1e3
    assert floor.mean_position_mm == pytest.approx(true_mm, rel=3 * floor.relative_uncertainty)
    assert floor.mean_position_mm == pytest.approx(floor_from_stated(truth.noise_m, robot.reflector_positions_in_E)
                                                   .mean_position_mm, rel=3 * floor.relative_uncertainty)


def test_no_floor_is_said_and_a_bad_stated_noise_is_one_line(tmp_path, robot, capsys):
    run, _, _ = imported_run(tmp_path, robot, n=80)
    capsys.readouterr()
    assert main(["diagnose", str(run), "--folds", "2", "--candidates", "drift", "--no-report"]) == 0
    out = capsys.readouterr().out
    assert "no noise floor" in out and "cannot be said" in out
    cfg = yaml.safe_load((run / "campaign.yaml").read_text())
    cfg["tracker"] = {"noise_m": -1.0}
    (run / "campaign.yaml").write_text(yaml.safe_dump(cfg))
    assert main(["diagnose", str(run), "--folds", "2", "--candidates", "drift", "--no-report"]) == 1
    err = capsys.readouterr().err.strip()
    assert len(err.splitlines()) == 1 and "tracker.noise_m" in err


def test_a_plans_repeat_measurements_share_the_fold_of_the_pose_they_repeat():
    from campaign.diagnose.engine import pose_folds
    from campaign.plan.selection import REPEAT_ID_STRIDE

    ids = np.arange(1, 201, dtype=np.int64)
    rep = np.concatenate([ids, ids[:30] + REPEAT_ID_STRIDE, ids[:30] + 2 * REPEAT_ID_STRIDE])
    f, f_rep = pose_folds(ids, 4), pose_folds(rep, 4)
    np.testing.assert_array_equal(f_rep[:200], f)  # the originals keep their folds
    np.testing.assert_array_equal(f_rep[200:230], f[:30])
    np.testing.assert_array_equal(f_rep[230:], f[:30])
    assert np.bincount(f, minlength=4).min() == 50


# -- the model-free test's pieces on functions known in advance ------------------------------------

def test_the_regressor_learns_a_known_function_of_two_inputs_and_drops_the_others():
    from campaign.diagnose.structure import FourierRidge

    rng = np.random.default_rng(3)
    X = rng.uniform(-2.5, 2.5, (1200, 6))
    f = np.stack([np.sin(X[:, 1]) * X[:, 3], np.cos(X[:, 1]), 0.3 * X[:, 3] ** 2], axis=1) * 1e-5
    Y = f + rng.normal(0, 2e-6, f.shape)
    m = FourierRidge(random_state=1).fit(X[:900], Y[:900])
    assert list(np.flatnonzero(m.active_)) == [1, 3]
    resid = f[900:] - m.predict(X[900:])
    assert np.sqrt(np.mean(resid ** 2)) < 0.15 * np.sqrt(np.mean((f[900:] - f[900:].mean(axis=0)) ** 2))
    # noise only: the penalty chosen by leave-one-out keeps the prediction near zero
    m0 = FourierRidge(random_state=1).fit(X[:900], rng.normal(0, 2e-6, (900, 3)))
    assert np.sqrt(np.mean(m0.predict(X[900:]) ** 2)) < 0.3 * 2e-6


def test_the_harmonic_order_of_a_periodic_residual_is_named_and_a_trend_is_not_periodic():
    from campaign.diagnose.signature import harmonic_order

    rng = np.random.default_rng(4)
    x = rng.uniform(-2.8, 2.8, 800)
    lever = rng.normal(1.0, 0.3, (800, 1))  # an amplitude that varies with the other joints
    for k in (1, 2, 3):
        Y = lever * np.stack([np.sin(k * x + 0.4), 0.5 * np.cos(k * x)], axis=1) + rng.normal(0, 0.3, (800, 2))
        assert harmonic_order(x, Y) == k
    assert harmonic_order(x, np.stack([0.3 * x, 0.1 * x ** 2], axis=1) + rng.normal(0, 0.3, (800, 2))) is None
    assert harmonic_order(x, rng.normal(0, 0.3, (800, 2))) is None


class _TurnAboutTheTool(Effect):
    """The tool turns about its own z axis by θ: the tool point stays, the reflectors move."""

    name = "turn_about_the_tool"
    description = "a turn about the tool's own z axis"
    param_names = ("theta",)
    param_units = ("rad",)

    def pose_map(self, params, T, q, context):
        c, s = np.cos(params[0]), np.sin(params[0])
        return np.asarray(T, dtype=float) @ np.array([[c, -s, 0, 0], [s, c, 0, 0], [0, 0, 1, 0], [0, 0, 0, 1.0]])


class _TemperatureOffset(Effect):
    """Joint 3's zero moves with the temperature: nothing moves at 20 °C."""

    name = "temperature_offset"
    description = "joint 3 offset k (T - 20 °C)"
    param_names = ("k",)
    param_units = ("rad/K",)
    context_keys = ("temperature_c",)

    def joint_offset(self, params, q, context):
        dq = np.zeros_like(q, dtype=float)
        dq[:, 2] = params[0] * (np.asarray(context["temperature_c"], dtype=float) - 20.0)
        return dq


def test_a_hidden_turn_about_the_tools_own_origin_is_sized_by_what_the_reflectors_see(robot):
    from campaign.sim.truth import DEFAULT_EFFECT_DISPLACEMENT_M, _unit_displacement_scale, tool_points

    # qa31c: a joint-6 offset of the UR3 (tool0 on joint 6's axis) was drawn as 3e290 rad, the tool
    # point's displacement being round-off; a turn θ about z moves each reflector by θ times its radius
    points = tool_points(robot)
    radius = np.hypot(points[:, 0], points[:, 1]).mean()
    assert radius > 0.01
    scale = _unit_displacement_scale(_TurnAboutTheTool(robot), np.random.default_rng(3))
    np.testing.assert_allclose(scale, DEFAULT_EFFECT_DISPLACEMENT_M / radius, rtol=1e-3)


def test_a_hidden_effect_that_moves_nothing_where_it_is_sized_asks_for_its_params(robot):
    from campaign.sim.truth import hidden_effect_params

    with pytest.raises(ConfigError, match=r"sim\.hidden_effects: effect 'temperature_offset': its parameter k moves "
                                          r"neither the tool point nor its reflectors .* at temperature_c = 20, .*"
                                          r"state its params"):
        hidden_effect_params(_TemperatureOffset(robot), seed=1)
    np.testing.assert_array_equal(hidden_effect_params(_TemperatureOffset(robot), seed=1, params=[2e-4]), [2e-4])
