"""`campaign calibrate`: from a run's measurements to a calibrated model and its metrics.

Stages, each evaluated on the same fixed 80/20 split (campaign.identify.split):
``nominal`` (p_e = 0), ``geometric`` (base parameters), ``geometric+<effect>+...`` (when
effects are enabled), then the neural residual stages when the ANN is enabled.

Writes ``RUN/calibration/metrics.json`` (DESIGN.md), ``params.yaml`` and appends the
model's held-out errors to ``RUN/calibration/history.json``.
"""

from __future__ import annotations

import contextlib
import html
import json
import tempfile
import time
from dataclasses import dataclass, replace
from pathlib import Path

import numpy as np
import yaml

from campaign.effects.base import (EffectSet, effect_context, effect_name, make_effect, merge_effects,
                                   parse_effect_list, resolve_effect_spec)
from campaign.errors import ConfigError, DataError, Implausible
from campaign.fileio import atomic_write, atomic_write_json
from campaign.identify.ann_stage import AnnStages
from campaign.identify.cells import check_cell_segment, decide_cells
from campaign.identify.metrics import error_stats, format_table6, reflector_stats
from campaign.identify.model_choice import check_model_options, choice_json, choice_text, fit_model, geometric_fix
from campaign.identify.outliers import OUTLIER_PASSES, outlier_findings, screen_outliers
from campaign.identify.solver import CalibrationModel
from campaign.identify.split import not_the_plans, run_split, validation_file
from campaign.measure import plausibility
from campaign.measure.drift import Drift, measured_drift
from campaign.measure.floor import noise_floor, times_the_noise
from campaign.measure.reflectors import transform_points
from campaign.measure.store import open_run
from campaign.model.kinematics import forward, pose_error
from campaign.model.robot import RobotModel
from campaign.run import RunFolder
from campaign.identify.checks import with_checks
from campaign.identify.poses import (check_pose_count, distinct_poses, equations_per_pose,  # noqa: F401 (their home)
                                     informative_equations, measured_point, mounting_from_json, mounting_json,
                                     prepare_measured, register_tracker, tool_mounting, tracker_block,
                                     tracker_to_robot, training_poses_needed)
from campaign.identify.domain import DOMAIN_FILE, domain_record
from campaign.identify.identifiability import hold_unidentified
from campaign.measure.importer import joint_slack
from campaign.versioned import Version, calibration_folder

CALIBRATION_DIR = "calibration"
#: fewer training poses than this: `calibrate` trains no network unless asked (``ann=True``).
#: benchmarks/bench_select_ann.py (smooth effects the physical model lacks, the case most
#: favourable to the network): its cross-validation does not beat the geometric model with 120
#: training poses (the Bayesian regularisation leaves it at zero) and does with 250
ANN_MIN_TRAIN_POSES = 250


