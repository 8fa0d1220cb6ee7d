"""The calibrated domain: where in joint space the training poses lie, and a test that tells a new
pose from them.

Written beside params.yaml as ``domain.json`` (the same ``calibration_id``), with the model's
uncertainty (campaign.identify.uncertainty) and the identifiability on the training poses
(campaign.identify.identifiability). A pose is inside when

* every joint lies within the training range widened by a margin: ``DOMAIN_MARGIN_POSES / n`` of
  the range (the gap a fresh draw from the same spread leaves beyond the extremes of n poses is
  about range / n; this many of them keeps a fresh pose's chance of falling beyond below 1 %
  a joint), at least DOMAIN_MIN_MARGIN_RAD (m for a prismatic joint);
* and, for every pair of joints, it lies inside the convex hull of the training poses in those two
  joints, or within DOMAIN_PAIR_FACTOR times the largest nearest-neighbour distance among them of a
  training pose (ranges scaled to 1; from DOMAIN_PAIR_MIN_POSES training poses on): a corner of the
  workspace no measured pose reached (joints 1 and 2 both high) is outside; the poses between a
  D-optimal plan's extremes, where the model interpolates, are inside. (A distance over all N joints
  would flag those, and miss the corner: the other joints dominate it.)
"""

from __future__ import annotations

from dataclasses import dataclass
from functools import cached_property
from pathlib import Path

import numpy as np

from campaign.errors import DataError
from campaign.tolerances import (DOMAIN_COVERAGE_BINS, DOMAIN_MARGIN_POSES, DOMAIN_MIN_MARGIN_M,
                                 DOMAIN_MIN_MARGIN_RAD, DOMAIN_PAIR_FACTOR,
                                 DOMAIN_PAIR_MIN_POSES, DOMAIN_RELATION_EXTRA_POSES,
                                 DOMAIN_RELATION_RTOL)

DOMAIN_FILE = "domain.json"


def _largest_nearest_distance(points) -> float:
    """The largest distance from a point to its nearest other point among the distinct ``points`` (n, d):
    a plan's repeated poses, and a grid's poses seen in two joints, coincide, and a distance of 0 to
    a copy would make the threshold 0 (every pose off the grid outside)."""
    from scipy.spatial import cKDTree

    u = np.unique(np.asarray(points, dtype=float), axis=0)
    if len(u) < 2:
        return 1e-9
    d, _ = cKDTree(u).query(u, k=2)
    return max(float(d[:, 1].max()), 1e-9)


def encode_array(a) -> dict:
    """A float64 array as strict JSON: {"dtype": "<f8", "shape", "base64"} (little-endian, C order):
    exact, and a 14,000-pose campaign's joints are written in milliseconds, not as 84,000 numbers."""
    import base64

    a = np.ascontiguousarray(a, dtype="<f8")
    return {"dtype": "<f8", "shape": list(a.shape), "base64": base64.b64encode(a.tobytes()).decode("ascii")}


def decode_array(d) -> np.ndarray:
    """The array of :func:`encode_array` (or a plain nested list)."""
    import base64
    import binascii

    if isinstance(d, dict):
        if d.get("dtype") != "<f8":
            raise ValueError(f"dtype {d.get('dtype')!r}, expected '<f8'")
        try:
            raw = base64.b64decode(d["base64"], validate=True)
        except binascii.Error as exc:
            raise ValueError(f"base64: {exc}") from None
        a = np.frombuffer(raw, dtype="<f8")
        shape = tuple(int(v) for v in d["shape"])
        if a.size != int(np.prod(shape)):
            raise ValueError(f"{a.size} values for shape {shape}")
        return a.reshape(shape).astype(float)
    return np.asarray(d, dtype=float)


