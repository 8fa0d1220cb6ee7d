"""A run measured on more than one cell: one registration per cell segment, and whether the
segments are one robot beyond it.

A run resumed on another cell (``--allow-other-cell``, campaign.measure.cell_identity) holds
*cell segments*: the poses of each recorded cell (``RunFolder.cell_segments``). Two cells are two
tracker placements at least (another base frame, another tracker registration) and possibly two
robots. So a mixed run is modelled, not read as one cell:

1. **A step per segment, not a drift.** Each segment's measurements are mapped into the frame
   of the reference segment (the first kept one: the run's base-frame set-up was measured there)
   by a rigid transform ``M_s``: first the closed-form registration of the nominal model's tool
   points to each segment's measured ones (Kabsch), then refined jointly with the geometric model
   (and the current effects) as six unknowns per other segment (:class:`CellStep`, a pose map
   identified by the same solver), on the training poses.
2. **Do the segments agree beyond it?** On the training poses, K folds (within each segment):
   the *joint* model (geometric + current effects + the steps) fitted on the other folds of every
   segment, against a *separate* model per segment (geometric + current effects, fitted on that
   segment's other folds alone), both predicting the held-out poses. For a segment with enough
   poses for its own model the statistic is a one-sided paired t-test of the held-out position
   errors, joint minus separate, on its held-out poses; for a smaller one a one-sided Welch test
   of its held-out errors under the joint model against the other segments'. A segment
   *disagrees* when p < CELL_AGREEMENT_ALPHA / (segments tested) and its mean held-out error
   under the joint model exceeds the other's by more than CELL_AGREEMENT_MARGIN
   (campaign.tolerances). Poses measured on both cells, each cell in its own set-up's frame,
   decide instead when there are any (:func:`repeat_tests`): a model's test on two parts of the
   workspace also finds what the model lacks there.
3. **The decision.** All agree: calibrate on every pose with the per-segment registrations
   (``"mixed"``). One disagrees: refused in one line naming the segments, unless one segment is
   asked for (``--cell-segment N``: ``"segment"``, its poses alone, mapped by the initial
   registration into the reference frame).

A segment with fewer than CELL_MIN_REGISTRATION_POSES training poses cannot be registered: its
poses are left out, and the line says so. A run measured on one cell is left exactly as it is.
"""

from __future__ import annotations

from dataclasses import dataclass, field, replace

import numpy as np

from campaign.effects.base import Effect
from campaign.errors import ConfigError, DataError
from campaign.tolerances import (CELL_AGREEMENT_ALPHA, CELL_AGREEMENT_MARGIN, CELL_FOLDS,
                                 CELL_MIN_REGISTRATION_POSES)

#: the context column carrying each pose's segment (index into the kept segments) during the fits
SEGMENT_KEY = "cell_segment"


class CellStep(Effect):
    """The step of each non-reference segment: its measured poses are ``E_s · T`` of the model's
    ``T``, E_s a rigid motion (translation t_s in m, rotation vector r_s in rad, in the reference
    frame). Context ``cell_segment``: the segment's index (0: the reference, no step). Not in the
    registry: no candidate of `diagnose`, only built for a mixed run."""

    name = "cell_step"
    description = "a step between cell segments: another tracker placement or base frame"
    context_keys = (SEGMENT_KEY,)

    def __init__(self, robot, n_segments: int):
        super().__init__(robot)
        self.n_segments = int(n_segments)
        self.param_names = tuple(f"{n}_segment{s + 1}" for s in range(1, self.n_segments)
                                 for n in ("t_x", "t_y", "t_z", "r_x", "r_y", "r_z"))
        self.param_units = tuple(u for _ in range(1, self.n_segments) for u in ("m",) * 3 + ("rad",) * 3)

    def pose_map(self, params, T, q, context):
        seg = np.asarray(context[SEGMENT_KEY]).astype(int)
        out = np.array(T, dtype=float, copy=True)
        for s in range(1, self.n_segments):
            rows = seg == s
            if rows.any():
                out[rows] = step_matrix(params[6 * (s - 1):6 * s]) @ out[rows]
        return out


