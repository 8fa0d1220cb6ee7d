"""Issue 31, part 4: the drift with its uncertainty, from every reading of the reference poses.

The fit is checked against its definition on synthetic readings whose truth the test draws
itself (false alarms of a still pose, coverage of a true drift, the closed form of the
interval for isotropic scatter), and the driver's moved-pose threshold against the noise it is
meant to exceed rarely.
"""

import numpy as np
import pytest

from campaign.measure.drift import _norm_range, fit_drift, moved_threshold_m, same_pose_groups
from campaign.tolerances import DRIFT_WARNING_ALPHA

#: the noise of a measured tool position (m per coordinate): a 10 µm tracker through 3 reflectors,
#: anisotropic and correlated as a tracker's distance and angles make it
NOISE_COV = np.array([[36.0, 8.0, 0.0], [8.0, 25.0, -5.0], [0.0, -5.0, 60.0]]) * 1e-12


def readings(rng, v_m_per_h, n_checks=8, span_h=1.0, poses=1):
    """The reference poses' readings: each pose its own position, n_checks + 1 readings spread
    over span_h, all moving at v (3,) m/h, the noise NOISE_COV."""
    t, x, g = [], [], []
    for p in range(poses):
        tp = np.sort(rng.uniform(0, span_h, n_checks + 1)) * 3600.0
        a = rng.normal(0, 0.3, 3)
        noise = rng.multivariate_normal(np.zeros(3), NOISE_COV, len(tp))
        t.append(tp)
        x.append(a + np.outer(tp / 3600.0, v_m_per_h) + noise)
        g.append(np.full(len(tp), p))
    return np.concatenate(t), np.concatenate(x), np.concatenate(g)


def test_a_still_reference_pose_reads_a_significant_drift_in_about_one_run_of_twenty():
    rng = np.random.default_rng(1)
    hits = [fit_drift(*readings(rng, np.zeros(3))).significant for _ in range(600)]
    assert 0.03 <= np.mean(hits) <= 0.075, np.mean(hits)


def test_a_true_drift_lies_inside_its_interval_in_about_95_percent():
    rng = np.random.default_rng(2)
    v = np.array([30.0, -15.0, 14.0]) * 1e-6  # 37 µm/h
    inside, significant = [], []
    for _ in range(400):
        f = fit_drift(*readings(rng, v, n_checks=8, span_h=2.0))
        inside.append(f.ci95_um_per_h[0] <= 37.0 <= f.ci95_um_per_h[1])
        significant.append(f.significant)
    assert np.mean(inside) >= 0.94, np.mean(inside)
    assert np.mean(significant) > 0.8  # 37 µm/h over 2 h against 6-8 µm of noise: found


def test_several_reference_poses_each_keep_their_own_position():
    rng = np.random.default_rng(3)
    v = np.array([0.0, 40e-6, 0.0])
    f = fit_drift(*readings(rng, v, n_checks=4, span_h=3.0, poses=6))
    assert f.poses == 6 and f.n == 30 and f.dof == 30 - 6 - 1
    assert f.velocity_um_per_h[1] == pytest.approx(40.0, abs=4 * (f.ci95_um_per_h[1] - f.um_per_h))
    assert f.significant and f.ci95_um_per_h[0] <= 40.0 <= f.ci95_um_per_h[1]


def test_the_interval_of_a_spherical_region_is_the_distance_to_its_centre_plus_minus_its_radius():
    c = np.array([3.0, -4.0, 0.0])
    assert _norm_range(c, 2.0 * np.eye(3)) == pytest.approx((3.0, 7.0), rel=1e-4)
    assert _norm_range(c, 6.0 * np.eye(3)) == pytest.approx((0.0, 11.0), rel=1e-4)
    # an ellipsoid: its farthest point from 0 along the long axis
    lo, hi = _norm_range(np.array([0.0, 0.0, 10.0]), np.diag([1.0, 2.0, 3.0]))
    assert lo == pytest.approx(7.0, rel=1e-3) and hi == pytest.approx(13.0, rel=1e-3)