@dataclass(frozen=True)
class CalibrationResult:
    """What `calibrate` produced: the stages' metrics, the fitted model and what was learned
    about the data on the way (metrics.json, params.yaml and the report are written from it)."""

    run_dir: Path
    #: stage name -> {"train": S, "test": S} (metrics.json's Table 6 statistics, DESIGN.md)
    stages: dict
    #: stage names in the order they were added; the last is the current model
    order: list
    #: the current physical model (geometric + effects)
    model: CalibrationModel
    #: (n,) bool: the held-out test poses
    is_test: np.ndarray
    #: effects identified with the geometry (specs, as in params.yaml)
    effects: tuple = ()
    #: the data's kind ("pose", "point", "markers") and frame ("robot", "tracker")
    measurement_kind: str = "pose"
    frame: str = "robot"
    #: wall time of the geometric identification, s
    identification_time_s: float | None = None
    #: one-reflector data: where they were measured in the tool frame, (3,) m
    measured_point_in_tool_m: tuple | None = None
    #: 6-D or raw-reflector data measured on a tool mounting: the measured frame in the URDF's tool frame
    #: ({"translation_m": [3], "rotation_vector_rad": [3]}, params.yaml's ``tool_mounting_in_tool``)
    tool_mounting_in_tool: dict | None = None
    #: data in the tracker's frame: the tracker's pose T_L_I and its registration's rms (metrics.json's
    #: ``tracker``, :func:`tracker_block`)
    tracker: dict | None = None
    #: the measurement noise floor (campaign.diagnose.floor.NoiseFloor.as_json())
    noise_floor: dict | None = None
    #: the drift over the campaign's time (campaign.measure.drift.Drift.as_json()), apart from the floor
    drift: dict | None = None
    #: the neural stages, when trained
    ann: AnnStages | None = None
    #: why no network was trained, when it was not asked for explicitly
    ann_skipped: str | None = None
    #: how the network's cross-validation was folded (campaign.identify.split.FoldRule.as_json()), when trained
    folds: dict | None = None
    #: the written report.html, when one was written
    report_path: Path | None = None
    #: plausibility warnings (campaign.measure.plausibility.Finding), metrics.json's ``warnings``
    warnings: tuple = ()
    #: ids of the held-out test poses, in the order of the run's poses (metrics.json's ``test_pose_ids``)
    test_pose_ids: tuple = ()
    #: the id every output of this calibration carries (campaign.versioned; None when not written)
    calibration_id: str | None = None
    #: which model was identified and why (campaign.identify.model_choice; metrics.json's ``model``)
    model_choice: dict | None = None
    #: the calibrated domain, the uncertainty and the identifiability (campaign.identify.domain.domain_record;
    #: domain.json beside params.yaml)
    domain: dict | None = None
    #: a run measured on more than one cell: the segments, their registrations and agreement test, the
    #: decision (campaign.identify.cells.CellDecision.as_json(); metrics.json's ``cells``); None: one cell
    cells: dict | None = None
    #: the training poses left out of the fit as reading faults (campaign.identify.outliers.Outlier)
    outliers: tuple = ()

    @property
    def excluded_pose_ids(self) -> list:
        """The pose ids left out of the fit (metrics.json's and params.yaml's ``excluded_pose_ids``)."""
        return [o.pose_id for o in self.outliers]

    @property
    def metrics(self) -> dict:
        out = {"calibration_id": self.calibration_id, "stages": self.stages, "order": self.order}
        first = self.stages[self.order[0]]["test"]
        out["ratio_to_nominal_test"] = {
            name: {block: {k: st["test"][block][k] / max(first[block][k], 1e-300) for k in ("max", "mean", "q90")}
                   for block in ("position_mm", "orientation_mrad") if block in first}
            for name, st in self.stages.items()}
        out["measurement_kind"], out["frame"] = self.measurement_kind, self.frame
        if self.tracker is not None:
            out["tracker"] = self.tracker
        if self.ann is not None:
            out["ann_cross_validation"] = self.ann.cross_validation
            out["ann_gain"] = self.ann.gain
        if self.noise_floor is not None:
            out["noise_floor"] = self.noise_floor
        if self.drift is not None:
            out["drift"], out["drift_um_per_h"] = self.drift, self.drift["um_per_h"]
        if self.folds is not None:
            out["folds"] = self.folds
        out["warnings"] = [w.as_json() for w in self.warnings]
        out["test_pose_ids"] = [int(i) for i in self.test_pose_ids]
        out["excluded_pose_ids"] = self.excluded_pose_ids
        out["outliers"] = [o.as_json() for o in self.outliers]
        if self.model_choice is not None:
            out["model"] = self.model_choice
        if self.domain is not None:
            from campaign.identify.domain import domain_metrics

            current = next((n for n in reversed(self.order) if n in self.domain["over_domain"]), None)
            out.update(domain_metrics(self.domain, None, self.stages, current))
            out["identifiability"] = {k: v for k, v in self.domain["identifiability"].items()}
        if self.cells is not None:
            out["cells"] = self.cells
        return out

    def floor_line(self) -> str:
        """``test set: mean 0.1390 mm = 8.7× the measurement noise`` for every model stage (the
        held-out test poses), or why there is no floor."""
        floor = self.noise_floor
        if floor is None or floor.get("mean_position_mm") is None:
            return ("no noise floor: no repeated measurements and no `tracker: {noise_m: ...}` in campaign.yaml, "
                    "so how far the model is from the measurement noise cannot be said")
        unc = f" ± {100 * floor['relative_uncertainty']:.0f} %" if floor["relative_uncertainty"] else ""
        lines = [f"noise floor {floor['mean_position_mm']:.4f} mm{unc} (mean position error of the noise alone; "
                 f"{floor['detail']})"]
        for name in self.order[1:]:
            mean = self.stages[name]["test"]["position_mm"]["mean"]
            lines.append(f"  {name}: test set ({self.stages[name]['test']['n_poses']} held-out poses): mean {mean:.4f} mm "
                         f"{times_the_noise(mean, floor['mean_position_mm'])}")
        if self.drift is not None:
            lines.append(Drift.from_json(self.drift).text())
        return "\n".join(lines)


def check_once(effects: EffectSet) -> EffectSet:
    """``effects`` when each effect is named once; a calibration's stages and params.yaml hold
    one block per effect name, so one joint-indexed effect over two joint lists
    (``joint_compliance:2,joint_compliance:3``) is one line giving the one spec to write instead."""
    seen = {}
    for e in effects.effects:
        if e.name in seen:
            first = seen[e.name]
            merged = merge_effects([first.spec], [e.spec])[0]
            hint = f" (name it once: {merged})" if merged != first.spec else ""
            raise ConfigError(f"effects '{first.spec}' and '{e.spec}' are both '{e.name}': a calibration holds each "
                              f"effect once{hint}")
        seen[e.name] = e
    return effects