def step_matrix(p) -> np.ndarray:
    """(4, 4) of a step (t_x, t_y, t_z in m, r_x, r_y, r_z a rotation vector in rad)."""
    from campaign.model.rotations import rotvec_to_matrix

    E = np.eye(4)
    E[:3, :3] = rotvec_to_matrix(np.asarray(p[3:6], dtype=float))
    E[:3, 3] = p[:3]
    return E


def _rigid_json(T) -> dict:
    from campaign.model.rotations import matrix_to_rotvec

    T = np.asarray(T, dtype=float)
    return {"translation_m": [float(v) for v in T[:3, 3]],
            "rotation_vector_rad": [float(v) for v in matrix_to_rotvec(T[:3, :3])]}


@dataclass(frozen=True)
class SegmentTest:
    """The agreement test of one segment (module docstring, step 2)."""

    segment: int  # 0-based, into CellSegments.cells
    test: str  # "paired" (its own model), "welch" (too few poses for one) or "repeat" (the same poses)
    n_heldout: int  # held-out poses; "repeat": the poses measured on both cells
    joint_mm: float  # mean held-out position error under the joint model; "repeat": mean distance between cells
    other_mm: float  # ... under its own model (paired) or of the other segments under the joint one (welch);
    #                  "repeat": the distance the noise and the two set-ups allow (rms)
    t: float  # t; "repeat": chi-squared
    p: float
    disagrees: bool
    #: whether this test decides (a model's test does not where the same poses were measured on both cells)
    decisive: bool = True

    @property
    def ratio(self) -> float:
        return self.joint_mm / max(self.other_mm, 1e-300)

    def as_json(self) -> dict:
        if self.test == "repeat":
            return {"segment": self.segment + 1, "test": "repeat", "n_poses": self.n_heldout,
                    "mean_distance_mm": self.joint_mm, "expected_distance_mm": self.other_mm, "chi2": self.t,
                    "p": self.p, "disagrees": self.disagrees, "decisive": True}
        return {"segment": self.segment + 1, "test": self.test, "n_heldout": self.n_heldout, "decisive": self.decisive,
                "heldout_mean_position_mm_joint": self.joint_mm,
                ("heldout_mean_position_mm_alone" if self.test == "paired" else
                 "heldout_mean_position_mm_other_segments"): self.other_mm,
                "ratio": self.ratio, "t": self.t, "p": self.p, "disagrees": self.disagrees}

    def text(self) -> str:
        if self.test == "repeat":
            return (f"segment {self.segment + 1}: {self.n_heldout} pose{'s' if self.n_heldout > 1 else ''} measured on "
                    f"both cells {self.joint_mm:.4f} mm apart, the noise and the set-ups allow {self.other_mm:.4f} mm "
                    f"(chi2 = {self.t:.3g}, p = {self.p:.2g})")
        other = "alone" if self.test == "paired" else "the other segments' in it"
        return (f"segment {self.segment + 1}: held-out {self.joint_mm:.4f} mm in one model vs {self.other_mm:.4f} mm "
                f"{other} (x{self.ratio:.2f}, {'paired' if self.test == 'paired' else 'Welch'} t = {self.t:.2f}, "
                f"p = {self.p:.2g}, {self.n_heldout} poses{'' if self.decisive else '; not deciding'})")


