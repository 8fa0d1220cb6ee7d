"""The model-free test for structure: does a flexible regressor predict the model's held-out residual?

:class:`FourierRidge` is kernel ridge regression with a Gaussian kernel, approximated by
random Fourier features (Rahimi & Recht 2007) so that it costs O(n D²) on n poses and D
features: inputs standardised, a global length scale and the ridge penalty chosen by
leave-one-out cross-validation (closed form from one eigendecomposition of the D×D Gram
matrix), then "ARD-ish" relevance: inputs whose removal does not worsen the LOO score are dropped
(one backward pass), so the remaining inputs are those the residual depends on.

:func:`structure_test` runs it on the diagnosis folds: for fold k the regressor is fitted to
the residuals of the current model fitted on the other folds, at those folds' poses, and
predicts the residual of fold k, which neither saw. The held-out gain is
``1 − mean‖r − f̂‖ / mean‖r‖`` over all held-out poses; it is significant when a one-sided
paired t-test on the per-pose errors gives p < α and the gain reaches the detection limit.
Which inputs matter: permutation importance on the held-out folds (the increase of the
held-out error when one input is shuffled among the held-out poses, as a share of the sum
over all inputs).
"""

from __future__ import annotations

from dataclasses import dataclass, field, replace

import numpy as np
from scipy import stats

#: random Fourier features of the regressor
N_FEATURES = 300
#: poses the regressor is fitted on at most, per fold (a random subset beyond that)
MAX_FIT_POSES = 1500
#: global length scales tried, in standard deviations of the inputs
LENGTH_SCALES = (0.5, 1.0, 2.0)
#: ridge penalties tried (relative to the mean squared singular value of the features)
ALPHAS = np.logspace(-5, 2, 15)
#: an input is dropped when the LOO score without it is at most this much worse
ARD_TOLERANCE = 1e-3


def _loo_path(Phi, Y):
    """Leave-one-out mean squared error for every α in ALPHAS, and those α: Phi (n, D), Y (n, m), centred.

    Closed form of ridge regression: with ΦᵀΦ = V diag(s²) Vᵀ and U = Φ V diag(1/s), the fit is
    Ŷ = U diag(f) UᵀY, f = s²/(s² + α), the leverages h = (U∘U) f, and the leave-one-out
    residual (y − ŷ)/(1 − h)."""
    G = Phi.T @ Phi
    s2, V = np.linalg.eigh(G)
    keep = s2 > max(s2.max(), 1e-300) * 1e-10
    s2, V = s2[keep], V[:, keep]
    U = Phi @ V
    U /= np.sqrt(s2)
    UY = U.T @ Y
    alphas = ALPHAS * (s2.mean() if s2.size else 1.0)
    F = s2[:, None] / (s2[:, None] + alphas)  # (D', a): the shrinkage of each α, all at once
    fitted = U @ (F[:, :, None] * UY[:, None, :]).reshape(len(s2), -1)  # (n, a·m)
    res = Y[:, None, :] - fitted.reshape(len(Y), len(alphas), -1)
    h = np.minimum((U ** 2) @ F, 0.99)  # (n, a)
    scores = np.mean((res / (1.0 - h)[:, :, None]) ** 2, axis=(0, 2))
    return scores, alphas