def configured_effects(run_dir) -> tuple:
    """Effects enabled in the run's campaign.yaml (``RunFolder(run_dir).effects``), user effect
    files (``path/file.py:ClassName``) made absolute against that file's folder."""
    return RunFolder(run_dir).effects


def load_robot_for_run(run_dir) -> RobotModel:
    """The run's robot (``RunFolder(run_dir).robot()``)."""
    return RunFolder(run_dir).robot()


def check_ann_options(options: dict) -> dict:
    """Validate the neural stage's options (``folds`` >= 2 when given, ``max_epochs`` >= 1,
    ``workers`` >= 1, ``device`` usable here); ConfigError naming the command-line option otherwise.
    Returns them."""
    folds = options.get("folds")
    if folds is not None and (isinstance(folds, bool) or not isinstance(folds, int) or folds < 2):
        raise ConfigError(f"--folds must be an integer >= 2 (cross-validation needs two folds), got {folds!r}")
    epochs = options.get("max_epochs", 1)
    if isinstance(epochs, bool) or not isinstance(epochs, int) or epochs < 1:
        raise ConfigError(f"--epochs must be an integer >= 1, got {epochs!r}")
    workers = options.get("workers", 1)
    if workers is not None and (isinstance(workers, bool) or not isinstance(workers, int) or workers < 1):
        raise ConfigError(f"--workers must be at least 1, not {workers!r}")
    if options.get("device") not in (None, "auto"):  # auto always resolves: no torch import for it
        from campaign.ann.grid import resolve_device

        resolve_device(options["device"])  # an unknown or absent device: one line, before any work
    return options


def stage_name(effects) -> str:
    """``geometric+<effect>+...`` with each effect's short name (a user file's class ``name``)."""
    return "+".join(["geometric", *(effect_name(e) for e in effects)])


def calibrate(run_dir, *, effects=None, position_only: bool = False, ann: bool = False,
              ann_options: dict | None = None, progress=None, robot: RobotModel | None = None,
              write: bool = True, report: bool = True, strict: bool = False, model: str = "auto",
              fix=None, cell_segment: int | None = None,
              keep_outliers: bool = False) -> CalibrationResult:
    """Identify the model of a run and write its calibration folder, holding the run's lock
    (:meth:`campaign.run.RunFolder.lock`; ``write=False``: compute only, no lock).

    effects: names of physical effects to identify jointly with the geometric parameters
    (None: those enabled in the run's campaign.yaml). ann: also train the neural residual
    compensator (campaign.ann); ``"auto"``: only with at least ANN_MIN_TRAIN_POSES training
    poses. model: "lsq", "map" or "auto" (campaign.identify.model_choice); fix: ``--fix``, {name or
    group: value (SI) or None (nominal)} held, not fitted. progress: optional callable receiving status lines (str) and,
    during ANN training, campaign.ann.selection.TrainingProgress reports. report: also write
    report.html and its plots (with ``write``). The result carries plausibility ``warnings``
    (campaign.identify.checks); strict: any warning raises :class:`campaign.errors.Implausible`
    and nothing is written. cell_segment: ``--cell-segment N``, the poses of the run's N-th cell
    segment alone (campaign.identify.cells; a run measured on more than one cell is otherwise
    calibrated on all, with a registration per segment, or refused when they disagree).
    A training pose whose reading is a fault (campaign.identify.outliers)
    is left out of the fit and named in a warning (``outlier``); keep_outliers: keep it, still named.
    """
    run_dir = Path(run_dir)
    run = RunFolder(run_dir)
    if ann:
        check_ann_options(ann_options or {})
    robot = robot or run.robot()
    effects = run.effects if effects is None else tuple(resolve_effect_spec(e) for e in parse_effect_list(effects))
    check_once(EffectSet(tuple(make_effect(name, robot) for name in effects)))  # unknown or twice: before any fit
    fix = check_model_options(robot, effects, model, fix)  # a bad --model or --fix: one line before any fit
    segments = run.cell_segments()
    check_cell_segment(segments, cell_segment)  # a segment the run lacks: one line before any fit
    # one writer at a time: a second calibrate (or a driver) is refused before any work
    with run.lock("calibrate") if write else contextlib.nullcontext():
        if not write:  # a network trained on the way is saved in a scratch folder, then dropped
            with tempfile.TemporaryDirectory() as scratch:
                return _calibrate(run_dir, robot, effects, position_only, ann, ann_options, progress, write, report,
                                  strict, Version(None, Path(scratch)), model, fix, (segments, cell_segment),
                                  keep_outliers)
        # every output into a new version of RUN/calibration, current only once whole (campaign.versioned)
        with calibration_folder(run_dir).new_version() as version:
            result = _calibrate(run_dir, robot, effects, position_only, ann, ann_options, progress, write, report,
                                strict, version, model, fix, (segments, cell_segment), keep_outliers)
    if result.report_path is not None:
        result = replace(result, report_path=run.calibration_dir / Path(result.report_path).name)
    return result


