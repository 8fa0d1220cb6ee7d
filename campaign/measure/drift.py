"""The drift of a run, in µm per hour: how far the measured tool position of one pose moves
over the campaign's time (a warm-up, a creeping tracker stand), apart from the noise floor.

Two sources, each a rate fitted to displacements d over time differences Δt:

- **monitor** — the driver's drift check (``run.drift_check_every``): the reference pose
  re-measured during the campaign, each ``drift_check`` event the distance d of its measured
  position from the reference's first measurement, at the event's time;
- **repeats** — successive measurements of one pose further apart in time than
  :data:`campaign.tolerances.REPEAT_CLOSE_S` (imported data with repeats spread over the
  campaign; the plan measures its repeats back to back, so there are none), d the distance
  between them.

A distance includes the noise of both measurements: E d² = v² Δt² + 2 Σ σ² (σ per coordinate
of the measured position, the noise floor's). The rate is the least-squares
v² = Σ (d² − 2Σσ²) Δt² / Σ Δt⁴, clipped at 0, so the noise does not read as drift; without a
floor the noise term is fitted too (three or more distances). A warm-up is not linear: the rate
is its average over the times measured, and ``max_mm`` the largest displacement seen.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from campaign.measure.floor import NoiseFloor, repeat_pairs
from campaign.measure.store import open_run


@dataclass(frozen=True)
class DriftSource:
    """One source's estimate: rate µm/h, how many displacements, over how long (h), the largest (mm)."""

    um_per_h: float
    n: int
    span_h: float
    max_mm: float

    def as_json(self) -> dict:
        return {"um_per_h": self.um_per_h, "n": self.n, "span_h": self.span_h, "max_mm": self.max_mm}


@dataclass(frozen=True)
class Drift:
    """The run's drift: ``monitor`` (drift checks) and ``repeats`` (repeats far apart in time),
    each a :class:`DriftSource` or None; ``um_per_h`` the headline (the monitor's when there is
    one: its reference spans the campaign), None when neither source exists."""

    monitor: DriftSource | None = None
    repeats: DriftSource | None = None

    @classmethod
    def from_json(cls, doc: dict) -> "Drift":
        """The Drift that :meth:`as_json` wrote (metrics.json's ``drift``)."""
        src = lambda d: None if d is None else DriftSource(**d)  # noqa: E731
        return cls(src(doc.get("monitor")), src(doc.get("repeats")))

    @property
    def um_per_h(self) -> float | None:
        src = self.monitor or self.repeats
        return None if src is None else src.um_per_h

    def as_json(self) -> dict:
        return {"um_per_h": self.um_per_h,
                "source": "drift checks" if self.monitor else "repeats far apart" if self.repeats else None,
                "monitor": None if self.monitor is None else self.monitor.as_json(),
                "repeats": None if self.repeats is None else self.repeats.as_json()}

    def text(self) -> str:
        parts = []
        for name, src in (("drift checks", self.monitor), ("repeats far apart in time", self.repeats)):
            if src is not None:
                parts.append(f"{src.um_per_h:.3g} µm/h from {src.n} {name} over {src.span_h:.2f} h "
                             f"(largest displacement {src.max_mm * 1e3:.3g} µm)")
        if not parts:
            return ("drift: not measured (no drift checks and no repeats far apart in time; "
                    "run.drift_check_every in campaign.yaml sets the monitor)")
        return "drift: " + "; ".join(parts)


def drift_rate(dt_s, d_m, sigma_m=None) -> DriftSource | None:
    """The rate fitted to displacements ``d_m`` (k,) m over time differences ``dt_s`` (k,) s, the
    noise of each displacement 2Σσ² from ``sigma_m`` (3,) m per coordinate (None: fitted)."""
    dt = np.abs(np.asarray(dt_s, dtype=float))
    d = np.asarray(d_m, dtype=float)
    ok = np.isfinite(dt) & np.isfinite(d) & (dt > 0)
    dt, d = dt[ok] / 3600.0, d[ok]
    if len(d) == 0 or (sigma_m is None and len(d) < 3):
        return None
    if sigma_m is not None:
        c = 2.0 * float(np.sum(np.asarray(sigma_m, dtype=float) ** 2))
        v2 = float(np.sum((d ** 2 - c) * dt ** 2) / np.sum(dt ** 4))
    else:  # d² = c + v² Δt², both fitted
        A = np.column_stack([np.ones_like(dt), dt ** 2])
        v2 = float(np.linalg.lstsq(A, d ** 2, rcond=None)[0][1])
    return DriftSource(float(np.sqrt(max(v2, 0.0)) * 1e6), int(len(d)), float(dt.max()), float(d.max() * 1e3))


def drift_checks(run_dir, poses) -> tuple:
    """(Δt (k,) s, d (k,) m) of the run's drift checks: each re-measurement's time after the
    reference pose's first measurement (in ``poses``, the run's MeasuredPoses) and its distance."""
    with open_run(run_dir) as store:
        events = [(t, d) for _, _, t, d in store.events("drift_check")
                  if isinstance(d, dict) and d.get("drift_mm") is not None and t is not None]
    if not events:
        return np.zeros(0), np.zeros(0)
    ref = [d.get("reference_pose_id") for _, d in events][0]
    at = np.flatnonzero(np.asarray(poses.pose_id) == ref)
    t_ref = float(np.nanmin(poses.time_s[at])) if len(at) and np.isfinite(poses.time_s[at]).any() else np.nan
    t = np.array([float(t) for t, _ in events])
    return t - t_ref, np.array([d["drift_mm"] * 1e-3 for _, d in events])


def measured_drift(run_dir, poses, floor: NoiseFloor | None = None) -> Drift:
    """The run's drift (see the module): from its drift checks and from its repeats far apart
    in time, the noise taken from ``floor`` (its σ, when known and not an upper bound)."""
    sigma = floor.sigma_position_m if floor is not None and floor.known and not floor.upper_bound else None
    dt, d = drift_checks(run_dir, poses)
    monitor = drift_rate(dt, d, sigma)
    _, far = repeat_pairs(poses.q, poses.time_s)
    repeats = None
    if len(far):
        i, j = far[:, 0], far[:, 1]
        repeats = drift_rate(poses.time_s[j] - poses.time_s[i], np.linalg.norm(poses.xyz[j] - poses.xyz[i], axis=1),
                             sigma)
    return Drift(monitor, repeats)
