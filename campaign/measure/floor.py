"""The measurement noise floor, from the measurements themselves, never from the model's fit.

Definition (docs/effects.md, "The noise floor"): the floor is the expected mean position error
``E‖e‖`` (mm) of a residual that is measurement noise only, e ~ N(0, diag(σ_x², σ_y², σ_z²)),
σ the noise of the measured tool position (origin of F_E in F_I) per coordinate. A model whose
held-out mean position error equals the floor has nothing left to explain.

Sources, in order of preference:

1. **repeats** — poses measured more than once with identical joint vectors (the plan's
   repeat poses, measured back to back; re-imported data with repeated joint rows). Only
   successive measurements of one pose *close in time* (at most
   :data:`campaign.tolerances.REPEAT_CLOSE_S` apart, or
   :data:`~campaign.tolerances.REPEAT_CLOSE_ROWS` rows without times) give the floor: σ² is
   pooled over them from successive differences, Σ (x_{i+1} − x_i)²/2 over their count, per
   coordinate. Repeats further apart measure the drift as well: they are reported as drift
   (campaign.measure.drift), never as noise. Only when no repeats are close in time do the
   repeats far apart and the drift check's re-measurements of its reference pose
   (``drift_check`` events in the store, each the distance from the reference's first
   measurement; d²/2 spread over 3 coordinates) give a floor, marked as an upper bound
   (``upper_bound``: it includes whatever drifted between them).
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
from campaign.tolerances import REPEAT_CLOSE_ROWS, REPEAT_CLOSE_S

#: two joint vectors closer than this (rad, every joint) are the same pose
REPEAT_JOINT_TOL_RAD = 1e-9
#: Monte Carlo samples for E‖e‖ and for carrying the reflector noise through the rigid fit
_MC_SAMPLES = 200_000
_MC_SEED = 20261123


@dataclass(frozen=True)
class NoiseFloor:
    """The measurement noise floor of a run.

    source: ``"repeats"``, ``"stated"`` or ``"none"``; sigma_position_m: (3,) σ of the measured
    tool position per coordinate of F_I, m (None without a floor); mean_position_mm: the floor,
    E‖e‖ in mm (None without one); dof: degrees of freedom of the estimate (0 when stated);
    relative_uncertainty: 1-σ relative uncertainty of mean_position_mm; detail: where it came from;
    upper_bound: True when it comes from measurements far apart in time (no back-to-back
    repeats), which include the drift between them.
    """

    source: str
    sigma_position_m: np.ndarray | None = None
    mean_position_mm: float | None = None
    dof: int = 0
    relative_uncertainty: float = 0.0
    detail: str = ""
    upper_bound: bool = False

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
                "dof": self.dof, "relative_uncertainty": self.relative_uncertainty, "detail": self.detail,
                "upper_bound": self.upper_bound}

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


def repeat_pairs(q, time_s=None, close_s: float = REPEAT_CLOSE_S, close_rows: int = REPEAT_CLOSE_ROWS):
    """Successive measurements of one pose (q (n, N) rad, time_s (n,) s or None), in time order
    (row order where a time is unknown): (close (k, 2), far (m, 2)) index pairs, close when at
    most ``close_s`` apart (``close_rows`` rows when either time is unknown)."""
    n = len(q)
    t = np.full(n, np.nan) if time_s is None else np.asarray(time_s, dtype=float)
    close, far = [], []
    for g in repeat_groups(q):
        if np.isfinite(t[g]).all():
            g = g[np.argsort(t[g], kind="stable")]
        for i, j in zip(g[:-1], g[1:]):
            dt = t[j] - t[i]
            near = abs(dt) <= close_s if np.isfinite(dt) else abs(int(j) - int(i)) <= close_rows
            (close if near else far).append((int(i), int(j)))
    as_pairs = lambda p: np.asarray(p, dtype=np.int64).reshape(-1, 2)  # noqa: E731
    return as_pairs(close), as_pairs(far)


def floor_from_repeats(xyz, q, drift_m=(), time_s=None) -> NoiseFloor | None:
    """The floor from repeated poses (xyz (n, 3) m, q (n, N) rad, time_s (n,) s or None): from
    the successive measurements of one pose close in time (:func:`repeat_pairs`); only when
    there are none, from those far apart and the drift checks' distances (m), as an upper bound."""
    xyz = np.asarray(xyz, dtype=float)
    close, far = repeat_pairs(q, time_s)
    bound = len(close) < 2
    pairs = np.concatenate([close, far]) if bound else close
    # successive differences: var(x_{i+1} − x_i) = 2σ², and a slow drift between repeats
    # measured close together cancels
    ss = np.sum((xyz[pairs[:, 1]] - xyz[pairs[:, 0]]) ** 2, axis=0) / 2.0 if len(pairs) else np.zeros(3)
    drift = np.asarray([d for d in drift_m if d is not None and np.isfinite(d)], dtype=float) if bound else np.zeros(0)
    # a re-measurement minus the first: variance 2σ² per coordinate, spread evenly over 3
    ss = ss + np.sum(drift ** 2) / 2.0 / 3.0
    dof_total = len(pairs) + len(drift)
    if dof_total < 2:
        return None
    sigma = np.sqrt(ss / dof_total)
    n_coord_dof = 3 * dof_total
    parts = []
    if len(pairs):
        groups = [g for g in repeat_groups(q) if np.isin(g, pairs).any()]
        lo, hi = min(len(g) for g in groups), max(len(g) for g in groups)
        times = f"{lo}-{hi}" if hi > lo else f"{lo}"
        parts.append(f"{len(groups)} poses measured {times} times, " +
                     (f"{len(pairs)} successive differences " + (f"within {REPEAT_CLOSE_S:g} s" if time_s is not None
                                                                   and np.isfinite(time_s).all() else
                                                                   f"at most {REPEAT_CLOSE_ROWS} rows apart")
                      + " (back to back)" if not bound
                      else f"{len(pairs)} successive differences, far apart in time"))
    if len(drift):
        parts.append(f"{len(drift)} drift-check re-measurements")
    if bound:
        parts.append("an upper bound: measurements far apart in time include the drift between them")
    elif len(far):
        parts.append(f"{len(far)} repeats further apart left to the drift")
    return NoiseFloor("repeats", sigma, mean_norm_mm(sigma), int(dof_total),
                      # successive differences are ~1.5 times less efficient than deviations from a mean
                      float(np.sqrt(1.5 / (2.0 * n_coord_dof))), "; ".join(parts), upper_bound=bool(bound))


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
    """Distances (m) of the drift check's re-measurements from the reference's first measurement;
    of a run measured on more than one cell, those on the reference's cell (on another the reading
    is in another frame: campaign.measure.cell_identity)."""
    from campaign.measure.cell_identity import cell_segments, segment_events

    with open_run(run_dir) as store:
        segments = cell_segments(store._db)
        reference = store.get_meta("drift_reference")
        mine = int(segments.of([reference["pose_id"]])[0]) if reference and segments.mixed else 0
        return [d["drift_mm"] * 1e-3 for s, _, d in segment_events(store._db, "drift_check", segments)
                if isinstance(d, dict) and d.get("drift_mm") is not None and s == mine]


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