def _calibrate(run_dir, robot, effects, position_only, ann, ann_options, progress, write,
               report, strict, version, model_kind="auto", fix=None, cells=None, keep_outliers=False,
               excluded=()) -> CalibrationResult:
    """excluded: the wild training readings (campaign.identify.outliers.Outlier) earlier passes found,
    left out of this one."""
    say = progress or (lambda msg: None)
    with open_run(run_dir) as store:
        poses = store.load_measured(include_unusable=True)
    if excluded:
        poses = poses.subset(np.flatnonzero(~np.isin(poses.pose_id, [o.pose_id for o in excluded])))
    if poses.q.shape[1] != robot.n_joints:
        raise DataError(f"{run_dir}: the measurements have {poses.q.shape[1]} joint values per pose, the run's robot "
                        f"{robot.name} has {robot.n_joints} joints")
    robot.check_joints(poses.q, field=f"{run_dir}: q", slack=joint_slack(run_dir, robot), pose_ids=poses.pose_id,
                       slack_source="the --limit-slack its import recorded")
    usable = np.isfinite(poses.T_IE[:, :3, 3]).all(axis=1)
    raw = poses.kind == "markers" and poses.markers is not None
    if raw:  # identified from the seen reflectors' positions: every pose with one seen contributes
        n_seen = np.isfinite(poses.markers).all(axis=2).sum(axis=1)
        if not (n_seen > 0).any():
            raise DataError(f"{run_dir}: no pose has a reflector seen")
        if (n_seen == 0).any():
            say(f"{int((n_seen == 0).sum())} of {len(poses)} poses have no reflector seen: left out")
            keep = np.flatnonzero(n_seen > 0)
            poses, usable, n_seen = poses.subset(keep), usable[keep], n_seen[keep]
        if not usable.all():
            say(f"{int((~usable).sum())} of {len(poses)} poses have fewer than three reflectors seen: identified "
                "from their reflectors' positions, left out of the errors at the tool origin (no pose there)")
    elif not usable.all():  # raw reflectors without their positions: fewer than three seen
        say(f"{int((~usable).sum())} of {len(poses)} poses have fewer than three reflectors seen: left out")
        poses = poses.subset(np.flatnonzero(usable))
        usable = usable[usable]
    position_only = position_only or not poses.has_orientation
    is_test = run_split(run_dir, poses.pose_id)  # the plan's validation poses, else 80/20
    decision = None if cells is None else decide_cells(run_dir, robot, poses, ~is_test, cells[0], effects=effects,
                                                       cell_segment=cells[1], say=say)
    if decision is not None:  # more than one cell: a registration per segment (or one segment), said once
        poses, kept = decision.apply(poses)
        usable, is_test = usable[kept], is_test[kept]
        if raw:
            n_seen = n_seen[kept]
        say(decision.line())
    foreign = not_the_plans(run_dir, poses.pose_id)
    if foreign:
        say(foreign)
    tr, te = ~is_test, is_test
    n_effect = sum(make_effect(e, robot).n_params for e in effects)
    points = poses.marker_positions if raw else None
    check_pose_count(run_dir, robot, distinct_poses(poses.q[tr]), int(te.sum()), position_only,
                     n_effect_params=n_effect, validation=validation_file(run_dir).is_file() and not foreign,
                     points=points,
                     rows_per_pose=informative_equations(n_seen[tr]) if raw else None)
    point = measured_point(robot, poses, tr)
    if point is not None and np.any(point) and len(robot.reflectors) != 1:
        named = "robot.yaml names none" if robot.meta_path is not None else \
            f"none named ({robot.name} was given without a robot.yaml)"
        say(f"one reflector, {named}: measured at {plausibility.point_text(point)} in "
            f"{robot.tool_frame}, as the training poses place it on the nominal model (params.yaml's "
            "measured_point_in_tool_m)")
    mounting = tool_mounting(robot, poses, tr)
    if mounting is not None:
        k = poses.markers.shape[1] if raw and poses.markers is not None else None
        say(f"{plausibility.mounting_text(robot, mounting, k)}: a tool mounting, fitted (the nominal model's tool "
            "frame, and the tolerance priors of the tool, moved there; params.yaml's tool_mounting_in_tool)")
    poses, robot, tracker = prepare_measured(robot, poses, tr, point, mounting)
    if tracker is not None:
        what = "reflectors" if raw else "poses"
        say(f"measurements in the tracker's frame: registered to the nominal model "
            f"(rms {tracker['registration_rms_mm']:.3f} mm over the {what} of {int(tr.sum())} training poses)")
    context = effect_context(poses.context, poses.time_s)
    ctx_tr = {k: v[tr] for k, v in context.items()}
    # the errors at the tool origin: where a pose was measured (raw reflectors: three or more seen);
    # two-reflector data have none, and their position errors are the reflectors' (reflector_position_mm)
    at_origin = bool(usable[tr].any() and usable[te].any())
    if raw and not at_origin:
        say("no pose of three or more reflectors in the training and the test set: the position errors are "
            "the reflectors' (no orientation)")

    stages, order, residuals = {}, [], {}

    def add_stage(name, dz, dp=None):
        o = poses.has_orientation and at_origin
        dz = np.array(dz, dtype=float)
        if not o:  # orientation rows only where orientation was measured
            dz[:, 3:6] = np.nan
        dz[~usable] = np.nan
        st = {}
        for split, m in (("train", tr), ("test", te)):
            if at_origin:
                st[split] = error_stats(dz[m & usable], orientation=o)
            else:
                st[split] = reflector_stats(dp[m], key="position_mm")
                st[split]["n_poses"] = int(m.sum())  # poses whose reflectors were scored
            if dp is not None:
                st[split]["reflector_position_mm"] = reflector_stats(dp[m])["reflector_position_mm"]
        stages[name] = st
        order.append(name)
        if not at_origin:  # the report's per-pose error: the mean of the seen reflectors' errors
            dz = np.concatenate([np.nanmean(dp, axis=1), np.full((len(dp), 3), np.nan)], axis=1)
        residuals[name] = dz

    T_nom = forward(robot, poses.q)
    dz_nom = pose_error(T_nom, poses.T_IE)
    dp_nom = None
    if raw:
        P_E = poses.marker_positions
        dp_nom = transform_points(T_nom, np.broadcast_to(P_E, poses.markers.shape)) - poses.markers
    add_stage("nominal", dz_nom, dp_nom)

    Y = poses.markers if raw else poses.T_IE
    say(f"geometric identification on {int(tr.sum())} training poses"
        + (f" ({int(n_seen[tr].sum())} seen reflectors)" if raw else ""))
    t0 = time.perf_counter()
    geo, choice = fit_model(lambda **kw: CalibrationModel(robot=robot, position_only=position_only, points=points,
                                                          **kw), poses.q[tr], Y[tr], model=model_kind,
                            fixed=geometric_fix(fix), progress=say)
    geo, ident = hold_unidentified(
        lambda **kw: CalibrationModel(robot=robot, position_only=position_only, points=points,
                                      **{**choice.model_kwargs(), "fixed": geometric_fix(fix), **kw}),
        geo, poses.q[tr], Y[tr], frame=poses.frame, progress=say)
    t_geo = time.perf_counter() - t0
    dz_geo = geo.residuals(poses.q, poses.T_IE)
    add_stage("geometric", dz_geo, geo.point_residuals(poses.q, poses.markers) if raw else None)
    model = geo
    dz_model = dz_geo
    if effects:
        say(f"identifying geometric + {', '.join(effects)}")
        make = lambda **kw: CalibrationModel(robot=robot, effects=effects, position_only=position_only,  # noqa: E731
                                             points=points, **{**choice.model_kwargs(), "fixed": fix, **kw})
        model, ident = hold_unidentified(make, make().fit(poses.q[tr], Y[tr], ctx_tr), poses.q[tr], Y[tr], ctx_tr,
                                         frame=poses.frame, progress=say)
        dz_model = model.residuals(poses.q, poses.T_IE, context)
        add_stage(stage_name(effects), dz_model, model.point_residuals(poses.q, poses.markers, context) if raw else None)
    wild = screen_outliers(model, poses, tr, te & usable, context)
    if wild.train and wild.isolated and not keep_outliers and len(excluded) < OUTLIER_PASSES:
        for o in wild.train:
            say(f"pose {o.pose_id}: {o.error_mm:.3f} mm from the model, {o.ratio:.1f} σ of the poses' robust "
                "scatter: a reading fault, left out; fitting again")
        return _calibrate(run_dir, robot, effects, position_only, ann, ann_options, progress, write, report, strict,
                          version, model_kind, fix, cells, keep_outliers, (*excluded, *wild.train))
    ann_skipped = ann_stages = rule = None
    n_ann = int((tr & usable).sum())  # the network learns pose residuals: poses with a pose
    if ann == "auto":
        ann = n_ann >= ANN_MIN_TRAIN_POSES
        if not ann:
            ann_skipped = (f"no neural compensator: {n_ann} training poses are below the "
                           f"{ANN_MIN_TRAIN_POSES} where its cross-validation beats the physical model "
                           "(a short campaign calibrates the physical model; --ann trains one anyway)")
            # said once, in the summary (summary_text), not also as progress
    if ann and not at_origin:
        raise DataError(f"{run_dir}: the neural compensator learns pose errors, and no pose was measured (raw "
                        "reflectors, fewer than three seen in the training or the test set): run with --no-ann")

    if ann:
        from campaign.identify.ann_stage import run_ann_stages
        from campaign.identify.split import choose_folds

        ann_options = dict(ann_options or {})
        rule = choose_folds(n_ann, ann_options.get("folds"))
        ann_options["folds"] = rule.k
        say(f"cross-validation of the network: {rule.text()}")
        if not usable.all():
            say(f"the network on the {int(usable.sum())} poses with three or more reflectors seen "
                f"({int((~usable).sum())} without a pose skipped)")
        T_prior = {"nominal": T_nom[usable], stage_name(effects): model.predict(poses.q, context)[usable]}
        ann_residuals, ann_stages = run_ann_stages(run_dir, robot, poses.subset(np.flatnonzero(usable)),
                                                   is_test[usable], T_prior, options=ann_options, progress=progress,
                                                   out_dir=version.path)
        for name, dz in ann_residuals.items():
            full = np.full((len(poses), 6), np.nan)
            full[usable] = dz
            add_stage(name, full)

    measured = poses.subset(np.flatnonzero(usable)) if at_origin else poses
    floor = noise_floor(run_dir, measured, robot)
    result = CalibrationResult(
        run_dir, stages, order, model, is_test, effects=tuple(effects), measurement_kind=poses.kind,
        frame=poses.frame, identification_time_s=t_geo,
        measured_point_in_tool_m=None if point is None else tuple(float(v) for v in point), tracker=tracker,
        tool_mounting_in_tool=None if mounting is None else mounting_json(mounting),
        noise_floor=floor.as_json(),
        drift=measured_drift(run_dir, measured, floor, tracker_to_robot(tracker), cells=decision).as_json(),
        cells=None if decision is None else {**decision.as_json(), "line": decision.line()},
        ann=ann_stages, ann_skipped=ann_skipped,
        folds=None if rule is None else rule.as_json(), calibration_id=version.id,
        model_choice=choice_json(choice, model, poses.q[te], ctx_te=None if not context else
                                 {k: v[te] for k, v in context.items()}, stages=stages,
                                 stage=stage_name(effects) if effects else "geometric", fix=fix))
    result = with_checks(result, robot, poses, geo, stage_name(effects))
    result = replace(result, outliers=tuple(excluded), warnings=tuple(result.warnings)
                     + outlier_findings(excluded, wild, keep_outliers))
    models = {"geometric": geo, **({stage_name(effects): model} if effects else {})}
    record = domain_record(robot, models, poses.q[tr], poses.q, context, floor.as_json(), is_test, ident)
    result = replace(result, domain=record, warnings=tuple(result.warnings) + tuple(ident.findings(robot)))
    if strict and result.warnings:
        raise Implausible(f"{run_dir}: {len(result.warnings)} plausibility warning(s) with --strict "
                          f"({', '.join(w.code for w in result.warnings)}): nothing written", result.warnings)
    if write:
        _write(result, robot, geo, version.path)
    if write and report:
        from campaign.identify.report import model_choice_html, write_report

        say("writing the report")
        shown = np.flatnonzero(usable) if at_origin else np.arange(len(poses))  # rows with an error at the origin
        xyz = poses.xyz if at_origin else np.nanmean(poses.markers, axis=1)
        # the chart's floor line is the floor the text states (result.floor_line), or none
        page = write_report(run_dir, stages, order, {k: v[shown] for k, v in residuals.items()}, poses.q[shown], xyz[shown], is_test[shown],
                            param_text=parameter_text(model), noise_floor=floor if floor.known else None,
                            extra_html=f"<h2>Against the measurement noise</h2>"
                            f"<pre>{html.escape(result.floor_line())}</pre>" + model_choice_html(result.model_choice)
                            + _domain_section(robot, result, models, poses.q, context, version.path)
                            + (result.ann.report_html() if result.ann is not None else ""),
                            out_dir=version.path, calibration_id=version.id)
        result = replace(result, report_path=Path(page))
    return result


