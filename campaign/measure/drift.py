"""The drift of a run, in µm per hour, with its 95 % interval: how fast the measured tool
position of one pose moves over the campaign's time (a warm-up, a creeping tracker stand),
apart from the noise.

The readings: every measurement of a *reference pose*, a pose measured again later (two of its
successive measurements further apart than :data:`campaign.tolerances.REPEAT_CLOSE_S`, the
floor's "back to back"):

- **monitor** — the driver's drift check (``run.drift_check_every``): the campaign's first
  pose, its stored measurement and each ``drift_check`` re-measurement (``xyz_m``);
- **repeats** — any other pose measured again later (imported repeats far apart in time,
  `campaign auto`'s re-measured poses, whose last joint differs by a few µrad: within
  :data:`campaign.tolerances.SAME_POSE_TOL_RAD` they are one pose).

No reading is special (none is "the" reference): each pose i has its own position a_i, and
all share one velocity v, x_ik = a_i + v t_ik + e_ik, fitted by least squares (v from the
times and positions centred per pose). The residuals' 3×3 scatter Σ̂ (n − poses − 1 degrees of
freedom) gives v's covariance Σ̂ / Σ(t − t̄_i)², Hotelling's test of v = 0 (``significant`` at
5 %) and the 95 % confidence ellipsoid of v, whose nearest and farthest points from 0 bound
the speed |v| (``ci95_um_per_h``; the lower bound is 0 exactly when the drift is not
significant). With too few readings for a 3×3 scatter, one σ pooled over the coordinates.
With none left over (one pose read twice), the noise floor's σ (χ²₃) when the run has one.
A warm-up is not linear: the rate is then its least-squares average over the times measured.

Runs measured before the drift check stored its position (``drift_mm`` only) keep the
distance estimate of those days (E d² = v² Δt² + 2Σσ²), with no interval.

A run measured on more than one cell (``cells``, campaign.identify.cells): a cell switch is a
step, never a drift. Each reading is mapped into the reference frame by its segment's
registration, and each pose has its own position a_i *per segment*, so v is fitted only from
readings within one segment; readings of a segment the calibration left out are not used.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from campaign.measure.floor import NoiseFloor
from campaign.measure.store import open_run
from campaign.tolerances import (DRIFT_ALPHA, DRIFT_NUMERICAL_SIGMA_M, DRIFT_WARNING_ALPHA, REPEAT_CLOSE_S,
                                 SAME_POSE_TOL_RAD)

#: directions on the unit sphere searched for the speed's bounds over the confidence ellipsoid
_SPHERE_POINTS = 4096


@dataclass(frozen=True)
class DriftFit:
    """One fit (module docstring): speed ``um_per_h`` = |v|, its 95 % interval (None when the
    readings leave no degree of freedom), ``significant`` (None likewise), ``p_value``,
    ``velocity_um_per_h`` (3,) in the measurement's frame, ``n`` readings of ``poses`` reference
    poses over ``span_h`` hours, ``dof``, and ``max_mm`` the largest distance of a reading from
    its pose's mean position."""

    um_per_h: float
    ci95_um_per_h: tuple | None
    significant: bool | None
    p_value: float | None
    velocity_um_per_h: tuple | None
    n: int
    poses: int
    span_h: float
    dof: int
    max_mm: float

    def as_json(self) -> dict:
        return {"um_per_h": self.um_per_h,
                "ci95_um_per_h": None if self.ci95_um_per_h is None else list(self.ci95_um_per_h),
                "significant": self.significant, "p_value": self.p_value,
                "velocity_um_per_h": None if self.velocity_um_per_h is None else list(self.velocity_um_per_h),
                "n": self.n, "poses": self.poses, "span_h": self.span_h, "dof": self.dof, "max_mm": self.max_mm}

    @classmethod
    def from_json(cls, doc) -> "DriftFit":
        ci, vel = doc.get("ci95_um_per_h"), doc.get("velocity_um_per_h")
        return cls(float(doc["um_per_h"]), None if ci is None else tuple(ci), doc.get("significant"),
                   doc.get("p_value"), None if vel is None else tuple(vel), int(doc.get("n", 0)),
                   int(doc.get("poses", 1)), float(doc.get("span_h", 0.0)), int(doc.get("dof", 0)),
                   float(doc.get("max_mm", 0.0)))

    def text(self, what: str) -> str:
        if self.ci95_um_per_h is None:
            head = f"{self.um_per_h:.3g} µm/h (no interval: too few readings)"
        else:
            lo, hi = self.ci95_um_per_h
            head = (f"{self.um_per_h:.3g} µm/h (95 %: {lo:.3g}–{hi:.3g} µm/h, "
                    f"{'significant' if self.significant else 'not significant'})")
        return (f"{head} from {self.n} readings of {self.poses} {what} over {self.span_h:.2f} h "
                f"(largest deviation {self.max_mm * 1e3:.3g} µm)")


