"""Where does the model fail, how far is it from the measurement noise, and what is missing?

For a run, the *current model* is the geometric model plus the effects enabled in the run's
campaign.yaml (or given). On the training part of the fixed 80/20 split, K folds: for each
fold the current model is fitted on the other folds and predicts the held-out fold. Five
questions are answered on those held-out residuals (the test set is not touched, nothing
here reads a simulator's truth):

1. **How far from the noise?** The held-out mean position error over the noise floor
   (:mod:`campaign.measure.floor`, from repeated measurements or the stated tracker noise,
   never from the model's fit): ``model_to_noise``.
2. **Is there structure left?** A flexible regressor of the residual on the joint
   coordinates and the per-pose context (:mod:`campaign.diagnose.structure`), fitted on the
   same folds: its held-out gain, significance and the inputs it depends on.
3. **Which catalogued (or user) effect explains it?** Every registered effect not in the
   model, and any installed or named user effect, is fitted on the folds with the current
   model: a candidate is *significant* when its held-out per-pose position errors are smaller
   by a one-sided paired t-test at p < 0.01 / (number of candidates) (Bonferroni) and the mean
   improves by at least 2 % — or, when the model is already at the noise floor, by more than
   the detection limit (parsimony).

   A joint-indexed candidate named without joints is searched over the robot's joints
   (:mod:`campaign.diagnose.joints`); the simplest candidate within one standard error of the
   best (plus one per joint a search added) comes first. Each of its joints is compared with the
   other joint-indexed candidates on that joint: a joint a rival fits better, or that the poses
   cannot tell apart from one, is not named for it (``indistinguishable`` in diagnosis.json).
4. **Does each effect of the model earn its place?** Each (and each joint of a joint-indexed
   one) taken out on the same folds (:mod:`campaign.diagnose.contribution`).
5. **Is it time, or the poses the tour sweeps?** When time or temperature ranks among the
   structure's inputs, the same poses measured at different times decide
   (:mod:`campaign.diagnose.timing`).

:func:`diagnose` runs these as named steps: :func:`load_data`, :func:`fit_current`,
:func:`judge_floor`, :func:`find_structure`, :func:`score_candidates`, the contributions,
:func:`choose_verdict`, :func:`run_time_test`.

The verdict: the best significant candidate when it explains the structure (its held-out
error is within 5 % of the regressor's, or the regressor finds nothing); ``"unexplained"`` when
systematic error remains that no candidate explains (the regressor finds it, or the model
is above the floor's uncertainty); ``None`` only when the model is at the floor and the
regressor finds nothing either (or, with no floor, when nothing at all is found).
"""

from __future__ import annotations

from dataclasses import dataclass, field, replace
from pathlib import Path

import numpy as np

from campaign.diagnose.candidates import combined_effect, fit_candidate, linearise
from campaign.diagnose.contribution import contributions, joint_swaps, param_index
from campaign.diagnose.joints import (Rival, contested_joints, model_joints, paired_p, search_joints,
                                      searches_joints, shared_joint_rivals)
from campaign.diagnose.structure import pose_or_all_structure
from campaign.diagnose.timing import TIME_INPUTS, rank_by_time_test, time_test
from campaign.effects.base import (available, effect_class, effect_context, effect_label,
                                   entry_point_effects, joint_spec, make_effect, merge_effects, parse_effect_list,
                                   resolve_effect_spec, split_joints, takes_joints, without_joints)
from campaign.errors import ConfigError
from campaign.errors import DataError
from campaign.identify.cells import decide_cells
from campaign.identify.poses import (check_pose_count, distinct_poses, equations_per_pose, prepare_measured,
                                     tracker_to_robot, training_poses_needed)
from campaign.identify.solver import CalibrationModel
from campaign.identify.split import FoldRule, choose_folds, run_split, train_test_split, validation_file
from campaign.measure.drift import Drift, drift_readings, measured_drift
from campaign.measure.floor import NoiseFloor, floor_from_stated, noise_floor, times_the_noise
from campaign.model.base_params import base_parameters
from campaign.run import RunFolder
from campaign.tolerances import MIN_ROUND_SHARE, ZERO_NOISE_MODEL_ATOL_M

