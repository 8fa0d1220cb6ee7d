"""Which physical effect is missing? Fit each candidate on training folds, score it on held-out folds.

For a run, the *current model* is the geometric model plus the effects enabled in the run's
campaign.yaml (or given). Every registered effect not in it is a candidate. On the training
part of the fixed 80/20 split, K folds: for each fold the current model and the current
model + candidate are fitted on the other folds and predict the held-out fold. A candidate is
*significant* when its held-out per-pose position errors are smaller than the current
model's by a one-sided paired t-test at p < 0.01 / (number of candidates) (Bonferroni) and
the mean improves by at least 2 %; the verdict is the significant candidate with the lowest
held-out error. The test set is not touched. Nothing here reads a simulator's truth.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
from scipy import stats

from campaign.effects.base import available, effect_context, make_effect, parse_effect_list
from campaign.errors import DataError
from campaign.identify.calibrate import configured_effects, load_robot_for_run
from campaign.identify.solver import CalibrationModel
from campaign.identify.split import train_test_split
from campaign.measure.store import open_run
from campaign.model.base_params import base_parameters

#: family-wise significance level of the candidate ranking
ALPHA = 0.01
#: smallest relative improvement of the held-out mean position error that counts
MIN_RELATIVE_GAIN = 0.02


@dataclass(frozen=True)
class CandidateScore:
    """Held-out performance of the current model + one candidate effect (errors in mm)."""

    effect: str
    heldout_mean_position_mm_before: float
    heldout_mean_position_mm_after: float
    p_value: float
    significant: bool
    r2: float
    absorbed: tuple = ()
    description: str = ""

    def as_json(self) -> dict:
        return {
            "effect": self.effect,
            "heldout_mean_position_mm_before": self.heldout_mean_position_mm_before,
            "heldout_mean_position_mm_after": self.heldout_mean_position_mm_after,
            "significant": self.significant,
            "p_value": self.p_value,
            "heldout_residual_variance_explained_r2": self.r2,
            "absorbed_parameters": list(self.absorbed),
            "description": self.description,
        }


@dataclass(frozen=True)
class Diagnosis:
    run_dir: Path
    current_effects: tuple
    ranking: tuple
    verdict: str | None
    n_train: int
    folds: int
    residuals: np.ndarray = field(repr=False, default=None)  # Δz of the current model, (n, 6)
    is_test: np.ndarray = field(repr=False, default=None)

    def as_json(self) -> dict:
        return {
            "verdict": self.verdict,
            "ranking": [c.as_json() for c in self.ranking],
            "current_effects": list(self.current_effects),
            "config_line": config_line(self.current_effects, self.verdict),
            "folds": self.folds,
            "n_train_poses": self.n_train,
        }

    def text(self) -> str:
        lines = [f"current model: geometric" + "".join(f" + {e}" for e in self.current_effects),
                 f"candidates scored on {self.folds} held-out folds of {self.n_train} training poses "
                 f"(test set untouched):", "",
                 f"{'effect':<20}{'before mm':>11}{'after mm':>11}{'gain':>8}{'R²':>7}{'p':>10}  significant"]
        for c in self.ranking:
            gain = 1 - c.heldout_mean_position_mm_after / max(c.heldout_mean_position_mm_before, 1e-300)
            note = " (absorbed: " + ", ".join(c.absorbed) + ")" if c.absorbed else ""
            lines.append(f"{c.effect:<20}{c.heldout_mean_position_mm_before:>11.4f}{c.heldout_mean_position_mm_after:>11.4f}"
                         f"{100 * gain:>7.1f}%{c.r2:>7.2f}{c.p_value:>10.2g}  {'yes' if c.significant else 'no'}{note}")
        lines.append("")
        lines.append(verdict_text(self))
        return "\n".join(lines)


def config_line(current, verdict) -> str | None:
    if verdict is None:
        return None
    return f"effects: [{', '.join([*current, verdict])}]"


def verdict_text(d: Diagnosis) -> str:
    if d.verdict is None:
        return "verdict: no missing effect found above the noise."
    c = next(c for c in d.ranking if c.effect == d.verdict)
    return (f"verdict: add {c.effect} ({c.description}).\n"
            f"  the held-out residual follows it: R² {c.r2:.2f}; held-out mean position error "
            f"{c.heldout_mean_position_mm_before:.3f} → {c.heldout_mean_position_mm_after:.3f} mm (p = {c.p_value:.2g}).\n"
            f"  add to {d.run_dir}/campaign.yaml:   {config_line(d.current_effects, d.verdict)}\n"
            f"  or run:   campaign calibrate {d.run_dir} --effects {','.join([*d.current_effects, c.effect])}")


def _folds(pose_id, k):
    """Fold index per pose, from a hash of the pose id (independent of the 80/20 split's hash)."""
    u = train_test_split(pose_id, seed=7919, test_fraction=0.5)  # decorrelated bits
    rank = np.argsort(np.argsort(pose_id * 2654435761 % 4294967291 + u))
    return rank % k


def diagnose(run_dir, *, effects=None, candidates=None, folds: int = 5, progress=None) -> Diagnosis:
    """Rank the candidate effects of a run's current model by held-out error reduction."""
    run_dir = Path(run_dir)
    say = progress or (lambda msg: None)
    robot = load_robot_for_run(run_dir)
    current = configured_effects(run_dir) if effects is None else parse_effect_list(effects)
    names = list(available()) if candidates is None else list(parse_effect_list(candidates))
    names = [n for n in names if n not in current]
    for name in (*current, *names):  # an unknown name is one line now, not after the fits
        make_effect(name, robot)
    with open_run(run_dir) as store:
        poses = store.load_measured()
    is_test = train_test_split(poses.pose_id)
    tr = np.flatnonzero(~is_test)
    if len(tr) < 10 * folds:
        raise DataError(f"{run_dir}: {len(tr)} training poses are too few for {folds}-fold diagnosis")
    context = effect_context(poses.context, poses.time_s)
    fold = _folds(poses.pose_id[tr], folds)
    base = base_parameters(robot)

    ctx_tr = {key: v[tr] for key, v in context.items()}
    say("current model on the whole training set")
    full = CalibrationModel(robot=robot, effects=list(current)).fit(poses.q[tr], poses.T_IE[tr], ctx_tr, base=base)
    noise = full.noise_sigma_

    def heldout_errors(effs):
        """Fold fits start from the full fit and keep its noise weights: a few LM steps each."""
        err = np.empty(len(tr))
        dz_all = np.empty((len(tr), 3))
        absorbed = set()
        for k in range(folds):
            fit_idx, out_idx = tr[fold != k], tr[fold == k]
            ctx_fit = {key: v[fit_idx] for key, v in context.items()}
            ctx_out = {key: v[out_idx] for key, v in context.items()}
            m = CalibrationModel(robot=robot, effects=effs, estimate_noise=False,
                                 sigma_position_m=noise["position_m"],
                                 sigma_orientation_rad=noise["orientation_rad"] or 1e-4)
            m.fit(poses.q[fit_idx], poses.T_IE[fit_idx], ctx_fit, base=base, init=full.values_)
            absorbed |= {m.unknown_names_[i] for i in m.absorbed_}
            dz = m.residuals(poses.q[out_idx], poses.T_IE[out_idx], ctx_out)
            err[fold == k] = np.linalg.norm(dz[:, :3], axis=1) * 1e3
            dz_all[fold == k] = dz[:, :3]
        return err, dz_all, tuple(sorted(absorbed))

    say(f"current model on {folds} folds")
    before, dz_before, _ = heldout_errors(list(current))
    ss_before = float(np.sum((dz_before - dz_before.mean(axis=0)) ** 2))
    scores = []
    n_cand = max(len(names), 1)
    for i, name in enumerate(names):
        say(f"candidate {i + 1}/{len(names)}: {name}")
        cls = available()[name]
        if any(key not in context for key in getattr(cls, "context_keys", ())):
            say(f"  {name}: skipped (needs context {', '.join(cls.context_keys)})")
            continue
        after, dz_after, absorbed = heldout_errors([*current, name])
        d = before - after
        if np.all(d == 0):
            p = 1.0
        else:
            p = float(stats.ttest_rel(before, after, alternative="greater").pvalue)
        gain = 1 - after.mean() / max(before.mean(), 1e-300)
        r2 = 1 - float(np.sum((dz_after - dz_after.mean(axis=0)) ** 2)) / max(ss_before, 1e-300)
        n_params = len(getattr(cls(robot), "param_names", ()))
        fully_absorbed = len(absorbed) >= n_params and n_params > 0
        significant = (p < ALPHA / n_cand) and gain >= MIN_RELATIVE_GAIN and not fully_absorbed
        scores.append(CandidateScore(name, float(before.mean()), float(after.mean()), p, bool(significant),
                                     float(r2), absorbed, cls.description))
    scores.sort(key=lambda c: (not c.significant, c.heldout_mean_position_mm_after))
    verdict = scores[0].effect if scores and scores[0].significant else None
    residuals = full.residuals(poses.q, poses.T_IE, context)
    return Diagnosis(run_dir, tuple(current), tuple(scores), verdict, len(tr), folds, residuals, is_test)
