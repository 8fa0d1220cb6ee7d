"""What the measured poses cannot tell: identifiability on the training data, in words.

The base parameters (:mod:`campaign.model.base_params`) are those of the robot in general, from
random poses. A campaign's own poses may determine fewer: a joint that never moved merges its
zero offset and axis with its neighbours' frames, a wrist that barely turned leaves directions
known a thousand times worse than the rest, two reflectors never see the rotation about their
line. Here the fit's own whitened Jacobian on the training poses (its free unknowns: base
parameters, effect parameters, the tracker pose through the base transform) is column-scaled and
decomposed; each direction whose singular value is below :data:`~campaign.tolerances.
IDENT_NULL_RTOL` of the largest is *not identified*, below :data:`~campaign.tolerances.
IDENT_WEAK_RTOL` *barely identified*. Each is named by its largest parameters in a calibration
engineer's words and by the joints that did not move.

A least-squares fit then holds one unknown per unidentified direction at its nominal value
(the columns a QR with column pivoting leaves last), a MAP fit holds them at the prior, and the
warnings (code ``unidentifiable``) say which.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from campaign.measure.plausibility import Finding
from campaign.tolerances import IDENT_NULL_RTOL, IDENT_WEAK_RTOL, JOINT_NARROW_FRACTION, JOINT_STILL_RAD

CODE = "unidentifiable"
_AXES = {"x": "x", "y": "y", "z": "z"}


def parameter_words(robot, name: str, frame: str = "robot") -> str:
    """A parameter in a calibration engineer's words: ``pq1`` -> "joint 1's zero offset",
    ``pR_6E_x`` -> "the tool's rotation about its x axis"; effect parameters by name."""
    if name not in robot.param_names:
        return f"the effect parameter {name}"
    N = robot.n_joints
    k = robot.param_names.index(name) // 6  # the transform: 0 base, 1..N joints, N + 1 tool
    axis = _AXES.get(name[-1], name[-1])
    if name.startswith("pq"):
        return f"joint {k}'s zero offset"
    if name.startswith("pd"):
        return f"joint {k}'s length offset"
    who = ("the base's (the tracker's pose)" if frame == "tracker" else "the base's") if k == 0 else \
        "the tool's" if k == N + 1 else f"joint {k}'s"
    if name.startswith("pL"):
        return f"{who} position along {axis}" if k in (0, N + 1) else f"{who} frame offset along {axis}"
    if k in (0, N + 1):
        return f"{who} rotation about its {axis} axis" if k == N + 1 else f"{who} rotation about {axis}"
    return f"{who} axis tilt about {axis}"


def still_joints(robot, q) -> list:
    """[(joint index j (0-based), its value (rad or m), poses)] of the joints whose training range
    ``q`` (n, N) spans less than JOINT_STILL_RAD (a joint that never moved)."""
    q = np.asarray(q, dtype=float)
    span = q.max(axis=0) - q.min(axis=0)
    return [(j, float(np.median(q[:, j])), len(q)) for j in range(robot.n_joints) if span[j] < JOINT_STILL_RAD]


def _joint_value(robot, j, value) -> str:
    return f"{value * 1e3:.1f} mm" if robot.prismatic[j] else f"{np.degrees(value):.1f}°"


@dataclass(frozen=True)
class Direction:
    """One direction of the unknowns the data do not (``kind`` "unidentified") or barely ("weak")
    determine: its singular value relative to the largest, its largest parameters (name, weight)."""

    kind: str
    ratio: float
    parameters: tuple

    def as_json(self) -> dict:
        return {"kind": self.kind, "relative_singular_value": float(self.ratio),
                "parameters": [{"name": n, "weight": float(w)} for n, w in self.parameters]}


@dataclass(frozen=True)
class Identifiability:
    """The training poses' verdict on the unknowns of a fit: ``rank`` of ``n_unknowns`` free ones,
    the column-scaled ``condition_number`` (inf when rank-deficient), the unidentified and weak
    ``directions``, the joints that never moved (``still``), the unknowns ``held`` for it and how
    (``held_at``: "nominal" for least squares, "prior" for MAP)."""

    rank: int
    n_unknowns: int
    condition_number: float
    directions: tuple = ()
    still: tuple = ()
    held: tuple = ()
    held_at: str = "nominal"
    words: tuple = ()
    held_words: tuple = ()
    #: (joint index, training span) of the joints that moved less than JOINT_NARROW_FRACTION of their range
    narrow: tuple = ()
    #: what in the measurement leaves a direction unobserved (raw reflectors: at most two seen a pose)
    hint: str = ""
    #: a relation among joints the training poses kept ("q2 + q3 = 81.9°"), and their number
    relation: str = ""
    n_train: int = 0
    #: the directions the measured points do not see that move the tool frame's origin, in words
    unseen: tuple = ()
    #: positions only at the tool point (one reflector): no orientation of the tool is observed
    orientation_unseen: bool = False

    @property
    def unidentified(self) -> list:
        return [d for d in self.directions if d.kind == "unidentified"]

    @property
    def weak(self) -> list:
        return [d for d in self.directions if d.kind == "weak"]

    def findings(self, robot) -> list:
        """Warnings (code ``unidentifiable``): one per joint that never moved, one for the other
        unidentified directions, one for the barely identified ones."""
        out = []
        where = "at their nominal value" if self.held_at == "nominal" else "at their prior (the tolerances)"
        held = f"; held {where}: {', '.join(self._held_words)}" if self.held else (
            f"; held {where}" if self.unidentified else "")
        for j, value, n in self.still:
            what = "length offset and axis direction" if robot.prismatic[j] else "zero offset and axis"
            out.append(Finding(CODE, f"joint {j + 1} never moved (q{j + 1} = {_joint_value(robot, j, value)} in all "
                                     f"{n} training poses): its {what} cannot be identified, and the "
                                     f"model holds only at q{j + 1} = {_joint_value(robot, j, value)}{held}; "
                                     f"measure poses over q{j + 1}'s range"))
            held = ""
        if self.unidentified and not self.still:
            hint = self.hint or (f"{self.relation} in all {self.n_train} training poses (those joints moved only "
                                 "together)" if self.relation else "")
            out.append(Finding(CODE, f"{hint + ': ' if hint else ''}{len(self.unidentified)} direction(s) "
                                     f"of the model are not identified by the training poses (rank {self.rank} of "
                                     f"{self.n_unknowns} unknowns): {'; '.join(self.words[:len(self.unidentified)])}"
                                     f"{held}; measure poses that move them"))
        if self.orientation_unseen:
            out.append(Finding(CODE, "positions only (one reflector, or --position-only): the tool's orientation is not observed: its "
                                     "rotation about its x, y and z axes is held at nominal, so the rx, ry, rz that "
                                     "predict writes are the nominal tool's there and sigma_mm is the position's; "
                                     "measure three reflectors (6-D poses) for the orientation"))
        if self.unseen:
            out.append(Finding(CODE, f"{self.hint or 'the reflectors measured'}: the tool frame's origin moves along "
                                     f"what they do not see ({'; '.join(self.unseen)}): held at nominal there, "
                                     "its tolerance is in sigma_mm; measure three reflectors or the tool point"))
        if self.weak:
            w = self.words[len(self.unidentified):]
            out.append(Finding(CODE, f"{len(self.weak)} direction(s) barely identified (singular value below "
                                     f"{IDENT_WEAK_RTOL:g} of the largest, σ ≥ {1 / IDENT_WEAK_RTOL:.0f}× the best "
                                     f"known){self._narrow_text(robot)}: {'; '.join(w)}; their uncertainty is in "
                                     "sigma_mm"))
        return out

    @property
    def _held_words(self) -> list:
        return [f"{w} ({n})" for n, w in zip(self.held, self.held_words)]

    def _narrow_text(self, robot) -> str:
        if not self.narrow:
            return ""
        return "; " + ", ".join(f"joint {j + 1} moved only {_joint_value(robot, j, span)} of its "
                                f"{_joint_value(robot, j, robot.q_upper[j] - robot.q_lower[j])} range"
                                for j, span in self.narrow)

    def as_json(self) -> dict:
        return {"rank": self.rank, "n_unknowns": self.n_unknowns,
                "condition_number": None if not np.isfinite(self.condition_number) else float(self.condition_number),
                "directions": [d.as_json() for d in self.directions], "words": list(self.words),
                "still_joints": [{"joint": j + 1, "value": v, "poses": n} for j, v, n in self.still],
                "held": list(self.held), "held_at": self.held_at}


def _scaled_directions(J):
    """(singular values, right singular vectors, column norms) of the column-scaled (n·m, f) J, largest
    first: from the eigen-decomposition of its f × f normal matrix (a 14,000-pose campaign's J has
    84,000 rows; its SVD costs a quarter of a second, this a few milliseconds). Round-off leaves a
    null direction's singular value near √eps ≈ 1e-8 of the largest, which IDENT_NULL_RTOL is above."""
    from campaign.identify.solver import _normal_equations

    H, _ = _normal_equations(J, np.zeros(J.shape[:2]))
    d = np.sqrt(np.diag(H))
    d = np.where(d > 0, d, 1.0)
    w, V = np.linalg.eigh(H / np.outer(d, d))
    order = np.argsort(w)[::-1]
    return np.sqrt(np.clip(w[order], 0.0, None)), V[:, order].T, d


