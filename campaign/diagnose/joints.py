"""Which joints a joint-indexed candidate acts on: forward selection with a stopping rule.

A joint-indexed effect (joint compliance, backlash, cyclic, a user's effect whose ``__init__``
takes ``joints``) named without joints is not scored over a default list: the search fits it on
each joint alone (on the diagnosis folds, with the current model), keeps the joint whose
held-out mean position error is lowest, then adds, one at a time, the joint that lowers it most,
as long as that step is significant on the held-out poses (one-sided paired t-test on the
per-pose errors at p < alpha / the joints left, and a gain of at least the detection limit) —
the stopping rule against chasing noise. A compliant joint 4 is thus "joint compliance of
joint 4", not the default joints with the noise's share on each.

Two effects on one joint can look alike: backlash ``β tanh(τ / 1 N·m)`` is compliance ``c τ`` up to
the tanh's bend, all the closer the smaller the joint's gravity torque (a Panda's joint 6 carries
1-2.5 N·m: a quarter of backlash's shape is not compliance's). Each joint j the leading candidate
acts on is therefore compared with every other joint-indexed candidate on j
(:func:`shared_joint_rivals`): the candidate over its other joints plus the rival on j, fitted
together on the same folds. The one whose held-out mean is lower by more than
:data:`RIVAL_STANDARD_ERRORS` standard errors of the paired difference keeps the joint; closer, the
two are *indistinguishable on these poses* and neither is named for it (auto then measures poses
that separate them).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy import stats

from campaign.effects.base import effect_class, effect_label, joint_spec, make_effect, split_joints, takes_joints

#: two effects on one joint are told apart when the held-out mean of one is lower than the other's by
#: more than this many standard errors of their paired difference (one-sided p ≈ 0.023 each way);
#: closer, they are indistinguishable on these poses
RIVAL_STANDARD_ERRORS = 2.0


@dataclass(frozen=True)
class JointStep:
    """One step of the search: the joints chosen so far, the held-out mean after it (mm), and
    the step's p-value against the step before (None for the first)."""

    joints: tuple
    heldout_mean_position_mm: float
    p_value: float | None

    def as_json(self) -> dict:
        return {"joints": list(self.joints), "heldout_mean_position_mm": self.heldout_mean_position_mm,
                "p_value": self.p_value}


def paired_p(before, after) -> float:
    """One-sided paired t-test p of "after is smaller than before" (1.0 when they are equal)."""
    d = np.asarray(before) - np.asarray(after)
    if np.all(d == 0):
        return 1.0
    return float(stats.ttest_rel(before, after, alternative="greater").pvalue)


def search_joints(spec, robot, score, exclude=(), *, alpha: float, detection: float):
    """Forward selection of the joints of candidate ``spec`` (a bare joint-indexed name).

    score(spec) -> (after (n,) held-out position errors mm, fully_absorbed bool) fits one spec on
    the folds; ``exclude``: joints the current model already gives this effect. Returns
    (chosen spec or None when no joint can be fitted, its after errors, steps, joints tried)."""
    base, _ = split_joints(spec)
    joints = [j for j in range(1, robot.n_joints + 1) if j not in set(exclude)]
    singles = {}
    for j in joints:
        after, absorbed = score(joint_spec(base, [j]))
        if not absorbed:
            singles[j] = after
    if not singles:
        return None, None, (), len(joints)
    best = min(singles, key=lambda j: singles[j].mean())
    chosen, current = [best], singles[best]
    steps = [JointStep((best,), float(current.mean()), None)]
    left = [j for j in singles if j != best]
    while left:
        trials = {j: score(joint_spec(base, sorted(chosen + [j]))) for j in left}
        trials = {j: a for j, (a, absorbed) in trials.items() if not absorbed}
        if not trials:
            break
        j = min(trials, key=lambda j: trials[j].mean())
        p = paired_p(current, trials[j])
        gain = 1 - trials[j].mean() / max(current.mean(), 1e-300)
        if not (p < alpha / len(left) and gain >= detection):
            break
        chosen, current = sorted(chosen + [j]), trials[j]
        steps.append(JointStep(tuple(chosen), float(current.mean()), p))
        left = [k for k in left if k != j]
    return joint_spec(base, chosen), current, tuple(steps), len(joints)


