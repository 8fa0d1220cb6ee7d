"""The tracker noise floor: the mean position error ‖Δt‖ (mm) that measurement noise alone
leaves to a perfect model, drawn as a line on the history chart.

A measured tool position is the origin of F_E from a rigid least-squares fit (Kabsch) of the
k reflectors measured with N(0, σ²) noise per coordinate (one reflector: the point itself).
Linearised about the true pose, the fit's unknowns (δt, δθ) see each reflector p_i (in F_E,
m) through the rows [I₃, −[p_i]×], so the origin's covariance is the δt block of
σ² (Jᵀ J)⁻¹ (:func:`fitted_origin_covariance`; for the COMAU's three reflectors and
σ = 10 µm: about 6 µm per coordinate, 9.8 µm mean norm, not the 16 µm of one point).
The mean norm of e ~ N(0, Σ) is E‖e‖ = 1/(2√π) ∫₀^∞ (1 − Πᵢ (1 + 2λᵢ s)^(−1/2)) s^(−3/2) ds
over Σ's eigenvalues λᵢ (from ‖e‖ = 1/(2√π) ∫₀^∞ (1 − exp(−s‖e‖²)) s^(−3/2) ds); for
Σ = σ² I₃ it is the Maxwell mean σ · 2√2/√π ≈ 1.596 σ (:func:`mean_norm`).

σ comes, in this order, from a value the user states, from repeated measurements of the same
commanded joints in the run (their pooled spread, which measures the noise of the derived
position itself), or from the tracker noise configured in RUN/campaign.yaml (``sim.noise_m``).
A held-out error can only approach the floor from above: the model's own estimation error adds.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np

#: E‖e‖ / σ for e ~ N(0, σ² I₃): the mean of a Maxwell distribution, 2√2/√π
MAXWELL_MEAN_PER_SIGMA = 2.0 * np.sqrt(2.0) / np.sqrt(np.pi)


@dataclass(frozen=True)
class NoiseFloor:
    """The mean position error ‖Δt‖ (mm) that tracker noise alone gives a perfect model."""

    position_mm: float
    #: covariance (3, 3) of the measured tool position's noise, m²
    covariance_m2: np.ndarray
    #: how it was found, in words (for the chart's legend)
    source: str


def mean_norm(cov) -> float:
    """E‖e‖ for e ~ N(0, cov), cov (3, 3) (any unit u²; the answer in u)."""
    from scipy.integrate import quad

    lam = np.clip(np.linalg.eigvalsh(np.asarray(cov, dtype=float)), 0.0, None)
    top = lam.max()
    if top <= 0:
        return 0.0
    lam = lam / top  # a scale-free integrand; E‖e‖ scales with the square root of the largest

    def f(s):
        return (1.0 - np.prod(1.0 + 2.0 * lam * s) ** -0.5) * s ** -1.5

    value = quad(f, 0.0, 1.0, limit=200)[0] + quad(f, 1.0, np.inf, limit=200)[0]
    return float(value / (2.0 * np.sqrt(np.pi)) * np.sqrt(top))


def fitted_origin_covariance(markers_in_E, sigma_m: float) -> np.ndarray:
    """Covariance (3, 3) m² of the tool origin from a rigid fit of the reflectors markers_in_E
    (k, 3) m, each measured with N(0, σ²) per coordinate (linearised; one reflector: σ² I₃)."""
    P = np.atleast_2d(np.asarray(markers_in_E, dtype=float))
    if len(P) == 1:
        return sigma_m ** 2 * np.eye(3)
    J = np.zeros((3 * len(P), 6))
    for i, p in enumerate(P):
        J[3 * i : 3 * i + 3, :3] = np.eye(3)
        J[3 * i : 3 * i + 3, 3:] = -np.array([[0, -p[2], p[1]], [p[2], 0, -p[0]], [-p[1], p[0], 0]])
    return sigma_m ** 2 * np.linalg.pinv(J.T @ J)[:3, :3]


def noise_floor_from_sigma(sigma_m: float, markers_in_E=None, source: str = "stated") -> NoiseFloor:
    """The floor for tracker noise σ (m) per coordinate on each reflector of markers_in_E
    (k, 3) m (None: the position is one measured point)."""
    cov = fitted_origin_covariance(np.zeros((1, 3)) if markers_in_E is None else markers_in_E, float(sigma_m))
    return NoiseFloor(mean_norm(cov) * 1e3, cov, source)


def noise_floor_from_repeats(q, xyz, *, min_dof: int = 6):
    """The floor from repeated measurements: poses with the same commanded joints q (n, N) rad
    measured more than once; the covariance is the pooled within-pose scatter of their tool
    positions xyz (n, 3) m, with Σ(n_pose − 1) degrees of freedom (None below ``min_dof``)."""
    q, xyz = np.asarray(q, dtype=float), np.asarray(xyz, dtype=float)
    if len(q) < 2:
        return None
    _, group, counts = np.unique(np.round(q, 9), axis=0, return_inverse=True, return_counts=True)
    group = group.reshape(-1)
    dof = int(np.sum(counts[counts > 1] - 1))
    if dof < min_dof:
        return None
    sums = np.zeros((len(counts), 3))
    np.add.at(sums, group, xyz)
    dev = xyz - (sums / counts[:, None])[group]
    cov = dev.T @ dev / dof
    n_rep = int(np.sum(counts > 1))
    sd_um = np.sqrt(np.trace(cov) / 3) * 1e6
    return NoiseFloor(mean_norm(cov) * 1e3, cov, f"from repeats of {n_rep} poses, σ ≈ {sd_um:.3g} µm per coordinate")


def _run_markers(run_dir):
    """The reflectors (k, 3) m in F_E of the run's robot, or None when it cannot be loaded."""
    try:
        from campaign.run import RunFolder

        robot = RunFolder(run_dir).robot()
        return np.asarray(robot.reflector_positions_in_E, dtype=float)
    except Exception:
        return None


