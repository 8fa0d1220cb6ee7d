"""Where in the chain an error arises: the model's rotation error in each joint's frame.

The model-free test (:mod:`campaign.diagnose.structure`) reads the *position* residual, and a
position error at the tool is a rotation somewhere in the arm times the lever from there to the
tool. The lever turns with every joint after the one that errs, so for a tilt of a wrist joint's
axis the joints after it (q6) carry as much of the position error as the joint that tilts (q4 or
q5), and permutation importance ranks the wrong one first.

The rotation error has no lever. An error that arises at joint j and depends on its own angle (a
bearing's run-out, a cyclic error of its gear) rotates the links after j by the same small angle,
whatever the joints after j do: expressed in the frame after joint j, the measured rotation
residual is a function of the joints up to j alone, and of q_j alone for a run-out of joint j.
In the frame after joint 1 the same residual turns with q2 ... q_j, in the tool frame with
q_{j+1} ... q_N. So the test is run on the rotation residual in the frame after each joint; the
frame where the regressor predicts most of it is where the error arises, and its inputs are
what the error depends on (a run-out of the COMAU's joint 4: q4 alone there, against q6 0.47, q4
0.45 on the position residual in the tool frame).

It needs the rotation: a run measured with fewer than three reflectors per pose has none, and the
position test alone speaks. A pure translation (a link that grows as it warms) has no rotation
error, and the test finds nothing there.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from campaign.diagnose.structure import StructureResult, joints_only, pose_or_all_structure, structure_test

#: the screen of the joint frames fits the regressor on at most this many poses per fold (the full
#: test on the chosen frame on MAX_FIT_POSES): 12 fits of 1,500 poses cost about 40 s on 14,000 poses
SCREEN_FIT_POSES = 400
#: the rotation test's inputs lead only when it predicts at least this share of the held-out gain
#: the position test reaches (each of its own error)
ROTATION_LEADS_SHARE = 0.5


@dataclass(frozen=True)
class ChainStructure:
    """The model-free test on the held-out rotation residual (errors in mrad), in the frame after
    the joint where it predicts most: ``joint`` (1-based), its ``result`` (importance computed);
    ``gains``: each joint frame's held-out gain, in the order of the joints; ``p_value``: the
    best frame's, times the number of tests (Bonferroni); ``significant``: p < α and the gain
    reaches the detection limit."""

    joint: int
    result: StructureResult = field(repr=False)
    gains: tuple
    p_value: float
    significant: bool
    n_joints: int = 6
    #: the held-out rotation residual (n, 3) rad resolved in the frame after ``joint``, and the
    #: regressor's inputs (n, d) it was tested on, in the order of the training poses
    residual: np.ndarray = field(repr=False, default=None)
    inputs: np.ndarray = field(repr=False, default=None)

    @property
    def heldout_gain(self) -> float:
        return self.result.heldout_gain

    @property
    def after_mrad(self) -> float:
        """The regressor's held-out mean rotation error, mrad."""
        return float(self.result.after.mean())

    @property
    def before_mrad(self) -> float:
        """The current model's held-out mean rotation error, mrad."""
        return float(self.result.before.mean())

    def depends_on(self, min_share: float) -> list:
        return self.result.depends_on(min_share)

    def text(self, min_share: float) -> str:
        verdict = "significant" if self.significant else "not significant"
        out = (f"rotation error in the frame after joint {self.joint}: a flexible regressor predicts "
               f"{100 * self.heldout_gain:.1f} % of it ({self.before_mrad:.3f} → {self.after_mrad:.3f} mrad; "
               f"p = {self.p_value:.2g}): {verdict}")
        if self.significant:
            inputs = self.depends_on(min_share)
            out += "\n    depends on " + ", ".join(f"{k} ({100 * self.result.importance[k]:.0f} %)" for k in inputs)
            last = max((int(k[1:]) for k in inputs if k[:1] == "q" and k[1:].isdigit()), default=None)
            if last is not None and last < self.n_joints:
                out += (f"; no joint after joint {last} changes it there: it arises at joint {last} or before it "
                        "(a rotation there turns every link after it alike, without a lever)")
        return out

    def as_json(self) -> dict:
        return {"joint": self.joint, "heldout_gain": self.heldout_gain, "p_value": self.p_value,
                "significant": bool(self.significant), "heldout_mean_mrad_before": self.before_mrad,
                "heldout_mean_mrad_after": self.after_mrad,
                "importance": dict(sorted(self.result.importance.items(), key=lambda kv: -kv[1])),
                "gain_by_joint_frame": {f"J{j + 1}": float(g) for j, g in enumerate(self.gains)}}


def chain_structure(R_joints, X, input_names, n_joints: int, fold, rot_fit, rot_out, *, alpha: float,
                    detection: float) -> ChainStructure:
    """The model-free test on the held-out rotation residual in the frame after each joint.

    R_joints (n, N, 3, 3): each training pose's frame after each joint (nominal); X (n, d) the
    regressor's inputs (joints first); fold (n,); rot_fit: fold -> the fold model's rotation
    residual (n_fit, 3) rad at its fitting poses (fold != k, in order); rot_out (n, 3) rad: the
    held-out rotation residual, both in the robot's base frame. Each frame is screened on the
    joints alone (the regressor on at most SCREEN_FIT_POSES poses per fold); the frame where it
    predicts most is then tested in full on the joints alone and, when X has more columns (time,
    temperature), on every input: the better of the two (lower held-out error), its p times the
    number of frames and input sets (Bonferroni over the 2 N tests the screen chose among)."""
    X = np.asarray(X, dtype=float)
    X_q = joints_only(X, n_joints)
    framed = []
    for j in range(n_joints):
        R = R_joints[:, j]
        out_j = np.einsum("nji,nj->ni", R, rot_out)
        fit_j = {k: np.einsum("nji,nj->ni", R[fold != k], r) for k, r in rot_fit.items()}
        framed.append((fit_j, out_j))
    gains = [structure_test(X if X_q is None else X_q, input_names, fold, fit_j, out_j, importance=False,
                            max_fit_poses=SCREEN_FIT_POSES).heldout_gain for fit_j, out_j in framed]
    j = int(np.argmax(gains))
    fit_j, out_j = framed[j]
    result = pose_or_all_structure(X, input_names, n_joints, fold, [(fit_j, out_j)])  # p × its input sets
    p = min(1.0, n_joints * result.p_value)
    significant = bool(p < alpha and result.heldout_gain >= detection)
    return ChainStructure(j + 1, result, tuple(gains), p, significant, n_joints=n_joints, residual=out_j, inputs=X)


def with_rotation_first(depends_on, chain: ChainStructure | None, min_share: float,
                        position_gain: float | None = None) -> list:
    """The inputs ``depends_on`` (the position test's) with the rotation test's in front, when it is
    significant: where the error arises says which joint it depends on (module docstring). Not
    when the position test is significant (``position_gain``: its held-out gain) and the rotation
    test predicts less than ROTATION_LEADS_SHARE of that share of its own error: a weak rotation
    beside a strong position structure is not what the error is (an elbow that sags along z3 by
    k cos(q2 + q3), a translation: the position test 80 % on q1, q3, q2; the rotation 4 % on q4,
    p = 0.007)."""
    if chain is None or not chain.significant:
        return list(depends_on)
    if position_gain is not None and chain.heldout_gain < ROTATION_LEADS_SHARE * position_gain:
        return list(depends_on)
    first = chain.depends_on(min_share)
    return first + [k for k in depends_on if k not in first]