def _domain_section(robot, result, models, q, context, out) -> str:
    """The report's section on the calibrated domain and the uncertainty, with its figure."""
    from campaign.identify.domain import Domain
    from campaign.identify.domain_figures import domain_html, joint_sweeps, svg_domain
    from campaign.identify.uncertainty import Uncertainty

    record = result.domain
    stage = list(record["over_domain"])[-1]
    m = models[stage]
    unc = Uncertainty.from_json(record["uncertainty"][stage], "uncertainty")
    dom = Domain.from_json(record["domain"], "domain")
    ctx0 = {k: np.full(1, float(np.median(v))) for k, v in (context or {}).items()} if m.effect_set_.effects else {}

    def sigma_fn(Q):
        c = {k: np.repeat(v, len(Q)) for k, v in ctx0.items()}
        return 1e3 * unc.sigma_m(robot, m.effect_set_, m.params_, m.effect_params_, Q, c)

    fig = svg_domain(robot, dom, joint_sweeps(robot, dom, sigma_fn, dom.q_train), q, record["sigma_all"][stage], out)
    heldout = result.stages.get(stage, {}).get("test", {}).get("position_mm", {}).get("mean")
    return domain_html(robot, record, fig, heldout)


def parameter_text(model: CalibrationModel) -> str:
    """Identified parameters with σ, one per line, units in the header."""
    rows = [(model.base_.expression(i) if i < model.base_.n_base else name, unit, value, sigma)
            for i, (name, unit, value, sigma) in enumerate(model.parameter_table())]
    width = max([len("parameter")] + [len(r[0]) for r in rows])  # full names, never cut
    lines = [f"{'#':>3} {'parameter':<{width}} {'value':>14} {'sigma':>12}  unit"]
    for i, (label, unit, value, sigma) in enumerate(rows):
        lines.append(f"{i + 1:>3} {label:<{width}} {value:>14.6g} {sigma:>12.3g}  {unit}")
    return "\n".join(lines)


