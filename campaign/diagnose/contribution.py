"""What each effect of the current model earns: its cross-validated gain, with its uncertainty.

On each diagnosis fold the current model was fitted on the fold's other poses (at its optimum
x̂, linearised there by :func:`campaign.diagnose.candidates.linearise`) and predicts the held-out
poses. Taking an effect out (or one joint of a joint-indexed effect: the parameters the effect
over the other joints lacks) is the same fit with those parameters held at zero: to first order
in the small effects, the other unknowns move by the least-squares step
``δ_F = −(J_F)⁺ (r − J_R x̂_R)`` (weighted residual r and Jacobian J at x̂, R the parameters taken
out, F the other fitted ones), and the held-out residual by ``J_out,F δ_F − J_out,R x̂_R``.

The contribution is the mean over the held-out poses of ``d = e_without − e_with`` (their
position errors, mm) and its standard error ``sd(d) / √n``. An effect (or joint) *earns its place*
when the mean exceeds :data:`KEEP_STANDARD_ERRORS` standard errors: one whose removal does not
worsen the cross-validated error beyond its standard error is taken out (the one-standard-error
rule of model selection: the simpler model unless the data say otherwise).

A joint of a joint-indexed effect may earn its place and still belong to another effect: backlash
of a joint read as its compliance. :func:`joint_swaps` lists, for each such joint, the other
joint-indexed candidates that could take it; diagnose fits each in its place on the same folds
(the joint's parameters held at zero, :func:`campaign.diagnose.candidates.fit_candidate`) and
compares the two as :mod:`campaign.diagnose.joints` compares a candidate's joints.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from campaign.diagnose.joints import model_joints
from campaign.effects.base import (effect_class, effect_label, joint_spec, make_effect, split_joints, takes_joints,
                                   without_joints)

#: an effect earns its place when taking it out worsens the held-out mean by more than this many
#: standard errors of the paired difference (the one-standard-error rule)
KEEP_STANDARD_ERRORS = 1.0


@dataclass(frozen=True)
class Contribution:
    """One effect (``joint`` None) or one joint of it in the current model: the held-out mean
    position error with it and without it (mm), their paired difference's mean and standard
    error (mm); ``without``: the effect's spec once it is taken out (None: the whole effect)."""

    spec: str
    joint: int | None
    heldout_mean_position_mm_with: float
    heldout_mean_position_mm_without: float
    gain_mm: float
    gain_se_mm: float
    without: str | None

    @property
    def earns_place(self) -> bool:
        return self.gain_mm > KEEP_STANDARD_ERRORS * self.gain_se_mm

    @property
    def label(self) -> str:
        base = effect_label(self.spec if self.joint is None else split_joints(self.spec)[0])
        return base if self.joint is None else f"{base} of joint {self.joint}"

    def as_json(self) -> dict:
        return {"effect": self.spec, "joint": self.joint, "label": self.label,
                "heldout_mean_position_mm_with": self.heldout_mean_position_mm_with,
                "heldout_mean_position_mm_without": self.heldout_mean_position_mm_without,
                "heldout_gain_mm": self.gain_mm, "heldout_gain_se_mm": self.gain_se_mm,
                "earns_place": self.earns_place}

    def text(self) -> str:
        verdict = "earns its place" if self.earns_place else "does not earn its place"
        return (f"{self.label}: held-out {self.heldout_mean_position_mm_with:.4f} mm with it, "
                f"{self.heldout_mean_position_mm_without:.4f} without (gain {1e3 * self.gain_mm:+.1f} ± "
                f"{1e3 * self.gain_se_mm:.1f} µm): {verdict}")


def removals(current, robot) -> list:
    """What to try taking out of the current model ``current`` (specs): each effect, and each joint
    of a joint-indexed effect over two or more joints; [(spec, joint or None, param names taken
    out, spec once taken out or None)]."""
    out = []
    for spec in current:
        effect = make_effect(spec, robot)
        out.append((spec, None, tuple(effect.param_names), None))
        if not takes_joints(type(effect)) or len(getattr(effect, "joints", ())) < 2:
            continue
        for j in effect.joints:
            rest = without_joints(spec, [j], robot)
            kept = set(make_effect(rest, robot).param_names)
            out.append((spec, j, tuple(p for p in effect.param_names if p not in kept), rest))
    return out


def contributions(current, robot, folds, before_mm, dz_before, fold) -> tuple:
    """The :class:`Contribution` of each effect (and joint) of ``current``: ``folds`` a list of
    (FoldLinearisation, held-out Jacobian (n_out, 3, u) of the fold's unknowns in the position
    rows) per fold; before_mm (n,) the held-out position errors of the current model (mm),
    dz_before (n, 3) their residuals (m), fold (n,) the fold of each held-out pose."""
    out = []
    if not current or not folds:
        return ()
    for spec, joint, params, rest in removals(current, robot):
        after = np.empty_like(before_mm)
        for k, (lin, J_out) in enumerate(folds):
            idx = param_index(lin.model, spec, params)
            after[fold == k] = _heldout_without(lin, J_out, idx, dz_before[fold == k])
        d = after - before_mm
        se = float(d.std(ddof=1) / np.sqrt(len(d))) if len(d) > 1 else float("inf")
        out.append(Contribution(spec, joint, float(before_mm.mean()), float(after.mean()), float(d.mean()), se, rest))
    return tuple(out)


def param_index(model, spec, params) -> np.ndarray:
    """Indices into the model's unknowns x of effect ``spec``'s parameters ``params``."""
    i = model.base_.n_base
    for e in model.effect_set_.effects:
        if e.spec == spec:
            return np.array([i + e.param_names.index(p) for p in params], dtype=int)
        i += e.n_params
    raise KeyError(spec)


def _heldout_without(lin, J_out, idx, dz_out) -> np.ndarray:
    """Held-out position errors (mm) of the fold's model with the unknowns ``idx`` held at zero
    (first order, see the module)."""
    x = lin.model.x_
    free = np.array([i for i in lin.free if i not in set(idx)], dtype=int)
    shifted = lin.residual - lin.J[:, idx] @ x[idx]
    step = -np.linalg.lstsq(lin.J[:, free], shifted, rcond=None)[0] if len(free) else np.zeros(0)
    moved = dz_out + np.einsum("nap,p->na", J_out[:, :, free], step) - np.einsum("nap,p->na", J_out[:, :, idx], x[idx])
    return np.linalg.norm(moved, axis=1) * 1e3


def joint_swaps(current, robot, rivals) -> list:
    """Each joint of each joint-indexed effect of ``current`` (specs) with each of ``rivals`` (bare
    names of joint-indexed effects) that is another effect and not on that joint in the model:
    [(spec, joint, param names of the joint taken out, the effect on that joint alone, the rival
    on it)]."""
    out = []
    for spec in current:
        effect = make_effect(spec, robot)
        if not takes_joints(type(effect)):
            continue
        base = split_joints(spec)[0]
        for j in effect.joints:
            rest = without_joints(spec, [j], robot)
            kept = set(make_effect(rest, robot).param_names) if rest else set()
            params = tuple(p for p in effect.param_names if p not in kept)
            for other in rivals:
                if effect_class(other).name == effect.name or j in model_joints(current, other, robot):
                    continue
                out.append((spec, j, params, joint_spec(base, [j]), joint_spec(split_joints(other)[0], [j])))
    return out