def analyse(model, q_train, frame: str = "robot", held=(), held_at: str = "nominal") -> Identifiability:
    """The identifiability of a fitted CalibrationModel's free unknowns on its training poses
    ``q_train`` (n, N): from its whitened Jacobian at the fit (``fit_jacobian_``)."""
    robot = model.robot
    J = model.fit_jacobian_
    names = [model.unknown_names_[i] for i in model.free_]
    still = tuple(still_joints(robot, q_train))
    q_train = np.asarray(q_train, dtype=float)
    span = q_train.max(axis=0) - q_train.min(axis=0)
    limits = robot.q_upper - robot.q_lower
    narrow = tuple((j, float(span[j])) for j in range(robot.n_joints)
                   if JOINT_STILL_RAD <= span[j] < JOINT_NARROW_FRACTION * limits[j])
    if J.shape[-1] == 0:
        return Identifiability(0, 0, float("inf"), still=still)
    s, vt, _ = _scaled_directions(J)
    s_max = s[0] if len(s) and s[0] > 0 else 1.0
    ratio = s / s_max
    n_free = J.shape[-1]
    rank = int(np.sum(ratio >= IDENT_NULL_RTOL))
    dirs, words = [], []
    for i in range(len(s) - 1, -1, -1):  # the least determined first
        if ratio[i] >= IDENT_WEAK_RTOL:
            continue
        kind = "unidentified" if ratio[i] < IDENT_NULL_RTOL else "weak"
        v = vt[i]
        top = np.argsort(-np.abs(v))[:3]
        top = [t for t in top if abs(v[t]) >= 0.25 * abs(v[top[0]])]
        dirs.append(Direction(kind, float(ratio[i]), tuple((names[t], float(v[t])) for t in top)))
    dirs.sort(key=lambda d: (d.kind != "unidentified", d.ratio))
    for d in dirs:
        words.append(" with ".join(parameter_words(robot, n, frame) for n, _ in d.parameters))
    cond = float(s_max / s[-1]) if s[-1] > 0 and rank == n_free else float("inf")
    return Identifiability(rank=min(rank, n_free), n_unknowns=n_free, condition_number=cond, directions=tuple(dirs),
                           still=still, held=tuple(held), held_at=held_at, words=tuple(words),
                           held_words=tuple(parameter_words(robot, n, frame) for n in held), narrow=narrow,
                           relation=_relation(robot, q_train), n_train=len(q_train))