def test_a_noise_free_cell_reads_no_drift_and_an_exact_drift_exactly():
    t = np.linspace(0, 7200, 9)
    still = fit_drift(t, np.tile([0.5, 0.2, 0.9], (9, 1)), np.zeros(9))
    assert not still.significant and still.um_per_h < 1e-6
    moving = fit_drift(t, np.array([0.5, 0.2, 0.9]) + np.outer(t / 3600, [0, 0, 50e-6]), np.zeros(9))
    assert moving.significant and moving.um_per_h == pytest.approx(50.0, rel=1e-9)
    assert moving.ci95_um_per_h[0] == pytest.approx(50.0, abs=0.01) and moving.ci95_um_per_h[1] < 50.01


def test_too_few_readings_give_a_rate_without_an_interval():
    f = fit_drift([0.0, 3600.0], [[0, 0, 0], [0, 0, 1e-5]], [0, 0])
    assert f.dof == 0 and f.ci95_um_per_h is None and f.significant is None and f.um_per_h == pytest.approx(10.0)
    assert fit_drift([0.0, 0.0], [[0, 0, 0], [0, 0, 1e-5]], [0, 0]) is None  # no time between them


def test_one_pose_read_twice_takes_its_interval_from_the_noise_floor():
    # one drift check: 2 readings, no scatter of their own; with the floor's σ a sphere of radius
    # sqrt(χ²₃(0.95)) σ / sqrt(S) around v, S = Σ(t − t̄)² = T² / 2 (hours)
    from scipy import stats

    sigma, T = 10e-6, 0.5
    f = fit_drift([0.0, 3600 * T], [[0, 0, 0], [0, 0, 20e-6]], [0, 0], sigma_m=[sigma, 4e-6, 4e-6])
    R = np.sqrt(stats.chi2.ppf(0.95, 3)) * sigma / np.sqrt(T ** 2 / 2) * 1e6
    assert f.um_per_h == pytest.approx(40.0) and f.significant is False
    assert f.ci95_um_per_h[0] == 0.0 and f.ci95_um_per_h[1] == pytest.approx(40.0 + R, rel=1e-4)
    # a true drift lies inside in at least 95 % of such pairs (the speed's interval bounds the 95 % sphere of
    # the velocity: at least as often), and a still pose reads significant in about 5 %
    rng = np.random.default_rng(3)
    inside = significant = 0
    for _ in range(200):
        x = np.array([[0, 0, 0], [0, 0, 100e-6 * T]]) + rng.normal(0, sigma, (2, 3))
        lo, hi = fit_drift([0.0, 3600 * T], x, [0, 0], sigma_m=[sigma] * 3).ci95_um_per_h
        inside += lo <= 100.0 <= hi
        still = fit_drift([0.0, 3600 * T], rng.normal(0, sigma, (2, 3)), [0, 0], sigma_m=[sigma] * 3)
        significant += still.significant
    assert inside / 200 >= 0.94 and significant / 200 <= 0.1, (inside, significant)


def test_a_pose_measured_again_with_its_last_joint_a_few_microradians_on_is_the_same_pose():
    q = np.array([[0.1, 0.2, 0.3, 0.4, 0.5, 0.6],
                  [0.1, 0.2, 0.3, 0.4, 0.5, 0.6 + 1e-6],
                  [0.1, 0.2, 0.3, 0.4, 0.5, 0.6 + 3e-6],
                  [0.1, 0.2, 0.3, 0.4, 0.5, 0.601],   # another pose
                  [0.1, 0.2, 0.3, 0.4, 0.5001, 0.6]])  # another pose
    g = same_pose_groups(q)
    assert g[0] == g[1] == g[2] and len({g[0], g[3], g[4]}) == 3