@dataclass(frozen=True, eq=False)
class Domain:
    """Per joint (N,): training ``lower``/``upper``, ``margin``, ``scale`` (rad or m), ``coverage``
    (share of the joint's limit range, in DOMAIN_COVERAGE_BINS bins, holding a training pose);
    the training poses ``q_train`` (n, N), whose pairwise tests are built when first asked (a
    calibration that only writes its domain does not pay for them)."""

    lower: np.ndarray
    upper: np.ndarray
    margin: np.ndarray
    scale: np.ndarray
    coverage: np.ndarray
    q_train: np.ndarray

    def within_ranges(self, q) -> np.ndarray:
        """(n, N) bool: each joint within its widened training range."""
        q = np.asarray(q, dtype=float)
        return (q >= self.lower - self.margin) & (q <= self.upper + self.margin)

    @cached_property
    def _pairs(self) -> list:
        """[(i, j, span (2,), KD-tree of the distinct training poses in joints i, j scaled by span, threshold,
        their convex hull's half-planes (k, 3) or None)] for every pair of joints; empty below
        DOMAIN_PAIR_MIN_POSES training poses."""
        from scipy.spatial import ConvexHull, QhullError, cKDTree

        if len(self.q_train) < DOMAIN_PAIR_MIN_POSES:
            return []
        span = np.maximum(self.upper - self.lower, self.margin)
        out = []
        N = len(self.scale)
        for i in range(N):
            for j in range(i + 1, N):
                pts = np.unique(self.q_train[:, [i, j]] / span[[i, j]], axis=0)
                try:
                    hull = ConvexHull(pts).equations
                except (QhullError, ValueError):  # on a line (a joint that never moved: the ranges say it)
                    hull = None
                out.append((i, j, span[[i, j]], cKDTree(pts), DOMAIN_PAIR_FACTOR * _largest_nearest_distance(pts),
                            hull))
        return out

    def pairs_reached(self, q) -> np.ndarray:
        """(n,) bool: in every pair of joints, the pose lies near a training pose or inside their convex
        hull (between measured poses: interpolated, as inside a D-optimal plan's extremes)."""
        q = np.asarray(q, dtype=float).reshape(-1, len(self.scale))
        ok = np.ones(len(q), dtype=bool)
        for i, j, span, tree, threshold, hull in self._pairs:
            p = q[:, [i, j]] / span
            d, _ = tree.query(p, k=1)
            far = np.asarray(d) > threshold
            if hull is not None and far.any():
                far &= np.max(p @ hull[:, :2].T + hull[:, 2], axis=1) > 1e-12
            ok &= ~far
        return ok

    @cached_property
    def relations(self) -> list:
        """[(v (N,) unit, centre (N,), half-width)]: the directions of the joint space (each joint over its
        ``scale``) along which the training poses hardly spread, on two joints or more (q2 + q3 held
        constant; a joint alone that never moved is its range's), with the half-width of the band they
        keep: their own spread along it plus DOMAIN_MIN_MARGIN_RAD a joint (its margin when smaller)."""
        n, N = self.q_train.shape
        if n < N + DOMAIN_RELATION_EXTRA_POSES:
            return []
        z = self.q_train / self.scale
        centre = z.mean(axis=0)
        _, s, vt = np.linalg.svd(z - centre, full_matrices=False)
        out = []
        for k in np.flatnonzero(s < DOMAIN_RELATION_RTOL * s[0]):
            v = vt[k]
            if np.sum(np.abs(v) >= 0.1 * np.abs(v).max()) < 2:
                continue
            band = np.sum(np.abs(v) * np.minimum(self.margin, DOMAIN_MIN_MARGIN_RAD) / self.scale)
            out.append((v, centre, float(np.abs((z - centre) @ v).max()) + band))
        return out

    def keeps_relations(self, q) -> np.ndarray:
        """(n,) bool: the pose keeps every relation among joints the training poses kept."""
        q = np.asarray(q, dtype=float).reshape(-1, len(self.scale))
        ok = np.ones(len(q), dtype=bool)
        for v, centre, half in self.relations:
            ok &= np.abs((q / self.scale - centre) @ v) <= half
        return ok

    def contains(self, q) -> np.ndarray:
        """(n,) bool: inside the calibrated domain."""
        q = np.asarray(q, dtype=float).reshape(-1, len(self.scale))
        if not len(q):
            return np.zeros(0, dtype=bool)
        return self.within_ranges(q).all(axis=1) & self.keeps_relations(q) & self.pairs_reached(q)

    def why_outside(self, q, joint_names) -> list:
        """For each row of q: "" inside, else what puts it outside (the first joint beyond its range, or a
        corner of two joints no training pose reached)."""
        q = np.asarray(q, dtype=float).reshape(-1, len(self.scale))
        ok = self.within_ranges(q)
        pairs = self.pairs_reached(q)
        kept = self.keeps_relations(q)
        out = []
        for i in range(len(q)):
            bad = np.flatnonzero(~ok[i])
            if len(bad):
                out.append(f"{joint_names[bad[0]]} beyond the training range")
            elif not kept[i]:
                out.append(f"off the relation {self.relation_words(joint_names)} the training poses kept")
            elif not pairs[i]:
                out.append("in a corner of two joints' ranges no training pose reached")
            else:
                out.append("")
        return out

    def relation_words(self, joint_names, value_words=None) -> str:
        """The first relation among joints the training poses kept, in words: "q2 + q3 constant", or with
        ``value_words`` (a function of the relation's value in the joints' units) "q2 + q3 = 81.9°"."""
        if not self.relations:
            return ""
        c = self.relations[0][0] / self.scale
        c = c / c[np.argmax(np.abs(c))]
        terms = [(f"{'-' if c[j] < 0 else '+'} " + ("" if abs(abs(c[j]) - 1) < 0.05 else f"{abs(c[j]):.2f}·") +
                  joint_names[j]) for j in np.flatnonzero(np.abs(c) >= 0.1)]
        what = " ".join(terms).removeprefix("+ ")
        return f"{what} constant" if value_words is None else \
            f"{what} = {value_words(float(np.median(self.q_train @ c)))}"

    def as_json(self, robot) -> dict:
        unit = ["m" if p else "rad" for p in robot.prismatic]
        return {"joints": [{"joint": f"q{j + 1}", "unit": unit[j], "lower": float(self.lower[j]),
                            "upper": float(self.upper[j]), "margin": float(self.margin[j]),
                            "scale": float(self.scale[j]), "coverage": float(self.coverage[j])}
                           for j in range(len(self.scale))],
                "n_train": int(len(self.q_train)),
                "training_q": encode_array(self.q_train)}

    @classmethod
    def from_json(cls, d, where, n_joints=None) -> "Domain":
        try:
            joints = d["joints"]
            get = lambda key: np.array([float(j[key]) for j in joints])  # noqa: E731
            q = decode_array(d["training_q"])
            n_train = int(d["n_train"])
            out = cls(get("lower"), get("upper"), get("margin"), get("scale"), get("coverage"), q)
        except (KeyError, TypeError, ValueError) as exc:
            raise DataError(f"{where}: malformed domain ({exc.__class__.__name__}: {exc})") from None
        if n_joints is not None and len(joints) != n_joints:
            raise DataError(f"{where}: the domain has {len(joints)} joints, the run's robot {n_joints}; re-run calibrate")
        if q.shape != (n_train, len(joints)):  # reshaped, another campaign's poses would answer in_domain
            raise DataError(f"{where}: training_q has shape {list(q.shape)}, the domain says {n_train} poses of "
                            f"{len(joints)} joints; re-run calibrate")
        if not len(q) or not np.all(out.scale > 0) or not np.all(np.isfinite(q)):
            raise DataError(f"{where}: the domain needs training poses and positive scales")
        return out

    def summary(self, robot) -> list:
        """Per joint: (name, lower, upper, coverage) in degrees (mm for prismatic joints)."""
        f = np.where(robot.prismatic, 1e3, 180.0 / np.pi)
        return [(f"q{j + 1}", float(self.lower[j] * f[j]), float(self.upper[j] * f[j]), float(self.coverage[j]))
                for j in range(len(self.scale))]