def searches_joints(spec, robot) -> bool:
    """Whether diagnose searches the joints of candidate ``spec``: a joint-indexed effect named
    without joints."""
    base, joints = split_joints(spec)
    return joints is None and takes_joints(effect_class(base)) and robot.n_joints > 0


def model_joints(current, spec, robot) -> tuple:
    """The joints the current model (specs) gives the effect of ``spec`` (by class name), or ()."""
    name = effect_class(spec).name
    out = []
    for s in current:
        if effect_class(s).name == name:
            out += list(getattr(make_effect(s, robot), "joints", ()))
    return tuple(sorted(set(out)))


@dataclass(frozen=True)
class Rival:
    """A joint that a candidate and another joint-indexed effect both fit: ``own`` the candidate on
    that joint ("joint_compliance:6"), ``rival`` the other effect on it ("backlash:6"); the held-out
    mean (mm) of the candidate over all its joints and of the candidate over its other joints plus
    the rival on this one, and the standard error of their paired difference (mm)."""

    joint: int
    own: str
    rival: str
    own_mm: float
    rival_mm: float
    diff_se_mm: float

    @property
    def outcome(self) -> str:
        """"own", "rival" (the one lower by more than RIVAL_STANDARD_ERRORS standard errors keeps
        the joint) or "indistinguishable"."""
        d = self.own_mm - self.rival_mm
        if d > RIVAL_STANDARD_ERRORS * self.diff_se_mm:
            return "rival"
        if -d > RIVAL_STANDARD_ERRORS * self.diff_se_mm:
            return "own"
        return "indistinguishable"

    def as_json(self) -> dict:
        return {"joint": self.joint, "effects": [self.own, self.rival],
                "heldout_mean_position_mm": [self.own_mm, self.rival_mm], "difference_se_mm": self.diff_se_mm,
                "outcome": self.outcome}

    def words(self) -> str:
        """"joint_compliance of joint 6 and backlash of joint 6 are indistinguishable", or which keeps it."""
        a, b = effect_label(self.own), effect_label(self.rival)
        if self.outcome == "indistinguishable":
            return f"{a} and {b} are indistinguishable"
        return f"{a} rather than {b}" if self.outcome == "own" else f"{b} rather than {a}"

    def text(self) -> str:
        out = (f"{self.words()} on these poses (held-out {self.own_mm:.4f} mm with {effect_label(self.own)}, "
               f"{self.rival_mm:.4f} mm with {effect_label(self.rival)} instead, ± {self.diff_se_mm:.4f})")
        return out + (": poses that separate them are needed" if self.outcome == "indistinguishable" else "")


def shared_joint_rivals(spec, after, rivals, score_with) -> tuple:
    """Each joint of candidate ``spec`` (with joints; its held-out errors ``after`` (n,) mm) against
    each rival effect (bare joint-indexed names other than the candidate's) on that joint:
    ``score_with(rest, rival)`` -> held-out errors (n,) mm, or None when the pair cannot be fitted,
    of the candidate over ``rest`` (its other joints' spec, None when it has no other) together with
    ``rival`` on the joint. Returns the :class:`Rival` comparisons."""
    base, joints = split_joints(spec)
    out = []
    for j in joints or ():
        rest = [k for k in joints if k != j]
        for other in rivals:
            if split_joints(other)[0] == base:
                continue
            pair = score_with(joint_spec(base, rest) if rest else None, joint_spec(split_joints(other)[0], [j]))
            if pair is None:
                continue
            d = np.asarray(after) - np.asarray(pair)
            se = float(d.std(ddof=1) / np.sqrt(len(d))) if len(d) > 1 else float("inf")
            out.append(Rival(j, joint_spec(base, [j]), joint_spec(split_joints(other)[0], [j]),
                             float(np.mean(after)), float(np.mean(pair)), se))
    return tuple(out)


def contested_joints(rivals) -> tuple:
    """The joints of a candidate that a rival takes or that are indistinguishable from one, sorted."""
    return tuple(sorted({r.joint for r in rivals if r.outcome != "own"}))
