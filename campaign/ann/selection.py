"""Model selection for the residual network: K-fold cross-validation over hidden sizes (Table 5)."""

from __future__ import annotations

import time
from dataclasses import dataclass

import numpy as np

from campaign.errors import DataError
from campaign.ann.gain import heldout_gain
from campaign.ann.grid import best_row, cv_row_text, cv_stats, diverged_folds, fold_of
from campaign.ann.network import ResidualNetwork
from campaign.model.rotations import rotvec_to_matrix


def compensate_pose(T_model, dz_hat) -> np.ndarray:
    """Remove a predicted residual from model poses: t = t_model − Δt̂, R = exp(−Δφ̂) R_model. (n, 4, 4).

    dz_hat (n, 6) (m, rad), or (n, 3) (m) from a network trained on position-only data: then
    only the position is corrected and R = R_model.
    """
    T = np.array(T_model, dtype=float, copy=True)
    dz_hat = np.asarray(dz_hat, dtype=float)
    if dz_hat.ndim != 2 or dz_hat.shape[1] not in (3, 6) or len(dz_hat) != len(T):
        raise DataError(f"compensate_pose: residuals (n, 6) or (n, 3) for {len(T)} poses, got {dz_hat.shape}")
    T[:, :3, 3] -= dz_hat[:, :3]
    if dz_hat.shape[1] == 6:
        T[:, :3, :3] = rotvec_to_matrix(-dz_hat[:, 3:6]) @ T[:, :3, :3]
    return T


@dataclass(frozen=True)
class TrainingProgress:
    """One progress report of a training inside model selection (what a progress bar shows).

    ``str()`` gives a one-line status, so a callback that just prints lines works too.
    fold is 1-based, or None for the final retraining on the whole training set.
    """

    hidden: tuple
    fold: int | None
    folds: int
    epoch: int
    max_epochs: int
    mse: float  # normalised training MSE (mean over the 6 mapped outputs)
    gamma: float  # effective number of parameters
    stage: str = ""  # calibrate's stage name (e.g. "geometric+ann"), set by the caller

    @property
    def task(self) -> str:
        """Which training this is: stage, hidden size and fold (constant over its epochs)."""
        where = "final" if self.fold is None else f"fold {self.fold}/{self.folds}"
        return " ".join(p for p in (self.stage, f"{self.hidden[0]}x{self.hidden[1]}", where) if p)

    def __str__(self) -> str:
        return f"{self.task}: epoch {self.epoch}/{self.max_epochs}, mse {self.mse:.4g}, γ {self.gamma:.0f}"


def _reporter(progress, hidden, fold, folds):
    if progress is None:
        return None
    return lambda **kw: progress(TrainingProgress(tuple(hidden), fold, folds, kw["epoch"], kw["max_epochs"],
                                                  kw["mse"], kw["gamma"]))


def _fold_of(n, folds, seed):
    return fold_of(n, folds, seed)


def cross_validate(q, dz, *, sizes, folds=5, seed=0, q_lower=None, q_upper=None, progress=None, **net_options):
    """K-fold CV over hidden sizes on training data only (the paper's Table 5).

    q (n, N) (rad, m), dz (n, 6) residuals (m, rad) after the prior model (nominal or geometric),
    or (n, 3) (m) for position-only data.
    Folds are a seeded random partition; each fold's network fits its own mappings on its
    training part. Returns a JSON-ready dict ``{"sizes": [row, ...], "best": [N1, N2],
    "folds": K}`` with one row per size: ``hidden``, ``rmse_normalised`` (RMSE of the held-out
    Δz_tot, each component divided by the standard deviation of the targets), ``max_position_mm``,
    ``max_orientation_mrad``, ``mean_position_mm``, ``epochs`` (per fold), ``wall_s``.
    The best size has the lowest RMSE. progress: optional callable(TrainingProgress) and, after
    each size, callable(str).
    """
    q = np.asarray(q, dtype=float)
    dz = np.asarray(dz, dtype=float)
    fold = _fold_of(len(q), folds, seed)
    scale = np.where(dz.std(axis=0) > 0, dz.std(axis=0), 1.0)
    if len(q) < 2 * folds or q.ndim != 2 or dz.ndim != 2 or dz.shape[0] != len(q) or dz.shape[1] not in (3, 6):
        raise DataError(f"cross_validate: need q (n, N) and dz (n, 6) or (n, 3) with n >= {2 * folds}, got "
                        f"{q.shape}, {dz.shape}")
    rows = []
    for hidden in sizes:
        pred = np.empty_like(dz)
        epochs = []
        t0 = time.perf_counter()
        for k in range(folds):
            tr, te = fold != k, fold == k
            net = ResidualNetwork(hidden=tuple(hidden), q_lower=q_lower, q_upper=q_upper, seed=seed,
                                  progress=_reporter(progress, hidden, k + 1, folds), **net_options).fit(q[tr], dz[tr])
            pred[te] = net.predict(q[te])
            epochs.append(net.n_epochs_)
        row = {"hidden": list(hidden), **cv_stats(dz, pred, scale), "heldout_gain": heldout_gain(dz, dz - pred, scale),
               "epochs": epochs,
               "diverged_folds": diverged_folds(dz, pred, fold, scale), "wall_s": time.perf_counter() - t0}
        rows.append(row)
        if progress:
            progress(cv_row_text(row))
    best = best_row(rows, progress)
    return {"sizes": rows, "best": list(best["hidden"]), "heldout_gain": best["heldout_gain"], "folds": folds}


def fit_ann_stage(q_train, dz_train, *, sizes, folds=5, seed=0, q_lower=None, q_upper=None, progress=None,
                  **net_options):
    """Choose the hidden size by CV on the training set, retrain it on the whole training set.

    q_train (n, N) (rad, m), dz_train (n, 6) (m, rad) or (n, 3) (m): residuals of the prior model
    on the training set only. q_lower, q_upper: joint limits of eq. 17 (N,) for the input mapping
    (None: the embedded robot's, 6 joints). net_options: further ResidualNetwork hyperparameters (max_epochs, ...).
    Returns (ResidualNetwork fitted on the whole training set, cv dict of :func:`cross_validate`
    plus ``"final"``). With a single size, CV is still run (for Table 5).
    """
    cv = cross_validate(q_train, dz_train, sizes=sizes, folds=folds, seed=seed, q_lower=q_lower,
                        q_upper=q_upper, progress=progress, **net_options)
    net = ResidualNetwork(hidden=tuple(cv["best"]), q_lower=q_lower, q_upper=q_upper, seed=seed,
                          progress=_reporter(progress, cv["best"], None, folds), **net_options).fit(q_train, dz_train)
    cv["final"] = {"hidden": list(cv["best"]), "epochs": net.n_epochs_, "gamma": net.gamma_, "alpha": net.alpha_,
                   "beta": net.beta_, "stop": net.stop_reason_, "switched_off": net.switched_off_}
    return net, cv