def calibrated_domain(robot, q_train) -> Domain:
    """The :class:`Domain` of the training poses q_train (n, N) of ``robot``."""

    q = np.asarray(q_train, dtype=float)
    n = len(q)
    lower, upper = q.min(axis=0), q.max(axis=0)
    floor = np.where(robot.prismatic, DOMAIN_MIN_MARGIN_M, DOMAIN_MIN_MARGIN_RAD)
    margin = np.maximum((upper - lower) * DOMAIN_MARGIN_POSES / max(n, 1), floor)
    scale = np.maximum(q.std(axis=0), margin)
    limits = np.stack([robot.q_lower, robot.q_upper], axis=1)
    coverage = np.empty(robot.n_joints)
    for j in range(robot.n_joints):
        lo, hi = limits[j]
        if not (np.isfinite(lo) and np.isfinite(hi) and hi > lo):
            lo, hi = lower[j], upper[j] + 1e-12
        b = np.clip(((q[:, j] - lo) / (hi - lo) * DOMAIN_COVERAGE_BINS).astype(int), 0, DOMAIN_COVERAGE_BINS - 1)
        coverage[j] = len(np.unique(b)) / DOMAIN_COVERAGE_BINS
    return Domain(lower, upper, margin, scale, coverage, q)


def domain_path(folder) -> Path:
    return Path(folder) / DOMAIN_FILE


