import numpy as np

from campaign.model.base_params import base_parameters
from campaign.model.kinematics import PARAM_NAMES

# The paper's Table 3, written as {parameter: coefficient}; lengths as in our URDF
# (0.0405 where the paper rounds to 0.041).
TABLE3 = [
    {"pL_I0_x": 1, "pL_01_y": -1, "pR_01_x": -0.189},
    {"pL_I0_y": 1, "pL_01_z": -1, "pL_12_z": -1},
    {"pL_I0_z": 1, "pL_01_x": 1, "pR_01_y": -0.189},
    {"pL_12_x": 1},
    {"pL_12_y": 1, "pL_23_z": 1, "pL_34_z": 1, "pR_12_x": -0.050},
    {"pL_23_x": 1},
    {"pL_23_y": 1, "pq3": -0.370, "pR_34_y": -0.370},
    {"pL_34_x": 1, "pL_45_z": 1, "pR_34_y": -0.050},
    {"pL_34_y": 1, "pR_34_y": -0.0405},
    {"pL_45_x": 1},
    {"pL_45_y": 1, "pL_56_z": 1},
    {"pL_56_x": 1, "pL_6E_z": 1},
    {"pL_56_y": 1, "pR_56_y": -0.080},
    {"pL_6E_x": 1, "pR_6E_z": -0.040},
    {"pL_6E_y": 1, "pR_6E_z": -0.016},
    {"pq1": 1, "pR_I0_z": 1, "pR_12_x": 1},
    {"pq2": 1, "pq3": 1, "pR_34_y": 1},
    {"pq4": 1, "pR_45_x": 1},
    {"pq5": 1, "pR_56_y": 1},
    {"pq6": 1, "pR_6E_z": 1},
    {"pR_I0_x": 1, "pR_01_x": 1},
    {"pR_I0_y": 1, "pR_01_y": 1},
    {"pR_12_y": 1},
    {"pR_23_x": 1},
    {"pR_23_y": 1},
    {"pR_34_x": 1},
    {"pR_45_y": 1},
    {"pR_56_x": 1},
    {"pR_6E_x": 1},
    {"pR_6E_y": 1},
]


def test_position_and_orientation_give_30_base_parameters(base):
    assert base.n_base == 30
    assert base.rank_pivoted == 30


def test_base_combinations_agree_with_table3(base):
    assert base.n_base == len(TABLE3)
    for j, expected in enumerate(TABLE3):
        row = base.combination[j]
        got = {PARAM_NAMES[i]: row[i] for i in np.flatnonzero(np.abs(row) > 1e-6)}
        assert set(got) == set(expected), f"row {j + 1}: {base.expression(j)}"
        for name, coeff in expected.items():
            assert abs(got[name] - coeff) < 1e-6, f"row {j + 1}, {name}: {got[name]} vs {coeff}"


def test_count_does_not_depend_on_the_random_poses(robot):
    assert base_parameters(robot, seed=7, n_poses=60).n_base == 30


def test_position_only_measurements_identify_fewer_parameters(robot):
    b = base_parameters(robot, position_only=True)
    assert b.n_base < 30
    assert b.n_base == b.rank_pivoted


def test_min_norm_vector_reproduces_the_base_parameters(base, rng):
    p_b = rng.normal(0, 1e-3, base.n_base)
    p_e = base.min_norm(p_b)
    np.testing.assert_allclose(base.project(p_e), p_b, atol=1e-15)
    np.testing.assert_allclose(base.project(base.expand(p_b)), p_b, atol=1e-15)
    assert np.linalg.norm(p_e) <= np.linalg.norm(base.expand(p_b)) + 1e-15


def test_table_prints_like_the_paper(base):
    text = base.table()
    assert "30 identifiable base parameters" in text
    assert "pL_I0_x - pL_01_y - 0.189 pR_01_x" in text
    assert "pq1 + pR_I0_z + pR_12_x" in text
