"""Optimal pose selection for one or two reflectors (position-only data): the information of the
measured positions, the design's algebra for blocks of 3 and 6 rows, and the prediction, on one-
and two-reflector Pandas (example-robot-data)."""

import json
from importlib import metadata
from pathlib import Path

import numpy as np
import pytest
import yaml

from campaign.cli import main
from campaign.effects.base import EffectSet, effect_context, make_effect, model_pose
from campaign.model.robot import RobotModel
from campaign.plan import selection as S
from campaign.sim.truth import random_joint_poses

SIGMA_M = 10e-6
HAND = {"tool_frame": "panda_hand", "locked_joints": {"panda_finger_joint1": 0.02, "panda_finger_joint2": 0.02}}
ONE = [{"name": "m1", "position_m": [0.0, 0.0, 0.12]}]
TWO = [{"name": "a", "position_m": [0.05, 0.04, 0.02], "axis": [1, 0, 0], "half_angle_deg": 40},
       {"name": "b", "position_m": [0.05, -0.04, 0.02], "axis": [1, 0, 0], "half_angle_deg": 40}]
GRID = [6, 4, 5, 4, 5, 4, 3]  # 28,800 candidates, about a thousand suitable with one reflector


def _panda_urdf():
    try:
        dist = metadata.distribution("example-robot-data")
    except metadata.PackageNotFoundError:
        pytest.skip("example-robot-data (test extra) is not installed")
    return Path(dist.locate_file("cmeel.prefix/share")) / "example-robot-data/robots/panda_description/urdf/panda.urdf"


def _robot_yaml(folder, name, reflectors):
    path = folder / f"{name}.yaml"
    path.write_text(yaml.safe_dump({"urdf": str(_panda_urdf()), "name": name, **HAND, "reflectors": reflectors}))
    return path


@pytest.fixture(scope="module")
def panda_yamls(tmp_path_factory):
    folder = tmp_path_factory.mktemp("pandas")
    return {"one": _robot_yaml(folder, "panda_one", ONE), "two": _robot_yaml(folder, "panda_two", TWO)}


@pytest.fixture(scope="module")
def robots(panda_yamls):
    return {k: RobotModel.load(v) for k, v in panda_yamls.items()}


def _fd_positions(robot, q, names, effects, h=1e-6):
    """Finite differences of the reflectors' positions (F_I) of the model `calibrate` fits to
    one-reflector data (the robot whose tool point is the first reflector), perturbed one unknown
    at a time: (n, 3k, p) m per unit."""
    P = robot.reflector_positions_in_E
    tool = robot.with_tool_point(P[0])
    es = EffectSet(tuple(make_effect(e, robot) for e in effects))
    ctx = effect_context({}, np.zeros(len(q)))
    theta0 = es.initial_params()

    def positions(p_e, theta):
        T = model_pose(tool, q, p_e, es, theta, ctx)
        return np.einsum("nij,kj->nki", T[:, :3, :3], P - P[0]) + T[:, None, :3, 3]  # (n, k, 3)

    cols = []
    for name in names:
        plus, minus = [np.zeros(tool.n_params), theta0.copy()], [np.zeros(tool.n_params), theta0.copy()]
        if name in tool.param_names:
            i, where = tool.param_names.index(name), 0
        else:
            i, where = es.param_names.index(name), 1
        plus[where][i] += h
        minus[where][i] -= h
        cols.append(((positions(*plus) - positions(*minus)) / (2 * h)).reshape(len(q), -1))
    return np.stack(cols, axis=2)


@pytest.mark.parametrize("which, effects", [("one", ("ground_compliance",)), ("two", ())])
def test_position_only_information_is_the_finite_difference_jacobian_of_the_reflector_positions(
        robots, which, effects):
    robot = robots[which]
    q = random_joint_poses(robot, 25, seed=11)
    info = S.information_model(robot, q, effects=effects, noise_m=SIGMA_M)
    k = len(robot.reflectors)
    assert info.measured == "points" and info.block_size == 3 * k and info.J.shape == (25, 3 * k, info.n_unknowns)
    es = EffectSet(tuple(make_effect(e, robot) for e in effects))
    assert info.names[len(info.names) - es.n_params:] == tuple(es.param_names)
    fd = _fd_positions(robot, q, info.names, effects)
    np.testing.assert_allclose(info.J, fd, rtol=0, atol=1e-6 * np.abs(fd).max())
    # the information is that of the coordinates, each with σ: Σ JᵀJ / σ² (in the scaled columns)
    M = np.einsum("nri,nrj->ij", fd, fd) / SIGMA_M**2
    np.testing.assert_allclose(info.information(np.arange(25)), M / np.outer(info.scale, info.scale),
                               rtol=1e-5, atol=1e-8)
    # the unknowns: the position-only base parameters `calibrate` identifies from one reflector
    if which == "one":
        from campaign.model.base_params import base_parameters

        base = base_parameters(robot.with_tool_point(robot.reflector_positions_in_E[0]), position_only=True)
        assert info.names[:base.n_base] == base.names and info.n_unknowns == base.n_base + es.n_params
    # every unknown is informed: M has full rank
    assert np.linalg.matrix_rank(M / np.outer(np.sqrt(np.diag(M)), np.sqrt(np.diag(M)))) == info.n_unknowns