@dataclass(frozen=True)
class Drift:
    """The run's drift: ``fit`` over every reference pose (the headline), and the same fit on
    the ``monitor`` (drift checks) and on the ``repeats`` (other poses measured again later)
    alone; each a :class:`DriftFit` or None."""

    fit: DriftFit | None = None
    monitor: DriftFit | None = None
    repeats: DriftFit | None = None

    @classmethod
    def from_json(cls, doc: dict) -> "Drift":
        """The Drift that :meth:`as_json` wrote (metrics.json's ``drift``)."""
        src = lambda d: None if d is None else DriftFit.from_json(d)  # noqa: E731
        fit = None if doc.get("um_per_h") is None else DriftFit.from_json({**doc, **(doc.get("fit") or {})})
        return cls(fit, src(doc.get("monitor")), src(doc.get("repeats")))

    @property
    def um_per_h(self) -> float | None:
        return None if self.fit is None else self.fit.um_per_h

    @property
    def significant(self) -> bool | None:
        return None if self.fit is None else self.fit.significant

    def as_json(self) -> dict:
        f = self.fit
        source = ("drift checks and repeats far apart" if self.monitor and self.repeats else
                  "drift checks" if self.monitor else "repeats far apart" if self.repeats else None)
        return {"um_per_h": None if f is None else f.um_per_h,
                "ci95_um_per_h": None if f is None or f.ci95_um_per_h is None else list(f.ci95_um_per_h),
                "significant": None if f is None else f.significant,
                "source": source, "fit": None if f is None else f.as_json(),
                "monitor": None if self.monitor is None else self.monitor.as_json(),
                "repeats": None if self.repeats is None else self.repeats.as_json()}

    def text(self) -> str:
        if self.fit is None:
            return ("drift: not measured (no drift checks and no repeats far apart in time; "
                    "run.drift_check_every in campaign.yaml sets the monitor)")
        what = ("reference pose" if self.fit.poses == 1 else "reference poses") + (
            " (drift checks)" if self.monitor and not self.repeats else
            " (measured again later)" if self.repeats and not self.monitor else
            " (drift checks and poses measured again later)")
        return "drift: " + self.fit.text(what)