def _relation(robot, q_train) -> str:
    """A relation among joints the training poses kept, in words ("q2 + q3 = 81.9°"; "" when none)."""
    from campaign.identify.domain import calibrated_domain

    if robot.prismatic.any() and not robot.prismatic.all():
        unit = lambda v: f"{v:.4f} (rad and m)"  # noqa: E731
    else:
        unit = lambda v: _joint_value(robot, 0, v)  # noqa: E731
    return calibrated_domain(robot, q_train).relation_words([f"q{j + 1}" for j in range(robot.n_joints)], unit)


def unknowns_to_hold(model) -> list:
    """Names of the free unknowns a least-squares fit holds at nominal so that the rest are
    identified on its training poses: QR with column pivoting of the column-scaled Jacobian, the
    last pivots beyond its rank."""
    import scipy.linalg

    J = model.fit_jacobian_
    J2 = J.reshape(-1, J.shape[-1])
    d = np.linalg.norm(J2, axis=0)
    J2 = J2 / np.where(d > 0, d, 1.0)
    _, R, piv = scipy.linalg.qr(J2, mode="economic", pivoting=True)
    diag = np.abs(np.diag(R))
    rank = int(np.sum(diag >= IDENT_NULL_RTOL * diag[0])) if len(diag) else 0
    names = [model.unknown_names_[i] for i in model.free_]
    return [names[i] for i in piv[rank:]] + [names[i] for i in range(len(names)) if i not in set(piv.tolist())]


def hold_unidentified(make, model, q, Y, context=None, *, frame: str = "robot", progress=None):
    """(model, Identifiability): ``model`` (fitted by ``make(**kw)`` on q, Y, context) analysed on
    its training poses; a least-squares fit with unidentified directions is fitted again with one
    unknown a direction held at nominal (base parameters dropped, effect parameters fixed); a MAP
    fit keeps its prior there. ``make(drop=..., fixed=...)`` gives the unfitted model again."""
    from dataclasses import replace

    say = progress or (lambda msg: None)
    from campaign.identify.uncertainty import unseen_at_tool

    first = analyse(model, q, frame)
    unseen = tuple(" with ".join(parameter_words(model.robot, n, frame) for n in d) for d in unseen_at_tool(model))
    first = replace(first, unseen=unseen, orientation_unseen=bool(model.position_only and model.points is None))
    if model.points is not None and (first.unidentified or unseen):
        seen = np.isfinite(np.asarray(Y, dtype=float)).all(axis=2).sum(axis=1)
        if seen.max(initial=0) <= 2:
            first = replace(first, hint=f"at most two of the {len(model._points())} reflectors seen in any pose: the "
                                        "tool's rotation about their line is not observed")
    if not first.unidentified:
        return model, first
    if model.kind_ == "map":
        return model, replace(first, held_at="prior")
    hold = unknowns_to_hold(model)
    base_names = set(model.base_.names)
    drop = tuple(model.drop or ()) + tuple(n for n in hold if n in base_names)
    fixed = dict(model.fixed or {})
    fixed.update({n: None for n in hold if n not in base_names})
    say(f"{len(hold)} unknown(s) not identified by the training poses: held at nominal ({', '.join(hold)})")
    refit = make(drop=drop, fixed=fixed or None).fit(q, Y, context, base=model.base_,
                                                     init={k: v for k, v in model.values_.items() if k not in hold})
    return refit, replace(first, held=tuple(hold), held_at="nominal",
                          held_words=tuple(parameter_words(model.robot, n, frame) for n in hold))