def _param_block(model: CalibrationModel) -> dict:
    base = model.base_
    out = {
        "base_parameters": [
            {"index": j + 1, "name": base.names[j], "unit": base.units[j], "combination": base.expression(j),
             "value": float(model.base_params_[j]), "sigma": float(model.base_sigma_[j])}
            for j in range(base.n_base)
        ],
        "p_e": [float(v) for v in model.params_],
        "p_e_min_norm": [float(v) for v in model.params_min_norm_],
        "p_e_names": list(model.robot.param_names),
        "effects": {},
        "absorbed_effect_parameters": [model.unknown_names_[i] for i in model.absorbed_],
        "noise_sigma": model.noise_sigma_,
        "condition_number": model.condition_number_,
        "iterations": model.n_iter_,
        "strongly_correlated": [{"a": a, "b": b, "r": r} for a, b, r in model.correlated_pairs_],
    }
    i0 = 0  # into effect_sigma_
    for e, th in zip(model.effect_set_.effects, model.effect_set_.split(model.effect_params_)):
        out["effects"][e.name] = {
            "spec": e.spec,
            "description": e.description,
            "parameters": [
                {"name": pn, "unit": pu, "value": float(v), "sigma": float(model.effect_sigma_[i0 + k])}
                for k, (pn, pu, v) in enumerate(zip(e.param_names, e.param_units, th))
            ],
        }
        i0 += e.n_params
    return out