# -- the fit ---------------------------------------------------------------------------------------
def fit_drift(time_s, xyz_m, group, alpha: float = DRIFT_ALPHA, sigma_m=None) -> DriftFit | None:
    """The per-pose-offset linear fit (module docstring) of readings at ``time_s`` (n,) s with
    positions ``xyz_m`` (n, 3) m, ``group`` (n,) labelling the pose of each. None without a
    pose read at two different times. ``sigma_m`` (3,) m: the noise floor's σ per coordinate,
    which gives the interval (χ²₃ with the largest σ on every axis) when the readings leave no
    degree of freedom of their own (one pose read twice: a rate without it is noise over time)."""
    from scipy import stats

    t = np.asarray(time_s, dtype=float) / 3600.0
    x = np.asarray(xyz_m, dtype=float).reshape(-1, 3)
    g = np.asarray(group)
    ok = np.isfinite(t) & np.isfinite(x).all(axis=1)
    t, x, g = t[ok], x[ok], g[ok]
    labels, inv = np.unique(g, return_inverse=True)
    inv = inv.reshape(-1)
    counts = np.bincount(inv, minlength=len(labels))
    t_mean = np.bincount(inv, weights=t) / counts
    tc = t - t_mean[inv]
    S = float(np.sum(tc ** 2))
    if S <= 0.0:
        return None
    x_mean = np.stack([np.bincount(inv, weights=x[:, c]) / counts for c in range(3)], axis=1)
    xc = x - x_mean[inv]
    v = tc @ xc / S  # m/h
    r = xc - np.outer(tc, v)
    n, k = len(t), len(labels)
    dof = n - k - 1
    spans = [np.ptp(t[inv == i]) for i in range(k) if counts[i] > 1]
    common = dict(n=int(n), poses=int(np.sum(counts > 1)), span_h=float(max(spans)), dof=int(max(dof, 0)),
                  max_mm=float(np.linalg.norm(xc, axis=1).max() * 1e3),
                  velocity_um_per_h=tuple(float(c) for c in v * 1e6))
    speed = float(np.linalg.norm(v) * 1e6)
    eps = DRIFT_NUMERICAL_SIGMA_M ** 2
    if dof < 1 and sigma_m is None:
        return DriftFit(speed, None, None, None, **common)
    if dof < 1:  # σ known (the floor's): T² = S vᵀ Σ⁻¹ v ~ χ²₃
        cov = (float(np.max(np.asarray(sigma_m, dtype=float))) ** 2 + eps) * np.eye(3)
        T2 = float(S * v @ np.linalg.solve(cov, v))
        p, c = float(stats.chi2.sf(T2, 3)), float(stats.chi2.ppf(1.0 - alpha, 3))
        return _with_interval(v, cov, S, T2, p, c, speed, common)
    if dof >= 5:  # Hotelling's T² with the full 3x3 scatter: F = T² (dof − 2) / (3 dof) ~ F(3, dof − 2)
        cov = r.T @ r / dof + eps * np.eye(3)
        f_dof = dof - 2
        scale = 3.0 * dof / f_dof
    else:  # one σ pooled over the three coordinates: |v|² S / (3 σ̂²) ~ F(3, 3 dof)
        cov = (float(np.sum(r ** 2)) / (3 * dof) + eps) * np.eye(3)
        f_dof = 3 * dof
        scale = 3.0
    T2 = float(S * v @ np.linalg.solve(cov, v))
    p = float(stats.f.sf(T2 / scale, 3, f_dof))
    c = scale * float(stats.f.ppf(1.0 - alpha, 3, f_dof))
    return _with_interval(v, cov, S, T2, p, c, speed, common)


def _with_interval(v, cov, S, T2, p, c, speed, common) -> DriftFit:
    """The fit with the speed's interval from the confidence ellipsoid T² ≤ ``c`` of v."""
    lo, hi = _norm_range(v, np.linalg.cholesky(cov * c / S))
    significant = bool(T2 > c)
    if not significant:
        lo = 0.0
    return DriftFit(speed, (float(lo * 1e6), float(hi * 1e6)), significant, p, **common)


