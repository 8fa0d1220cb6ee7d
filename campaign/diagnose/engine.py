"""Where does the model fail, how far is it from the measurement noise, and what is missing?

For a run, the *current model* is the geometric model plus the effects enabled in the run's
campaign.yaml (or given). On the training part of the fixed 80/20 split, K folds: for each
fold the current model is fitted on the other folds and predicts the held-out fold. Three
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
from scipy import stats

from campaign.diagnose.candidates import fit_candidate, linearise
from campaign.effects.base import (available, effect_class, effect_context, entry_point_effects, make_effect,
                                   parse_effect_list, resolve_effect_spec)
from campaign.errors import DataError
from campaign.identify.calibrate import (check_pose_count, distinct_poses, equations_per_pose,
                                         load_robot_for_run, training_poses_needed)
from campaign.identify.solver import CalibrationModel
from campaign.identify.split import FoldRule, choose_folds, run_split, train_test_split, validation_file
from campaign.measure.drift import Drift, measured_drift
from campaign.measure.floor import NoiseFloor, noise_floor, times_the_noise
from campaign.measure.store import open_run
from campaign.model.base_params import base_parameters
from campaign.run import RunFolder
from campaign.tolerances import ZERO_NOISE_MODEL_ATOL_M

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

    @property
    def gain(self) -> float:
        return 1 - self.heldout_mean_position_mm_after / max(self.heldout_mean_position_mm_before, 1e-300)

    def as_json(self) -> dict:
        return {
            "effect": self.effect,
            "spec": self.spec or self.effect,
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

    @property
    def model_to_noise(self) -> float | None:
        """Held-out mean over the floor; None without a floor or for a floor of exactly 0."""
        return self.floor.ratio(self.heldout_mean_position_mm)

    @property
    def depends_on(self) -> list:
        if self.structure is None:
            return []
        return self.structure.depends_on(MIN_IMPORTANCE_SHARE) if self.structure_significant else []

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
            },
            "current_effects": list(self.current_effects),
            "model_note": self.model_note,
            "config_line": config_line(self.current_effects, self._verdict_spec()),
            "folds": self.folds,
            "fold_rule": None if self.fold_rule is None else self.fold_rule.as_json(),
            "fold_pose_ids": [list(ids) for ids in self.fold_pose_ids],
            "skipped_candidates": [{"effect": e, "reason": r} for e, r in self.skipped],
            "n_train_poses": self.n_train,
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
            out += "\n  depends on " + ", ".join(f"{k} ({100 * s.importance[k]:.0f} %)" for k in self.depends_on)
        return out

    def text(self) -> str:
        lines = [f"current model: geometric" + "".join(f" + {e}" for e in self.current_effects),
                 *([f"  {self.model_note}"] if self.model_note else []),
                 f"candidates scored on {folds_text(self.folds, self.n_train, self.fold_rule)} (test set untouched):",
                 "",
                 f"{'effect':<20}{'before mm':>11}{'after mm':>11}{'gain':>8}{'R²':>7}{'p':>10}  significant"]
        for c in self.ranking:
            note = " (absorbed: " + ", ".join(c.absorbed) + ")" if c.absorbed else ""
            lines.append(f"{c.effect:<20}{c.heldout_mean_position_mm_before:>11.4f}{c.heldout_mean_position_mm_after:>11.4f}"
                         f"{100 * c.gain:>7.1f}%{c.r2:>7.2f}{c.p_value:>10.2g}  {'yes' if c.significant else 'no'}{note}")
        for effect, reason in self.skipped:
            lines.append(f"{effect:<20}skipped: {reason}")
        lines += ["", self.floor_line(), self.structure_line()]
        if self.signature is not None and self.structure_significant:
            lines.append("  signature: " + self.signature.text())
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
    return f"effects: [{', '.join([*current, verdict_spec])}]"


#: the line diagnose ends with when the model is at the noise floor and nothing is found
AT_NOISE_TEXT = "verdict: at the measurement noise: nothing left to find."


def verdict_text(d: Diagnosis) -> str:
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
            return (f"verdict: unexplained — systematic error remains that no candidate explains: {words}.{extra}\n"
                    f"  write an effect for it (docs/effects.md) and add it to {d.run_dir}/campaign.yaml")
        return (f"verdict: unexplained — the model's cross-validated mean {d.heldout_mean_position_mm:.4g} mm is "
                f"{times_the_noise(d.heldout_mean_position_mm, d.floor.mean_position_mm).lstrip('= ')}, but neither a "
                "candidate nor the regressor finds on which input the rest depends (a pose-to-pose error the inputs "
                "do not carry, or a floor that is too low)")
    c = next(c for c in d.ranking if c.effect == d.verdict)
    return (f"verdict: add {c.effect} ({c.description}).\n"
            f"  the held-out residual follows it: R² {c.r2:.2f}; cross-validated mean position error (the folds) "
            f"{c.heldout_mean_position_mm_before:.4f} → {c.heldout_mean_position_mm_after:.4f} mm (p = {c.p_value:.2g}).\n"
            f"  add to {d.run_dir}/campaign.yaml:   {config_line(d.current_effects, c.spec or c.effect)}\n"
            f"  or run:   campaign calibrate {d.run_dir} --effects {','.join([*d.current_effects, c.spec or c.effect])}")


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


def residual_in_joint1_frame(robot, q, dt, R1=None):
    """Position residuals dt (n, 3) resolved in the frame after joint 1 (nominal), so that an
    effect inside the arm does not appear to depend on q1 merely because the arm turns;
    R1: :func:`joint1_rotation` at q, when the caller has it."""
    R1 = joint1_rotation(robot, q) if R1 is None else R1
    return np.einsum("nji,nj->ni", R1, dt)


def candidate_specs(candidates, current, run_dir):
    """Candidate specs: the built-ins and installed entry points not in the model, or those given."""
    if candidates is None:
        specs = list(available()) + sorted(set(entry_point_effects()) - set(available()))
    else:
        specs = [resolve_effect_spec(s) for s in parse_effect_list(candidates, "--candidates")]
    current_names = {effect_class(e).name for e in current}
    return [s for s in specs if s not in current and effect_class(s).name not in current_names]


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


def diagnose(run_dir, *, effects=None, candidates=None, folds: int | None = None, progress=None,
             structure: bool = True) -> Diagnosis:
    """Diagnose a run's current model: noise floor, model-free structure test, candidate ranking.

    folds: held-out folds of the training poses; None: from the data
    (:func:`campaign.identify.split.choose_folds`: leave-one-out below 60 training poses, else 5).
    Too few poses for every fold fit to identify the current model is one line saying how many
    are needed; a candidate whose parameters the fold fits cannot identify is skipped (and said)."""
    run_dir = Path(run_dir)
    say = progress or (lambda msg: None)
    robot = load_robot_for_run(run_dir)
    model_note = None
    if effects is None:
        current, model_note = current_model_effects(run_dir)
    else:
        current = tuple(resolve_effect_spec(e) for e in parse_effect_list(effects))
    if model_note:
        say(model_note)
    names = candidate_specs(candidates, current, run_dir)
    with open_run(run_dir) as store:
        poses = store.load_measured(include_unusable=True)
    usable = np.isfinite(poses.T_IE[:, :3, 3]).all(axis=1)
    if not usable.any():
        raise DataError(f"{run_dir}: diagnose compares fits of poses, and no pose has three reflectors seen "
                        "(raw reflectors); `campaign calibrate` identifies these data from the reflectors' positions")
    if not usable.all():  # raw reflectors: the candidates are compared on poses
        say(f"{int((~usable).sum())} of {len(poses)} poses have fewer than three reflectors seen: left out "
            "(diagnose compares fits of poses)")
        poses = poses.subset(np.flatnonzero(usable))
    is_test = run_split(run_dir, poses.pose_id)  # calibrate's test set (a plan's validation poses)
    # the data as calibrate's model sees them: registered from the tracker's frame, at the measured point
    from campaign.identify.calibrate import prepare_measured, tracker_to_robot

    poses, robot, tracker = prepare_measured(robot, poses, ~is_test)
    position_only = not poses.has_orientation
    tr = np.flatnonzero(~is_test)
    from campaign.plan.selection import base_pose_id

    rule = choose_folds(len(np.unique(base_pose_id(poses.pose_id[tr]))), folds)
    folds = rule.k
    n_current = sum(make_effect(e, robot).n_params for e in current)
    # every fold fit must identify the model: distinct poses, the smallest fold fit (the same rule)
    n_distinct = distinct_poses(poses.q[tr])
    fit_rule = replace(rule, n_poses=n_distinct, k=n_distinct if rule.leave_one_out else rule.k)
    check_pose_count(run_dir, robot, n_distinct, int(is_test.sum()), position_only, n_effect_params=n_current,
                     fold_rule=fit_rule, validation=validation_file(run_dir).is_file())
    say(f"folds: {folds_text(folds, len(tr), rule)}")
    context = effect_context(poses.context, poses.time_s)
    fold = pose_folds(poses.pose_id[tr], folds)
    base = base_parameters(robot, position_only=position_only)
    rows = equations_per_pose(position_only)

    ctx_tr = {key: v[tr] for key, v in context.items()}
    say("current model on the whole training set")
    full = CalibrationModel(robot=robot, effects=list(current), position_only=position_only).fit(
        poses.q[tr], poses.T_IE[tr], ctx_tr, base=base)
    noise = full.noise_sigma_

    def fold_data(k):
        """(q, T_IE, context) of fold k's fitting poses, then of its held-out poses."""
        fit_idx, out_idx = tr[fold != k], tr[fold == k]
        return (poses.q[fit_idx], poses.T_IE[fit_idx], {key: v[fit_idx] for key, v in context.items()},
                poses.q[out_idx], poses.T_IE[out_idx], {key: v[out_idx] for key, v in context.items()})

    fold_sets = {k: fold_data(k) for k in range(folds)}

    say(f"current model on {folds} folds")
    # fold fits start from the full fit and keep its noise weights: a few LM steps each
    before = np.empty(len(tr))
    dz_before = np.empty((len(tr), 3))
    fit_res, fold_models = {}, {}
    model_var = np.zeros(len(tr))  # each fold model's own position variance at its held-out poses, m²
    for k in range(folds):
        q_fit, T_fit, ctx_fit, q_out, T_out, ctx_out = fold_sets[k]
        m = CalibrationModel(robot=robot, effects=list(current), estimate_noise=False, position_only=position_only,
                             sigma_position_m=noise["position_m"],
                             sigma_orientation_rad=noise["orientation_rad"] or 1e-4)
        m.fit(q_fit, T_fit, ctx_fit, base=base, init=full.values_, init_jacobian=full.jacobian_at_fit_[fold != k])
        dz = m.residuals(q_out, T_out, ctx_out)
        before[fold == k] = np.linalg.norm(dz[:, :3], axis=1) * 1e3
        dz_before[fold == k] = dz[:, :3]
        fit_res[k] = m.residual_at_fit_[:, :3]  # m.residuals(q_fit, T_fit, ctx_fit), kept by the fit
        fold_models[k] = m
        J = m.jacobian(q_out, T_out, ctx_out)[:, :3, :]
        C = m.covariance_ / max(m.variance_factor_, 1e-300)  # the covariance of the fit's own weights
        model_var[fold == k] = np.einsum("nap,pq,naq->n", J, C, J)
    ss_before = float(np.sum((dz_before - dz_before.mean(axis=0)) ** 2))
    held_mean = float(before.mean())
    expected = expected_heldout_ratio(model_var, noise["position_m"])

    floor = noise_floor(run_dir, poses, robot)
    at_floor = None
    detection = MIN_RELATIVE_GAIN
    if floor.known:
        # a correct model's own estimation error (few poses), then the floor's uncertainty and the
        # sampling error of the held-out mean, combined
        held_unc = float(before.std() / max(held_mean, 1e-300) / np.sqrt(len(before)))
        threshold = max(1.0 + AT_FLOOR_MARGIN, expected) + FLOOR_UNCERTAINTIES * float(
            np.hypot(floor.relative_uncertainty, held_unc))
        if floor.mean_position_mm > 0:
            at_floor = held_mean / floor.mean_position_mm <= threshold
        else:  # noise-free measurements: at the floor means at the fit's round-off
            at_floor = held_mean <= ZERO_NOISE_MODEL_ATOL_M * 1e3
        if at_floor:
            # at the floor a gain must exceed what the floor's own uncertainty allows
            detection = max(MIN_RELATIVE_GAIN, 1.0 - 1.0 / threshold)

    X, input_names = regressor_inputs(poses.q[tr], ctx_tr)
    R1 = joint1_rotation(robot, poses.q[tr])  # each training pose's, for the held-out and the fold fits' residuals
    r_out = residual_in_joint1_frame(robot, poses.q[tr], dz_before, R1)
    struct = None
    struct_sig = False
    if structure:
        from campaign.diagnose.structure import structure_test

        say("model-free structure test (flexible regressor on the same folds)")
        q_tr = poses.q[tr]
        r_fit = {k: residual_in_joint1_frame(robot, q_tr[fold != k], fit_res[k], R1[fold != k]) for k in fit_res}
        struct = structure_test(X, input_names, fold, r_fit, r_out)
        struct_sig = bool(struct.p_value < ALPHA and struct.heldout_gain >= detection)
        if struct_sig and at_floor:  # structure the model-free test finds is above the noise, whatever the ratio
            at_floor = False

    scores, skipped = [], []
    n_cand = max(len(names), 1)
    lins = None
    for i, spec in enumerate(names):
        cls = effect_class(spec)
        say(f"candidate {i + 1}/{len(names)}: {cls.name}")
        lacking = [k for k in getattr(cls, "context_keys", ()) if k not in context
                   or not np.isfinite(np.asarray(context[k], dtype=float)).all()]  # e.g. data without time_s
        if lacking:
            skipped.append((cls.name, f"needs context {', '.join(cls.context_keys)} "
                                      f"({', '.join(lacking)}: not in the data for every pose)"))
            say(f"  {cls.name}: skipped ({skipped[-1][1]})")
            continue
        n_params = make_effect(spec, robot).n_params
        need = training_poses_needed(base.n_base + n_current + n_params, position_only)
        if fit_rule.fit_poses < need:
            skipped.append((cls.name, f"its {n_params} parameters need {need} poses in every fold fit "
                                      f"({rows} equations each), the folds have {fit_rule.fit_poses}"))
            say(f"  {cls.name}: skipped ({skipped[-1][1]})")
            continue
        if lins is None:
            # the current model linearised at each fold's optimum, shared by every candidate
            lins = {k: linearise(fold_models[k], *fold_sets[k][:3]) for k in range(folds)}
        effect = make_effect(spec, robot)
        after = np.empty(len(tr))
        dz_after = np.empty((len(tr), 3))
        absorbed = set()
        for k in range(folds):
            fit = fit_candidate(lins[k], effect, *fold_sets[k])
            after[fold == k] = np.linalg.norm(fit.heldout_dz[:, :3], axis=1) * 1e3
            dz_after[fold == k] = fit.heldout_dz[:, :3]
            absorbed |= set(fit.absorbed)
        absorbed = tuple(sorted(absorbed))
        d = before - after
        if np.all(d == 0):
            p = 1.0
        else:
            p = float(stats.ttest_rel(before, after, alternative="greater").pvalue)
        gain = 1 - after.mean() / max(before.mean(), 1e-300)
        r2 = 1 - float(np.sum((dz_after - dz_after.mean(axis=0)) ** 2)) / max(ss_before, 1e-300)
        n_params = effect.n_params
        fully_absorbed = len(absorbed) >= n_params and n_params > 0
        significant = (p < ALPHA / n_cand) and gain >= detection and not fully_absorbed
        scores.append(CandidateScore(cls.name, float(before.mean()), float(after.mean()), p, bool(significant),
                                     float(r2), absorbed, cls.description, spec))
    scores.sort(key=lambda c: (not c.significant, c.heldout_mean_position_mm_after))

    verdict = None
    best = scores[0] if scores and scores[0].significant else None
    if best is not None:
        reg_after = struct.after.mean() if struct is not None else np.inf
        explains = not struct_sig or best.heldout_mean_position_mm_after <= EXPLAINS_FACTOR * reg_after
        verdict = best.effect if explains else "unexplained"
    elif struct_sig:
        verdict = "unexplained"
    elif floor.known and not at_floor:
        verdict = "unexplained"

    signature = None
    if struct is not None and struct_sig:
        from campaign.diagnose.signature import describe

        say("signature of the structure (periodicity, time, gravity load)")
        signature = describe(robot, poses.q[tr], X, input_names, struct, struct.depends_on(MIN_IMPORTANCE_SHARE),
                             r_out, poses.time_s[tr], residual_fit=r_fit)
    residuals = full.residuals(poses.q, poses.T_IE, context)
    return Diagnosis(run_dir, tuple(current), tuple(scores), verdict, len(tr), folds, residuals, is_test,
                     floor, held_mean, struct, struct_sig, detection, at_floor, signature, tr, X,
                     r_out, rule, tuple(skipped), expected,
                     fold_pose_ids(poses.pose_id[tr], fold, folds),
                     measured_drift(run_dir, poses, floor, tracker_to_robot(tracker)),
                     model_note)
