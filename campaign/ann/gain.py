"""Does the network help? Its held-out gain over the prior model, with an uncertainty.

The measure is Table 5's: the RMSE of the normalised residual Δz (each component divided by the
training spread of the prior model's residual), with the network (``after``) and without it
(``before``: the prior model alone), over the same held-out poses. Their ratio is below 1 when
the network removes part of the residual. Its uncertainty comes from the spread over the poses
(the delta method on ln of the ratio of two means of per-pose squared errors, paired: both
means are over the same poses, so what the poses share cancels). A gain is *significant* when
the upper end of the 95 % interval is below 1.
"""

from __future__ import annotations

import math

import numpy as np

#: two-sided 95 % quantile of the normal distribution
Z95 = 1.959963984540054


def heldout_gain(before, after, scale) -> dict:
    """The held-out RMSE ratio of the network, ``{"ratio", "se", "ci95": [lo, hi], "n_poses",
    "significant"}``.

    before, after: (n, k) residuals (m, rad) of the same held-out poses without and with the
    network; scale: (k,) the normalisation (the training spread of each component). ``se`` is the
    standard error of the ratio (delta method), ``ci95`` the interval ``ratio · exp(±1.96 se_ln)``.
    With fewer than 2 poses (or no residual at all) the ratio is None and nothing is significant.
    """
    b = np.sum((np.asarray(before, dtype=float) / scale) ** 2, axis=1)
    a = np.sum((np.asarray(after, dtype=float) / scale) ** 2, axis=1)
    n = int(len(a))
    A, B = float(np.mean(a)) if n else 0.0, float(np.mean(b)) if n else 0.0
    if n < 2 or not (A > 0 and B > 0) or not (np.isfinite(A) and np.isfinite(B)):
        return {"ratio": None, "se": None, "ci95": None, "n_poses": n, "significant": False}
    cov = np.cov(np.stack([a, b]), ddof=1)
    # var of ln(A/B) = var(a)/(n A²) + var(b)/(n B²) − 2 cov(a, b)/(n A B); the ratio of RMSEs is its square root
    var_ln = max(cov[0, 0] / A ** 2 + cov[1, 1] / B ** 2 - 2.0 * cov[0, 1] / (A * B), 0.0) / n
    se_ln = 0.5 * math.sqrt(var_ln)
    ratio = math.sqrt(A / B)
    lo, hi = ratio * math.exp(-Z95 * se_ln), ratio * math.exp(Z95 * se_ln)
    return {"ratio": ratio, "se": ratio * se_ln, "ci95": [lo, hi], "n_poses": n, "significant": bool(hi < 1.0)}


def gain_text(stage: str, gain: dict) -> str:
    """One line: the stage's held-out gain and whether it is significant, with γ of N_w, e.g.
    ``geometric+ann: no significant held-out gain from the network, switched off: the stage is the
    geometric model (γ = 2-5 of 486 weights in the cross-validation's fold networks; held-out RMSE
    ratio 1.01 ± 0.02, 95 % 0.97-1.05 over 159 cross-validation poses)``.
    gain: a stage's block of metrics.json's ``ann_gain`` (campaign.identify.ann_stage.stage_gain)."""
    cv, test = gain.get("cv") or {}, gain.get("test") or {}
    n_w = gain["n_weights"]
    if gain.get("gamma") is not None:
        who = f"γ = {gain['gamma']:.0f} of {n_w} weights"
    elif gain.get("gamma_folds"):
        lo, hi = min(gain["gamma_folds"]), max(gain["gamma_folds"])
        who = f"γ = {lo:.0f}{'' if round(lo) == round(hi) else f'-{hi:.0f}'} of {n_w} weights in the fold networks"
    else:
        who = f"{n_w} weights, {gain.get('solver') or 'adam'}: no γ"
    if cv.get("ratio") is not None:
        detail = (f"held-out RMSE ratio {cv['ratio']:.2f} ± {cv['se']:.2f}, 95 % {cv['ci95'][0]:.2f}-"
                  f"{cv['ci95'][1]:.2f} over {cv['n_poses']} cross-validation poses")
    else:
        detail = "no held-out ratio (no residual to compare)"
    if test.get("ratio") is not None and not gain.get("switched_off"):
        detail += f"; test set {test['ratio']:.2f} ± {test['se']:.2f} over {test['n_poses']} poses"
    prior = gain.get("prior") or "its prior"
    if gain.get("significant"):
        return f"{stage}: held-out gain from the network ({who}; {detail})"
    if gain.get("switched_off"):
        return (f"{stage}: no significant held-out gain from the network, switched off: the stage is the {prior} "
                f"model ({who}; {detail})")
    return f"{stage}: no significant held-out gain from the network ({who}; {detail}): not a correction"
