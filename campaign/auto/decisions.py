"""The decisions of `campaign auto`: :func:`decide`, a pure function of the diagnosis, the round
and the rounds before, and the poses each decision measures."""

from __future__ import annotations

from dataclasses import replace

import numpy as np

from campaign.auto.state import Decision, Limits, Round
from campaign.diagnose.engine import is_time_effect, leads_to
from campaign.diagnose.timing import TIME_INPUTS
from campaign.effects.base import effect_label

#: poses per round that reveal the structure of an "unexplained" (a quarter of the default selection)
REVEAL_POSES = 30
#: poses per round of the optimal design at most (at least DESIGN_MIN_POSES)
DESIGN_MAX_POSES = 60
DESIGN_MIN_POSES = 8
#: rounds of revealing poses for one "unexplained" at most
REVEAL_ROUNDS = 3
#: a revealing round the limits cut below this is not measured, the limit stops: a few poses cannot
#: change a verdict fitted on a hundred or more (a third of REVEAL_POSES)
REVEAL_MIN_POSES = 10
#: without --target-mm: the model's own predicted error may be this share of the noise floor (its
#: held-out error is then about √(1 + share²) ≈ 1.1× the floor)
TARGET_FLOOR_SHARE = 0.5
#: the noise floor assumed for the target when the run has none (10 µm per reflector coordinate, 3 reflectors)
DEFAULT_FLOOR_MM = 0.0099
#: a candidate that explains only part of an "unexplained" is added when it takes at least this share
#: of the held-out error away (on the folds): a few per cent are as often a wrong effect fitting a
#: little of a missing one (cyclic for a bearing run-out), which then stays in the model
MIN_PARTIAL_GAIN = 0.10
#: a floor known to worse than this (relative, 1 σ) does not decide "at the floor" alone: FLOOR_POSES
#: poses are measured FLOOR_TIMES times back to back first (once), for the noise itself
FLOOR_UNCERTAINTY_MAX = 0.1
#: ... and only when it explains at least this share of what the model-free test explains (cyclic on
#: one joint fits 16 % of a bearing run-out that the regressor finds 40 % of: the run-out is missing)
PARTIAL_SHARE = 0.5
#: a candidate that leaves the model above this many times the floor while the model-free test finds
#: nothing significant is tested on more poses before it is added (:func:`_test_first`)
PARTIAL_FLOOR_FACTOR = 3.0
FLOOR_POSES = 8
FLOOR_TIMES = 4
#: the reason of a decision that takes effects of time out of the model: with all of them the same
#: poses, measured again, still move (campaign.diagnose.engine.Diagnosis.time_removal)
TIME_REMOVAL = "time"
#: rounds of poses chosen to separate two effects that the poses cannot tell apart on one joint
#: (diagnose's ``indistinguishable``), at most, in a run
SEPARATE_ROUNDS = 2