def domain_record(robot, models: dict, q_train, q_all, ctx_all, noise_floor, is_test, identifiability) -> dict:
    """What ``domain.json`` holds (without its calibration_id) and what metrics.json says of it
    (``over_domain``), with ``sigma_all`` {stage: (n,) mm at every measured pose} for the report.

    models: {stage: fitted CalibrationModel} (the geometric model and the current physical one);
    q_train: their training poses; q_all, ctx_all: every measured pose (the uncertainty over the
    domain), the training ones those of q_train in order; is_test (n,) bool of those; identifiability: the current
    model's :class:`campaign.identify.identifiability.Identifiability`."""
    from campaign.identify.uncertainty import model_uncertainty

    domain = calibrated_domain(robot, q_train)
    unc, over, sigma_all = {}, {}, {}
    train = ~np.asarray(is_test, dtype=bool)
    for stage, m in models.items():
        u = model_uncertainty(m, noise_floor)
        unc[stage] = u
        s = np.empty(len(q_all))
        if m.points is None and len(q_all[train]) == len(m.jacobian_at_fit_):  # the fit's own rows at its poses
            s[train] = 1e3 * u.sigma_from_jacobian(m.jacobian_at_fit_[:, :3, :], m)
            rest = ~train
        else:
            rest = np.ones(len(q_all), dtype=bool)
        s[rest] = 1e3 * u.sigma_m(robot, m.effect_set_, m.params_, m.effect_params_, q_all[rest],
                                  {k: np.asarray(v)[rest] for k, v in (ctx_all or {}).items()})
        sigma_all[stage] = s
        over[stage] = {"sigma_mm_mean": float(np.mean(s)), "sigma_mm_q95": float(np.quantile(s, 0.95)),
                       "test_sigma_mm_mean": float(np.mean(s[is_test])) if np.any(is_test) else None,
                       "basis": u.basis}
    return {"domain": domain.as_json(robot), "uncertainty": {k: u.as_json() for k, u in unc.items()},
            "identifiability": identifiability.as_json(), "over_domain": over, "sigma_all": sigma_all}


def domain_metrics(record: dict, robot, stages: dict, current: str) -> dict:
    """metrics.json's ``domain`` and ``uncertainty``: per-joint ranges and coverage; the current
    model's sigma_mm over the measured poses (mean, 95th percentile) beside its held-out error."""
    joints = [{k: j[k] for k in ("joint", "unit", "lower", "upper", "coverage")} for j in record["domain"]["joints"]]
    out = {"domain": {"joints": joints, "n_train": record["domain"]["n_train"], "file": DOMAIN_FILE}}
    unc = {}
    for stage, over in record["over_domain"].items():
        test = stages.get(stage, {}).get("test", {}).get("position_mm", {})
        unc[stage] = {**over, "heldout_mean_position_mm": test.get("mean")}
    out["uncertainty"] = {"stage": current, "stages": unc,
                          "network": "a network stage's rows (predict, compensate, export) add the spread of its "
                                     "cross-validation members when it is a fold ensemble (solver adam); a single "
                                     "network's (br-lm) own uncertainty is not estimated: its rows carry the physical "
                                     "model's sigma_mm"}
    return out


@dataclass(frozen=True)
class StoredDomain:
    """domain.json read back: the :class:`Domain`, the uncertainty of each stage that has one
    ({stage: campaign.identify.uncertainty.Uncertainty}) and the identifiability record."""

    domain: Domain
    uncertainty: dict
    identifiability: dict


def read_domain(folder, calibration_id, robot=None) -> StoredDomain | None:
    """The calibration's domain.json (None when the calibration has none: made before it existed);
    DataError when it is malformed, of another calibration, or (with ``robot``) of another joint count
    or error model."""
    import json

    from campaign.identify.uncertainty import Uncertainty

    path = domain_path(folder)
    if not path.is_file():
        return None
    try:
        d = json.loads(path.read_text())
    except (OSError, ValueError) as exc:
        raise DataError(f"{path}: unreadable ({exc.__class__.__name__})") from None
    if not isinstance(d, dict) or d.get("calibration_id") != calibration_id:
        raise DataError(f"{path}: of calibration {d.get('calibration_id') if isinstance(d, dict) else None!r}, "
                        f"params.yaml is of {calibration_id!r}; re-run calibrate")
    unc = d.get("uncertainty") or {}
    if not isinstance(unc, dict):
        raise DataError(f"{path}: uncertainty must be a mapping of stages")
    stored = StoredDomain(Domain.from_json(d.get("domain"), path, None if robot is None else robot.n_joints),
                          {k: Uncertainty.from_json(v, f"{path}: uncertainty.{k}") for k, v in unc.items()},
                          d.get("identifiability") or {})
    for stage, u in stored.uncertainty.items():
        if robot is not None and tuple(u.names[:robot.n_params]) != tuple(robot.param_names):
            raise DataError(f"{path}: uncertainty.{stage} is not of {robot.name}'s error parameters; re-run calibrate")
    return stored


def domain_summary(in_domain, sigma_mm, what: str = "rows") -> str:
    """One line: how many rows are outside the calibrated domain and the largest sigma_mm."""
    if in_domain is None:
        return f"no calibrated domain (a calibration from before domain.json): in_domain and sigma_mm left empty; " \
               "re-run calibrate"
    n_out = int(np.sum(~np.asarray(in_domain, dtype=bool)))
    worst = f"; largest sigma_mm {float(np.max(sigma_mm)):.4f} mm" if sigma_mm is not None and len(sigma_mm) else ""
    return f"{n_out} of {len(in_domain)} {what} outside the calibrated domain (in_domain = 0){worst}"
