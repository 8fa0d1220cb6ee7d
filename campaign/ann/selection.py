"""Model selection for the residual network: K-fold cross-validation over hidden sizes (Table 5)."""

from __future__ import annotations

import numpy as np

from campaign.ann.network import ResidualNetwork
from campaign.model.rotations import rotvec_to_matrix


def compensate_pose(T_model, dz_hat) -> np.ndarray:
    """Remove a predicted residual from model poses: t = t_model − Δt̂, R = exp(−Δφ̂) R_model. (n, 4, 4)."""
    T = np.array(T_model, dtype=float, copy=True)
    dz_hat = np.asarray(dz_hat, dtype=float)
    T[:, :3, 3] -= dz_hat[:, :3]
    T[:, :3, :3] = rotvec_to_matrix(-dz_hat[:, 3:6]) @ T[:, :3, :3]
    return T


def _fold_of(n, folds, seed):
    rng = np.random.default_rng(seed)
    return rng.permutation(n) % folds


def cv_stats(dz_true, dz_pred, target_scale) -> dict:
    """Table 5 statistics of held-out predictions: RMSE of normalised Δz_tot, max ‖Δr‖ mm, max ‖Δφ‖ mrad."""
    res = dz_true - dz_pred
    return {"rmse_normalised": float(np.sqrt(np.mean((res / target_scale) ** 2))),
            "max_position_mm": float(np.max(np.linalg.norm(res[:, :3], axis=1)) * 1e3),
            "max_orientation_mrad": float(np.max(np.linalg.norm(res[:, 3:], axis=1)) * 1e3),
            "mean_position_mm": float(np.mean(np.linalg.norm(res[:, :3], axis=1)) * 1e3)}


def cross_validate(q, dz, *, sizes, folds=5, seed=0, q_lower=None, q_upper=None, progress=None, **net_options):
    """K-fold CV over hidden sizes on training data only. Returns {"sizes": [...], "best": (N1, N2)}.

    The normalisation of Δz_tot in the RMSE uses the standard deviation of the training targets
    (the same mapping as the network's own).
    """
    q = np.asarray(q, dtype=float)
    dz = np.asarray(dz, dtype=float)
    fold = _fold_of(len(q), folds, seed)
    scale = np.where(dz.std(axis=0) > 0, dz.std(axis=0), 1.0)
    rows = []
    for hidden in sizes:
        pred = np.empty_like(dz)
        epochs = []
        for k in range(folds):
            tr, te = fold != k, fold == k
            say = (lambda _h=hidden, _k=k, **kw: progress(f"CV {_h} fold {_k + 1}/{folds}: epoch {kw['epoch']}, "
                                                         f"mse {kw['mse']:.4g}, γ {kw['gamma']:.0f}")) if progress else None
            net = ResidualNetwork(hidden=hidden, q_lower=q_lower, q_upper=q_upper, seed=seed, progress=say,
                                  **net_options).fit(q[tr], dz[tr])
            pred[te] = net.predict(q[te])
            epochs.append(net.n_epochs_)
        row = {"hidden": list(hidden), **cv_stats(dz, pred, scale), "epochs": epochs}
        rows.append(row)
        if progress:
            progress(f"CV {hidden}: RMSE {row['rmse_normalised']:.3f}, max ‖Δr‖ {row['max_position_mm']:.3f} mm")
    best = min(rows, key=lambda r: r["rmse_normalised"])
    return {"sizes": rows, "best": list(best["hidden"]), "folds": folds}


def fit_ann_stage(q_train, dz_train, *, sizes, folds=5, seed=0, q_lower=None, q_upper=None, progress=None,
                  **net_options):
    """Choose the hidden size by CV on the training set, retrain it on the whole training set.

    Returns (ResidualNetwork, cv dict). With a single size, CV is still run (for Table 5).
    """
    cv = cross_validate(q_train, dz_train, sizes=sizes, folds=folds, seed=seed, q_lower=q_lower,
                        q_upper=q_upper, progress=progress, **net_options)
    say = (lambda **kw: progress(f"final {tuple(cv['best'])}: epoch {kw['epoch']}, mse {kw['mse']:.4g}, "
                                 f"γ {kw['gamma']:.0f}")) if progress else None
    net = ResidualNetwork(hidden=tuple(cv["best"]), q_lower=q_lower, q_upper=q_upper, seed=seed, progress=say,
                          **net_options).fit(q_train, dz_train)
    cv["final"] = {"hidden": list(cv["best"]), "epochs": net.n_epochs_, "gamma": net.gamma_, "alpha": net.alpha_,
                   "beta": net.beta_, "stop": net.stop_reason_}
    return net, cv