def decide(diagnosis, rnd: Round, before: list, limits: Limits, loop) -> Decision:
    """The next step from a diagnosis (module docstring, 2.). ``before``: the earlier rounds;
    ``loop`` answers what the run holds (planned poses, training poses, the room the limits leave)
    and chooses poses. Deterministic: the same stored data give the same decision."""
    if diagnosis.round_off:
        return Decision("stop", "stop: noise-free measurements, and the model fits them to round-off (held-out mean "
                                f"{diagnosis.heldout_mean_position_mm:.2g} mm): nothing left to measure for",
                        reason="at_floor")
    removal = diagnosis.removal
    if removal is not None:  # every round re-earns the model: take out before adding
        return Decision("remove_effect", f"take out {removal.label}: {removal_words(removal)}",
                        effect=removal.label, effects=tuple(diagnosis.effects_after_removal()))
    timed_out = getattr(diagnosis, "time_removal", ())
    if timed_out:  # effects of time with which the same poses still move: none is the answer, each goes
        return Decision("remove_effect", f"take out {' and '.join(c.label for c in timed_out)}: "
                                         f"{diagnosis.time_removal_text()}",
                        effect=", ".join(c.label for c in timed_out),
                        effects=tuple(diagnosis.effects_after_time_removal()), reason=TIME_REMOVAL)
    earlier = {tuple(sorted(r.effects)) for r in before}
    if diagnosis.swap is not None and tuple(sorted(diagnosis.swap[1])) not in earlier:
        # a joint of the model that another effect fits better in its place (never back to a model
        # of an earlier round: a pair that close swaps back and forth on the noise)
        rival, after = diagnosis.swap
        return Decision("remove_effect", f"replace {effect_label(rival.own)} by {effect_label(rival.rival)}: "
                                         f"{rival.text()}", effect=effect_label(rival.own), effects=tuple(after))
    best = diagnosis.ranking[0] if diagnosis.ranking and diagnosis.ranking[0].significant else None
    structure = diagnosis.structure
    # where the rotation test alone finds the error (campaign.diagnose.chain: the position test finds
    # nothing), a part of it is a part of the rotation error
    chain = getattr(diagnosis, "chain", None)
    rotation_decides = bool(getattr(diagnosis, "chain_significant", False) and not diagnosis.structure_significant)
    if best is not None and diagnosis.verdict == "unexplained" and (best.gain < MIN_PARTIAL_GAIN or (
            structure is not None and best.gain < PARTIAL_SHARE * structure.heldout_gain) or (
            rotation_decides and not best.rotation_gain >= PARTIAL_SHARE * chain.heldout_gain)):
        best = None  # a small part of an unexplained error: the effect that explains it is more likely missing
    if best is not None and not leads_to(best, rnd.depends_on,
                                         None if structure is None else float(structure.after.mean())):
        best = None  # it fits part of a structure that depends on something else first: that is missing
    if best is not None and getattr(diagnosis, "time_effects_fail", False) and is_time_effect(best.spec or best.effect):
        best = None  # the poses measured again still move with every effect of time added: none is the answer
    if best is not None and (best.spec or best.effect) in _taken_out_for_time(before):
        best = None  # taken out because the poses still moved with it: not added back on a change of significance
    if best is None and worth_separating(diagnosis):
        separate = _separate(diagnosis, before, loop)
        if separate is not None:
            return separate
    if best is not None and diagnosis.verdict is not None:
        test = _test_first(diagnosis, best, before, loop)
        if test is not None:
            return test
        part = "" if diagnosis.verdict == best.effect else ", which explains part of what is left"
        return Decision("add_effect", f"add {best.label}{part} (cross-validated on the folds "
                                      f"{best.heldout_mean_position_mm_before:.4f} → "
                                      f"{best.heldout_mean_position_mm_after:.4f} mm; {best.description})",
                        effect=best.spec or best.effect)
    floor_mm = rnd.floor_mm
    target = limits.target_mm
    if target is None:
        target = TARGET_FLOOR_SHARE * (floor_mm if floor_mm else DEFAULT_FLOOR_MM)
    floor_round = _floor_round(diagnosis, before, loop)
    if diagnosis.verdict is None:
        if not diagnosis.floor.known:
            cap, limit = loop.measure_cap()
            if limit is not None and cap == 0:  # the plan's poses (its repeats) wait for the limit, not the model
                return Decision("stop", "stop: no missing effect found and no noise floor yet: planned poses "
                                        f"left unmeasured, the {'budget' if limit == 'budget' else 'pose limit'} "
                                        "allows no more", reason=limit)
            return Decision("stop", "stop: no missing effect found, but the run has no noise floor to say how close "
                                    "the model is to the noise", reason="no_floor")
        weak = weak_structure_inputs(diagnosis)
        if weak and floor_round is None:
            s = diagnosis.structure
            what = (f"the model-free test finds {100 * s.heldout_gain:.0f} % of the held-out error on "
                    f"{inputs_text(list(rnd.depends_on) or weak)} (p = {s.p_value:.2g}), below what the floor's "
                    "uncertainty lets it call significant")
            if _measuring(before) and _measuring(before)[-1].decision.reason == "probe":
                from campaign.diagnose.engine import ALPHA

                if s.p_value < ALPHA:
                    return Decision("stop", f"stop: unexplained — again after the poses chosen to test it, {what}",
                                    reason="unexplained")
                # tested, and not found at diagnose's own level: the floor
            elif loop.room(REVEAL_POSES)[0] > 0:
                d = _reveal(list(rnd.depends_on) or weak, diagnosis.signature, loop, loop.room(REVEAL_POSES)[0])
                if d is not None:
                    return replace(d, text=f"at the floor, but {what}: {d.text}", reason="probe")
        return floor_round or _design_or_stop(rnd, limits, loop, target, at_floor=True)
    # "unexplained"
    reveals = _reveal_rounds(before)
    if diagnosis.worth_a_round and rnd.depends_on:
        top = rnd.depends_on[0]
        last = _measuring(before)[-1] if _measuring(before) else None
        if reveals and last is not None and last.verdict == "unexplained" and last.depends_on[:1] and (
                last.depends_on[0] == top or {last.depends_on[0], top} <= set(TIME_INPUTS)):
            # time and a temperature that follows it swap places on the noise: the same poses measured again
            # reveal either
            return Decision("stop", f"stop: unexplained, and {_revealed_text(before, rnd)} (depends on {top} "
                                    "first)", reason="unexplained")
        if reveals >= REVEAL_ROUNDS:
            chosen, measured = _revealed_poses(before, rnd)
            return Decision("stop", f"stop: unexplained after {reveals} rounds of poses chosen to reveal it ("
                                    + (f"{measured} measured)" if measured == chosen else
                                       f"{measured} of the {chosen} chosen measured)"), reason="unexplained")
        n, limit = loop.room(REVEAL_POSES)
        if n <= 0:
            return _limit_stop(limit, rnd)
        if limit is not None and n < REVEAL_MIN_POSES:
            what = "budget" if limit == "budget" else "pose limit"
            return Decision("stop", f"stop: unexplained, depends on {inputs_text(rnd.depends_on)}; the {what} leaves "
                                    f"room for {n} pose{'s' if n > 1 else ''}, fewer than the {REVEAL_MIN_POSES} that "
                                    "could change the verdict", reason=limit)
        d = _reveal(list(rnd.depends_on), diagnosis.signature, loop, n)
        if d is None:
            return Decision("stop", "stop: unexplained, and no suitable pose is left to measure", reason="no_poses")
        return replace(d, text=f"unexplained, depends on {inputs_text(rnd.depends_on)}: {d.text}")
    # above the floor, and nothing says on what the rest depends
    tested = getattr(diagnosis, "test_set", None)
    if tested is not None and not tested.holds and tested.sparse and reveals < REVEAL_ROUNDS:
        d = _spread_sparse(tested, loop)  # the folds cannot see it: the training poses do not vary it
        if d is not None:
            return d
    if floor_round is not None:
        return floor_round
    d = _design_or_stop(rnd, limits, loop, target, at_floor=False)
    if d.kind != "stop" or reveals >= REVEAL_ROUNDS:
        return d
    n, limit = loop.room(REVEAL_POSES)
    if n <= 0:
        return _limit_stop(limit, rnd)
    pose_ids = _spread(loop, None, n)
    if len(pose_ids) == 0:
        return Decision("stop", "stop: unexplained, and no suitable pose is left to measure", reason="no_poses")
    return Decision("reveal", f"above the floor, and no input found for it: measure {len(pose_ids)} poses spread over "
                              "the joints", pose_ids=tuple(pose_ids))


