"""A wild reading among the training poses: found, named, and left out of the fit.

A laser tracker's reading can be wrong by far more than its noise (a beam broken mid-reading, a
reflector swapped, a reading matched to the wrong stop); one such pose among a hundred pulls every
parameter of a least-squares fit, and the calibrated model is then off everywhere by millimetres.

After the fit, each training pose's position residual (its position rows; raw reflectors: the rows
of its seen reflectors) is studentized with the fit's own hat matrix: with e_i the whitened residual
of pose i and H_ii its block of ``J (JᵀJ + P)⁺ Jᵀ``, ``T_i = e_iᵀ (I − H_ii)⁻¹ e_i`` follows χ²(d_i)
(d_i rows) when the noise is Gaussian with the rows' σ, whatever the pose's leverage. The rows' σ are
the fit's, which the wild reading inflates, so the statistics are divided by a robust scale, the
median of ``T_i / median χ²(d_i)`` (unmoved while fewer than half the poses are wild), bounded
below by what no tracker measures better (TRACKER_NOISE_MIN_M: round-off is not a noise). The
noise floor from repeats is not that scale: it is a mean of squared differences, which one wild
repeat reading inflates as much as the fit's σ. A pose is wild when ``T_i / scale`` exceeds the
quantile at OUTLIER_ALPHA / n for n training poses of d_i · F(d_i, ν), ν the position rows'
residual degrees of freedom (χ²(d_i) for a large campaign; the F counts the σ's own scatter in a
small one) by OUTLIER_FACTOR: a clean campaign of any size reaches the quantile in about
OUTLIER_ALPHA of cases, and an effect the model lacks (residuals heavier-tailed than noise) up to
1.4 times it; a fault worth a word lies tens of times beyond. A test pose, outside the fit, is judged on its prediction
error against the same noise plus the model's own variance there.

A model that misses an effect spreads its error over every pose and raises the median with it: that
is structure for `diagnose`, not a reading fault; so is a share of flagged poses above
OUTLIER_MAX_SHARE, which `calibrate` keeps and says so. Otherwise `calibrate` leaves the wild
training poses out (``--keep-outliers`` keeps them), fits again, and names each in one line.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy import stats

from campaign.identify.solver import hat_inverse
from campaign.measure.plausibility import Finding
from campaign.tolerances import OUTLIER_ALPHA, OUTLIER_FACTOR, OUTLIER_MAX_SHARE, TRACKER_NOISE_MIN_M

#: fits again at most this many times, each without the faults the last one found (a fault can hide
#: another: the first pulls the fit towards itself)
OUTLIER_PASSES = 3


@dataclass(frozen=True)
class Outlier:
    """A wild reading: its ``pose_id``, in the ``test`` set or not, its position error ``error_mm``
    (the fit's residual at a training pose, of its worst reflector for raw reflectors; the prediction
    error at a test pose), and ``ratio``,
    its studentized error over the robust scale, against the ``threshold`` (both as a distance:
    the square roots of the χ² values)."""

    pose_id: int
    test: bool
    error_mm: float
    ratio: float
    threshold: float

    def text(self, kept: str | None = None) -> str:
        """One line; ``kept``: why a training fault stays in the fit (None: it was left out)."""
        where = "test" if self.test else "training"
        fate = ("kept in the test-set figures (it is not fitted)" if self.test else
                f"kept in the fit ({kept})" if kept else "left out of the fit (--keep-outliers keeps it)")
        return (f"pose {self.pose_id} ({where}): {self.error_mm:.3f} mm from the model, {self.ratio:.1f} σ of "
                f"the poses' robust scatter (a fault from {self.threshold:.1f} σ, {OUTLIER_FACTOR:g}× what a clean "
                f"campaign of this size reaches once in {1 / OUTLIER_ALPHA:.0f}): a reading fault; {fate}")

    def as_json(self) -> dict:
        return {"pose_id": self.pose_id, "test": self.test, "error_mm": self.error_mm, "ratio": self.ratio,
                "threshold": self.threshold}


@dataclass(frozen=True)
class OutlierScreen:
    """The screen's answer: the wild poses (training and test), the robust scale over the fit's
    rows' σ (``scale``, a factor on the variance), and whether the training ones are few enough to
    be reading faults (``isolated``)."""

    outliers: tuple
    scale: float
    n_train: int

    @property
    def train(self) -> tuple:
        return tuple(o for o in self.outliers if not o.test)

    @property
    def isolated(self) -> bool:
        return len(self.train) <= max(1, int(OUTLIER_MAX_SHARE * self.n_train))

    def structure_text(self) -> str:
        """One line when too many training poses are flagged to be reading faults."""
        return (f"{len(self.train)} of {self.n_train} training poses lie beyond the outlier threshold: more than "
                f"isolated reading faults ({100 * OUTLIER_MAX_SHARE:.0f} % at most), kept in the fit: a systematic "
                "error (`campaign diagnose`) or a set-up that changed during the campaign")


def _position_rows(model) -> np.ndarray:
    """(m,) bool: the fit's rows that are positions (all of a raw-reflector fit's)."""
    m = model.fit_residual_.shape[1]
    return np.ones(m, dtype=bool) if model.points is not None else np.arange(m) < 3


def studentized(model) -> tuple:
    """(T (n,), d (n,), dof): each training pose's studentized position residual ``e_iᵀ (I − H_ii)⁻¹ e_i``
    on its d_i measured position rows (module docstring), from a fitted CalibrationModel's kept
    linearisation (``fit_jacobian_``, ``fit_residual_``, ``fit_prior_precision_``), and the position
    rows' residual degrees of freedom (their count less their leverage), on which their σ rests."""
    J, e, P = model.fit_jacobian_, model.fit_residual_, model.fit_prior_precision_
    rows = _position_rows(model)
    n = len(J)
    A_inv = hat_inverse(J, P)  # the same hat matrix as the solver's leverage
    Jp = J[:, rows, :]
    H = np.einsum("nif,fg,njg->nij", Jp, A_inv, Jp)
    ep = e[:, rows]
    seen = np.abs(J[:, rows, :]).sum(axis=2) > 0  # a missed reflector's rows are zero
    seen |= ep != 0
    d = seen.sum(axis=1)
    Imh = np.eye(rows.sum())[None] - H
    if seen.all():  # pose data, or every reflector seen: one batched solve
        try:
            T = np.einsum("ni,ni->n", ep, np.linalg.solve(Imh, ep[:, :, None])[:, :, 0])
            return T, d, float(np.trace(Imh, axis1=1, axis2=2).sum())
        except np.linalg.LinAlgError:  # a pose of leverage 1 (no residual of its own): pose by pose
            pass
    T, dof = np.zeros(n), 0.0
    for i in np.flatnonzero(d):
        s = seen[i]
        block = Imh[i][np.ix_(s, s)]
        T[i] = float(ep[i, s] @ np.linalg.lstsq(block, ep[i, s], rcond=1e-10)[0])
        dof += float(np.trace(block))
    return T, d, dof