def tracker_noise_floor(run_dir, q=None, xyz=None, sigma_m: float | None = None, markers_in_E=None):
    """The run's tracker noise floor (:class:`NoiseFloor`) or None: from a stated ``sigma_m``
    (m, per reflector coordinate), else from repeated measurements in q, xyz (the run's own when
    not given), else from the tracker noise configured in RUN/campaign.yaml (``sim.noise_m``).
    markers_in_E: the reflectors (k, 3) m (default: the run's robot's)."""
    from campaign.fileio import read_yaml_mapping

    run_dir = Path(run_dir)
    cfg_path = run_dir / "campaign.yaml"
    try:
        cfg = read_yaml_mapping(cfg_path) if cfg_path.is_file() else {}
    except Exception:  # a chart's reference line is never worth failing a report for
        cfg = {}
    if sigma_m is not None:
        markers = _run_markers(run_dir) if markers_in_E is None else markers_in_E
        return noise_floor_from_sigma(sigma_m, markers, f"stated σ = {sigma_m * 1e6:.3g} µm per reflector coordinate")
    if q is None or xyz is None:
        try:
            from campaign.measure.store import open_run

            with open_run(run_dir) as store:
                poses = store.load_measured()
            q, xyz = poses.q, poses.xyz
        except Exception:
            q = xyz = None
    if q is not None:
        floor = noise_floor_from_repeats(q, xyz)
        if floor is not None:
            return floor
    sim = cfg.get("sim") if isinstance(cfg, dict) else None
    try:
        sigma = float(sim["noise_m"]) if isinstance(sim, dict) and "noise_m" in sim else None
    except (TypeError, ValueError):
        sigma = None
    if sigma is None or not np.isfinite(sigma) or sigma <= 0:
        return None
    markers = _run_markers(run_dir) if markers_in_E is None else markers_in_E
    fit = f"{len(markers)}-reflector fit" if markers is not None and len(markers) > 1 else "one point"
    return noise_floor_from_sigma(sigma, markers, f"configured tracker noise sim.noise_m, σ = {sigma * 1e6:.3g} µm, "
                                                  f"{fit}")