def _floor_round(diagnosis, before, loop) -> Decision | None:
    """Poses measured back to back for the noise floor, when the floor is known to worse than
    FLOOR_UNCERTAINTY_MAX: too uncertain to tell a model at the noise from one a little above it
    (and a floor from repeats spread over the campaign holds the drift between them); once per
    run. None otherwise, or when the limits leave no room."""
    from campaign.plan.extend import design_poses
    from campaign.plan.selection import REPEAT_ID_STRIDE

    from campaign.diagnose.engine import AT_FLOOR_MARGIN, FLOOR_UNCERTAINTIES

    floor, ratio = diagnosis.floor, diagnosis.model_to_noise
    if not floor.known or ratio is None or floor.relative_uncertainty <= FLOOR_UNCERTAINTY_MAX:
        return None
    if ratio / (1.0 + FLOOR_UNCERTAINTIES * floor.relative_uncertainty) > 1.0 + AT_FLOOR_MARGIN:
        return None  # a floor even that much larger leaves the model above it: the noise cannot turn the verdict
    if any(r.decision.kind == "floor" for r in before):
        return None
    n, _ = loop.room(FLOOR_POSES * FLOOR_TIMES)
    n = min(n, loop.room(10 ** 9)[0] // 2)  # half of what the limits leave at most: the model may need the rest
    if n < 2 * FLOOR_TIMES:
        return None
    ids_train, _ = loop.training()
    ids = _not_again(loop)
    chosen, _, _ = design_poses(loop.space, ids_train, ids, loop.design_effects(), n_max=n // FLOOR_TIMES,
                                noise_m=design_noise_m(loop, floor.mean_position_mm))
    pose_ids = tuple(int(p) + r * REPEAT_ID_STRIDE for p in chosen for r in range(FLOOR_TIMES))
    return Decision("floor", f"the floor is known only to ±{100 * floor.relative_uncertainty:.0f} % "
                             f"(cross-validated {ratio:.2f}× it on the folds): "
                             f"measure {len(chosen)} informative poses {FLOOR_TIMES} times back to back, for the noise",
                    pose_ids=pose_ids)


#: a structure the model-free test finds at the floor with p below this (and a positive gain) is
#: tested with more poses before auto calls it the floor; after them it must reach diagnose's ALPHA
PROBE_ALPHA = 0.1


def weak_structure_inputs(diagnosis, alpha: float = PROBE_ALPHA) -> list:
    """The inputs (by permutation importance) of a structure the model-free test finds by its
    p-value (p < ``alpha``, a positive held-out gain) but does not call significant: below the
    detection limit that the floor's uncertainty sets at the floor, and at least MIN_ROUND_SHARE of
    the held-out error. Empty otherwise."""
    from campaign.diagnose.engine import MIN_IMPORTANCE_SHARE

    from campaign.tolerances import MIN_ROUND_SHARE

    s = diagnosis.structure
    if s is None or diagnosis.structure_significant or not (s.p_value < alpha and s.heldout_gain >= MIN_ROUND_SHARE):
        return []  # below MIN_ROUND_SHARE of the error: no round is spent on it
    return s.depends_on(MIN_IMPORTANCE_SHARE)


def _reveal(inputs, signature, loop, n: int) -> Decision | None:
    """``n`` poses that reveal a structure depending on ``inputs``: measured poses again now when
    time (or temperature) comes first, else new poses spread over the joints among the inputs (and
    the gravity load when the signature says it grows with it). None when no pose is left."""
    if inputs and inputs[0] in TIME_INPUTS:
        from campaign.plan.extend import remeasure_poses

        ids_train, times = loop.training()
        pose_ids = remeasure_poses(loop.space, ids_train, times, n)
        return Decision("remeasure", f"measure {len(pose_ids)} of the oldest poses again now",
                        pose_ids=tuple(int(p) for p in pose_ids))
    chosen = [i for i in inputs if i not in TIME_INPUTS]
    if signature is not None and any(k != "time_s" for k in signature.growth):
        chosen.append("gravity load")
    pose_ids = _spread(loop, chosen, n)
    if len(pose_ids) == 0:
        return None
    return Decision("reveal", f"measure {len(pose_ids)} poses spread over {', '.join(chosen) or 'the joints'}",
                    pose_ids=tuple(int(p) for p in pose_ids))


def design_noise_m(loop, floor_mm) -> float | None:
    """The tracker noise (m per reflector coordinate) the design predicts the model's error with:
    the one whose floor is the run's own (measured from repeats, or from campaign.yaml's stated
    ``tracker.noise_m``), so that the prediction and its target (a share of that floor) scale
    alike; None (the plan's default, TRACKER_NOISE_M) without a floor or for a floor of 0. A 3 µm
    cell was predicted at 10 µm, 2.5 µm against a target of 1.5 µm, and measured six rounds more."""
    from campaign.plan.extend import reflector_noise_for_floor

    return reflector_noise_for_floor(loop.space.robot, floor_mm)


def _design_or_stop(rnd, limits, loop, target, *, at_floor: bool) -> Decision:
    from campaign.plan.extend import design_poses

    ids_train, _ = loop.training()
    ids = _not_again(loop)
    n, limit = loop.room(DESIGN_MAX_POSES)
    effects = loop.design_effects()
    noise_m = design_noise_m(loop, rnd.floor_mm)
    _, predicted, _ = design_poses(loop.space, ids_train, ids, effects, n_max=0, noise_m=noise_m)
    what = "at the measurement noise" if at_floor else "above the floor, and nothing says why"
    if predicted <= target:
        if at_floor:
            return Decision("stop", f"stop: at the measurement noise, and the model well determined (predicted "
                                    f"error {1e3 * predicted:.1f} µm ≤ target {1e3 * target:.1f} µm)",
                            reason="at_floor")
        left = f"the test set is {rnd.ratio:.1f}× the floor" if rnd.ratio is not None else "the error left"
        return Decision("stop", f"stop: unexplained — {left} and nothing says on what the rest depends; more poses "
                                f"would not sharpen this model (its predicted error is {1e3 * predicted:.1f} µm ≤ "
                                f"target {1e3 * target:.1f} µm): what is left is an effect the model lacks",
                        reason="unexplained")
    if n < DESIGN_MIN_POSES:
        if at_floor:  # the limit stops it, not the model: the reason names the limit
            return Decision("stop", f"stop: at the measurement noise; the model's predicted error "
                                    f"{1e3 * predicted:.1f} "
                                    f"µm is above the target {1e3 * target:.1f} µm, but the "
                                    f"{'budget' if limit == 'budget' else 'pose limit'} allows no more poses",
                            reason="budget" if limit == "budget" else "max_poses")
        return _limit_stop(limit, rnd)
    chosen, _, after = design_poses(loop.space, ids_train, ids, effects, n_max=n, target_mm=target,
                                    n_min=DESIGN_MIN_POSES, noise_m=noise_m)
    if len(chosen) == 0:
        return Decision("stop", f"stop: {what}; no suitable pose is left to measure", reason="at_floor" if at_floor
                        else "no_poses")
    return Decision("design", f"{what}, but the model poorly determined (predicted error {1e3 * predicted:.1f} µm > "
                              f"target {1e3 * target:.1f} µm): measure the {len(chosen)} most informative poses "
                              f"(predicted {1e3 * after:.1f} µm)", pose_ids=tuple(int(p) for p in chosen))


def _limit_stop(limit, rnd) -> Decision:
    if limit == "budget":
        return Decision("stop", f"stop: the budget is spent ({rnd.hours:.2f} h)", reason="budget")
    return Decision("stop", f"stop: the pose limit is reached ({rnd.planned} poses planned)", reason="max_poses")


def _test_first(diagnosis, best, before, loop) -> Decision | None:
    """Poses spread over the joints before ``best`` is added, when the model-free test cannot yet
    say what the error depends on and the model stays far above the floor with it
    (PARTIAL_FLOOR_FACTOR): a flexible candidate (a joint search over harmonics) then fits part of an
    effect no catalogue holds as readily as a true one, and only more poses tell them apart (the
    model-free test finds the rest, or the candidate explains it). Once after each effect added;
    None otherwise."""
    floor = diagnosis.floor
    if diagnosis.structure_significant or getattr(diagnosis, "chain_significant", False) or not floor.known \
            or not floor.mean_position_mm > 0:
        return None
    if best.heldout_mean_position_mm_after <= PARTIAL_FLOOR_FACTOR * floor.mean_position_mm:
        return None
    for r in reversed(before):
        if r.decision.kind == "add_effect":
            break
        if r.decision.reason == "test":
            return None
    n, _ = loop.room(REVEAL_POSES)
    if n <= 0:
        return None
    pose_ids = _spread(loop, None, n)
    if len(pose_ids) == 0:
        return None
    return Decision("reveal", f"{best.label} is significant but leaves {best.heldout_mean_position_mm_after:.3f} mm "
                              f"({best.heldout_mean_position_mm_after / floor.mean_position_mm:.0f}× the floor) and the "
                              f"model-free test cannot yet say on what the rest depends: measure {len(pose_ids)} poses "
                              "spread over the joints before adding it", pose_ids=tuple(pose_ids), reason="test")


def removal_words(removal) -> str:
    """What taking out an effect that does not earn its place does to the held-out mean on the folds:
    lower by more than its standard error (it did harm), or a change within it (it did nothing)."""
    gain, se = 1e3 * removal.gain_mm, 1e3 * removal.gain_se_mm
    if se > 0 and -gain > se:
        return (f"without it the held-out mean on the folds is {-gain:.1f} ± {se:.1f} µm lower ({-gain / se:.1f} "
                "standard errors: it fits the folds' noise, not the robot)")
    return f"without it the held-out mean on the folds changes by {gain:+.1f} ± {se:.1f} µm (within its standard error)"


def worth_separating(diagnosis) -> tuple:
    """The pairs of diagnose's ``indistinguishable`` worth poses to separate: those whose better
    effect takes at least MIN_PARTIAL_GAIN of the held-out error away and, when the verdict is
    "unexplained", at least PARTIAL_SHARE of what the model-free test explains. Two effects that
    each fit a small part of an error neither causes (cyclic and backlash of joint 1 each 6 % of a
    cable's wind-up that the regressor finds 74 % of) are not the question: what is missing is."""
    held = diagnosis.heldout_mean_position_mm
    structure = diagnosis.structure
    out = []
    for r in diagnosis.indistinguishable:
        gain = 1.0 - min(r.own_mm, r.rival_mm) / held if held > 0 else 0.0
        if gain < MIN_PARTIAL_GAIN:
            continue
        if diagnosis.verdict == "unexplained" and structure is not None and gain < PARTIAL_SHARE * structure.heldout_gain:
            continue
        out.append(r)
    return tuple(out)


def _separate(diagnosis, before, loop) -> Decision | None:
    """Poses that separate two effects the poses cannot tell apart on one joint (diagnose's
    ``indistinguishable``, neither named for it): where one's signal differs most from the best fit
    of the other (:func:`campaign.plan.extend.separating_poses`; for backlash against compliance,
    where the joint's gravity torque bends the tanh), the room shared among the pairs. After
    SEPARATE_ROUNDS such rounds, a stop that names both; None when the limits leave no room or no
    pose is left."""
    from campaign.plan.extend import separating_poses

    pairs = worth_separating(diagnosis)
    what = "; ".join(f"{r.words()} on these poses" for r in pairs)
    done = sum(1 for r in before if r.decision.reason == "separate")
    if done >= SEPARATE_ROUNDS:
        either = " or ".join(f"[{spec}]" for spec in dict.fromkeys(s for r in pairs for s in (r.own, r.rival)))
        return Decision("stop", f"stop: {what}, still after {done} rounds of poses chosen to separate them: the "
                                f"data cannot say which, and neither is added (they predict alike here: if you know "
                                f"which is there, add it, effects: {either})", reason="indistinguishable")
    n, _ = loop.room(REVEAL_POSES)
    if n <= 0:
        return None
    ids_train, _ = loop.training()
    ids = _not_again(loop)
    chosen = []
    for k, r in enumerate(pairs):
        share = (n - len(chosen)) // (len(pairs) - k)
        chosen += [int(p) for p in separating_poses(loop.space, ids_train, np.concatenate([ids, chosen]), r.own,
                                                    r.rival, share)]
    if not chosen:
        return None
    return Decision("design", f"{what}: measure the {len(chosen)} poses where they differ most",
                    pose_ids=tuple(chosen), reason="separate")


def _taken_out_for_time(before) -> set:
    """The specs that rounds ``before`` took out as effects of time (TIME_REMOVAL)."""
    return {s for r in before if r.decision.kind == "remove_effect" and r.decision.reason == TIME_REMOVAL
            for s in set(r.effects) - set(r.decision.effects)}


def _measuring(before) -> list:
    """The rounds ``before`` without those that took effects of time out (TIME_REMOVAL): such a
    round measures nothing and follows a revealing round on the same poses, whose count it must
    not reset (the revealing rounds would start over after it)."""
    return [r for r in before if not (r.decision.kind == "remove_effect" and r.decision.reason == TIME_REMOVAL)]


def _reveal_rounds(before) -> int:
    """Rounds just before this one that measured poses to reveal an "unexplained" (consecutive;
    those that took effects of time out between them are passed over: :func:`_measuring`)."""
    n = 0
    for r in reversed(_measuring(before)):
        if r.decision.kind not in ("reveal", "remeasure"):
            break
        n += 1
    return n


def _revealed_poses(before, rnd) -> tuple:
    """(poses chosen, poses measured) by the revealing rounds just before ``rnd``
    (:func:`_reveal_rounds`): what they chose, and the readings the run gained since the first of
    them (the store's count each round holds, :attr:`Round.poses`). The two differ when the plan
    reached only some of the chosen poses (no collision-free motion) or the limits cut them."""
    measuring = _measuring(before)
    revealing = measuring[len(measuring) - _reveal_rounds(before):]
    if not revealing:
        return 0, 0
    return sum(len(r.decision.pose_ids) for r in revealing), max(int(rnd.poses) - int(revealing[0].poses), 0)


def _revealed_text(before, rnd) -> str:
    """What the revealing rounds before ``rnd`` measured, for a stop that says they did not change
    the verdict: the poses measured, and the poses chosen when these differ (qa31c: "90 poses
    chosen to reveal it did not change the verdict" after 6 measured)."""
    chosen, measured = _revealed_poses(before, rnd)
    if measured == 0:
        return f"none of the {chosen} poses chosen to reveal it was measured: the verdict stands"
    if measured == chosen:
        return f"the {measured} poses measured to reveal it did not change the verdict"
    return (f"the {measured} poses measured to reveal it (of {chosen} chosen, the rest not measured) "
            "did not change the verdict")


def _not_again(loop) -> np.ndarray:
    """Pose ids not to choose again: those the plan holds and those it dropped before (no
    collision-free motion reached them; RUN/plan/dropped.csv). A UR10 chose the same unreachable
    poses round after round."""
    ids, _ = loop.planned()
    unreached = getattr(loop, "unreached", None)  # a loop that knows of no dropped pose (a test's) has none
    dropped = np.zeros(0) if unreached is None else unreached()
    return np.concatenate([np.asarray(ids, dtype=np.int64), np.asarray(dropped, dtype=np.int64)])


def inputs_text(inputs) -> str:
    inputs = ["time" if i == "time_s" else i for i in inputs]
    return inputs[0] if len(inputs) == 1 else ", ".join(inputs[:-1]) + " and " + inputs[-1]


def _spread(loop, inputs, n: int):
    """``n`` new poses (grid indices) that fill the largest gaps the training poses leave over
    ``inputs`` (None: every joint), none of them planned already (campaign.plan.extend.spread_poses)."""
    from campaign.plan.extend import spread_poses

    if inputs is None:
        inputs = [f"q{j + 1}" for j in range(loop.space.robot.n_joints)]
    ids_train, _ = loop.training()
    ids = _not_again(loop)
    return spread_poses(loop.space, ids_train, ids, inputs, n)


def _spread_sparse(tested, loop) -> Decision | None:
    """Poses spread over the joints the training poses leave sparse, when the test set says the
    model does not hold beyond them (campaign.diagnose.testset), or None without room or poses."""
    n, _ = loop.room(REVEAL_POSES)
    if n <= 0:
        return None
    pose_ids = _spread(loop, tested.sparse_joints, n)
    if len(pose_ids) == 0:
        return None
    return Decision("reveal", f"the test set is {tested.ratio:.1f}× the folds (p = {tested.p_value:.2g}) and the "
                              f"training poses hold {', '.join(c.text() for c in tested.sparse)}: measure "
                              f"{len(pose_ids)} poses spread over {', '.join(tested.sparse_joints)}",
                    pose_ids=tuple(pose_ids))