def _norm_range(center, L) -> tuple:
    """(smallest, largest) |center + L u| over |u| ≤ 1 (the ellipsoid of v): the smallest is 0
    when the ellipsoid holds the origin; the extremes are on its surface otherwise, found over a
    dense set of directions and polished by a local search in the two angles of u."""
    from scipy.optimize import minimize

    center = np.asarray(center, dtype=float)
    k = np.arange(_SPHERE_POINTS) + 0.5
    polar = np.arccos(1.0 - 2.0 * k / _SPHERE_POINTS)
    azimuth = np.pi * (1.0 + 5.0 ** 0.5) * k

    def norm(angles):
        a, b = angles
        return float(np.linalg.norm(center + L @ [np.sin(a) * np.cos(b), np.sin(a) * np.sin(b), np.cos(a)]))

    u = np.stack([np.sin(polar) * np.cos(azimuth), np.sin(polar) * np.sin(azimuth), np.cos(polar)], axis=1)
    norms = np.linalg.norm(center + u @ L.T, axis=1)
    out = []
    for sign, best in ((1.0, int(np.argmin(norms))), (-1.0, int(np.argmax(norms)))):
        res = minimize(lambda x: sign * norm(x), [polar[best], azimuth[best]], method="Nelder-Mead",
                       options={"xatol": 1e-10, "fatol": 1e-14 * (1.0 + float(norms.max()))})
        out.append(min(sign * res.fun, sign * norms[best]) * sign)
    inside = center @ np.linalg.solve(L @ L.T, center) <= 1.0
    return (0.0 if inside else float(out[0])), float(out[1])


# -- the readings ----------------------------------------------------------------------------------
def same_pose_groups(q, tol: float = SAME_POSE_TOL_RAD) -> np.ndarray:
    """A label (n,) per measured pose, q (n, N) rad: poses with the same label share their joints
    (every joint but the last exactly, the last within ``tol``: `campaign auto` re-measures a pose
    with its last joint a few µrad on, campaign.tolerances.SAME_POSE_TOL_RAD)."""
    q = np.asarray(q, dtype=float)
    n = len(q)
    labels = np.full(n, -1, dtype=np.int64)
    if n == 0:
        return labels
    _, head = np.unique(q[:, :-1], axis=0, return_inverse=True)
    head = head.reshape(-1)
    order = np.lexsort((q[:, -1], head))
    new = np.ones(n, dtype=bool)
    new[1:] = (head[order][1:] != head[order][:-1]) | (np.diff(q[order, -1]) > tol)
    labels[order] = np.cumsum(new) - 1
    return labels