@dataclass(frozen=True)
class CellDecision:
    """How a mixed-cell run is modelled: its segments, the kept ones and the reference, the map of
    each kept segment's measurements into the reference frame, the agreement tests, and the decision
    ("mixed", "segment" or "refused")."""

    segments: object  # campaign.measure.cell_identity.CellSegments
    pose_segment: np.ndarray  # (n,) segment of each pose of the data it was made for
    kept: tuple
    reference: int
    maps: dict  # segment -> (4, 4) map of its measurements into the reference frame
    initial_maps: dict
    tests: tuple
    decision: str
    chosen: int | None = None
    left_out: dict = field(default_factory=dict)  # segment -> why its poses were left out
    pose_ids: np.ndarray | None = None

    @property
    def agree(self) -> bool:
        return not any(t.disagrees and t.decisive for t in self.tests)

    def registration_json(self) -> list:
        return [{"segment": s + 1, "reference": s == self.reference, **_rigid_json(self.maps[s])}
                for s in sorted(self.maps)]

    def as_json(self) -> dict:
        """metrics.json / diagnosis.json ``cells`` (docs/cells.md)."""
        return {"decision": self.decision, "segment": None if self.chosen is None else self.chosen + 1,
                "reference_segment": self.reference + 1,
                "segments": self.segments.as_json(self.pose_ids),
                "left_out": [{"segment": s + 1, "why": why} for s, why in sorted(self.left_out.items())],
                "registration": self.registration_json(),
                "agreement": {"statistic": "held-out position error of one model with a registration per "
                                           "segment against each segment alone (paired one-sided t) or, for a "
                                           "segment too small for its own model, against the other segments "
                                           "(one-sided Welch t); where poses were measured on both cells, each "
                                           "in its own set-up's frame, their distance against the noise and the "
                                           "set-ups (chi-squared), which then decides",
                              "alpha": CELL_AGREEMENT_ALPHA, "margin": CELL_AGREEMENT_MARGIN,
                              "agree": self.agree, "tests": [t.as_json() for t in self.tests]}}

    def _names(self) -> str:
        """Each segment described (its cell, its poses), "; "-separated."""
        return "; ".join(self.segments.describe(s, self.pose_ids) for s in range(self.segments.n))

    def line(self) -> str:
        """One line: what was decided, and why."""
        names = self._names()
        tests = "; ".join(t.text() for t in self.tests) or "no segment could be tested"
        out = "".join(f"; {self.segments.label(s)} left out: {why}" for s, why in sorted(self.left_out.items()))
        if self.decision == "mixed":
            steps = ", ".join(f"segment {s + 1} {_step_words(self.maps[s])}" for s in sorted(self.maps)
                              if s != self.reference)
            return (f"measured on {self.segments.n} cells ({names}): they agree beyond one registration per segment "
                    f"({tests}); modelled on all poses with per-segment registrations into segment "
                    f"{self.reference + 1}'s frame ({steps}){out}")
        return (f"measured on {self.segments.n} cells ({names}); --cell-segment {self.chosen + 1}: its poses alone "
                f"({tests}){out}")

    def refusal(self, run_dir) -> str:
        names = self._names()
        bad = "; ".join(t.text() for t in self.tests if t.disagrees and t.decisive)
        if not any(t.test == "repeat" for t in self.tests):  # the model alone: say what else it can be
            bad += ("; no pose was measured on both cells in their own set-ups, so this rests on the model, which "
                    "an effect it lacks on two parts of the workspace can mislead too (docs/cells.md)")
        return (f"{run_dir}: measured on {self.segments.n} cells that do not agree beyond a registration ({names}; {bad}): "
                f"they are not one robot in one model; calibrate (diagnose, auto) one segment with --cell-segment N "
                f"(N = 1..{self.segments.n}), or measure the rest on one cell")

    def apply(self, poses):
        """``poses`` (MeasuredPoses of the run, as stored) restricted to the kept (or chosen) segment(s),
        each mapped into the reference frame; (poses, the kept rows)."""
        use = (self.chosen,) if self.chosen is not None else self.kept
        pose_segment = self.segments.of(poses.pose_id)
        rows = np.flatnonzero(np.isin(pose_segment, use))
        out = poses.subset(rows)
        seg = pose_segment[rows]
        M = np.stack([self.maps[int(s)] for s in seg]) if len(seg) else np.zeros((0, 4, 4))
        T = M @ out.T_IE
        if not out.has_orientation:
            T[:, :3, :3] = np.eye(3)
        markers = None if out.markers is None else \
            np.einsum("nij,nkj->nki", M[:, :3, :3], out.markers) + M[:, None, :3, 3]
        out = replace(out, T_IE=T, **({} if markers is None else {"markers": markers}))
        return out, rows

    def reading_map(self, segment: int):
        """(4, 4): a reading of ``segment`` (in its measured frame) into the reference frame, or None
        when the segment is not used."""
        use = (self.chosen,) if self.chosen is not None else self.kept
        return self.maps.get(segment) if segment in use else None