class FourierRidge:
    """Gaussian-kernel ridge regression on random Fourier features, with input relevance.

    Parameters (keyword-only, no logic): n_features (at most; never more than a third of
    the poses, so the ridge never interpolates), max_fit_poses, length_scales, ard,
    random_state. Learned: ``active_`` (d,) bool, ``length_scale_``, ``alpha_``,
    ``weights_`` (D, m), ``loo_mse_``.
    """

    def __init__(self, *, n_features=N_FEATURES, max_fit_poses=MAX_FIT_POSES, length_scales=LENGTH_SCALES,
                 ard=True, random_state=0):
        self.n_features = n_features
        self.max_fit_poses = max_fit_poses
        self.length_scales = length_scales
        self.ard = ard
        self.random_state = random_state

    def _features(self, Xs, active, ell):
        Z = (Xs * active) / ell
        A = Z @ self.omega_
        A += self.phase_
        np.cos(A, out=A)  # in place: the cosine of n × D values is the cost here, not a copy more
        A *= np.sqrt(2.0 / self.n_features_)
        return A

    def _score(self, Xs, Y, active, ell):
        """LOO mean squared error and α of the best α; then the centred features (n, D) and their
        mean (D,), which the final fit reuses when these inputs and this length scale win."""
        Phi = self._features(Xs, active, ell)
        mean = Phi.mean(axis=0)
        Phi -= mean
        scores, alphas = _loo_path(Phi, Y)
        i = int(np.argmin(scores))
        return scores[i], alphas[i], (Phi, mean)

    def fit(self, X, Y):
        """X (n, d) inputs, Y (n, m) targets; returns self."""
        X = np.asarray(X, dtype=float)
        Y = np.asarray(Y, dtype=float).reshape(len(X), -1)
        rng = np.random.default_rng(self.random_state)
        if len(X) > self.max_fit_poses:
            idx = np.sort(rng.choice(len(X), self.max_fit_poses, replace=False))
            X, Y = X[idx], Y[idx]
        d = X.shape[1]
        self.n_features_ = int(min(self.n_features, max(len(X) // 3, 10)))
        self.mean_ = X.mean(axis=0)
        sd = X.std(axis=0)
        self.scale_ = np.where(sd > 0, sd, 1.0)
        self.omega_ = rng.standard_normal((d, self.n_features_))
        self.phase_ = rng.uniform(0, 2 * np.pi, self.n_features_)
        self.y_mean_ = Y.mean(axis=0)
        Xs = (X - self.mean_) / self.scale_
        Yc = Y - self.y_mean_
        active = sd > 0
        best = min(((self._score(Xs, Yc, active, ell), ell) for ell in self.length_scales), key=lambda t: t[0][0])
        (score, alpha, feats), ell = best
        if self.ard and active.sum() > 1:
            # one backward pass: score the model without each input; drop every input whose
            # removal does not worsen the score, or, if dropping them together does, the best one
            trials = []
            best_trial = None  # (score, α, features, j) of the best trial: only its features are kept
            for j in np.flatnonzero(active):
                a = active.copy()
                a[j] = False
                g_j, a_j, feats_j = self._score(Xs, Yc, a, ell)
                trials.append(((g_j, a_j), j))
                if best_trial is None or g_j < best_trial[0]:
                    best_trial = (g_j, a_j, feats_j, j)
            useless = [j for (g_j, _), j in trials if g_j <= score * (1 + ARD_TOLERANCE)]
            if useless:
                a = active.copy()
                a[useless] = False
                if not a.any():
                    a[max(trials, key=lambda t: t[0][0])[1]] = True
                score_all, alpha_all, feats_all = self._score(Xs, Yc, a, ell)
                if score_all <= score * (1 + ARD_TOLERANCE):
                    active, score, alpha, feats = a, score_all, alpha_all, feats_all
                else:
                    g_j, a_j, feats_j, j = best_trial  # the first of the lowest, as min() takes
                    active[j] = False
                    score, alpha, feats = g_j, a_j, feats_j
        self.active_ = active
        self.length_scale_ = float(ell)
        self.alpha_ = float(alpha)
        self.loo_mse_ = float(score)
        Phi, self.phi_mean_ = feats  # the winner's features, centred
        A = Phi.T @ Phi + alpha * np.eye(self.n_features_)
        self.weights_ = np.linalg.solve(A, Phi.T @ Yc)
        return self

    def predict(self, X) -> np.ndarray:
        """Predicted targets (n, m) for inputs X (n, d)."""
        Xs = (np.asarray(X, dtype=float) - self.mean_) / self.scale_
        return (self._features(Xs, self.active_, self.length_scale_) - self.phi_mean_) @ self.weights_ + self.y_mean_


@dataclass(frozen=True)
class StructureResult:
    """Outcome of the model-free test on the held-out folds (errors in mm).

    ``before``/``after``: per-pose held-out ‖r‖ and ‖r − f̂‖ (n,) mm; ``prediction``: f̂ at
    each held-out pose (n, 3) m; ``importance``: input name -> its share of the summed
    permutation importances; ``fit_time_s``: the regressor's cost over all folds.
    """

    input_names: tuple
    before: np.ndarray = field(repr=False)
    after: np.ndarray = field(repr=False)
    prediction: np.ndarray = field(repr=False)
    heldout_gain: float
    p_value: float
    importance: dict
    fit_time_s: float
    n_fit_poses: int
    importance_time_s: float = 0.0
    models: dict = field(repr=False, default_factory=dict)  # fold -> fitted FourierRidge
    fold: np.ndarray = field(repr=False, default=None)

    def predict_heldout(self, X) -> np.ndarray:
        """Each fold's regressor at its own held-out poses, for inputs X (n, d) (e.g. with one input changed)."""
        out = np.zeros_like(self.prediction)
        for k, m in self.models.items():
            sel = self.fold == k
            out[sel] = m.predict(X[sel])
        return out

    def depends_on(self, min_share: float) -> list:
        """Inputs with at least ``min_share`` of the summed importance, most important first."""
        items = sorted(self.importance.items(), key=lambda kv: -kv[1])
        return [k for k, v in items if v >= min_share]


def structure_test(X, input_names, fold, residual_fit, residual_out, *, random_state=0, n_permutations=2,
                   importance=True, max_fit_poses=MAX_FIT_POSES):
    """Fit the regressor on each fold's training residuals and score it on the held-out fold.

    X (n, d) inputs of the n training poses; fold (n,) fold index; residual_fit: fold ->
    residuals (n_fit, m) m of the fold's model at its own fitting poses (fold != k, in order);
    residual_out (n, m) m: each pose's held-out residual; importance: compute the permutation
    importance (else every input's share is 0); max_fit_poses: the regressor's poses per fold at
    most (a random subset beyond that). Returns a :class:`StructureResult`.
    """
    import time

    X = np.asarray(X, dtype=float)
    r = np.asarray(residual_out, dtype=float)
    pred = np.zeros_like(r)
    rng = np.random.default_rng(random_state + 1)
    models = {}
    t0 = time.perf_counter()
    n_fit = 0
    for k in np.unique(fold):
        tr, out = fold != k, fold == k
        m = FourierRidge(random_state=random_state + int(k), max_fit_poses=max_fit_poses).fit(X[tr], residual_fit[k])
        n_fit = max(n_fit, min(int(tr.sum()), m.max_fit_poses))
        models[k] = m
        pred[out] = m.predict(X[out])
    fit_time = time.perf_counter() - t0
    before = np.linalg.norm(r, axis=1) * 1e3
    after = np.linalg.norm(r - pred, axis=1) * 1e3
    gain = 1.0 - after.mean() / max(before.mean(), 1e-300)
    d = before - after
    p = 1.0 if np.all(d == 0) else float(stats.ttest_rel(before, after, alternative="greater").pvalue)
    # permutation importance on the held-out folds
    t1 = time.perf_counter()
    lost = np.zeros(X.shape[1])
    for j in range(X.shape[1] if importance else 0):
        if not any(models[k].active_[j] for k in models):
            continue
        errs = []
        for _ in range(n_permutations):
            perm_pred = np.zeros_like(r)
            for k, m in models.items():
                out = np.flatnonzero(fold == k)
                perm = rng.permutation(len(out))
                if not m.active_[j]:  # a model without input j predicts the same (its features zero it)
                    perm_pred[out] = pred[out]
                    continue
                Xp = X[out].copy()
                Xp[:, j] = Xp[perm, j]
                perm_pred[out] = m.predict(Xp)
            errs.append(np.linalg.norm(r - perm_pred, axis=1).mean() * 1e3)
        lost[j] = np.mean(errs) - after.mean()
    lost = np.clip(lost, 0.0, None)
    share = lost / lost.sum() if lost.sum() > 0 else lost
    importance = {name: float(s) for name, s in zip(input_names, share)}
    return StructureResult(tuple(input_names), before, after, pred, float(gain), p, importance,
                           float(fit_time), int(n_fit), float(time.perf_counter() - t1), models, np.asarray(fold))


def joints_only(X, n_joints: int):
    """X (n, d) with its columns after the first ``n_joints`` (time, temperature, ...) held at 0, so
    that the regressor leaves them out and their importance is 0; None when X has no such column."""
    if X.shape[1] <= n_joints:
        return None
    X_q = np.array(X, dtype=float, copy=True)
    X_q[:, n_joints:] = 0.0
    return X_q


def pose_or_all_structure(X, input_names, n_joints: int, fold, residuals):
    """The model-free test on every input and on the joint angles alone, for the residuals in each
    frame of ``residuals`` ([(fold fits' residuals, held-out residual)], the frame after joint 1 and
    the tool frame): the one whose held-out error is lower, its p-value times the number of tests
    (Bonferroni: the best of several). The time and the temperature follow the order the poses were
    measured in, itself a path through the joint space: given them, the regressor (one length scale
    for all inputs) spreads over proxies of the pose and misses a structure of the pose alone (a
    bearing run-out of joint 4: 10 % of the held-out error on every input, 24 % on the joints, with
    q4 first). On the joints alone the time columns are held constant: the regressor leaves them out
    and their importance is 0. The frame: an effect near the base (joints 2-3) is a smooth function
    of few joints in the frame after joint 1; one in the wrist moves the tool point along a
    direction fixed in the tool frame, scaled by a function of the wrist joints alone (a run-out of
    joint 6: one input there, all six and their products in the frame after joint 1)."""
    X_q = joints_only(X, n_joints)
    tests = []
    for r_fit, r_out in residuals:
        tests.append(structure_test(X, input_names, fold, r_fit, r_out))
        if X_q is not None:
            tests.append(structure_test(X_q, input_names, fold, r_fit, r_out))
    best = min(tests, key=lambda t: t.after.mean())
    return replace(best, p_value=min(1.0, len(tests) * best.p_value))