def _write(result: CalibrationResult, robot, geo, out: Path) -> None:
    """metrics.json, params.yaml and history.json into ``out``, the new calibration's folder."""
    model = result.model
    params = {"calibration_id": result.calibration_id, "robot": robot.name, "model_stage": result.order[-1]}
    params.update(_param_block(model))
    if result.measured_point_in_tool_m is not None:  # the model's tool frame is this point (one reflector)
        params["measured_point_in_tool_m"] = list(result.measured_point_in_tool_m)
    if result.tool_mounting_in_tool is not None:  # the model's tool frame is this frame (a tool mounting)
        params["tool_mounting_in_tool"] = result.tool_mounting_in_tool
    if model is not geo:
        params["geometric_only"] = _param_block(geo)
    # networks trained by this calibrate run (stage -> file beside params.yaml)
    params["ann_stages"] = dict(result.ann.files) if result.ann is not None else {}
    params["excluded_pose_ids"] = result.excluded_pose_ids  # reading faults left out (diagnose leaves them too)
    atomic_write(out / "params.yaml", yaml.safe_dump(params, sort_keys=False))
    if result.domain is not None:  # the calibrated domain and the uncertainty, the same calibration_id
        atomic_write_json(out / DOMAIN_FILE, {"calibration_id": result.calibration_id, "robot": robot.name,
                                              **{k: v for k, v in result.domain.items()
                                                 if k not in ("over_domain", "sigma_all")}})
    metrics = result.metrics
    metrics.setdefault("warnings", [])  # plausibility warnings (DESIGN.md): an empty list when none
    atomic_write_json(out / "metrics.json", metrics)
    # history: one entry per completed calibrate run, so a report can show the error falling; the
    # previous calibration's history plus this one (a killed calibrate is in no history)
    history = []
    current = calibration_folder(result.run_dir).current()
    if current is not None and (current / "history.json").is_file():
        try:
            history = json.loads((current / "history.json").read_text()).get("runs", [])
        except (json.JSONDecodeError, AttributeError):
            history = []
    history.append({
        "calibration_id": result.calibration_id,
        "time_unix_s": time.time(),
        "effects": list(result.effects),
        "stages": {name: result.stages[name]["test"] for name in result.order},
        "order": result.order,
    })
    atomic_write_json(out / "history.json", {"runs": history})