def drift_readings(run_dir, poses, readings_to_poses=None, cells=None) -> dict:
    """The reference poses' readings of a run (its MeasuredPoses ``poses``): ``{"monitor": (t
    (k,) s, xyz (k, 3) m) or None, "repeats": (t, xyz, group) or None, "legacy": (Δt (k,) s,
    d (k,) m) or None, "monitor_group": (k,) the monitor's group labels (-1; -1 - s on segment s of a
    run measured on several cells) or None}``; legacy: drift checks stored as distances only (no ``xyz_m``).
    ``readings_to_poses`` (4, 4): maps the drift checks' stored readings into the frame of ``poses``
    (data measured in the tracker's frame that calibrate registered into the robot's; None: the same).
    ``cells``: the CellDecision of a run measured on more than one cell (its poses already mapped):
    the drift checks mapped by their segment's registration, and every pose's label one per segment
    (module docstring)."""
    with open_run(run_dir) as store:
        if cells is None:
            events = [(0, t, d) for _, _, t, d in store.events("drift_check")]
        else:
            from campaign.measure.cell_identity import segment_events

            events = segment_events(store._db, "drift_check", cells.segments)
        events = [(s, t, d) for s, t, d in events if isinstance(d, dict) and t is not None
                  and (d.get("drift_mm") is not None or d.get("xyz_m") is not None)]
        reference = store.get_meta("drift_reference")
    labels = same_pose_groups(poses.q)
    if cells is not None:  # one pose on two cells: two positions (a step is no drift)
        pose_seg = cells.segments.of(poses.pose_id)
        labels = labels * cells.segments.n + pose_seg
    t_all = np.asarray(poses.time_s, dtype=float)
    ref_label = None
    out = {"monitor": None, "monitor_group": None, "repeats": None, "legacy": None}
    if reference is not None:
        at = np.flatnonzero(np.asarray(poses.pose_id) == reference["pose_id"])
        if len(at):
            ref_label = labels[at[0]]
    ref_labels = np.zeros(0, dtype=np.int64) if ref_label is None else np.array([ref_label])
    if cells is not None and ref_label is not None:  # the reference pose on every segment
        ref_labels = np.unique(labels[labels // cells.segments.n == ref_label // cells.segments.n])
    if events and ref_label is not None:  # (a segment without the reference pose: no monitor)
        mine = np.flatnonzero(np.isin(labels, ref_labels))
        with_xyz = []
        for seg, t, d in events:
            M = np.eye(4) if cells is None else cells.reading_map(seg)
            if d.get("xyz_m") is not None and M is not None:
                with_xyz.append((float(t), M[:3, :3] @ np.asarray(d["xyz_m"], dtype=float) + M[:3, 3], seg))
        if with_xyz:
            t = np.r_[t_all[mine], [t for t, _, _ in with_xyz]]
            read = np.array([p for _, p, _ in with_xyz], dtype=float)
            if readings_to_poses is not None:
                T = np.asarray(readings_to_poses, dtype=float)
                read = read @ T[:3, :3].T + T[:3, 3]
            xyz = np.concatenate([poses.xyz[mine], read])
            out["monitor"] = (t, xyz)
            # one group a segment: the reference's position on each cell (a step is no drift)
            out["monitor_group"] = -1 - np.r_[np.zeros(len(mine), dtype=np.int64) if cells is None else
                                              pose_seg[mine], [s for _, _, s in with_xyz]].astype(np.int64)
        else:
            t_ref = np.nanmin(t_all[mine]) if np.isfinite(t_all[mine]).any() else np.nan
            out["legacy"] = (np.array([float(t) for _, t, _ in events]) - t_ref,
                             np.array([d["drift_mm"] * 1e-3 for _, _, d in events]))
    keep = []
    order = np.argsort(labels, kind="stable")
    starts = np.flatnonzero(np.r_[True, np.diff(labels[order]) != 0])
    for g in np.split(order, starts[1:]):  # the poses measured more than once (one pass, not one per label)
        if len(g) < 2 or (labels[g[0]] in ref_labels and out["monitor"] is not None):
            continue
        # measured again later: two successive readings further apart than back to back (the floor's)
        if len(g) > 1 and np.isfinite(t_all[g]).all() and np.diff(np.sort(t_all[g])).max() > REPEAT_CLOSE_S:
            keep.append(g)
    if keep:
        idx = np.concatenate(keep)
        out["repeats"] = (t_all[idx], poses.xyz[idx], labels[idx])
    return out


def measured_drift(run_dir, poses, floor: NoiseFloor | None = None, readings_to_poses=None, cells=None) -> Drift:
    """The run's drift (see the module): every reference pose's readings in one fit, and the
    monitor and the repeats each alone. ``floor``: its σ (when known and not an upper bound)
    gives readings too few for their own scatter an interval (and the distances of runs whose
    drift checks stored only those their rate); ``readings_to_poses``, ``cells``: as
    :func:`drift_readings`."""
    r = drift_readings(run_dir, poses, readings_to_poses, cells)
    monitor = repeats = legacy = None
    sigma = floor.sigma_position_m if floor is not None and floor.known and not floor.upper_bound else None
    monitor_group = r["monitor_group"]  # -1: the reference pose (-1 - s on segment s of several cells)
    if r["monitor"] is not None:
        monitor = fit_drift(r["monitor"][0], r["monitor"][1], monitor_group, sigma_m=sigma)
    if r["repeats"] is not None:
        repeats = fit_drift(*r["repeats"], sigma_m=sigma)
    if r["legacy"] is not None:
        legacy = _distance_rate(*r["legacy"], sigma)
    if monitor is not None and repeats is not None:
        t = np.r_[r["monitor"][0], r["repeats"][0]]
        xyz = np.concatenate([r["monitor"][1], r["repeats"][1]])
        fit = fit_drift(t, xyz, np.r_[monitor_group, r["repeats"][2]], sigma_m=sigma)
    else:
        fit = monitor or repeats or legacy
    if legacy is not None and monitor is None:
        monitor = legacy
        if repeats is not None:
            fit = repeats
    return Drift(fit, monitor, repeats)


def _distance_rate(dt_s, d_m, sigma_m=None) -> DriftFit | None:
    """The rate of drift checks stored as distances ``d_m`` (k,) m from the reference's first
    reading at ``dt_s`` (k,) s (runs before the checks stored positions): E d² = v² Δt² + 2Σσ²,
    σ from ``sigma_m`` (3,) or fitted; no interval."""
    dt = np.abs(np.asarray(dt_s, dtype=float))
    d = np.asarray(d_m, dtype=float)
    ok = np.isfinite(dt) & np.isfinite(d) & (dt > 0)
    dt, d = dt[ok] / 3600.0, d[ok]
    if len(d) == 0 or (sigma_m is None and len(d) < 3):
        return None
    if sigma_m is not None:
        v2 = float(np.sum((d ** 2 - 2.0 * float(np.sum(np.asarray(sigma_m) ** 2))) * dt ** 2) / np.sum(dt ** 4))
    else:
        v2 = float(np.linalg.lstsq(np.column_stack([np.ones_like(dt), dt ** 2]), d ** 2, rcond=None)[0][1])
    return DriftFit(float(np.sqrt(max(v2, 0.0)) * 1e6), None, None, None, None, int(len(d)) + 1, 1,
                    float(dt.max()), 0, float(d.max() * 1e3))


# -- the moved-pose warning --------------------------------------------------------------------------
def moved_threshold_m(sigma_m, n_earlier: int, alpha: float = DRIFT_WARNING_ALPHA) -> float:
    """The distance (m) beyond which a drift check's reading is farther from the mean of the
    ``n_earlier`` readings of the reference before it than the noise explains (probability
    ``alpha`` per check): the difference has σ_c √(1 + 1/m) per coordinate, so d² / (σ_max²
    (1 + 1/m)) ≤ χ²₃ with σ_max the largest of ``sigma_m`` (3,) m (anisotropic noise: bounded)."""
    from scipy import stats

    s = max(float(np.max(np.asarray(sigma_m, dtype=float))), DRIFT_NUMERICAL_SIGMA_M)  # a noise-free cell: round-off
    return s * float(np.sqrt((1.0 + 1.0 / max(int(n_earlier), 1)) * stats.chi2.ppf(1.0 - alpha, 3)))


def warning_sigma_m(poses, stated_noise_m=None, reflectors_in_E=None, setup_noise_m=None):
    """σ (3,) m of a measured position for the drift check's warning, from what is known so far:
    the back-to-back repeats of ``poses`` (MeasuredPoses with finite positions, or None; not an
    upper bound), else the stated tracker noise, else ``setup_noise_m`` (the scatter of the
    base-frame set-up's repeated readings), either carried through the reflectors' fit; else None."""
    from campaign.measure.floor import floor_from_repeats, floor_from_stated

    floor = floor_from_repeats(poses.xyz, poses.q, (), poses.time_s) if poses is not None and len(poses.xyz) else None
    if floor is not None and not floor.upper_bound:
        return np.asarray(floor.sigma_position_m, dtype=float)
    noise = stated_noise_m if stated_noise_m is not None else setup_noise_m
    if noise is None:
        return None
    if reflectors_in_E is not None and len(reflectors_in_E) >= 3:
        return np.asarray(floor_from_stated(noise, reflectors_in_E).sigma_position_m)
    return np.full(3, float(noise))


__all__ = ["Drift", "DriftFit", "fit_drift", "measured_drift", "moved_threshold_m", "same_pose_groups",
           "warning_sigma_m"]