def _step_words(M) -> str:
    from campaign.model.rotations import matrix_to_rotvec

    M = np.asarray(M, dtype=float)
    return (f"moved {np.linalg.norm(M[:3, 3]) * 1e3:.1f} mm, turned "
            f"{np.linalg.norm(matrix_to_rotvec(M[:3, :3])) * 1e3:.2f} mrad")


# -- the steps -------------------------------------------------------------------------------------
def check_cell_segment(segments, cell_segment) -> int | None:
    """``--cell-segment N`` (1-based) as a 0-based index, ConfigError naming the run's segments
    when out of range; None when not given."""
    if cell_segment is None:
        return None
    if isinstance(cell_segment, bool) or not isinstance(cell_segment, (int, np.integer)) \
            or not 1 <= cell_segment <= segments.n:
        what = "one cell segment (it was measured on one cell)" if segments.n == 1 else \
            f"{segments.n} cell segments"
        raise ConfigError(f"--cell-segment {cell_segment!r}: the run has {what}; give 1..{segments.n}")
    return int(cell_segment) - 1


def initial_maps(robot, poses, seg, train, kept) -> tuple:
    """(segment -> (4, 4) map of its measurements into the first kept segment's frame, the (4, 4)
    registration of the nominal model into that frame), from the closed-form registration of the
    nominal model's tool points to each segment's training poses."""
    from campaign.measure.reflectors import invert, register_points
    from campaign.model.kinematics import forward

    reg = {}
    for s in kept:
        rows = np.flatnonzero(train & (seg == s) & np.isfinite(poses.xyz).all(axis=1))
        reg[s] = register_points(forward(robot, poses.q[rows])[:, :3, 3], poses.xyz[rows])
    ref = kept[0]
    return {s: reg[ref] @ invert(reg[s]) for s in kept}, reg[ref]


def _fit(robot, effects, position_only, q, T, ctx, base, init=None):
    from campaign.identify.solver import CalibrationModel

    return CalibrationModel(robot=robot, effects=list(effects), position_only=position_only).fit(
        q, T, ctx, base=base, init=init)


def _folds(pose_id, seg, k) -> np.ndarray:
    """Fold (n,) of each pose: within each segment, round robin over its distinct poses in id order
    (a plan's repeats share their pose's fold)."""
    from campaign.plan.selection import base_pose_id

    base = base_pose_id(np.asarray(pose_id, dtype=np.int64))
    fold = np.zeros(len(base), dtype=np.int64)
    for s in np.unique(seg):
        rows = np.flatnonzero(seg == s)
        ids, inv = np.unique(base[rows], return_inverse=True)
        fold[rows] = (np.arange(len(ids)) % k)[inv.reshape(-1)]
    return fold


def decide_cells(run_dir, robot, poses, train, segments, *, effects=(), cell_segment=None, say=None) -> CellDecision | None:
    """The :class:`CellDecision` for ``poses`` (MeasuredPoses of the run ``run_dir``, in the frame
    they were stored in) with ``train`` (n,) bool the training poses, or None when they come from
    one cell (nothing changes). ``effects``: the current model's effect specs; ``cell_segment``:
    ``--cell-segment N`` (1-based). DataError (one line) when the segments disagree and no segment
    is chosen."""
    from campaign.identify.poses import training_poses_needed
    from campaign.model.base_params import base_parameters

    chosen = check_cell_segment(segments, cell_segment)
    if chosen is not None and not (segments.segment == chosen).any():
        raise DataError(f"{run_dir}: --cell-segment {chosen + 1}: {segments.label(chosen)} holds no measured pose")
    if not segments.mixed:  # one cell's measurements: exactly as they are
        return None
    say = say or (lambda line: None)
    seg = segments.of(poses.pose_id)
    position_only = not poses.has_orientation
    usable = np.isfinite(poses.xyz).all(axis=1)
    counts = {s: int((train & usable & (seg == s)).sum()) for s in range(segments.n)}
    posed = "" if poses.kind != "markers" else " with a pose (three or more reflectors seen)"
    left_out = {s: f"{n} training poses{posed}, too few to register it ({CELL_MIN_REGISTRATION_POSES} needed)"
                for s, n in counts.items() if n < CELL_MIN_REGISTRATION_POSES and (seg == s).any()}
    left_out.update({s: "no pose measured" for s in range(segments.n) if not (seg == s).any()})
    kept = tuple(s for s in range(segments.n) if s not in left_out)
    if not kept and chosen is None:
        raise DataError(f"{run_dir}: measured on {segments.n} cells, none with {CELL_MIN_REGISTRATION_POSES} "
                        f"training poses{posed} to register it: calibrate one segment with --cell-segment N "
                        f"(N = 1..{segments.n})")
    ref = kept[0] if kept else chosen
    maps0, to_ref = initial_maps(robot, poses, seg, train, kept) if kept else ({}, np.eye(4))
    maps, tests = dict(maps0), ()
    if len(kept) > 1:
        maps, tests = _register_and_test(robot, poses, seg, train & usable, kept, maps0, to_ref, effects, position_only,
                                         base_parameters(robot, position_only=position_only), say,
                                         training_poses_needed)
        tests = _with_repeats(tests, repeat_tests(run_dir, robot, poses, segments, kept), kept)
    decision = "mixed" if chosen is None else "segment"
    if chosen is not None:  # its poses alone, in their own frame (each cell's set-up is its own)
        ref, maps = chosen, {chosen: np.eye(4)}
    result = CellDecision(segments, seg, kept, ref, maps, maps0, tests, decision, chosen, left_out,
                          np.asarray(poses.pose_id))
    if chosen is None and not result.agree:
        raise DataError(result.refusal(run_dir))
    return result