@pytest.mark.parametrize("which, block", [("one", 3), ("two", 6)])
def test_design_gain_and_loss_are_the_log_det_ratios_for_blocks_of_3_and_6(robots, which, block):
    info = S.information_model(robots[which], random_joint_poses(robots[which], 200, seed=12))
    assert info.block_size == block
    d = S.Design(info, "D")
    rng = np.random.default_rng(4)
    picks = rng.choice(info.n_candidates, 30, replace=False)
    for j in picks:
        d.add(j)
    d.remove(picks[5])
    kept = np.delete(picks, 5)
    B = info.blocks
    M = S.RIDGE * np.eye(info.n_unknowns) + sum(B[j].T @ B[j] for j in kept)
    ld = np.linalg.slogdet(M)[1]
    assert d.criterion_value() == pytest.approx(ld, rel=1e-10)
    others = rng.choice(np.setdiff1d(np.arange(info.n_candidates), kept), 5, replace=False)
    direct = [np.linalg.slogdet(M + B[j].T @ B[j])[1] - ld for j in others]
    np.testing.assert_allclose(d.gains()[others], direct, rtol=1e-7)
    lost = [ld - np.linalg.slogdet(M - B[j].T @ B[j])[1] for j in kept[:5]]
    np.testing.assert_allclose(d.losses(kept[:5]), lost, rtol=1e-6)
    # A: the fall of tr M⁻¹ when a candidate is added
    a = S.Design(info, "A")
    for j in kept:
        a.add(j)
    tr = np.trace(np.linalg.inv(M))
    direct = [tr - np.trace(np.linalg.inv(M + B[j].T @ B[j])) for j in others]
    np.testing.assert_allclose(a.gains()[others], direct, rtol=1e-6)


@pytest.mark.parametrize("which", ["one", "two"])
def test_greedy_selection_adds_the_candidate_of_largest_log_det_each_step(robots, which):
    info = S.information_model(robots[which], random_joint_poses(robots[which], 60, seed=13))
    sel = S.select(info, 14, exchange=False)
    chosen, B = [], info.blocks
    M = S.RIDGE * np.eye(info.n_unknowns)
    for _ in range(14):
        ld = [np.linalg.slogdet(M + B[j].T @ B[j])[1] if j not in chosen else -np.inf for j in range(60)]
        j = int(np.argmax(ld))
        chosen.append(j)
        M = M + B[j].T @ B[j]
    assert sel.index.tolist() == chosen


def test_position_only_prediction_is_the_covariance_carried_to_the_measured_point(robots):
    """σ² (JᵀJ)⁻¹ carried to the reflector at every candidate, computed here with numpy; no
    orientation is predicted (none is measured)."""
    robot = robots["one"]
    q = random_joint_poses(robot, 150, seed=14)
    info = S.information_model(robot, q, noise_m=SIGMA_M)
    idx = S.select(info, 20).index
    J = info.J
    cov = SIGMA_M**2 * np.linalg.inv(np.einsum("nri,nrj->ij", J[idx], J[idx]))
    C = J @ cov @ np.swapaxes(J, 1, 2)
    pred = S.predict_accuracy(info, idx)
    assert pred.model_orientation_mrad is None and pred.heldout_orientation_mrad is None
    assert pred.model_position_rms_mm == pytest.approx(1e3 * np.sqrt(np.mean(np.trace(C, axis1=1, axis2=2))),
                                                       rel=1e-9)
    # E‖N(0, σ² I₃)‖ = 2σ √(2/π), from 256 fixed normal samples
    assert pred.noise_position_mm == pytest.approx(1e3 * 2 * SIGMA_M * np.sqrt(2 / np.pi), rel=0.05)
    assert pred.model_position_mm < pred.model_position_rms_mm < pred.heldout_position_mm