#: family-wise significance level of the candidate ranking and of the structure test
ALPHA = 0.01
#: smallest relative improvement of the held-out mean position error that counts
MIN_RELATIVE_GAIN = 0.02
#: how much a correct model's held-out error may exceed the pure noise (its own parameter
#: estimation error, a few per cent for tens of parameters on hundreds of poses)
AT_FLOOR_MARGIN = 0.05
#: the model is "at the floor" up to this many standard uncertainties of the floor (one-sided
#: ~0.1 %: with 2 the negative control with a floor from 10 poses measured 3 times gave 1 false
#: "unexplained" in 20 seeds, the floor's own sampling error)
FLOOR_UNCERTAINTIES = 3.0
#: an input is named in depends_on when it has this share of the summed permutation importance
MIN_IMPORTANCE_SHARE = 0.05
#: a candidate explains the structure when its held-out error is within this factor of the regressor's
EXPLAINS_FACTOR = 1.05
#: the rotation error is one the candidates explain when one of them takes this share of what the
#: rotation test's regressor takes (:func:`rotation_veto`)
PARTIAL_ROTATION_SHARE = 0.5


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
    spec: str = ""
    #: the joint search's steps (campaign.diagnose.joints.JointStep), for a joint-indexed candidate
    joint_steps: tuple = ()
    #: its joints against the other joint-indexed candidates on them (campaign.diagnose.joints.Rival);
    #: None when not compared (only the leading candidate is)
    rivals: tuple | None = None
    #: the held-out mean rotation error, mrad, of the current model and with the candidate (NaN: position only)
    heldout_mean_rotation_mrad_before: float = float("nan")
    heldout_mean_rotation_mrad_after: float = float("nan")
    #: one-sided paired p of "the candidate makes the held-out rotation error larger" (NaN: position only)
    rotation_p_worse: float = float("nan")
    #: not significant because it makes the held-out rotation error larger (:func:`rotation_veto`)
    rotation_veto: bool = False

    @property
    def joints(self):
        """The joints (1-based) the candidate acts on, or None (not joint-indexed, or its default)."""
        return split_joints(self.spec)[1] if self.spec else None

    @property
    def label(self) -> str:
        """In words: "joint_compliance of joint 4"."""
        return effect_label(joint_spec(self.effect, self.joints)) if self.joints else self.effect

    @property
    def gain(self) -> float:
        return 1 - self.heldout_mean_position_mm_after / max(self.heldout_mean_position_mm_before, 1e-300)

    @property
    def rotation_gain(self) -> float:
        """The share of the held-out rotation error it takes away (NaN: position only)."""
        return 1 - self.heldout_mean_rotation_mrad_after / max(self.heldout_mean_rotation_mrad_before, 1e-300)

    def as_json(self) -> dict:
        finite = lambda v: float(v) if np.isfinite(v) else None  # noqa: E731
        return {
            "effect": self.effect,
            "heldout_mean_rotation_mrad_before": finite(self.heldout_mean_rotation_mrad_before),
            "heldout_mean_rotation_mrad_after": finite(self.heldout_mean_rotation_mrad_after),
            "rotation_p_worse": finite(self.rotation_p_worse),
            "rotation_veto": self.rotation_veto,
            "spec": self.spec or self.effect,
            "heldout_mean_position_mm_before": self.heldout_mean_position_mm_before,
            "heldout_mean_position_mm_after": self.heldout_mean_position_mm_after,
            "significant": self.significant,
            "p_value": self.p_value,
            "heldout_residual_variance_explained_r2": self.r2,
            "absorbed_parameters": list(self.absorbed),
            "description": self.description,
            "joints": None if self.joints is None else list(self.joints),
            "label": self.label,
            "joint_search": [st.as_json() for st in self.joint_steps],
            "rivals": None if self.rivals is None else [r.as_json() for r in self.rivals],
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
    floor: NoiseFloor = field(default_factory=lambda: NoiseFloor("none"))
    heldout_mean_position_mm: float = float("nan")
    structure: object = None  # campaign.diagnose.structure.StructureResult
    structure_significant: bool = False
    detection_limit: float = MIN_RELATIVE_GAIN
    at_floor: bool | None = None
    signature: object = None  # campaign.diagnose.signature.Signature
    #: training-pose indices (into the run's poses) in the order of ``structure``'s arrays
    train_index: np.ndarray = field(repr=False, default=None)
    inputs: np.ndarray = field(repr=False, default=None)  # (n_train, d) regressor inputs
    #: held-out position residual (n_train, 3) m of the current model, in the frame after joint 1
    heldout_residual_j1: np.ndarray = field(repr=False, default=None)
    #: how the training poses were folded (campaign.identify.split.choose_folds)
    fold_rule: FoldRule | None = None
    #: candidates not scored: (effect, reason)
    skipped: tuple = ()
    #: held-out error a correct model reaches with these folds, over the pure noise (≥ 1)
    expected_model_to_noise: float = 1.0
    #: the training poses' ids of each held-out fold, in the order of the run's poses
    fold_pose_ids: tuple = ()
    #: the drift over the campaign's time, apart from the floor (campaign.measure.drift.Drift)
    drift: Drift = field(default_factory=Drift)
    #: where the current model's effects come from, when the last calibration and campaign.yaml differ
    model_note: str | None = None
    #: each current effect's (and joint's) cross-validated gain (campaign.diagnose.contribution)
    contributions: tuple = ()
    #: the same poses at different times against the noise (campaign.diagnose.timing.TimeTest) or None
    time_test: object = None
    #: noise-free measurements that the model fits to round-off: nothing was tested further
    round_off: bool = False
    #: a run measured on more than one cell: campaign.identify.cells.CellDecision (diagnosis.json's ``cells``)
    cells: object = field(repr=False, default=None)
    #: each joint of the model's joint-indexed effects against the other joint-indexed candidates in
    #: its place (campaign.diagnose.joints.Rival: own in the model, rival instead)
    model_rivals: tuple = ()
    #: (Rival, the model's effects after it) when a rival fits a joint of the model better: replaced
    swap: tuple | None = None
    #: the current model on the test set against the folds (campaign.diagnose.testset.TestSetCheck) or None
    test_set: object = None
    #: the ids of the poses diagnosed (n,), in the order of ``residuals``: without the reading faults the
    #: last calibration left out, and the poses with fewer than three reflectors seen
    pose_ids: np.ndarray = field(repr=False, default=None)
    #: the time test on the residuals of the current model with every significant candidate effect of
    #: time added (thermal, drift, a user's), when the best candidate is one or the model holds one and
    #: its poses moved; None otherwise (:func:`time_effects_test`)
    time_effects_test: object = None
    #: the model-free test on the rotation error in the frame after each joint
    #: (campaign.diagnose.chain.ChainStructure), or None (not run, or position only)
    chain: object = None

    @property
    def chain_significant(self) -> bool:
        return bool(self.chain is not None and self.chain.significant)

    @property
    def time_effects_fail(self) -> bool:
        """With the model's effects of time and every significant candidate one added, the same poses
        still move as the model does not predict: none of them is the answer (a warm-up of one link
        moves each pose its own way)."""
        return bool(self.time_effects_test is not None and self.time_effects_test.moved)

    @property
    def removal(self):
        """The current effect (or joint) that earns its place least, when one does not
        (campaign.diagnose.contribution.Contribution), else None: taken out before anything is added."""
        weak = [c for c in self.contributions if not c.earns_place]
        if not weak:
            return None
        return min(weak, key=lambda c: (c.gain_mm - c.gain_se_mm, c.joint is not None))

    @property
    def time_removal(self) -> tuple:
        """The contributions (campaign.diagnose.contribution.Contribution) of the current model's
        effects of time (thermal, drift, a user's of time or temperature alone) when the same poses,
        measured again, still move with them and every significant candidate effect of time added
        (:attr:`time_effects_fail`):
        each fits part of an error of time it does not cause, and all are taken out together (after
        :attr:`removal`, which goes first). Empty otherwise."""
        if not self.time_effects_fail:
            return ()
        return tuple(c for c in self.contributions if c.joint is None and is_time_effect(c.spec))

    def effects_after_time_removal(self) -> tuple:
        """The current effects once :attr:`time_removal`'s are taken out."""
        out = {c.spec for c in self.time_removal}
        return tuple(s for s in self.current_effects if s not in out)

    def time_effects_words(self) -> str:
        """The effects of time :attr:`time_effects_test` held, in words: "thermal in the model and
        drift added"."""
        held = [effect_label(s) for s in self.current_effects if is_time_effect(s)]
        added = [effect_label(s) for s in time_effects_added(self.ranking)]
        out = " and ".join([*([f"{', '.join(held)} in the model"] if held else []),
                            *([f"{', '.join(added)} added"] if added else [])])
        return f"every effect of time the folds find ({out or 'none'})"

    def time_removal_text(self) -> str:
        """Why :attr:`time_removal`'s effects go, with what each explains (its cross-validated gain
        ± its standard error); "" when none does."""
        out = self.time_removal
        if not out:
            return ""
        t = self.time_effects_test
        each = "; ".join(f"{c.label} takes {1e3 * c.gain_mm:.1f} ± {1e3 * c.gain_se_mm:.1f} µm off the held-out "
                         f"mean on the folds ({c.heldout_mean_position_mm_without:.4f} → "
                         f"{c.heldout_mean_position_mm_with:.4f} mm)" for c in out)
        return (f"with {self.time_effects_words()}, the same poses measured again still "
                f"move ({t.poses} pose{'' if t.poses == 1 else 's'} over {t.span_h:.2g} h, p = {t.p_value:.2g}): "
                f"{each}, part of an error of time {'it does' if len(out) == 1 else 'they do'} not cause")

    def effects_after_removal(self) -> tuple | None:
        """The current effects once :attr:`removal` is taken out, or None when nothing is."""
        c = self.removal
        if c is None:
            return None
        return tuple(c.without if s == c.spec else s for s in self.current_effects if s != c.spec or c.without)

    @property
    def indistinguishable(self) -> tuple:
        """Pairs of effects on one joint these poses cannot tell apart (campaign.diagnose.joints.Rival),
        once each: neither is named for that joint."""
        out = {}
        for r in (*[r for c in self.ranking for r in c.rivals or ()], *self.model_rivals):
            if r.outcome == "indistinguishable":
                out.setdefault(frozenset((r.own, r.rival)), r)
        return tuple(out.values())

    @property
    def verdict_spec(self) -> str | None:
        """The verdict as a spec to add (with its joints: "joint_compliance:4"), or None."""
        return self._verdict_spec()

    @property
    def worth_a_round(self) -> bool:
        """Structure significant and above MIN_ROUND_SHARE of the held-out error, or the same poses
        moved over time in a way the model does not predict: worth measuring for."""
        return bool((self.structure_significant and self.structure is not None
                     and self.structure.heldout_gain >= MIN_ROUND_SHARE) or self.time_moved
                    or (self.chain_significant and self.chain.heldout_gain >= MIN_ROUND_SHARE))

    @property
    def model_to_noise(self) -> float | None:
        """Held-out mean over the floor; None without a floor or for a floor of exactly 0."""
        return self.floor.ratio(self.heldout_mean_position_mm)

    @property
    def time_moved(self) -> bool:
        """The same poses, measured at different times, moved beyond the noise in a way the current
        model does not predict (the time test on its residuals): systematic error that depends on time."""
        return bool(self.time_test is not None and self.time_test.moved)

    @property
    def depends_on(self) -> list:
        """The inputs the error left depends on, most important first (:func:`ranked_inputs`)."""
        return ranked_inputs(self.structure, self.structure_significant, self.time_test, self.chain)

    @property
    def time_tested(self):
        """The time test when it ranks the inputs (time or temperature ranks among the structure's and
        the test could see the change over time the regressor predicts, or the same poses moved), else None."""
        if self.time_test is None or not self.time_test.conclusive:
            return None
        if self.time_test.moved or (self.structure is not None and self.structure_significant and set(
                self.structure.depends_on(MIN_IMPORTANCE_SHARE)) & set(TIME_INPUTS)):
            return self.time_test
        return None

    def as_json(self) -> dict:
        s = self.structure
        return {
            "verdict": self.verdict,
            "ranking": [c.as_json() for c in self.ranking],
            "noise_floor_mm": self.floor.mean_position_mm,
            "model_to_noise": self.model_to_noise,
            "heldout_mean_position_mm": self.heldout_mean_position_mm,
            "at_noise_floor": self.at_floor,
            "expected_model_to_noise": self.expected_model_to_noise,
            "noise_floor": self.floor.as_json(),
            "drift_um_per_h": self.drift.um_per_h,
            "drift": self.drift.as_json(),
            "unexplained": {
                "significant": bool(self.structure_significant),
                "heldout_gain": None if s is None else s.heldout_gain,
                "p_value": None if s is None else s.p_value,
                "detection_limit": self.detection_limit,
                "depends_on": self.depends_on,
                "importance": {} if s is None else dict(sorted(s.importance.items(), key=lambda kv: -kv[1])),
                "signature": None if self.signature is None else self.signature.as_json(),
                "regressor_fit_time_s": None if s is None else s.fit_time_s,
                "rotation": None if self.chain is None else self.chain.as_json(),
            },
            "current_effects": list(self.current_effects),
            "model_note": self.model_note,
            "config_line": config_line(self.current_effects, self._verdict_spec()),
            "verdict_spec": self._verdict_spec(),
            "verdict_label": None if self.verdict in (None, "unexplained") else effect_label(self._verdict_spec()),
            "contributions": [c.as_json() for c in self.contributions],
            "indistinguishable": [r.as_json() for r in self.indistinguishable],
            "model_rivals": [r.as_json() for r in self.model_rivals],
            "replace": None if self.swap is None else {**self.swap[0].as_json(), "effects_after": list(self.swap[1])},
            "remove": None if self.removal is None else {**self.removal.as_json(),
                                                          "effects_after": list(self.effects_after_removal())},
            "time_effects_test": None if self.time_effects_test is None else self.time_effects_test.as_json(),
            "remove_time": None if not self.time_removal else {
                "effects": [c.spec for c in self.time_removal], "contributions": [c.as_json() for c in self.time_removal],
                "effects_after": list(self.effects_after_time_removal()), "reason": self.time_removal_text()},
            "time_test": None if self.time_test is None else {**self.time_test.as_json(),
                                                              "ranks_inputs": self.time_tested is not None},
            "noise_free_round_off": self.round_off,
            "folds": self.folds,
            "fold_rule": None if self.fold_rule is None else self.fold_rule.as_json(),
            "fold_pose_ids": [list(ids) for ids in self.fold_pose_ids],
            "skipped_candidates": [{"effect": e, "reason": r} for e, r in self.skipped],
            "n_train_poses": self.n_train,
            **({} if self.cells is None else {"cells": {**self.cells.as_json(), "line": self.cells.line()}}),
            "test_set": None if self.test_set is None else {**self.test_set.as_json(), "line": self.test_set.text()},
        }

    def _verdict_spec(self):
        if self.verdict in (None, "unexplained"):
            return None
        c = next(c for c in self.ranking if c.effect == self.verdict)
        return c.spec or c.effect

    def floor_line(self) -> str:
        held = (f"cross-validated mean {self.heldout_mean_position_mm:.4f} mm (the current model on its "
                f"{self.folds} held-out folds of the training poses; calibrate's figure is the test set's)")
        if not self.floor.known:
            return (f"{held}; no noise floor (no repeated measurements, no `tracker: {{noise_m: ...}}` in "
                    "campaign.yaml): how far the model is from the measurement noise cannot be said")
        out = f"{held} {times_the_noise(self.heldout_mean_position_mm, self.floor.mean_position_mm)} ({self.floor.text()})"
        if self.expected_model_to_noise > 1.0 + AT_FLOOR_MARGIN:  # a small campaign: what a correct model reaches
            out += (f"\n  a correct model reaches about {self.expected_model_to_noise:.2f}× with these folds (its own "
                    f"parameters' estimation error on {self.fold_rule.fit_poses if self.fold_rule else '?'} poses)")
        return out + "\n" + self.drift.text()

    def structure_line(self) -> str:
        s = self.structure
        if s is None:
            return "model-free test: not run"
        inputs = ", ".join(s.input_names)
        verdict = "significant" if self.structure_significant else "not significant"
        out = (f"model-free test: a flexible regressor on {inputs} predicts {100 * s.heldout_gain:.1f} % of the "
               f"held-out error (p = {s.p_value:.2g}; detection limit {100 * self.detection_limit:.1f} %): {verdict}")
        if self.structure_significant:
            out += "\n  depends on " + ", ".join(f"{k} ({100 * s.importance[k]:.0f} %)"
                                                for k in s.depends_on(MIN_IMPORTANCE_SHARE))
        if self.chain is not None:
            out += "\n  " + self.chain.text(MIN_IMPORTANCE_SHARE)
        else:  # the structure test ran, the rotation test needs a rotation (campaign.diagnose.chain)
            out += ("\n  rotation test: not run (fewer than three reflectors per pose: no rotation measured), so "
                    "where in the chain the error arises is not told, and a tilt in the wrist may rank the joints "
                    "after it first")
        if self.structure_significant or self.chain_significant:
            out += "\n  depends on, ranked: " + ", ".join(self.depends_on)
        return out

    def text(self) -> str:
        lines = [f"current model: geometric" + "".join(f" + {e}" for e in self.current_effects),
                 *([f"  {self.model_note}"] if self.model_note else []),
                 *([f"  {self.cells.line()}"] if self.cells is not None else []),
                 f"candidates scored on {folds_text(self.folds, self.n_train, self.fold_rule)} (test set untouched):",
                 "",
                 f"{'effect':<20}{'before mm':>11}{'after mm':>11}{'gain':>8}{'R²':>7}{'p':>10}  significant"]
        for c in self.ranking:
            note = " (absorbed: " + ", ".join(c.absorbed) + ")" if c.absorbed else ""
            note += (f" (the rotation error {c.heldout_mean_rotation_mrad_before:.3f} → "
                     f"{c.heldout_mean_rotation_mrad_after:.3f} mrad, larger with p = {c.rotation_p_worse:.2g}: it fits "
                     "the position at the rotation's expense)") if c.rotation_veto else ""
            note += (f" (joints {','.join(map(str, c.joints))}: forward search, {len(c.joint_steps)} "
                     f"step{'s' if len(c.joint_steps) > 1 else ''})") if c.joint_steps else ""
            lines.append(f"{c.effect:<20}{c.heldout_mean_position_mm_before:>11.4f}{c.heldout_mean_position_mm_after:>11.4f}"
                         f"{100 * c.gain:>7.1f}%{c.r2:>7.2f}{c.p_value:>10.2g}  {'yes' if c.significant else 'no'}{note}")
        for effect, reason in self.skipped:
            lines.append(f"{effect:<20}skipped: {reason}")
        lines += ["", self.floor_line()]
        if self.test_set is not None:
            lines.append(self.test_set.text())
        lines.append(self.structure_line())
        shown = self.time_tested or (self.time_test if self.time_test is not None and self.structure_significant
                                     and not self.time_test.conclusive else None)
        if shown is not None:
            lines.append("  " + shown.text())
        if self.time_effects_fail:
            lines.append(f"  with {self.time_effects_words()}: "
                         + self.time_effects_test.text().removeprefix("time test: "))
        if self.signature is not None and self.structure_significant:
            lines.append("  signature: " + self.signature.text())
        if self.contributions:
            lines += ["", "what each current effect earns (taken out on the same folds):"]
            lines += ["  " + c.text() for c in self.contributions]
        rivals = [r for c in self.ranking for r in c.rivals or () if r.outcome != "own"]
        rivals += [r for r in self.model_rivals if r.outcome != "own"]
        if rivals:
            lines += ["", "effects on one joint compared (each with the leading candidate's other joints):"]
            lines += ["  " + r.text() for r in rivals]
        if self.removal is not None:
            after = self.effects_after_removal()
            lines.append(f"  take out {self.removal.label}: effects: [{', '.join(after)}]")
        elif self.swap is not None:
            r, after = self.swap
            lines.append(f"  replace {effect_label(r.own)} by {effect_label(r.rival)}: effects: [{', '.join(after)}]")
        elif self.time_removal:
            lines.append(f"  take out {' and '.join(c.label for c in self.time_removal)}: effects: "
                         f"[{', '.join(self.effects_after_time_removal())}]")
        lines += ["", verdict_text(self)]
        return "\n".join(lines)


def expected_heldout_ratio(model_var, sigma_position_m: float) -> float:
    """The held-out mean position error a correct model reaches, over the pure noise's:
    sqrt(1 + mean model variance / noise variance), from each fold model's own position variance
    at its held-out poses (``model_var`` (n,) m², from the covariance of its weights) and the noise
    σ per coordinate the fits weighted by (m). About sqrt(1 + p / (N − p)) for p unknowns and N
    equations: 1.01 on hundreds of 6-D poses, 1.25 for 25 parameters on two dozen positions."""
    if not len(model_var) or not sigma_position_m > 0:
        return 1.0
    return float(np.sqrt(1.0 + np.mean(model_var) / (3.0 * sigma_position_m ** 2)))


def config_line(current, verdict_spec) -> str | None:
    if verdict_spec is None:
        return None
    return f"effects: [{', '.join(merge_effects(current, [verdict_spec]))}]"


#: the line diagnose ends with when the model is at the noise floor and nothing is found
AT_NOISE_TEXT = "verdict: at the measurement noise: nothing left to find."


def verdict_text(d: Diagnosis) -> str:
    """The verdict in words; when the model's effects of time go (:attr:`Diagnosis.time_removal`),
    a last line says what each explained and why it goes all the same."""
    text = _verdict_words(d)
    if d.time_removal:
        text += (f"\n  take {' and '.join(c.label for c in d.time_removal)} out of the model "
                 f"(effects: [{', '.join(d.effects_after_time_removal())}]): {d.time_removal_text()}")
    return text


def _verdict_words(d: Diagnosis) -> str:
    if d.round_off:
        return (f"verdict: noise-free measurements, and the model fits them to round-off (held-out mean "
                f"{d.heldout_mean_position_mm:.2g} mm): nothing left to find, nothing to measure for.")
    if d.verdict is None:
        if d.at_floor:
            return AT_NOISE_TEXT
        return ("verdict: no missing effect found above the noise — but with no noise floor, how close the model "
                "is to the measurement noise is unknown (add repeat poses or `tracker: {noise_m: ...}`).")
    if d.verdict == "unexplained":
        if d.structure_significant:
            words = d.signature.text() if d.signature is not None else ", ".join(d.depends_on)
            partial = [c for c in d.ranking if c.significant]
            extra = (f"\n  {partial[0].effect} explains only part of it ({100 * partial[0].gain:.0f} % vs the regressor's "
                     f"{100 * d.structure.heldout_gain:.0f} %)") if partial else ""
            if partial and d.time_effects_fail and is_time_effect(partial[0].spec or partial[0].effect):
                extra += (f", and with {d.time_effects_words()} the same poses measured again still move: part of "
                          "an error of time it does not cause")
            return (f"verdict: unexplained — systematic error remains that no candidate explains: {words}.{extra}\n"
                    f"  write an effect for it (docs/effects.md) and add it to {d.run_dir}/campaign.yaml")
        if d.chain_significant:
            words = ", ".join(d.depends_on)
            return (f"verdict: unexplained — systematic rotation error remains that no candidate explains: in the "
                    f"frame after joint {d.chain.joint} a regressor predicts {100 * d.chain.heldout_gain:.0f} % of it, "
                    f"on {words} (the position test alone finds {100 * max(d.structure.heldout_gain, 0.0):.0f} %: the "
                    "lever to the tool turns with every joint after the error).\n"
                    f"  write an effect for it (docs/effects.md) and add it to {d.run_dir}/campaign.yaml")
        if d.time_moved:
            return (f"verdict: unexplained — the same poses, measured at different times, moved in a way the model "
                    f"does not predict ({d.time_test.poses} pose{'' if d.time_test.poses == 1 else 's'}, p = "
                    f"{d.time_test.p_value:.2g}): an effect of time that no candidate explains (a warm-up of one "
                    f"part moves each pose its own way).\n"
                    f"  write an effect for it (docs/effects.md) and add it to {d.run_dir}/campaign.yaml")
        if d.test_set is not None and not d.test_set.holds and d.floor.known and d.floor.ratio(
                d.heldout_mean_position_mm) is not None and d.test_set.folds_mean_mm <= d.test_set.mean_mm:
            sparse = ", ".join(d.test_set.sparse_joints)
            return (f"verdict: unexplained — the folds reach {times_the_noise(d.heldout_mean_position_mm, d.floor.mean_position_mm).lstrip('= ')}, "
                    f"but the test set is {d.test_set.ratio:.1f}× the folds: the model holds only on the training "
                    f"poses' values{f' of {sparse}' if sparse else ''}.\n  measure poses spread over "
                    f"{sparse or 'the joints'} (`campaign auto` does), then diagnose again")
        return (f"verdict: unexplained — the model's cross-validated mean {d.heldout_mean_position_mm:.4g} mm is "
                f"{times_the_noise(d.heldout_mean_position_mm, d.floor.mean_position_mm).lstrip('= ')}, but neither a "
                "candidate nor the regressor finds on which input the rest depends (a pose-to-pose error the inputs "
                "do not carry, or a floor that is too low)")
    c = next(c for c in d.ranking if c.effect == d.verdict)
    merged = merge_effects(d.current_effects, [c.spec or c.effect])
    return (f"verdict: add {c.label} ({c.description}).\n"
            f"  the held-out residual follows it: R² {c.r2:.2f}; cross-validated mean position error (the folds) "
            f"{c.heldout_mean_position_mm_before:.4f} → {c.heldout_mean_position_mm_after:.4f} mm (p = {c.p_value:.2g}).\n"
            f"  add to {d.run_dir}/campaign.yaml:   {config_line(d.current_effects, c.spec or c.effect)}\n"
            f"  or run:   campaign calibrate {d.run_dir} --effects {','.join(merged)}")


def folds_text(k: int, n_train: int, rule=None) -> str:
    """``5 held-out folds of 129 training poses (120 distinct: a pose and its repeats share a fold;
    5-fold: 60 training poses or more)``: one count of the training poses, on stdout and stderr alike."""
    notes = []
    if rule is not None and rule.n_poses != n_train:
        notes.append(f"{rule.n_poses} distinct: a pose and its repeats share a fold")
    if rule is not None:
        notes.append(rule.reason())
    return f"{k} held-out folds of {n_train} training poses" + (f" ({'; '.join(notes)})" if notes else "")


def pose_folds(pose_id, k):
    """Fold index per pose, from a hash of the pose id (independent of the 80/20 split's hash);
    a plan's repeat measurements (ids p + r·10⁹) share the fold of the pose p they repeat."""
    from campaign.plan.selection import base_pose_id

    ids, inverse = np.unique(base_pose_id(np.asarray(pose_id, dtype=np.int64)), return_inverse=True)
    u = train_test_split(ids, seed=7919, test_fraction=0.5)  # decorrelated bits
    rank = np.argsort(np.argsort(ids * 2654435761 % 4294967291 + u))
    return (rank % k)[inverse.reshape(-1)]


def fold_pose_ids(pose_id, fold, k) -> tuple:
    """The pose ids (n,) of each of the ``k`` folds (``fold`` (n,) its index per pose), in order."""
    return tuple(tuple(int(i) for i in pose_id[fold == j]) for j in range(k))


def regressor_inputs(q, context) -> tuple:
    """Inputs of the model-free test: q1..qN, time_s, then the other per-pose context columns
    (finite and not constant); returns (X (n, d), names)."""
    cols = [q[:, j] for j in range(q.shape[1])]
    names = [f"q{j + 1}" for j in range(q.shape[1])]
    keys = ["time_s"] + sorted(k for k in context if k != "time_s")
    for key in keys:
        if key not in context:
            continue
        v = np.asarray(context[key], dtype=float)
        if v.shape != (len(q),) or not np.all(np.isfinite(v)) or np.ptp(v) == 0:
            continue
        cols.append(v)
        names.append(key)
    return np.stack(cols, axis=1), tuple(names)


def joint1_rotation(robot, q):
    """The rotation (n, 3, 3) of the frame after joint 1 (nominal model) at poses q (n, N)."""
    from campaign.model.kinematics import frames

    R, _ = frames(robot, q)
    return R[:, robot.joint_frame_index[0]]


def tool_rotation(robot, q):
    """The rotation (n, 3, 3) of the tool frame (nominal model) at poses q (n, N)."""
    from campaign.model.kinematics import forward

    return forward(robot, q)[:, :3, :3]


def residual_in_joint1_frame(robot, q, dt, R1=None):
    """Position residuals dt (n, 3) resolved in the frame after joint 1 (nominal), so that an
    effect inside the arm does not appear to depend on q1 merely because the arm turns;
    R1: :func:`joint1_rotation` at q, when the caller has it."""
    R1 = joint1_rotation(robot, q) if R1 is None else R1
    return np.einsum("nji,nj->ni", R1, dt)


def candidate_specs(candidates, current, run_dir, robot=None):
    """Candidate specs: the built-ins and installed entry points not in the model, or those given.
    A joint-indexed effect already in the model stays a candidate (over the joints it lacks) when
    ``robot`` is given."""
    if candidates is None:
        specs = list(available()) + sorted(set(entry_point_effects()) - set(available()))
    else:
        specs = [resolve_effect_spec(s) for s in parse_effect_list(candidates, "--candidates")]
        for spec in specs if robot is not None else ():  # a joint the robot lacks or named twice: one line
            make_effect(spec, robot)
    current_names = {effect_class(e).name for e in current}
    out = []
    for s in specs:
        if s in current:
            continue
        if effect_class(s).name not in current_names:
            out.append(s)
        elif robot is not None and searches_joints(s, robot):
            if len(model_joints(current, s, robot)) < robot.n_joints:
                out.append(s)
        elif robot is not None and split_joints(s)[1] is not None:  # given over joints: those the model lacks
            lacks = [j for j in split_joints(s)[1] if j not in model_joints(current, s, robot)]
            if lacks:
                out.append(joint_spec(split_joints(s)[0], lacks))
    return out


def current_model_effects(run_dir) -> tuple:
    """(effects of the current model, a note or None): the effects the run's last calibration
    fitted (its params.yaml: `calibrate --effects` leaves campaign.yaml as it is), or campaign.yaml's
    when the run is not calibrated; the note says so when the two differ."""
    run = RunFolder(run_dir)
    configured = run.effects
    last = run.last_calibration()
    if last is None or set(last["effects"]) == set(configured):
        return configured, None
    fitted = last["effects"]

    def words(specs):
        return "geometric" + "".join(f" + {e}" for e in specs)

    return fitted, (f"the last calibration ({last['calibration_id']}) fitted {words(fitted)}, while "
                    f"{run.config_path} enables {', '.join(configured) or 'no effect'}: diagnosing the "
                    f"calibrated model (`campaign calibrate {run_dir}` without --effects fits campaign.yaml's)")


@dataclass(frozen=True)
class DiagnosisData:
    """A run's training poses as the current model sees them, and how they are folded."""

    run_dir: Path
    robot: object
    poses: object  # MeasuredPoses, registered into F_I at the measured point
    is_test: np.ndarray
    tr: np.ndarray  # training-pose indices
    context: dict
    rule: FoldRule
    fit_rule: FoldRule
    fold: np.ndarray  # (len(tr),) fold index of each training pose
    base: object  # BaseParameters
    current: tuple
    n_current: int
    model_note: str | None = None
    #: the candidate specs (:func:`candidate_specs`)
    candidates: tuple = ()
    #: the map of readings in the tracker's frame into the registered robot frame, or None
    tracker_to_robot: np.ndarray | None = None
    #: a run measured on more than one cell: its CellDecision (campaign.identify.cells), poses mapped
    cells: object = None

    @property
    def position_only(self) -> bool:
        return not self.poses.has_orientation

    @property
    def folds(self) -> int:
        return self.rule.k

    def subset(self, idx):
        """(q, T_IE, context) of the poses ``idx``."""
        return self.poses.q[idx], self.poses.T_IE[idx], {key: v[idx] for key, v in self.context.items()}

    def fold_data(self, k):
        """(q, T_IE, context) of fold k's fitting poses, then of its held-out poses."""
        return (*self.subset(self.tr[self.fold != k]), *self.subset(self.tr[self.fold == k]))


def without_faults(run: RunFolder, poses) -> tuple:
    """(the poses without the reading faults the run's last calibration left out, their ids)."""
    faults = np.isin(poses.pose_id, (run.last_calibration() or {}).get("excluded_pose_ids") or ())
    return (poses.subset(np.flatnonzero(~faults)) if faults.any() else poses), poses.pose_id[faults]


def load_data(run_dir, effects, candidates, folds, say, cell_segment=None) -> DiagnosisData:
    """The run's poses (those with a pose), its calibrate split, the current model's effects, the
    candidates and the folds; one line when the poses are too few for every fold fit."""
    from campaign.plan.selection import base_pose_id

    run = RunFolder(run_dir)
    robot = run.robot()
    model_note = None
    if effects is None:
        current, model_note = current_model_effects(run_dir)
    else:
        current = tuple(resolve_effect_spec(e) for e in parse_effect_list(effects))
    if model_note:
        say(model_note)
    specs = tuple(candidate_specs(candidates, current, run_dir, robot))  # a bad name: one line before any work
    with run.store() as store:
        poses, faults = without_faults(run, store.load_measured(include_unusable=True))
    if len(faults):  # reading faults calibrate left out (campaign.identify.outliers)
        say(f"poses {', '.join(str(int(i)) for i in faults)}: reading faults the last calibration "
            "left out, left out here too")
    usable = np.isfinite(poses.T_IE[:, :3, 3]).all(axis=1)
    if not usable.any():
        raise DataError(f"{run_dir}: diagnose compares fits of poses, and no pose has three reflectors seen "
                        "(raw reflectors); `campaign calibrate` identifies these data from the reflectors' positions")
    if not usable.all():  # raw reflectors: the candidates are compared on poses
        say(f"{int((~usable).sum())} of {len(poses)} poses have fewer than three reflectors seen: left out "
            "(diagnose compares fits of poses)")
        poses = poses.subset(np.flatnonzero(usable))
    is_test = run_split(run_dir, poses.pose_id)  # calibrate's test set (a plan's validation poses)
    cells = decide_cells(run_dir, robot, poses, ~is_test, run.cell_segments(), effects=current,
                         cell_segment=cell_segment, say=say)  # several cells: as calibrate models them
    if cells is not None:
        poses, kept = cells.apply(poses)
        is_test = is_test[kept]
        say(cells.line())
    poses, robot, tracker = prepare_measured(robot, poses, ~is_test)  # as calibrate's model sees them
    tr = np.flatnonzero(~is_test)
    rule = choose_folds(len(np.unique(base_pose_id(poses.pose_id[tr]))), folds)
    n_current = sum(make_effect(e, robot).n_params for e in current)
    # every fold fit must identify the model: distinct poses, the smallest fold fit (the same rule)
    n_distinct = distinct_poses(poses.q[tr])
    fit_rule = replace(rule, n_poses=n_distinct, k=n_distinct if rule.leave_one_out else rule.k)
    check_pose_count(run_dir, robot, n_distinct, int(is_test.sum()), not poses.has_orientation,
                     n_effect_params=n_current, fold_rule=fit_rule, validation=validation_file(run_dir).is_file())
    say(f"folds: {folds_text(rule.k, len(tr), rule)}")
    return DiagnosisData(Path(run_dir), robot, poses, is_test, tr, effect_context(poses.context, poses.time_s), rule,
                         fit_rule, pose_folds(poses.pose_id[tr], rule.k),
                         base_parameters(robot, position_only=not poses.has_orientation), tuple(current), n_current,
                         model_note, specs, tracker_to_robot(tracker), cells)


@dataclass(frozen=True)
class CurrentFits:
    """The current model on the whole training set and on each fold: held-out position errors
    ``before`` (n,) mm and residuals ``dz`` (n, 3) m, each fold model's own residual at its fitting
    poses, its held-out position Jacobian, and its position variance at the held-out poses (m²)."""

    full: object
    models: dict
    before: np.ndarray
    dz: np.ndarray
    fit_residuals: dict
    heldout_jacobians: dict
    model_var: np.ndarray
    #: the held-out rotation residual (n, 3) rad and each fold model's at its fitting poses (None: position only)
    dphi: np.ndarray | None = None
    fit_rotation: dict | None = None

    @property
    def heldout_mean_mm(self) -> float:
        return float(self.before.mean())


def fit_current(data: DiagnosisData, say) -> CurrentFits:
    """The current model fitted on all training poses, then on each fold (from the full fit's values
    and noise weights: a few LM steps each), predicting the held-out fold."""
    say("current model on the whole training set")
    full = CalibrationModel(robot=data.robot, effects=list(data.current), position_only=data.position_only).fit(
        *data.subset(data.tr), base=data.base)
    noise = full.noise_sigma_
    say(f"current model on {data.folds} folds")
    n = len(data.tr)
    before, dz_before, model_var = np.empty(n), np.empty((n, 3)), np.zeros(n)
    dphi = None if data.position_only else np.empty((n, 3))
    models, fit_res, jac, fit_rot = {}, {}, {}, {}
    for k in range(data.folds):
        q_fit, T_fit, ctx_fit, q_out, T_out, ctx_out = data.fold_data(k)
        m = CalibrationModel(robot=data.robot, effects=list(data.current), estimate_noise=False,
                             position_only=data.position_only, sigma_position_m=noise["position_m"],
                             sigma_orientation_rad=noise["orientation_rad"] or 1e-4)
        m.fit(q_fit, T_fit, ctx_fit, base=data.base, init=full.values_,
              init_jacobian=full.jacobian_at_fit_[data.fold != k])
        dz = m.residuals(q_out, T_out, ctx_out)
        out = data.fold == k
        before[out] = np.linalg.norm(dz[:, :3], axis=1) * 1e3
        dz_before[out] = dz[:, :3]
        fit_res[k] = m.residual_at_fit_[:, :3]  # m.residuals(q_fit, T_fit, ctx_fit), kept by the fit
        if dphi is not None:
            dphi[out] = dz[:, 3:6]
            fit_rot[k] = m.residual_at_fit_[:, 3:6]
        models[k] = m
        J = m.jacobian(q_out, T_out, ctx_out)[:, :3, :]
        jac[k] = J
        C = m.covariance_ / max(m.variance_factor_, 1e-300)  # the covariance of the fit's own weights
        model_var[out] = np.einsum("nap,pq,naq->n", J, C, J)
    return CurrentFits(full, models, before, dz_before, fit_res, jac, model_var, dphi,
                       None if dphi is None else fit_rot)


@dataclass(frozen=True)
class FloorVerdict:
    """How far the current model is from the floor: the floor, at it or not (None: no floor), the
    detection limit a gain must reach, what a correct model reaches over the noise, and whether the
    measurements are noise-free and the model fits them to round-off."""

    floor: NoiseFloor
    at_floor: bool | None
    detection: float
    expected: float
    round_off: bool = False


def judge_floor(data: DiagnosisData, fits: CurrentFits) -> FloorVerdict:
    """The floor (repeats, else the stated noise) and where the held-out mean stands against it."""
    floor = noise_floor(data.run_dir, data.poses, data.robot)
    expected = expected_heldout_ratio(fits.model_var, fits.full.noise_sigma_["position_m"])
    held_mean = fits.heldout_mean_mm
    if held_mean <= ZERO_NOISE_MODEL_ATOL_M * 1e3:  # exact data (a model's own predictions, a perfect
        # adapter) at round-off, whatever the floor: no structure can be told from round-off
        return FloorVerdict(floor, True, MIN_RELATIVE_GAIN, expected, round_off=True)
    if not floor.known:
        return FloorVerdict(floor, None, MIN_RELATIVE_GAIN, expected)
    if not floor.mean_position_mm > 0:  # noise-free measurements: at the floor means at the fit's round-off
        at = held_mean <= ZERO_NOISE_MODEL_ATOL_M * 1e3
        return FloorVerdict(floor, at, MIN_RELATIVE_GAIN, expected, round_off=at)
    # a correct model's own estimation error (few poses), then the floor's uncertainty and the
    # sampling error of the held-out mean, combined
    held_unc = float(fits.before.std() / max(held_mean, 1e-300) / np.sqrt(len(fits.before)))
    threshold = max(1.0 + AT_FLOOR_MARGIN, expected) + FLOOR_UNCERTAINTIES * float(
        np.hypot(floor.relative_uncertainty, held_unc))
    at = held_mean / floor.mean_position_mm <= threshold
    # at the floor a gain must exceed what the floor's own uncertainty allows
    detection = max(MIN_RELATIVE_GAIN, 1.0 - 1.0 / threshold) if at else MIN_RELATIVE_GAIN
    return FloorVerdict(floor, at, detection, expected)


def find_structure(data: DiagnosisData, fits: CurrentFits, detection: float, run: bool, say) -> tuple:
    """The model-free test on the held-out residuals: (inputs X, their names, the held-out residual
    in the frame after joint 1, the fold fits' residuals in that frame, StructureResult or None).
    The test is run on the residuals in the frame after joint 1 and in the tool frame
    (:func:`pose_or_all_structure`)."""
    q_tr = data.poses.q[data.tr]
    X, input_names = regressor_inputs(q_tr, {key: v[data.tr] for key, v in data.context.items()})
    R1 = joint1_rotation(data.robot, q_tr)  # each training pose's, for the held-out and the fold fits' residuals
    r_out = residual_in_joint1_frame(data.robot, q_tr, fits.dz, R1)
    if not run:
        return X, input_names, r_out, None, None
    say("model-free structure test (flexible regressor on the same folds)")
    r_fit = {k: residual_in_joint1_frame(data.robot, q_tr[data.fold != k], fits.fit_residuals[k], R1[data.fold != k])
             for k in fits.fit_residuals}
    RE = tool_rotation(data.robot, q_tr)
    r_out_E = np.einsum("nji,nj->ni", RE, fits.dz)
    r_fit_E = {k: np.einsum("nji,nj->ni", RE[data.fold != k], fits.fit_residuals[k]) for k in fits.fit_residuals}
    return X, input_names, r_out, r_fit, pose_or_all_structure(X, input_names, q_tr.shape[1], data.fold,
                                                               [(r_fit, r_out), (r_fit_E, r_out_E)])


def find_chain(data: DiagnosisData, fits: CurrentFits, X, input_names, detection: float, run: bool, say):
    """Where in the chain the error arises: the model-free test on the held-out rotation residual in
    the frame after each joint (:mod:`campaign.diagnose.chain`), or None (not run, or no rotation:
    fewer than three reflectors per pose)."""
    if not run or fits.dphi is None:
        return None
    from campaign.diagnose.chain import chain_structure
    from campaign.model.kinematics import frames

    say("model-free test on the rotation error, in the frame after each joint")
    q_tr = data.poses.q[data.tr]
    R, _ = frames(data.robot, q_tr)
    R_joints = R[:, list(data.robot.joint_frame_index)]
    return chain_structure(R_joints, X, input_names, q_tr.shape[1], data.fold, fits.fit_rotation, fits.dphi,
                           alpha=ALPHA, detection=detection)


def score_candidates(data: DiagnosisData, fits: CurrentFits, specs, detection: float, say, chain=None) -> tuple:
    """Every candidate fitted with the current model on the folds, scored on the held-out poses
    (joint-indexed ones over the joints :func:`campaign.diagnose.joints.search_joints` finds; those
    :func:`rotation_veto` takes out of the significant ones with the rotation test ``chain``):
    (scores best first, skipped (effect, reason), the fold linearisations or None)."""
    scores, skipped, errors = [], [], {}
    n_cand = max(len(specs), 1)
    ss_before = float(np.sum((fits.dz - fits.dz.mean(axis=0)) ** 2))
    rot_before = None if fits.dphi is None else np.linalg.norm(fits.dphi, axis=1) * 1e3
    rot_before_mean = np.nan if rot_before is None else float(rot_before.mean())
    lins = {}

    def fit_spec(spec, effect=None):
        """(after (n,) mm, dz_after (n, 3), absorbed names, fully absorbed, rotation error after (n,) mrad
        or None) of one spec (or ``effect``) on the folds."""
        if not lins:  # the current model linearised at each fold's optimum, shared by every candidate
            lins.update({k: linearise(fits.models[k], *data.fold_data(k)[:3]) for k in range(data.folds)})
        effect = effect or make_effect(spec, data.robot)
        after, dz_after, absorbed = np.empty(len(data.tr)), np.empty((len(data.tr), 3)), set()
        rot_after = None if data.position_only else np.empty(len(data.tr))
        for k in range(data.folds):
            fit = fit_candidate(lins[k], effect, *data.fold_data(k))
            after[data.fold == k] = np.linalg.norm(fit.heldout_dz[:, :3], axis=1) * 1e3
            dz_after[data.fold == k] = fit.heldout_dz[:, :3]
            if rot_after is not None:
                rot_after[data.fold == k] = np.linalg.norm(fit.heldout_dz[:, 3:6], axis=1) * 1e3
            absorbed |= set(fit.absorbed)
        return after, dz_after, tuple(sorted(absorbed)), len(absorbed) >= effect.n_params > 0, rot_after

    def one_candidate(i, spec):
        cls = effect_class(spec)
        say(f"candidate {i + 1}/{len(specs)}: {cls.name}")
        reason = _cannot_score(data, spec, cls)
        if reason:
            skipped.append((cls.name, reason))
            say(f"  {cls.name}: skipped ({reason})")
            return
        tried, steps = 1, ()
        if searches_joints(spec, data.robot):
            exclude = model_joints(data.current, spec, data.robot)
            spec, _, steps, tried = search_joints(spec, data.robot,
                                                         lambda s: (lambda r: (r[0], r[3]))(fit_spec(s)),
                                                         exclude, alpha=ALPHA, detection=detection)
            if spec is None:
                skipped.append((cls.name, "no joint's parameters can be identified with the current model"))
                return
        scores.append(score(spec, cls, steps, tried))
        tries[cls.name] = tried
        if takes_joints(cls):
            rivals.append(split_joints(spec)[0])

    def score(spec, cls, steps, tried) -> CandidateScore:
        after, dz_after, absorbed, fully, rot_after = fit_spec(spec)
        p = paired_p(fits.before, after)
        gain = 1 - after.mean() / max(fits.before.mean(), 1e-300)
        r2 = 1 - float(np.sum((dz_after - dz_after.mean(axis=0)) ** 2)) / max(ss_before, 1e-300)
        rot_p_worse = np.nan if rot_after is None else paired_p(rot_after, rot_before)
        significant = (p < ALPHA / (n_cand * tried)) and gain >= detection and not fully
        errors[spec] = (after, make_effect(spec, data.robot).n_params - len(absorbed), max(len(steps), 1))
        return CandidateScore(cls.name, float(fits.before.mean()), float(after.mean()), p, bool(significant),
                              float(r2), absorbed, _describe(cls, spec), spec, steps,
                              heldout_mean_rotation_mrad_before=rot_before_mean,
                              heldout_mean_rotation_mrad_after=np.nan if rot_after is None else float(rot_after.mean()),
                              rotation_p_worse=rot_p_worse)

    def score_with(rest, rival):
        """Held-out errors (n,) mm of the candidate over ``rest`` with ``rival`` fitted beside it, or
        None (the rival cannot act on that joint, the model already holds it there, or it is absorbed)."""
        base, (joint,) = split_joints(rival)
        if joint in model_joints(data.current, base, data.robot):
            return None
        try:
            parts = [make_effect(s, data.robot) for s in (rest, rival) if s is not None]
        except ConfigError:
            return None
        after, _, _, fully, _ = fit_spec(None, combined_effect(data.robot, parts) if len(parts) > 1 else parts[0])
        return None if fully else after

    rivals, tries = [], {}
    for i, spec in enumerate(specs):
        one_candidate(i, spec)
    ranked = settle_rivals(rank(list(rotation_veto(scores, chain)), errors), errors, rivals, score_with,
                           lambda spec, c: score(spec, effect_class(spec), c.joint_steps, tries[c.effect]))
    return ranked, tuple(skipped), (lins or None)


def settle_rivals(ranked, errors, rivals, score_with, rescore) -> tuple:
    """The ranking once the leading candidate's joints are compared with the other joint-indexed
    candidates (``rivals``, bare names) on each of them (:func:`campaign.diagnose.joints.shared_joint_rivals`):
    the joints a rival fits better, or that the poses cannot tell apart from one, are taken out of it
    (``rescore(spec, candidate)`` scores what is left); with none left it is not significant. Repeated
    on the new leader until one keeps its joints (or none is significant)."""
    out = list(ranked)
    for _ in range(2 * len(out)):
        first = out[0] if out else None
        if first is None or not first.significant or not first.joints or first.rivals is not None:
            break
        found = shared_joint_rivals(first.spec, errors[first.spec][0], rivals, score_with)
        lost = contested_joints(found)
        keep = [j for j in first.joints if j not in lost]
        if not lost:
            out[0] = replace(first, rivals=found)
        elif keep:
            out[0] = replace(rescore(joint_spec(split_joints(first.spec)[0], keep), first), rivals=found)
        else:
            out[0] = replace(first, significant=False, rivals=found)
        out = list(rank(out, errors))
    return tuple(out)


def rank(scores: list, errors: dict) -> tuple:
    """The candidates, significant ones first, by held-out error; then the simplest first (fewest
    fitted parameters) among those within the best's selection window of it: one standard error of
    the paired per-pose difference, plus one for each joint a search added after its first (each
    step picked the best of the joints left on the same held-out poses, whose error then flatters
    it by up to about that much; a search over many joints makes a flexible effect fit part of
    another one: cyclic on joints 1, 4 and 5 mimics an elastic ground's tilt, which turns with q1).
    ``errors``: spec -> (held-out errors (n,) mm, fitted parameters, search steps)."""
    scores = sorted(scores, key=lambda c: (not c.significant, c.heldout_mean_position_mm_after))
    if not scores or not scores[0].significant:
        return tuple(scores)
    best, _, steps = errors[scores[0].spec]
    near = []
    for c in scores:
        if not c.significant:
            break
        d = errors[c.spec][0] - best
        se = float(d.std(ddof=1) / np.sqrt(len(d))) if len(d) > 1 else 0.0
        if d.mean() <= steps * se:
            near.append(c)
    first = min(near, key=lambda c: (errors[c.spec][1], c.heldout_mean_position_mm_after))
    return (first, *[c for c in scores if c is not first])


def rotation_veto(scores, chain) -> tuple:
    """The ranking once the candidates that make the held-out rotation error larger (one-sided
    paired p < ALPHA) are not significant: such a candidate fits the position with a rotation the
    robot does not have (cyclic of the UR10's joint 3 took 16 % of the position error of a tilt of
    that axis and made its rotation error 1.1 % worse, p = 0.0004; compliance of the Z1's joints 3
    and 4 took 25 % of a forearm's shear and made it 6 % worse, p = 0.005, where the rotation test
    found nothing). Except where the rotation test (``chain``) finds an error that a candidate
    explains (one takes PARTIAL_ROTATION_SHARE of what the regressor takes of it): a worse rotation
    then says that another effect is missing, not that this one is wrong (an elastic ground beside
    a compliant joint 4: the rotation 5.8 % worse with the ground alone, 81 % better with the
    joint's compliance)."""
    if not scores:
        return tuple(scores)
    if chain is not None and chain.significant:
        explained = max((c.rotation_gain for c in scores if np.isfinite(c.rotation_gain)), default=0.0)
        if explained >= PARTIAL_ROTATION_SHARE * chain.heldout_gain:
            return tuple(scores)
    out = [replace(c, significant=False, rotation_veto=True) if c.significant and c.rotation_p_worse < ALPHA else c
           for c in scores]
    return tuple(out)


def _cannot_score(data: DiagnosisData, spec, cls) -> str | None:
    """Why a candidate cannot be scored on these data (context it needs, too many parameters), or None."""
    lacking = [k for k in getattr(cls, "context_keys", ()) if k not in data.context
               or not np.isfinite(np.asarray(data.context[k], dtype=float)).all()]  # e.g. data without time_s
    if lacking:
        return (f"needs context {', '.join(cls.context_keys)} "
                f"({', '.join(lacking)}: not in the data for every pose)")
    one = joint_spec(spec, [1]) if searches_joints(spec, data.robot) else spec  # a search starts on one joint
    n_params = make_effect(one, data.robot).n_params
    need = training_poses_needed(data.base.n_base + data.n_current + n_params, data.position_only)
    if data.fit_rule.fit_poses < need:
        return (f"its {n_params} parameters need {need} poses in every fold fit "
                f"({equations_per_pose(data.position_only)} equations each), the folds have {data.fit_rule.fit_poses}")
    return None


def _describe(cls, spec) -> str:
    joints = split_joints(spec)[1]
    if joints is None:
        return cls.description
    return f"{cls.description}, on joint{'s' if len(joints) > 1 else ''} {', '.join(map(str, joints))}"


def ranked_inputs(struct, struct_sig: bool, test, chain=None) -> list:
    """The inputs the error left depends on, most important first: the flexible regressor's (when
    its structure is significant), the rotation test's in front of them (when significant and not
    much weaker than the position test: where in the chain the error arises,
    campaign.diagnose.chain.with_rotation_first), time and temperature ranked by the
    time test on the model's residuals (campaign.diagnose.timing.rank_by_time_test: first when the
    same poses moved, out when they did not; time alone when only the test found it). Diagnose's
    and auto's alike."""
    from campaign.diagnose.chain import with_rotation_first

    sig = struct is not None and struct_sig
    inputs = struct.depends_on(MIN_IMPORTANCE_SHARE) if sig else []
    return rank_by_time_test(with_rotation_first(inputs, chain, MIN_IMPORTANCE_SHARE,
                                                 struct.heldout_gain if sig else None), test)


#: the inputs a catalogued effect depends on alone, when that is one kind: the harmonics of cyclic
#: are functions of its own joints' angles, thermal of the temperature, drift of the time
OWN_JOINT_INPUTS = ("cyclic",)
TIME_EFFECTS = ("thermal", "drift")
#: ... unless its held-out error is at most this share of the model-free regressor's: it then finds
#: far more than the regressor, whose ranking of the inputs says little (cyclic of the COMAU's joint
#: 4 moves the tool by a lever that turns with q5, ranked first: 0.026 → 0.0098 mm, below the floor,
#: the regressor 0.023)
BEATS_STRUCTURE_SHARE = 0.5


def leads_to(best, depends_on, structure_after_mm: float | None = None) -> bool:
    """Whether candidate ``best`` (:class:`CandidateScore`) may explain a structure whose inputs
    are ``depends_on`` (most important first; empty: nothing said): an effect that depends on
    known inputs alone must have the first among them. Cyclic of joint 1 fits 6 % of a bearing
    run-out of joint 4 whose structure depends on q4 first; added, it stays in the model and the
    structure then ranks q1 first. A cyclic effect whose held-out mean is at most
    BEATS_STRUCTURE_SHARE of the regressor's (``structure_after_mm``) leads whatever the ranking."""
    if not depends_on:
        return True
    if best.effect in OWN_JOINT_INPUTS and best.joints and structure_after_mm is not None \
            and best.heldout_mean_position_mm_after <= BEATS_STRUCTURE_SHARE * structure_after_mm:
        return True
    if best.effect in OWN_JOINT_INPUTS and best.joints:
        return depends_on[0] in {f"q{j}" for j in best.joints}
    if best.effect in TIME_EFFECTS:
        return depends_on[0] in TIME_INPUTS
    return True


def choose_verdict(scores, struct, struct_sig, fv: FloorVerdict, depends_on=(), time_moved: bool = False,
                   time_effects_fail: bool = False, chain=None):
    """The best significant candidate when it explains the structure (and the structure, when
    significant, depends first on an input the candidate can depend on: :func:`leads_to`), else
    "unexplained" when systematic error remains (the regressor finds it, the same poses moved over
    time as the model does not predict: ``time_moved``, or the model is above the floor), else None
    (module docstring). An effect of time is not the verdict when the same poses still move with
    every candidate effect of time added (``time_effects_fail``). With the rotation test significant
    (``chain``, campaign.diagnose.chain) and the position test not, the candidate must explain the
    rotation error: its held-out rotation error within EXPLAINS_FACTOR of that regressor's."""
    best = scores[0] if scores and scores[0].significant else None
    if best is not None and time_effects_fail and is_time_effect(best.spec or best.effect):
        return "unexplained"
    chain_sig = bool(chain is not None and chain.significant)
    if best is not None:
        reg_after = struct.after.mean() if struct is not None else np.inf
        explains = not struct_sig or best.heldout_mean_position_mm_after <= EXPLAINS_FACTOR * reg_after
        if chain_sig and not struct_sig:  # the rotation test alone finds it: the rotation error must be
            # explained (NaN: not fitted, not explained). With both, the position test decides, as
            # it did alone: two effects hidden at once are named one after the other
            explains = best.heldout_mean_rotation_mrad_after <= EXPLAINS_FACTOR * chain.after_mrad
        if struct_sig or chain_sig:
            explains = explains and leads_to(best, depends_on, reg_after)
        return best.effect if explains else "unexplained"
    if struct_sig or chain_sig or time_moved or (fv.floor.known and not fv.at_floor):
        return "unexplained"
    return None


def is_time_effect(spec) -> bool:
    """An effect of the campaign's time or temperature alone (thermal, drift, a user's warm-up)."""
    keys = tuple(getattr(effect_class(spec), "context_keys", ()))
    return bool(keys) and set(keys) <= set(TIME_INPUTS)


def time_effects_added(scores) -> list:
    """The specs of the significant candidate effects of time (thermal, drift, a user's), best first:
    those a round would add to the model (:func:`time_effects_test`)."""
    return [c.spec or c.effect for c in scores if c.significant and is_time_effect(c.spec or c.effect)]


def time_effects_test(data: DiagnosisData, floor: NoiseFloor, scores, say, timed=None):
    """When the best significant candidate is an effect of time, or the current model holds one and
    the same poses still move with it (``timed``: the time test on the current model's residuals):
    the time test (:func:`run_time_test`) on the residuals of the current model with every
    significant candidate effect of time added (:func:`time_effects_added`), fitted on the training
    poses (``timed`` itself when none is). A drift, a thermal expansion or both move the poses
    measured again as they say; when the poses still move with those the model holds and those it
    would add, none is the answer: not added, and those it holds are taken out
    (:attr:`Diagnosis.time_removal`). Only significant candidates count: a thermal kept because a
    drift that the folds do not find would stop the poses moving stays in a model whose poses move
    (a forearm's warm-up: thermal alone p = 1e-4, with drift p = 0.03). None otherwise."""
    best = scores[0] if scores and scores[0].significant else None
    held = any(is_time_effect(s) for s in data.current) and timed is not None and timed.moved
    if not held and (best is None or not is_time_effect(best.spec or best.effect)):
        return None
    added = time_effects_added(scores)
    if not added:
        return timed if held else None
    say(f"the poses measured again, with {', '.join(effect_class(s).name for s in added)} added")
    model = CalibrationModel(robot=data.robot, effects=[*data.current, *added], position_only=data.position_only)
    model.fit(*data.subset(data.tr), base=data.base)
    return run_time_test(data, floor, model)


def compare_model_joints(data: DiagnosisData, fits: CurrentFits, lins) -> tuple:
    """Each joint of the model's joint-indexed effects against every other joint-indexed candidate
    in its place (the joint's parameters held at zero, the rival fitted on the same folds):
    (:class:`campaign.diagnose.joints.Rival` each, the model being "own"; the swap to make or None)."""
    bases = [split_joints(s)[0] for s in data.candidates if takes_joints(effect_class(s))]
    out = []
    for spec, j, params, own, rival in joint_swaps(data.current, data.robot, bases):
        try:
            effect = make_effect(rival, data.robot)
        except ConfigError:  # the rival cannot act on that joint
            continue
        after, fully = np.empty(len(data.tr)), False
        for k in range(data.folds):
            fit = fit_candidate(lins[k], effect, *data.fold_data(k), hold=param_index(lins[k].model, spec, params))
            after[data.fold == k] = np.linalg.norm(fit.heldout_dz[:, :3], axis=1) * 1e3
            fully |= len(fit.absorbed) >= effect.n_params
        if fully:
            continue
        d = fits.before - after
        se = float(d.std(ddof=1) / np.sqrt(len(d))) if len(d) > 1 else float("inf")
        out.append(Rival(j, own, rival, float(fits.before.mean()), float(after.mean()), se))
    wins = [r for r in out if r.outcome == "rival"]
    if not wins:
        return tuple(out), None
    r = max(wins, key=lambda r: (r.own_mm - r.rival_mm) / max(r.diff_se_mm, 1e-300))
    base = split_joints(r.own)[0]
    after = [s if split_joints(s)[0] != base else without_joints(s, [r.joint], data.robot) for s in data.current]
    return tuple(out), (r, merge_effects([s for s in after if s is not None], [r.rival], data.robot))


def absent_in_time(specs, test) -> tuple:
    """(the specs kept, (effect, reason) of those the time test says are absent): an effect of the
    campaign's time alone (its context is ``time_s``: drift, a user's warm-up) moves a pose measured
    again later; when the time test (campaign.diagnose.timing.TimeTest) finds that those poses did
    not move, the effect is not in the data, and fitting it would only lend time the structure of
    the poses the tour sweeps. Without a test (no pose measured again), every spec is kept."""
    if test is None or test.moved:
        return tuple(specs), ()
    kept, absent = [], []
    for spec in specs:
        cls = effect_class(spec)
        if tuple(getattr(cls, "context_keys", ())) == ("time_s",):
            absent.append((cls.name, f"the re-measured poses did not move, p = {test.p_value:.2g} ({test.poses} "
                                     f"pose{'' if test.poses == 1 else 's'} measured again over {test.span_h:.2g} h, "
                                     f"{test.readings} readings): no effect of time to fit"))
        else:
            kept.append(spec)
    return tuple(kept), tuple(absent)


def run_time_test(data: DiagnosisData, floor: NoiseFloor, model=None, struct=None):
    """The time test (campaign.diagnose.timing) on every pose of the run measured at different
    times, against the noise of readings close in time (or the stated tracker noise); None without
    either: a floor from readings far apart holds the very changes over time the test looks for.

    ``model`` (the current model fitted on the training poses): the test runs on its residuals, so
    it asks whether the same poses moved in a way the model does not predict. A model without
    effects of time predicts the same position at each visit (the readings' own changes are
    tested); one with thermal or drift predicts how they move, and a warm-up of one link, which
    moves each pose its own way, still shows. ``struct`` (the flexible regressor's result, when it
    depends on time or temperature): the test's power against the change over time it predicts at
    these very readings (:func:`time_test_power`)."""
    if floor.known and floor.upper_bound:
        stated = RunFolder(data.run_dir).config.tracker.noise_m
        P_E = data.robot.reflector_positions_in_E
        floor = floor_from_stated(stated, P_E) if stated is not None and len(P_E) >= 3 else NoiseFloor("none")
    if not floor.known:
        return None
    readings = drift_readings(data.run_dir, data.poses, data.tracker_to_robot, data.cells)
    xyz, group, t, pose, context = time_readings(data, readings)
    keep = np.ones(len(t), dtype=bool)
    if model is not None and len(t):
        xyz = xyz - model.predict(data.poses.q[pose], context)[:, :3, 3]
        keep = np.isfinite(xyz).all(axis=1)  # readings the model cannot predict (no context then) left out
    legacy = readings["legacy"]
    test = time_test(xyz[keep], group[keep], t[keep], floor.sigma_position_m,
                     sigma_dof=3 * floor.dof if floor.source == "repeats" else 0,
                     drift_check_m=None if legacy is None else list(legacy[1]), alpha=ALPHA)
    if test is None or struct is None:
        return test
    sub = {key: v[keep] for key, v in context.items()}
    return replace(test, power=time_test_power(data.poses.q[pose[keep]], sub, group[keep], struct, floor.sigma_position_m,
                                               ALPHA))


def time_test_power(q, context, group, struct, sigma_position_m, alpha: float) -> float | None:
    """The probability that the time test sees the change over time the flexible regressor
    predicts at its readings (joints q (k, N), context with ``time_s``, pose labels ``group``): the
    regressor's mean prediction over its fold models, tested as noise-free readings, gives the χ²
    statistic's non-centrality λ; the power is P(χ²(dof, λ) > the α critical value). A time test
    that would probably miss that change says nothing when it finds no movement. None without
    readings at two times."""
    from scipy import stats

    cols = []
    for name in struct.input_names:
        if name.startswith("q") and name[1:].isdigit():
            cols.append(np.asarray(q, dtype=float)[:, int(name[1:]) - 1])
        else:
            cols.append(np.asarray(context.get(name, np.full(len(q), np.nan)), dtype=float))
    X = np.stack(cols, axis=1)
    if not len(X) or not np.isfinite(X).all() or not struct.models:
        return None
    pred = np.mean([m.predict(X) for m in struct.models.values()], axis=0)
    expected = time_test(pred, group, context["time_s"], sigma_position_m)
    if expected is None:
        return None
    critical = stats.chi2.ppf(1.0 - alpha, expected.dof)
    return float(stats.ncx2.sf(critical, expected.dof, max(expected.statistic, 1e-12)))


def time_readings(data: DiagnosisData, readings: dict) -> tuple:
    """The readings of the poses measured at different times (the repeats and poses measured again,
    the reference pose with its drift checks: ``readings`` of
    :func:`campaign.measure.drift.drift_readings`) as (position (k, 3) m, pose label (k,), time (k,)
    s, the index of the stored pose whose joints each measured (k,), the context at each: a stored
    pose's own, a drift check's (e.g. the temperature) interpolated in time from the poses measured
    around it, and ``time_s``)."""
    xyz, group, t = [np.zeros((0, 3))], [np.zeros(0, dtype=np.int64)], [np.zeros(0)]
    if readings["repeats"] is not None:
        t_r, xyz_r, g_r = readings["repeats"]
        xyz.append(xyz_r), group.append(np.asarray(g_r, dtype=np.int64)), t.append(t_r)
    if readings["monitor"] is not None:  # the reference pose, its drift checks among its readings
        t_m, xyz_m = readings["monitor"]
        xyz.append(xyz_m), group.append(readings["monitor_group"]), t.append(t_m)
    xyz, group, t = np.concatenate(xyz), np.concatenate(group), np.concatenate(t)
    poses = data.poses
    t_all = np.asarray(poses.time_s, dtype=float)
    # each reading that is a stored pose (its time and position), else a drift check of the reference pose
    at = {(float(s), *map(float, p)): i for i, (s, p) in enumerate(zip(t_all, poses.xyz))}
    stored = np.array([at.get((float(s), *map(float, p)), -1) for s, p in zip(t, xyz)], dtype=int)
    pose = stored.copy()
    if (stored < 0).any():
        with RunFolder(data.run_dir).store() as store:
            ref = store.get_meta("drift_reference")
        pose[stored < 0] = np.flatnonzero(np.asarray(poses.pose_id) == ref["pose_id"])[0]
    context = {"time_s": t}
    for key, v in data.context.items():  # the cell's state at each reading: a stored pose's own, else
        if key == "time_s":  # from the poses measured around it
            continue
        v = np.asarray(v, dtype=float)
        ok = np.isfinite(v) & np.isfinite(t_all)
        order = np.argsort(t_all[ok], kind="stable")
        c = np.interp(t, t_all[ok][order], v[ok][order]) if ok.any() else np.full(len(t), np.nan)
        c[stored >= 0] = v[stored[stored >= 0]]
        context[key] = c
    return xyz, group, t, pose, context


def diagnose(run_dir, *, effects=None, candidates=None, folds: int | None = None, progress=None,
             structure: bool = True, cell_segment: int | None = None) -> Diagnosis:
    """Diagnose a run's current model: noise floor, model-free structure test, time test, candidate
    ranking over the joints each acts on, and each current effect's contribution.

    folds: held-out folds of the training poses; None: from the data
    (:func:`campaign.identify.split.choose_folds`: leave-one-out below 60 training poses, else 5).
    Too few poses for every fold fit to identify the current model is one line saying how many
    are needed; a candidate whose parameters the fold fits cannot identify is skipped (and said).
    cell_segment: ``--cell-segment N`` of a run measured on more than one cell (campaign.identify.cells)."""
    say = progress or (lambda msg: None)
    data = load_data(Path(run_dir), effects, candidates, folds, say, cell_segment)
    fits = fit_current(data, say)
    fv = judge_floor(data, fits)
    X, input_names, r_out, r_fit, struct = find_structure(data, fits, fv.detection, structure and not fv.round_off, say)
    struct_sig = bool(struct is not None and struct.p_value < ALPHA and struct.heldout_gain >= fv.detection)
    chain = find_chain(data, fits, X, input_names, fv.detection, structure and not fv.round_off, say)
    chain_sig = bool(chain is not None and chain.significant)
    timed = run_time_test(data, fv.floor, fits.full, struct if struct_sig else None)
    time_moved = bool(timed is not None and timed.moved)
    # structure found, or poses that moved as the model does not predict, are above the noise
    at_floor = False if ((struct_sig or chain_sig or time_moved) and fv.at_floor) else fv.at_floor
    residuals = fits.full.residuals(data.poses.q, data.poses.T_IE, data.context)
    tested = test_set_check(data, fits, residuals)
    if tested is not None and not tested.holds and fv.at_floor:  # at the floor on the folds only
        say(tested.text())
        at_floor, fv = False, replace(fv, at_floor=False)
    specs, absent = absent_in_time(() if fv.round_off else data.candidates, timed)  # time the poses deny
    for name, reason in absent:
        say(f"{name}: {reason}")
    scores, skipped, lins = score_candidates(data, fits, specs, fv.detection, say, chain)
    skipped = absent + skipped
    timed_all = time_effects_test(data, fv.floor, scores, say, timed)
    if data.current and not fv.round_off:
        if lins is None:
            lins = {k: linearise(fits.models[k], *data.fold_data(k)[:3]) for k in range(data.folds)}
        say("each current effect's contribution (taken out on the folds)")
        contrib = contributions(data.current, data.robot, [(lins[k], fits.heldout_jacobians[k])
                                                            for k in range(data.folds)],
                                fits.before, fits.dz, data.fold)
        say("each joint of the current effects against the other effects in its place")
        model_rivals, swap = compare_model_joints(data, fits, lins)
    else:
        contrib, model_rivals, swap = (), (), None
    depends = ranked_inputs(struct, struct_sig, timed, chain)  # time and temperature as the time test ranks them
    signature = None
    if struct_sig:
        from campaign.diagnose.signature import describe

        say("signature of the structure (periodicity, time, gravity load)")
        signature = describe(data.robot, data.poses.q[data.tr], X, input_names, struct, depends, r_out,
                             data.poses.time_s[data.tr], residual_fit=r_fit)
    return Diagnosis(data.run_dir, data.current, scores,
                     choose_verdict(scores, struct, struct_sig, fv, depends, time_moved,
                                    bool(timed_all is not None and timed_all.moved), chain),
                     len(data.tr),
                     data.folds, residuals, data.is_test, fv.floor, fits.heldout_mean_mm, struct, struct_sig,
                     fv.detection, at_floor, signature, data.tr, X, r_out, data.rule, skipped, fv.expected,
                     fold_pose_ids(data.poses.pose_id[data.tr], data.fold, data.folds),
                     measured_drift(data.run_dir, data.poses, fv.floor, data.tracker_to_robot, data.cells),
                     data.model_note, contrib, timed, fv.round_off, data.cells, model_rivals, swap, tested,
                     data.poses.pose_id, timed_all, chain)


def test_set_check(data: DiagnosisData, fits: CurrentFits, residuals):
    """The current model (fitted on every training pose) on the test set against its held-out
    folds (campaign.diagnose.testset); None without a test set."""
    from campaign.diagnose.testset import check_test_set

    if not data.is_test.any():
        return None
    e_test = np.linalg.norm(residuals[data.is_test, :3], axis=1) * 1e3
    return check_test_set(e_test, fits.before, data.poses.q[data.tr], data.poses.q[data.is_test])