@dataclass(frozen=True)
class _Fitting:
    """The training poses of the kept segments as the fits see them: near the nominal model, with
    each pose's segment in the context (``ctx``; ``base_ctx`` without it)."""

    q: np.ndarray
    T: np.ndarray
    seg: np.ndarray  # (n,) segment of each (into CellSegments.cells)
    pose_id: np.ndarray
    ctx: dict
    base_ctx: dict

    def sub(self, rows, joint: bool = True) -> tuple:
        ctx = self.ctx if joint else self.base_ctx
        return self.q[rows], self.T[rows], {key: v[rows] for key, v in ctx.items()}


def _fitting(poses, seg, train, kept, maps0, to_ref) -> _Fitting:
    from campaign.effects.base import effect_context
    from campaign.measure.reflectors import invert

    index = {s: i for i, s in enumerate(kept)}
    rows = np.flatnonzero(train & np.isin(seg, kept))
    T = invert(to_ref) @ np.stack([maps0[int(s)] for s in seg[rows]]) @ poses.T_IE[rows]
    base_ctx = {k: v[rows] for k, v in effect_context(poses.context, poses.time_s).items()}
    ctx = {**base_ctx, SEGMENT_KEY: np.array([index[int(s)] for s in seg[rows]], dtype=float)}
    return _Fitting(poses.q[rows], T, seg[rows], np.asarray(poses.pose_id)[rows], ctx, base_ctx)