def screen(model, pose_id, train_index, *, q_test=None, T_test=None, context_test=None, test_ids=()) -> OutlierScreen:
    """Wild readings among a fitted model's training poses (``train_index`` (n,) into ``pose_id``:
    the poses it was fitted on, in order) and, for pose data, among the test poses (q_test,
    T_test, context_test, ``test_ids``)."""
    T, d, dof = studentized(model)
    fitted = d > 0
    n = int(fitted.sum())
    if n < 3:
        return OutlierScreen((), 1.0, n)
    scale = float(np.median(T[fitted] / stats.chi2.median(d[fitted])))
    sigma_rows = model.row_sigma_[_position_rows(model)]
    floor = (TRACKER_NOISE_MIN_M / float(np.mean(sigma_rows))) ** 2  # round-off is not a noise
    scale = max(scale, floor)
    out = []
    for i in np.flatnonzero(fitted):
        limit = _limit(d[i], dof, n)
        if T[i] / scale > limit:
            r = (model.fit_residual_[i] * model.row_sigma_).reshape(-1, 3)  # m; raw reflectors: one row each
            err = float(np.linalg.norm(r[:1] if model.points is None else r, axis=1).max()) * 1e3
            out.append(Outlier(int(pose_id[train_index[i]]), False, err, float(np.sqrt(T[i] / scale)),
                               float(np.sqrt(limit))))
    if q_test is not None and len(q_test) and model.points is None:
        out += _test_outliers(model, scale, dof, q_test, T_test, context_test, test_ids)
    return OutlierScreen(tuple(out), scale, n)


