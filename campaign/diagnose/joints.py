"""Which joints a joint-indexed candidate acts on: forward selection with a stopping rule.

A joint-indexed effect (joint compliance, backlash, cyclic, a user's effect whose ``__init__``
takes ``joints``) named without joints is not scored over a default list: the search fits it on
each joint alone (on the diagnosis folds, with the current model), keeps the joint whose
held-out mean position error is lowest, then adds, one at a time, the joint that lowers it most,
as long as that step is significant on the held-out poses (one-sided paired t-test on the
per-pose errors at p < alpha / the joints left, and a gain of at least the detection limit) —
the stopping rule against chasing noise. A compliant joint 4 is thus "joint compliance of
joint 4", not the default joints with the noise's share on each.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy import stats

from campaign.effects.base import effect_class, joint_spec, make_effect, split_joints, takes_joints


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