def summary_text(result: CalibrationResult) -> str:
    """The printed outcome: Table 6 for the test set, then the training set, then parameters."""
    m = result.model
    lines = []
    if result.ann is not None:
        lines += ["cross-validation on the training set (Table 5)", result.ann.table5, ""]
    lines += [format_table6(result.stages, result.order, "test"), "",
              format_table6(result.stages, result.order, "train"), ""]
    ident = (result.domain or {}).get("identifiability") or {}
    held = len(ident.get("held") or ())
    n_fit = m.base_.n_base - sum(1 for n in m.held_ if n in set(m.base_.names))
    n_prior = ident.get("n_unknowns", 0) - ident.get("rank", 0) if ident.get("held_at") == "prior" else 0
    cond = (f"condition number {m.condition_number_:.3g}" if np.isfinite(m.condition_number_) else
            "no finite condition number: directions not identified by the training poses, held at the prior")
    lines.append((f"identified {n_fit} of {m.base_.n_base} base parameters" if n_fit < m.base_.n_base else
                  f"estimated {m.base_.n_base} base parameters, {n_prior} direction(s) of them from the prior alone"
                  if n_prior else f"identified {m.base_.n_base} base parameters")
                 + (f" + {m.effect_set_.n_params} effect parameters" if m.effect_set_.n_params else "")
                 + f" in {m.n_iter_} iterations; {cond}; "
                 f"noise σ {m.noise_sigma_['position_m'] * 1e6:.2f} µm"
                 + (f", {m.noise_sigma_['orientation_rad'] * 1e6:.1f} µrad" if m.noise_sigma_['orientation_rad'] else ""))
    if ident and (held or ident.get("rank", 0) < ident.get("n_unknowns", 0)):
        lines.append(f"not identified by the training poses: {ident['n_unknowns'] - ident['rank']} direction(s); "
                     f"held at {'their nominal value' if ident['held_at'] == 'nominal' else 'the prior'}"
                     + (f": {', '.join(ident['held'])}" if held else "") + " (warnings: unidentifiable)")
    unc = result.metrics.get("uncertainty") if result.domain is not None else None
    if unc and unc.get("stage") in unc["stages"] and unc["stages"][unc["stage"]]["heldout_mean_position_mm"] is not None:
        u = unc["stages"][unc["stage"]]
        lines.append(f"uncertainty of the model over its domain: sigma_mm mean {u['sigma_mm_mean']:.4f}, 95th percentile "
                     f"{u['sigma_mm_q95']:.4f} mm (test-set mean error {u['heldout_mean_position_mm']:.4f} mm); "
                     f"{u['basis']}" + ("; a network stage's rows add the spread of its cross-validation members "
                                        "(a fold ensemble; a single network's own uncertainty is not estimated)"
                                        if result.ann is not None else ""))
    if m.absorbed_:
        lines.append("absorbed by the geometric parameters, or moving nothing on these poses (held at 0, not "
                     "identifiable): " + ", ".join(m.unknown_names_[i] for i in m.absorbed_))
    if m.correlated_pairs_:
        worst = sorted(m.correlated_pairs_, key=lambda t: -abs(t[2]))[:5]
        more = len(m.correlated_pairs_) - len(worst)
        pairs = "; ".join(f"{a} ~ {b} (r = {r:+.3f})" for a, b, r in worst)
        lines.append(f"strongly correlated: {pairs}" if more <= 0 else
                     f"strongly correlated: {len(m.correlated_pairs_)} pairs with |r| > 0.95; the worst five: {pairs}; "
                     "all in params.yaml")
    if result.cells is not None:
        lines.append(result.cells["line"])
    if result.ann_skipped:
        lines.append(result.ann_skipped)
    if result.ann is not None:
        lines += result.ann.gain_lines()
    if result.model_choice is not None:
        lines.append(choice_text(result.model_choice))
    lines.append(result.floor_line())
    lines.append(f"written: {result.run_dir / CALIBRATION_DIR}/metrics.json, params.yaml"
                 + (", report.html" if result.report_path is not None else "")
                 + (f" (calibration {result.calibration_id})" if result.calibration_id else ""))
    return "\n".join(lines)