def test_the_moved_pose_threshold_is_exceeded_by_the_noise_once_in_a_thousand_checks():
    rng = np.random.default_rng(4)
    sigma = np.array([6e-6, 6e-6, 6e-6])
    m = 3  # earlier readings
    earlier = rng.normal(0, sigma, size=(400_000, m, 3)).mean(axis=1)
    new = rng.normal(0, sigma, size=(400_000, 3))
    rate = np.mean(np.linalg.norm(new - earlier, axis=1) > moved_threshold_m(sigma, m))
    assert rate == pytest.approx(DRIFT_WARNING_ALPHA, rel=0.25)
    # a 100 µm tracker's tool position (σ ~60 µm): the threshold is well above the 0.235 mm the issue saw
    assert moved_threshold_m(np.full(3, 60e-6), 1) > 0.3e-3


def _plan_with_repeats(runs, n, noise_m, hidden=(), every=10):
    """A simulated run of ``n`` random poses whose first 3 are measured 3 times back to back
    (ids p + r·10⁹, as the plan writes repeats) and a drift check every ``every`` poses."""
    from campaign.plan.selection import REPEAT_ID_STRIDE

    run = runs.make(n=n, sim={"noise_m": noise_m, "hidden_effects": list(hidden)}, run={"drift_check_every": every})
    lines = (run / "plan" / "poses.csv").read_text().splitlines()
    head, rows = lines[0], lines[1:]
    out = []
    for k, row in enumerate(rows):
        out.append(row)
        if k < 3:
            pid, rest = row.split(",", 1)
            out += [f"{int(pid) + r * REPEAT_ID_STRIDE},{rest}" for r in (1, 2)]
    (run / "plan" / "poses.csv").write_text("\n".join([head] + out) + "\n")
    return run


def test_a_noisy_tracker_does_not_read_as_a_moved_reference_pose(runs):
    """The issue's 100 µm tracker: nine "moved 0.235 mm" warnings against a fixed 0.05 mm; the
    threshold from the floor (the back-to-back repeats) warns at none, and every check stores
    its reading and its threshold."""
    from campaign.cli import main
    from campaign.measure.store import open_run

    run = _plan_with_repeats(runs, 60, 1e-4)
    assert main(["run", str(run), "--sim", "--quiet"]) == 0
    with open_run(run) as store:
        checks = [d for _, _, _, d in store.events("drift_check")]
        warnings = store.events("warning")
    assert len(checks) >= 5 and warnings == []
    assert all(len(c["xyz_m"]) == 3 and c["threshold_from"].startswith("the noise") for c in checks)
    # the threshold of the first check: from the repeats' floor, well above the noise's typical distance
    assert all(0.25 < c["threshold_mm"] < 0.8 for c in checks), [c["threshold_mm"] for c in checks]


def test_a_moving_reference_pose_on_a_noise_free_cell_is_warned_and_its_drift_fitted(runs):
    from campaign.cli import main
    from campaign.diagnose import diagnose
    from campaign.measure.store import open_run

    run = _plan_with_repeats(runs, 50, 0.0, hidden=[{"effect": "drift", "params": [0.0, 2e-5, 0.0]}])  # 20 µm/h
    assert main(["run", str(run), "--sim", "--quiet"]) == 0
    with open_run(run) as store:
        checks = [d for _, _, _, d in store.events("drift_check")]
        warnings = store.events("warning")
    assert len(checks) == 5 and len(warnings) == 5  # 56 stored poses (6 repeats); nothing but the drift moves it
    d = diagnose(run, folds=3, candidates="cyclic").drift
    # the reference (the first pose) read 3 times back to back and at 5 checks; noise-free: exact
    assert d.monitor is not None and d.significant and d.fit.n == 3 + 5
    assert d.um_per_h == pytest.approx(20.0, rel=1e-6) and d.fit.ci95_um_per_h[0] <= 20.0 <= d.fit.ci95_um_per_h[1]