def _limit(d: int, dof: float, n: int) -> float:
    """The bound of a studentized statistic on ``d`` rows, for ``n`` poses: OUTLIER_FACTOR² times
    the quantile at the family-wise OUTLIER_ALPHA of d · F(d, dof), the rows' σ resting on ``dof``
    degrees of freedom (χ²(d) for many: on 12 poses the σ of 16 degrees of freedom made a test
    pose's χ²(3) quantile flag one campaign in 16 instead of one in 100)."""
    return float(OUTLIER_FACTOR ** 2 * d * stats.f.isf(OUTLIER_ALPHA / n, d, max(dof, 1.0)))


def _test_outliers(model, scale, dof, q, T_meas, context, ids) -> list:
    """Test poses whose position prediction error exceeds the noise (the rows' σ times the robust
    scale) plus the model's own variance there, at OUTLIER_ALPHA / n_test (:func:`_limit`)."""
    sig = model.row_sigma_[:3]
    r = model.residuals(q, T_meas, context)[:, :3]
    J = model.jacobian(q, T_meas, context)[:, :3, :][:, :, model.free_] / sig[None, :, None]
    J2 = model.fit_jacobian_.reshape(-1, model.fit_jacobian_.shape[2])
    A_inv = np.linalg.pinv(J2.T @ J2 + model.fit_prior_precision_, hermitian=True)
    C = np.eye(3)[None] + np.einsum("nif,fg,njg->nij", J, A_inv, J)  # whitened, per unit scale
    e = r / sig[None, :]
    T = np.einsum("ni,ni->n", e, np.linalg.solve(C, e[:, :, None])[:, :, 0]) / scale
    limit = _limit(3, dof, len(q))
    return [Outlier(int(ids[i]), True, float(np.linalg.norm(r[i])) * 1e3, float(np.sqrt(T[i])), float(np.sqrt(limit)))
            for i in np.flatnonzero(T > limit)]


def screen_outliers(model, poses, train, test, context) -> OutlierScreen:
    """The screen of a calibration's current model, fitted on the poses ``train`` (n,) bool of
    ``poses`` (MeasuredPoses, in order); ``test`` (n,) bool: the test poses with a pose; context:
    the effects' per-pose context (n,) arrays."""
    te = np.flatnonzero(test)
    return screen(model, poses.pose_id, np.flatnonzero(train), q_test=poses.q[te], T_test=poses.T_IE[te],
                  context_test={k: np.asarray(v)[te] for k, v in context.items()}, test_ids=poses.pose_id[te])


def outlier_findings(excluded, last: OutlierScreen, keep: bool) -> tuple:
    """The warnings (code ``outlier``), one line a pose: the faults left out (``excluded``), then
    what the last fit's screen found: faults kept (``keep``, or too many to be faults: one line
    naming them) and test poses."""
    out = [Finding("outlier", o.text()) for o in excluded]
    if last.train and not last.isolated:
        ids = ", ".join(str(o.pose_id) for o in last.train[:10]) + (", ..." if len(last.train) > 10 else "")
        out.append(Finding("outlier", f"{last.structure_text()} (poses {ids})"))
    elif last.train:
        why = "--keep-outliers" if keep else f"{OUTLIER_PASSES} fits left faults out already"
        out += [Finding("outlier", o.text(why)) for o in last.train]
    out += [Finding("outlier", o.text()) for o in last.outliers if o.test]
    return tuple(out)