def _register_and_test(robot, poses, seg, train, kept, maps0, to_ref, effects, position_only, base, say, needed):
    """(the refined maps, the agreement tests): the joint fit with a step per segment on all training
    poses, then K folds of the joint and the separate models (module docstring). The fits see the
    data near the nominal model (``to_ref``⁻¹ of the reference frame: data in a tracker's frame are
    metres from the robot's), where the model's linearisation holds."""
    from campaign.effects.base import make_effect
    from campaign.measure.reflectors import invert

    data = _fitting(poses, seg, train, kept, maps0, to_ref)
    joint_effects = (*effects, CellStep(robot, len(kept)))
    say(f"cell segments: one model with a registration per segment on {len(data.q)} training poses")
    full = _fit(robot, joint_effects, position_only, *data.sub(slice(None)), base)
    theta = full.effect_set_.split(full.effect_params_)[-1]
    maps = {kept[0]: maps0[kept[0]]}
    for i, s in enumerate(kept[1:], start=1):
        maps[s] = to_ref @ invert(step_matrix(theta[6 * (i - 1):6 * i])) @ invert(to_ref) @ maps0[s]
    need = needed(base.n_base + sum(make_effect(e, robot).n_params for e in effects), position_only)
    fold = _folds(data.pose_id, data.seg, CELL_FOLDS)
    own = {s for s in kept
           if len(np.unique(data.q[data.seg == s], axis=0)) * (CELL_FOLDS - 1) // CELL_FOLDS >= need}
    say(f"cell segments: do they agree beyond it? {CELL_FOLDS} folds, one model against "
        + (", ".join(f"segment {s + 1} alone" for s in sorted(own)) or "the segments' held-out errors"))
    joint_err, alone_err = _heldout_errors(robot, data, fold, joint_effects, effects, position_only, base,
                                           full.values_, own)
    return maps, tuple(_segment_test(s, data.seg == s, joint_err, alone_err, len(kept)) for s in kept)


def _heldout_errors(robot, data, fold, joint_effects, effects, position_only, base, init, own) -> tuple:
    """Held-out position errors (n,) mm of the joint model and of each ``own`` segment's model alone
    (NaN for the others, and for a segment whose own fit fails on a fold)."""
    from campaign.errors import CampaignError

    joint_err, alone_err = np.full(len(fold), np.nan), np.full(len(fold), np.nan)
    for f in range(CELL_FOLDS):
        fit, out = fold != f, fold == f
        if not out.any():
            continue
        m = _fit(robot, joint_effects, position_only, *data.sub(fit), base, init=init)
        joint_err[out] = np.linalg.norm(m.residuals(*data.sub(out))[:, :3], axis=1) * 1e3
        for s in own:
            fs, os_ = fit & (data.seg == s), out & (data.seg == s)
            if not os_.any():
                continue
            try:
                alone = _fit(robot, effects, position_only, *data.sub(fs, joint=False), base)
            except CampaignError:  # this segment's fold fit cannot identify the model: tested as a small one
                alone_err[data.seg == s] = np.nan
                own = own - {s}
                continue
            alone_err[os_] = np.linalg.norm(alone.residuals(*data.sub(os_, joint=False))[:, :3], axis=1) * 1e3
    for s in set(np.unique(data.seg)) - set(own):
        alone_err[data.seg == s] = np.nan
    return joint_err, alone_err


def _segment_test(s, mine, joint_err, alone_err, n_tests) -> SegmentTest:
    """Segment ``s``'s agreement test (module docstring, step 2): paired against its own model when
    every held-out pose of it has one, else Welch against the other segments in the joint model."""
    from scipy import stats

    joint = joint_err[mine]
    if np.isfinite(alone_err[mine]).all():
        alone = alone_err[mine]
        res = stats.ttest_rel(joint, alone, alternative="greater")
        kind, other = "paired", float(alone.mean())
    else:
        res = stats.ttest_ind(joint, joint_err[~mine], equal_var=False, alternative="greater")
        kind, other = "welch", float(joint_err[~mine].mean())
    t, p = float(res.statistic), float(res.pvalue)
    if not (np.isfinite(t) and np.isfinite(p)):  # no spread at all (exact data): nothing to tell apart
        t, p = 0.0, 1.0
    bad = bool(p < CELL_AGREEMENT_ALPHA / n_tests and float(joint.mean()) > (1.0 + CELL_AGREEMENT_MARGIN) * other)
    return SegmentTest(s, kind, int(mine.sum()), float(joint.mean()), other, t, p, bad)


# -- the same poses on two cells ------------------------------------------------------------------
def _with_repeats(tests, repeats: dict, kept) -> tuple:
    """The model's tests and the repeat tests: where a segment's poses were measured on the reference
    cell too, that test decides for it (a model's test on two parts of the workspace also finds what
    the model lacks there); the reference's own model test decides only while a segment has none."""
    if not repeats:
        return tests
    all_repeated = all(s in repeats for s in kept[1:])
    out = [replace(t, decisive=False) if t.segment in repeats or (t.segment == kept[0] and all_repeated) else t
           for t in tests]
    return tuple(out) + tuple(repeats[s] for s in kept[1:] if s in repeats)


def repeat_tests(run_dir, robot, poses, segments, kept) -> dict:
    """Segment -> its "repeat" :class:`SegmentTest` against the reference segment (``kept[0]``): the
    poses measured on both cells (the drift check's reference pose, poses measured again), each
    cell's readings in its own base frame (data in the robot's frame, each segment's cell with a
    set-up of its own: campaign.measure.driver), no model involved. Their mean positions differ by
    the noise and the two set-ups' errors alone when one robot stands in both cells, by its
    geometric errors' difference (millimetres) when two do. {} when no segment qualifies."""
    from scipy import stats

    from campaign.measure.cell_identity import segment_events
    from campaign.measure.drift import same_pose_groups, warning_sigma_m
    from campaign.measure.store import open_run
    from campaign.run import RunFolder

    if poses.frame != "robot" or len(kept) < 2 or poses.kind == "markers":
        return {}
    with open_run(run_dir) as store:
        setups = [d for _, _, _, d in store.events("setup")]
        checks = segment_events(store._db, "drift_check", segments)
        reference = store.get_meta("drift_reference")
        setup_noise = store.get_meta("setup_noise_m")
        points = store.get_meta("setup_points_L")
    own = [d.get("cell") for d in setups]
    if not all(segments.cells[s].get("fingerprint") in own or (s == 0 and own and own[0] is None) for s in kept):
        return {}  # a segment measured in another cell's set-up frame: its readings are not comparable as such
    ok = np.isfinite(poses.xyz).all(axis=1)
    sigma = warning_sigma_m(poses.subset(np.flatnonzero(ok)), RunFolder(run_dir).config.tracker.noise_m,
                            robot.reflector_positions_in_E, None if setup_noise is None else setup_noise["sigma"])
    if sigma is None:
        return {}
    labels = same_pose_groups(poses.q)
    seg = segments.of(poses.pose_id)
    rows = [(int(labels[i]), int(seg[i]), poses.xyz[i]) for i in np.flatnonzero(ok)]
    at = np.flatnonzero(np.asarray(poses.pose_id) == reference["pose_id"]) if reference else []
    if len(at):
        rows += [(int(labels[at[0]]), s, np.asarray(d["xyz_m"], dtype=float)) for s, _, d in checks
                 if isinstance(d, dict) and d.get("xyz_m") is not None]
    # a set-up point's σ after its repeats, and the set-up's lever: its frame's error at a pose r away
    # grows as 1 + √2 r / spacing (the two axes from points `spacing` apart)
    repeats = max(int(min((setups[-1].get("readings") or {"x": 1}).values())), 1) if setups else 1
    pt = (setup_noise["sigma"] if setup_noise else float(np.max(sigma))) / np.sqrt(repeats)
    P = np.array(list(points.values()), dtype=float) if isinstance(points, dict) and len(points) == 3 else None
    spacing = float(min(np.linalg.norm(P[i] - P[j]) for i in range(3) for j in range(i))) if P is not None else 0.3
    ref, out = kept[0], {}
    for s in kept[1:]:
        chi2, dist, allow = 0.0, [], []
        for g in {r[0] for r in rows if r[1] == s} & {r[0] for r in rows if r[1] == ref}:
            a = np.array([r[2] for r in rows if r[0] == g and r[1] == ref])
            b = np.array([r[2] for r in rows if r[0] == g and r[1] == s])
            d = b.mean(axis=0) - a.mean(axis=0)
            setup_m = pt * (1.0 + np.sqrt(2.0) * float(np.linalg.norm(a.mean(axis=0))) / max(spacing, 1e-3))
            var = float(np.max(sigma)) ** 2 * (1.0 / len(a) + 1.0 / len(b)) + 2.0 * setup_m ** 2
            chi2 += float(d @ d) / var
            dist.append(float(np.linalg.norm(d)))
            allow.append(3.0 * var)
        if not dist:
            continue
        p = float(stats.chi2.sf(chi2, 3 * len(dist)))
        mean, expected = float(np.mean(dist)) * 1e3, float(np.sqrt(np.mean(allow))) * 1e3
        bad = bool(p < CELL_AGREEMENT_ALPHA / (len(kept) - 1) and mean > (1.0 + CELL_AGREEMENT_MARGIN) * expected)
        out[s] = SegmentTest(s, "repeat", len(dist), mean, expected, chi2, p, bad)
    return out
