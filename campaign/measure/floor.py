"""The measurement noise floor, from the measurements themselves, never from the model's fit.

Definition (docs/effects.md, "The noise floor"): the floor is the expected mean position error
``E‖e‖`` (mm) of a residual that is measurement noise only, e ~ N(0, diag(σ_x², σ_y², σ_z²)),
σ the noise of the measured tool position (origin of F_E in F_I) per coordinate. A model whose
held-out mean position error equals the floor has nothing left to explain.

Sources, in order of preference:

1. **repeats** — poses measured more than once with identical joint vectors (the plan's
   repeat poses, re-imported data with repeated joint rows) and the drift check's
   re-measurements of its reference pose (``drift_check`` events in the store, each the
   distance from the reference's first measurement). σ² is pooled over the groups from
   successive differences in time order, Σ (x_{i+1} − x_i)²/2 over Σ (m_group − 1) per
   coordinate; each drift check adds d²/2 spread over 3 coordinates, and is used only when
   the repeats give fewer than 10 degrees of freedom. Repeats spread over a campaign include
   whatever drifts between them: the floor is then an upper bound of the noise (repeats
   measured back to back give the noise itself).
2. **stated** — ``tracker: {noise_m: σ}`` in the run's campaign.yaml: σ per coordinate of
   each reflector centre, carried through the same rigid fit of the reflectors that derives
   measured poses (Monte Carlo with a fixed seed).
3. **none** — said explicitly; ``diagnose`` then cannot state how far the model is from the noise.

A floor of exactly 0 (noise-free measurements: a simulated tracker without noise, repeats that
agree to the last bit) is a floor like any other, but no ratio to it exists: ``model_to_noise``
is then ``None`` (``null`` in JSON, never ``inf``, which JSON cannot hold), as without a floor.

This module sits below `identify` and `diagnose` (both read the floor; it reads only the
measurements, the run's campaign.yaml and the store's drift-check events).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from campaign.measure.reflectors import pose_from_reflectors
from campaign.measure.store import open_run
from campaign.run import RunFolder

#: two joint vectors closer than this (rad, every joint) are the same pose
REPEAT_JOINT_TOL_RAD = 1e-9
#: repeated poses giving at least this many degrees of freedom make the drift checks unnecessary
MIN_REPEAT_DOF = 10
#: Monte Carlo samples for E‖e‖ and for carrying the reflector noise through the rigid fit
_MC_SAMPLES = 200_000
_MC_SEED = 20261123


@dataclass(frozen=True)
class NoiseFloor:
    """The measurement noise floor of a run.

    source: ``"repeats"``, ``"stated"`` or ``"none"``; sigma_position_m: (3,) σ of the measured
    tool position per coordinate of F_I, m (None without a floor); mean_position_mm: the floor,
    E‖e‖ in mm (None without one); dof: degrees of freedom of the estimate (0 when stated);
    relative_uncertainty: 1-σ relative uncertainty of mean_position_mm; detail: where it came from.
    """

    source: str
    sigma_position_m: np.ndarray | None = None
    mean_position_mm: float | None = None
    dof: int = 0
    relative_uncertainty: float = 0.0
    detail: str = ""

    @property
    def known(self) -> bool:
        return self.mean_position_mm is not None

    def ratio(self, mean_position_mm) -> float | None:
        """``mean_position_mm`` over the floor (``model_to_noise``): None without a floor or for a
        floor of exactly 0 (see the module's docstring)."""
        return ratio_to_floor(mean_position_mm, self.mean_position_mm)

    def as_json(self) -> dict:
        return {"source": self.source, "mean_position_mm": self.mean_position_mm,
                "sigma_position_mm": None if self.sigma_position_m is None
                else [float(s) * 1e3 for s in self.sigma_position_m],
                "dof": self.dof, "relative_uncertainty": self.relative_uncertainty, "detail": self.detail}

    def text(self) -> str:
        if not self.known:
            return ("noise floor: none (no repeated measurements and no `tracker: {noise_m: ...}` in campaign.yaml); "
                    "how far the model is from the measurement noise cannot be said")
        unc = f" ± {100 * self.relative_uncertainty:.0f} %" if self.relative_uncertainty else ""
        return f"noise floor: {self.mean_position_mm:.4f} mm{unc} mean position error of the noise alone ({self.detail})"


def ratio_to_floor(mean_position_mm, floor_mm) -> float | None:
    """mean / floor (both mm), or None when there is no floor (None) or it is exactly 0."""
    if floor_mm is None or not floor_mm > 0:
        return None
    return float(mean_position_mm / floor_mm)


def times_the_noise(mean_position_mm, floor_mm) -> str:
    """``= 8.7× the measurement noise``, or, for a floor of exactly 0, why no ratio is given."""
    ratio = ratio_to_floor(mean_position_mm, floor_mm)
    if ratio is None:
        return "(the measurement noise is 0: no ratio to it)"
    return f"= {ratio:.1f}× the measurement noise"


def mean_norm_mm(sigma_m) -> float:
    """E‖e‖ in mm for e ~ N(0, diag(σ²)), σ (3,) m (fixed-seed Monte Carlo; isotropic: σ·√(8/π))."""
    sigma = np.asarray(sigma_m, dtype=float).reshape(3)
    if np.allclose(sigma, sigma[0]):
        return float(sigma[0] * np.sqrt(8.0 / np.pi) * 1e3)
    z = np.random.default_rng(_MC_SEED).standard_normal((_MC_SAMPLES, 3))
    return float(np.linalg.norm(z * sigma, axis=1).mean() * 1e3)


def repeat_groups(q, tol: float = REPEAT_JOINT_TOL_RAD) -> list:
    """Index arrays of the poses sharing one joint vector (groups of 2 or more), q (n, N) rad."""
    q = np.asarray(q, dtype=float)
    if len(q) < 2:
        return []
    key = np.round(q / max(tol, 1e-15)).astype(np.int64) if tol > 0 else q
    _, inverse, counts = np.unique(key, axis=0, return_inverse=True, return_counts=True)
    inverse = inverse.reshape(-1)
    return [np.flatnonzero(inverse == g) for g in np.flatnonzero(counts >= 2)]


def floor_from_repeats(xyz, q, drift_m=(), time_s=None) -> NoiseFloor | None:
    """The floor from repeated poses (xyz (n, 3) m, q (n, N) rad, in time order by ``time_s``)
    and drift-check distances (m; used only when the repeats give fewer than
    :data:`MIN_REPEAT_DOF` degrees of freedom, since they are spread over the campaign)."""
    xyz = np.asarray(xyz, dtype=float)
    groups = repeat_groups(q)
    order = np.zeros(len(xyz)) if time_s is None else np.asarray(time_s, dtype=float)
    ss = np.zeros(3)
    dof = 0
    for g in groups:
        # successive differences in time order: var(x_{i+1} − x_i) = 2σ², and a slow drift
        # between repeats measured close together cancels
        x = xyz[g[np.argsort(order[g], kind="stable")]]
        ss += np.sum(np.diff(x, axis=0) ** 2, axis=0) / 2.0
        dof += len(g) - 1
    drift = np.asarray([d for d in drift_m if d is not None and np.isfinite(d)], dtype=float)
    if dof >= MIN_REPEAT_DOF:
        drift = drift[:0]
    # a re-measurement minus the first: variance 2σ² per coordinate, spread evenly over 3
    ss += np.sum(drift ** 2) / 2.0 / 3.0
    dof_total = dof + len(drift)
    if dof_total < 2:
        return None
    sigma = np.sqrt(ss / dof_total)
    n_coord_dof = 3 * dof_total
    parts = []
    if groups:
        parts.append(f"{len(groups)} poses measured {min(len(g) for g in groups)}"
                     + (f"-{max(len(g) for g in groups)}" if max(len(g) for g in groups) > min(len(g) for g in groups) else "")
                     + " times")
    if len(drift):
        parts.append(f"{len(drift)} drift-check re-measurements")
    return NoiseFloor("repeats", sigma, mean_norm_mm(sigma), int(dof_total),
                      # successive differences are ~1.5 times less efficient than deviations from a mean
                      float(np.sqrt(1.5 / (2.0 * n_coord_dof))), ", ".join(parts))


def floor_from_stated(noise_m: float, reflectors_in_E) -> NoiseFloor:
    """The floor from a stated tracker noise σ (m per coordinate of each reflector centre),
    carried through the rigid fit of the reflectors (reflectors_in_E (k, 3) m)."""
    P_E = np.asarray(reflectors_in_E, dtype=float)
    n = 20_000
    rng = np.random.default_rng(_MC_SEED)
    P_L = P_E[None] + rng.normal(0.0, noise_m, size=(n, *P_E.shape))
    T, _ = pose_from_reflectors(np.eye(4), P_E, P_L)
    e = T[:, :3, 3]  # error of the tool origin; isotropic noise makes E‖e‖ orientation-free
    sigma = np.full(3, np.sqrt(np.mean(e ** 2)))
    return NoiseFloor("stated", sigma, float(np.linalg.norm(e, axis=1).mean() * 1e3), 0, 0.0,
                      f"stated tracker noise σ {noise_m * 1e6:.3g} µm per reflector coordinate")


def stated_tracker_noise_m(run_dir) -> float | None:
    """``tracker: {noise_m: σ}`` (m) from the run's campaign.yaml (validated by campaign.config), or None."""
    return RunFolder(run_dir).config.tracker.noise_m


def drift_check_distances_m(run_dir) -> list:
    """Distances (m) of the drift check's re-measurements from the reference's first measurement."""
    with open_run(run_dir) as store:
        return [d["drift_mm"] * 1e-3 for _, _, _, d in store.events("drift_check")
                if isinstance(d, dict) and d.get("drift_mm") is not None]


def noise_floor(run_dir, poses, robot) -> NoiseFloor:
    """The run's floor: repeats (and drift checks) first, then the stated tracker noise, else none.
    Raw reflectors with no pose (fewer than three seen anywhere): the floor of one reflector's
    position (the first's repeats), which their errors are."""
    kind = getattr(poses, "kind", "pose")
    no_pose = kind == "markers" and poses.markers is not None and not np.isfinite(poses.xyz).all(axis=1).any()
    if no_pose:
        seen = np.isfinite(poses.markers[:, 0]).all(axis=1)
        floor = floor_from_repeats(poses.markers[seen, 0], poses.q[seen], drift_check_distances_m(run_dir),
                                   poses.time_s[seen])
    else:
        floor = floor_from_repeats(poses.xyz, poses.q, drift_check_distances_m(run_dir), poses.time_s)
    if floor is not None:
        return floor
    stated = stated_tracker_noise_m(run_dir)
    if stated is None:
        return NoiseFloor("none")
    P_E = poses.marker_positions if kind == "markers" else robot.reflector_positions_in_E
    if kind == "point" or P_E is None or len(P_E) < 3:
        # one reflector (or 6-D poses from a reflector layout robot.yaml does not give): the stated
        # σ is the noise of the measured position itself
        why = ("one reflector" if kind == "point" else
               f"{len(P_E)} raw reflector{'s' if len(P_E) > 1 else ''}, no pose: each reflector's position"
               if kind == "markers" else "no reflector layout in robot.yaml: taken at the tool origin")
        sigma = np.full(3, float(stated))
        return NoiseFloor("stated", sigma, mean_norm_mm(sigma), 0, 0.0,
                          f"stated tracker noise σ {stated * 1e6:.3g} µm per coordinate, {why}")
    return floor_from_stated(stated, P_E)
