"""The loop of `campaign auto` (:mod:`campaign.auto`): plan, then measure → calibrate → diagnose →
decide → carry the decision out, until a decision says stop."""

from __future__ import annotations

import json
import time
from dataclasses import asdict, replace

from campaign.auto.decisions import decide, inputs_text
from campaign.auto.report import result
from campaign.auto.state import (MAX_POSES_FACTOR, AutoOptions, AutoResult, CellSource, Decision, Limits, Round,
                                 calibrated_key, load_state, save_state)
from campaign.errors import ConfigError, Implausible, PeerError, RobotFault
from campaign.run import RunFolder


# -- the loop --------------------------------------------------------------------------------------
def auto(run_dir, cell: CellSource | None = None, options: AutoOptions | None = None, *, say=None,
         progress: bool = False, report: bool = True, retry_failed: bool = False,
         allow_other_cell: bool = False, cell_segment: int | None = None) -> AutoResult:
    """Run the loop on ``run_dir`` until there is nothing more to learn (module docstring).

    cell: where to measure (None: the one the run's earlier `auto` used); options: limits (None
    fields: those stored by an earlier `auto` of this run, else the defaults); say: a callable
    receiving the story, one line at a time (None: silent); progress: progress bars on stderr;
    report: write the calibration report and RUN/auto/report.html at the end; retry_failed: the
    poses stored as failed are measured again (`campaign run --retry-failed`), a finished loop
    goes on for them; allow_other_cell: measure on another cell than the run's measurements so
    far came from (refused otherwise, campaign.measure.cell_identity; recorded in the run);
    cell_segment: of a run measured on more than one cell, calibrate and diagnose the poses of its
    N-th cell segment alone (campaign.identify.cells), kept in the loop's state for later rounds.
    The limits (``options``) cut the first campaign too: a plan auto makes holds what they allow
    (its repeats for the noise floor included); the run's own plan is measured as far as they
    allow. Holds the run's lock throughout."""
    say = say or (lambda line: None)
    run = RunFolder(run_dir)
    with run.lock("auto"):
        state = load_state(run)
        cell = _resolve_cell(run, state, cell)
        _check_cell(run, cell, allow_other_cell, say)  # before the state records the cell
        opts = _resolve_options(state, options)
        moved = state.get("cell") not in (None, cell.as_json())
        state["cell"], state["options"] = cell.as_json(), asdict(opts)
        if moved:  # another cell, allowed: remembered at once, so `auto RUN` alone resumes there even if
            save_state(run, state)  # this session stops before its first step (a refused calibration)
        if cell_segment is not None:
            state["cell_segment"] = cell_segment
        if cell.cell is not None and cell.cell != "sim":  # a bad spec in one line, before anything is planned
            from campaign.cell.launcher import cell_specs

            cell_specs(cell.cell)
        if cell.sim or cell.cell == "sim":  # what the simulated cell would refuse, before anything is planned
            from campaign.measure.session import check_simulated_cell

            check_simulated_cell(run.config, run.robot())
        if state["plan"] is None:
            _plan(run, state, opts, say, progress)
        limits = _limits(state, opts)
        for r in state["rounds"]:  # the story so far, when resumed
            say(Round.from_json(r).line())
        if retry_failed and not _failed_count(run):  # asked for, nothing to do: said, not silently ignored
            say("--retry-failed: no pose is stored as failed; nothing to measure again")
        if state["finished"] is not None:
            if not _reopen(run, state, limits, retry_failed):
                return result(run, state, say, report=False)
            say(f"continuing: {state['reopened']}")
        loop = _Loop(run, state, cell, limits, say, progress, retry_failed=retry_failed,
                     allow_other_cell=allow_other_cell)
        loop.go()
        return result(run, state, say, report=report)


def _resolve_cell(run, state, cell):
    if cell is not None:
        return cell
    if state.get("cell"):
        return CellSource.from_json(state["cell"])
    raise ConfigError(f"{run.path}: no earlier `campaign auto` to resume: say where to measure (--sim, --cell SPEC, "
                      "or --controller HOST:PORT --tracker HOST:PORT)")


def _check_cell(run, cell: CellSource, allow_other_cell: bool, say) -> None:
    """Refused in one line (campaign.measure.cell_identity) when the run's measurements come from
    another cell than ``cell`` and ``allow_other_cell`` is not given; said when it is."""
    from campaign.measure.cell_identity import cell_identity, check_cell, same_cell

    sim = cell.sim or cell.cell == "sim"
    identity = cell_identity(run.config, sim=sim, cell=None if sim else cell.cell, options=cell.options,
                             controller=cell.controller, tracker=cell.tracker)
    before = check_cell(run.path, identity, allow_other_cell)
    if before is not None and not same_cell(before, identity) and identity.get("resolved", True):
        say(f"measuring on another cell ({identity['spec']}) than so far ({before.get('spec')}), as "
            "--allow-other-cell says: recorded in the run")


def _resolve_options(state, options):
    stored = {k: v for k, v in (state.get("options") or {}).items() if k in AutoOptions.__dataclass_fields__}
    given = {} if options is None else {k: v for k, v in asdict(options).items()
                                       if v is not None and v != AutoOptions.__dataclass_fields__[k].default}
    return AutoOptions(**{**stored, **given}).check()


def _plan(run, state, opts, say, progress):
    from campaign.plan.pipeline import plan_campaign
    from campaign.plan.selection import SelectionOptions

    if run.poses_csv.is_file() and (run.plan_dir / "summary.json").is_file() and run.has_config:
        summary = json.loads((run.plan_dir / "summary.json").read_text())
        say(f"plan: the run's own plan, {summary['tour']['poses']} poses"
            + ("" if _within_limits(run, summary, opts) else "; measured as far as the limits allow"))
    else:
        what = ("every suitable pose" if opts.select == 0 else
                f"the {opts.select} most informative poses" if opts.select else "the default short campaign")
        scale = "" if opts.grid_scale == 1 else f" --grid-scale {opts.grid_scale:g}"
        selection = SelectionOptions(n=opts.select, effects=run.effects).check() if opts.select else None
        cut = _selection_within_max_poses(opts, run.effects)
        if cut is not None:
            selection, what = cut, f"{what}, cut to --max-poses {opts.max_poses}: the {cut.n} most informative poses"
        say(f"plan: {what} (as `campaign plan --run {run.path}{scale}`)")
        summary = _plan_within(plan_campaign, run, opts, selection, progress,
                               what="--max-poses" if cut is not None else None)
        if opts.budget_h is not None and _hours(summary) + _overhead_h(run, summary) > opts.budget_h:
            left_h = opts.budget_h - _overhead_h(run, summary)
            if left_h <= 0:
                raise ConfigError(f"--budget {opts.budget_h:g} is too small for a first campaign: the set-up and the "
                                  f"drift checks alone take {_overhead_h(run, summary):.2f} h")
            say(f"plan: {_hours(summary) + _overhead_h(run, summary):.2f} h is more than --budget {opts.budget_h:g} h: "
                f"the most informative poses that fit its {left_h:.2f} h besides the set-up and the drift checks, "
                f"repeats and validation poses included (as `campaign plan --budget {left_h:.2f}`)")
            budget = SelectionOptions(budget_h=left_h, effects=run.effects, min_validation=0).check()
            summary = _plan_within(plan_campaign, run, opts, budget, progress, what="--budget")
            if cut is not None and int(summary["tour"]["poses"]) > opts.max_poses:
                summary = _plan_within(plan_campaign, run, opts, cut, progress, what="--max-poses")
    est = summary.get("estimated_campaign", {})
    state["plan"] = {"poses": int(summary["tour"]["poses"]), "estimated_h": float(est.get("total_s", 0.0)) / 3600}
    say(f"plan: {state['plan']['poses']} poses, estimated {state['plan']['estimated_h']:.2f} h")
    save_state(run, state)


def _hours(summary) -> float:
    return float((summary.get("estimated_campaign") or {}).get("total_s", 0.0)) / 3600


def _overhead_h(run, summary) -> float:
    """Campaign hours the plan's estimate leaves out: the base-frame set-up (each set-up point read
    RunOptions.setup_repeats times) and the drift checks (each about a pose's time: a motion to the
    reference and back, the settling, its reflectors; the tracker's time dominates)."""
    from campaign.measure.driver import RunOptions
    from campaign.measure.protocol import SETUP_TARGETS

    cfg = run.config
    setup_s = RunOptions.setup_repeats * len(SETUP_TARGETS) * cfg.plan.tracker_time_per_reflector_s
    est = summary.get("estimated_campaign") or {}
    checks = int((summary.get("drift_monitor") or {}).get("checks", 0))
    return (setup_s + checks * float(est.get("seconds_per_pose", 0.0))) / 3600


def _within_limits(run, summary, opts) -> bool:
    """Whether a plan's tour fits ``--max-poses`` and ``--budget``."""
    return ((opts.max_poses is None or int(summary["tour"]["poses"]) <= opts.max_poses)
            and (opts.budget_h is None or _hours(summary) + _overhead_h(run, summary) <= opts.budget_h))


def _selection_within_max_poses(opts, effects):
    """The selection whose tour fits ``--max-poses`` (N chosen, a VALIDATION_FRACTION of N for
    validation, the repeats for the floor), or None when the default short campaign fits."""
    from campaign.plan.defaults import DEFAULT_SELECT
    from campaign.plan.selection import MIN_VALIDATION, VALIDATION_FRACTION, SelectionOptions

    if opts.max_poses is None:
        return None
    base = SelectionOptions(n=1, effects=effects)
    repeats = base.repeat_poses * (base.repeat_times - 1)
    chosen = opts.select or DEFAULT_SELECT
    planned = chosen + max(MIN_VALIDATION, round(VALIDATION_FRACTION * chosen)) + repeats
    if opts.max_poses >= planned and opts.select != 0:  # every suitable pose (--select 0): cut to the limit
        return None
    n = int((opts.max_poses - repeats) / (1.0 + VALIDATION_FRACTION))
    while n > 0 and n + round(VALIDATION_FRACTION * n) + repeats > opts.max_poses:
        n -= 1
    if n < 1:
        raise ConfigError(f"--max-poses {opts.max_poses} leaves no pose to choose after the {repeats} repeats the "
                          "noise floor needs")
    return replace(base, n=n, min_validation=0).check()


def _plan_within(plan_campaign, run, opts, selection, progress, *, what: str | None):
    """plan_campaign with ``selection``; a selection too small for the unknowns is one line
    naming the limit (``what``: "--max-poses", "--budget", or None: the user's own --select)
    that made it so."""
    try:
        return plan_campaign(None, run.path, grid_scale=opts.grid_scale, progress=progress, selection=selection,
                             all_poses=opts.select == 0 and selection is None)
    except ConfigError as exc:
        if what is None or selection is None or not ("--select" in str(exc) or "--budget" in str(exc)):
            raise
        limit = f"--max-poses {opts.max_poses}" if what == "--max-poses" else f"--budget {opts.budget_h:g}"
        raise ConfigError(f"{limit} is too small for a first campaign: {exc}") from None


def _limits(state, opts) -> Limits:
    max_poses = opts.max_poses if opts.max_poses is not None else MAX_POSES_FACTOR * int(state["plan"]["poses"])
    return Limits(max_poses, opts.budget_h, opts.target_mm)


def _reopen(run, state, limits, retry_failed: bool = False) -> bool:
    """Whether a finished loop goes on: its effects were changed in campaign.yaml since (a user
    effect added), it stopped at a limit that is now larger, or failed poses are to be measured
    again (``retry_failed``)."""
    last = Round.from_json(state["rounds"][-1])
    reason = state["finished"]["reason"]
    why = None
    failed = _failed_count(run) if retry_failed else 0
    if failed:
        why = f"--retry-failed: {failed} failed poses to measure again"
    elif tuple(run.effects) != tuple(last.effects):
        why = f"the effects in {run.config_path} changed since ({', '.join(run.effects) or 'none'})"
    elif reason == "max_poses" and limits.max_poses > state["finished"].get("max_poses", last.planned):
        why = f"--max-poses {limits.max_poses} allows more poses"
    elif reason == "budget" and (limits.budget_h is None
                                 or limits.budget_h > (state["finished"].get("budget_h") or last.hours)):
        why = "the budget allows more hours"
    if why is None:
        return False
    state["finished"], state["pending"], state["reopened"] = None, None, why
    return True


def unreached_again(decision: Decision, rnd: Round, before) -> Decision:
    """``decision``, or a stop (reason ``no_poses``) when it asks again for the very poses the last
    round asked for and nothing was measured since: the plan dropped them all (no collision-free
    motion reaches them), and asking once more would repeat the round for ever (a UR3 at 3 µm
    noise asked 60 poses, then 50, sixteen rounds on the same 268 poses)."""
    last = before[-1] if before else None
    if not decision.pose_ids or last is None or last.decision.kind != decision.kind \
            or set(last.decision.pose_ids) != set(decision.pose_ids) or last.poses != rnd.poses:
        return decision
    return Decision("stop", f"stop: {decision.text}; the plan reached none of these {len(decision.pose_ids)} poses "
                            "when last asked (no collision-free motion): nothing more this cell can measure",
                    reason="no_poses")


def _failed_count(run) -> int:
    """Poses stored as failed (0 without a log)."""
    if not run.measurements_path.is_file():
        return 0
    with run.store() as store:
        return int(store.counts().get("failed", 0))


class _Loop:
    def __init__(self, run, state, cell, limits, say, progress, *, retry_failed=False, allow_other_cell=False):
        self.run, self.state, self.cell, self.limits, self.say, self.progress = run, state, cell, limits, say, progress
        self.retry_failed, self.allow_other_cell = retry_failed, allow_other_cell
        self._space = None

    @property
    def space(self):
        if self._space is None:
            from campaign.plan.extend import plan_space

            self._space = plan_space(self.run)
        return self._space

    def save(self):
        save_state(self.run, self.state)

    def go(self):
        while True:
            pending = self.state.get("pending")
            if pending is not None:
                self.execute(Decision.from_json(pending))
                self.state["pending"] = None
                self.save()
            self.measure()
            metrics = self.calibrate()
            diagnosis = self.diagnose()
            rnd = self.round(metrics, diagnosis)
            self.state["rounds"].append(rnd.as_json())
            if rnd.decision.kind == "stop":
                # the limits in force: a later `auto` with larger ones goes on (_reopen)
                self.state["finished"] = {"reason": rnd.decision.reason, "time_unix_s": time.time(),
                                          "max_poses": self.limits.max_poses, "budget_h": self.limits.budget_h}
            else:
                self.state["pending"] = rnd.decision.as_json()
            self.save()
            self.say(rnd.line())
            if rnd.decision.kind == "stop":
                return

    # -- the steps ---------------------------------------------------------------------------
    def execute(self, d: Decision):
        if d.kind == "add_effect":
            self.run.add_effects([d.effect])
            self.say(f"  added {d.effect} to {self.run.config_path}")
        elif d.kind == "remove_effect":
            self.run.set_effects(d.effects)
            self.say(f"  took out {d.effect} in {self.run.config_path}: effects [{', '.join(d.effects)}]")
        elif d.pose_ids:
            from campaign.plan.extend import append_tour

            ext = append_tour(self.run, self.space, d.pose_ids, offset_repeats=d.kind == "remeasure")
            if ext.added or ext.dropped:
                self.say(f"  plan: {len(ext.added)} poses appended to {self.run.poses_csv}"
                         + (f" ({ext.via_poses} via poses)" if ext.via_poses else "")
                         + (f"; {len(ext.dropped)} dropped (no collision-free motion; reasons in "
                            f"{self.run.plan_dir / 'dropped.csv'})" if ext.dropped else ""))

    def measure(self):
        from campaign.measure.session import measure_run

        c = self.cell
        cap, limit = self.measure_cap()
        if cap is not None and cap <= 0:
            return  # the limits allow no more poses: the round decides with what is measured
        # the library call of `campaign run RUN --sim | --cell SPEC [--options FILE] | --controller --tracker`
        res = measure_run(self.run.path, sim=c.sim, cell=c.cell, options=c.options, controller=c.controller,
                          tracker=c.tracker, progress=self.progress, log=lambda msg: self.say(f"  {msg}"),
                          max_poses=cap, retry_failed=self.retry_failed, allow_other_cell=self.allow_other_cell)
        self.retry_failed = False  # once, at the start
        if res.remaining and limit is not None:
            self.say(f"  {res.remaining} planned poses left unmeasured: the "
                     f"{'budget' if limit == 'budget' else 'pose limit'} allows no more")
        if res.measured or res.failed:
            self.say(f"  measured {res.measured} poses" + (f", {res.failed} failed" if res.failed else "")
                     + f"; campaign clock {res.simulated_duration_s / 3600:.2f} h")
        if res.stopped_kind == "interrupted":
            raise KeyboardInterrupt
        if res.stopped_kind == "implausible":
            raise Implausible(f"campaign stopped: {res.stopped}; fix it, then run `campaign auto {self.run.path}` "
                              "again to resume")
        if res.stopped_kind == "robot_fault":
            raise RobotFault(f"campaign stopped: {res.stopped}; everything measured is stored, run `campaign auto "
                             f"{self.run.path}` again to resume")
        if res.stopped:
            raise PeerError(f"campaign stopped: {res.stopped}; everything measured is stored, run `campaign auto "
                            f"{self.run.path}` again to resume")

    def calibrate(self) -> dict:
        from campaign.identify.calibrate import calibrate

        key = calibrated_key(self.run, self.state)
        metrics_path = self.run.calibration_dir / "metrics.json"
        if self.state.get("calibrated") != key or not metrics_path.is_file():
            result = calibrate(self.run.path, ann=False, report=False, cell_segment=self.state.get("cell_segment"))
            self.state["calibrated"] = key
            self.save()
            self.say(f"  calibrate: {result.order[-1]} on {int((~result.is_test).sum())} training poses")
            said = None if result.cells is None else [result.cells["decision"], len(result.cells["segments"])]
            if said is not None and said != self.state.get("cells_said"):  # several cells: how they are modelled,
                self.say(f"  cells: {result.cells['line']}")  # said once (and again when that changes)
                self.state["cells_said"] = said
                self.save()
        return json.loads(metrics_path.read_text())

    def diagnose(self):
        from campaign.diagnose.engine import diagnose
        from campaign.diagnose.report import write_diagnosis

        d = diagnose(self.run.path, cell_segment=self.state.get("cell_segment"))
        write_diagnosis(d, report=False)
        verdict = {None: "nothing left to find" if d.at_floor else "nothing found", "unexplained": "unexplained"}
        self.say(f"  diagnose: {verdict.get(d.verdict, 'add ' + str(d.verdict))}"
                 + (f" (depends on {inputs_text(d.depends_on)})" if d.verdict == "unexplained" and d.depends_on
                    else ""))
        return d

    def round(self, metrics, diagnosis) -> Round:
        model = metrics["order"][-1]
        floor = (metrics.get("noise_floor") or {}).get("mean_position_mm")
        sig = diagnosis.signature.text() if diagnosis.signature is not None and diagnosis.structure_significant \
            else None
        ids, _ = self.planned()
        before = [Round.from_json(r) for r in self.state["rounds"]]
        importance = {} if diagnosis.structure is None else \
            {k: float(v) for k, v in diagnosis.structure.importance.items()}
        # diagnose's own, its time and temperature ranked by its test of the same poses at different
        # times: auto and diagnose give the same depends_on (one code path)
        depends_on = tuple(diagnosis.depends_on)
        if diagnosis.time_tested is not None and not diagnosis.time_tested.moved:
            sig = None  # the signature's time growth is the tour's, not the cell's
        base = Round(len(before) + 1, self.measured_count(), len(ids), self.run.clock_s() / 3600, model,
                     tuple(self.run.effects), float(metrics["stages"][model]["test"]["position_mm"]["mean"]), floor,
                     diagnosis.verdict, diagnosis.at_floor, depends_on, sig, Decision("stop", ""), importance)
        return replace(base, decision=unreached_again(decide(diagnosis, base, before, self.limits, self), base, before))

    def measure_cap(self) -> tuple:
        """(poses the limits let this round measure, or None for all; the limit that cuts them,
        or None): --max-poses against the poses stored (measured or failed; without the failed
        when they are to be retried), --budget against the campaign clock at the plan's estimated
        time per pose."""
        stored = self.run.stored_pose_count() - (_failed_count(self.run) if self.retry_failed else 0)
        cap, limit = self.limits.max_poses - stored, "max_poses"
        plan = self.state.get("plan") or {}
        if self.limits.budget_h is not None and plan.get("poses") and plan.get("estimated_h"):
            per_pose_s = 3600.0 * float(plan["estimated_h"]) / int(plan["poses"])
            by_budget = int((3600.0 * self.limits.budget_h - self.run.clock_s()) // per_pose_s)
            if by_budget < cap:
                cap, limit = by_budget, "budget"
        ids, _ = self.planned()
        if cap >= len(ids) - stored:
            return None, None
        return max(cap, 0), limit

    # -- what decide asks about the run --------------------------------------------------------
    def planned(self):
        from campaign.measure.driver import read_plan

        ids, Q, _ = read_plan(self.run.path)
        return ids, Q

    def unreached(self):
        """Pose ids the plan dropped (RUN/plan/dropped.csv: its own, and those appended poses no
        collision-free motion reached): not chosen again."""
        from campaign.plan.extend import dropped_ids

        return dropped_ids(self.run)

    def measured_count(self) -> int:
        with self.run.store() as store:
            return int(len(store.load_measured(include_unusable=True)))

    def training(self):
        """(pose ids, times s) of the measured training poses (not the plan's validation poses)."""
        from campaign.identify.split import run_split

        with self.run.store() as store:
            poses = store.load_measured(include_unusable=True)
        test = run_split(self.run.path, poses.pose_id)
        return poses.pose_id[~test], poses.time_s[~test]

    def room(self, wanted: int) -> tuple:
        """(poses the limits allow of ``wanted``, the limit that cut them or None)."""
        ids, _ = self.planned()
        n = min(wanted, self.limits.max_poses - len(ids))
        limit = "max_poses" if n < wanted else None
        if self.limits.budget_h is not None:
            left_h = self.limits.budget_h - self.run.clock_s() / 3600
            by_budget = int(left_h * 3600 / self.space.seconds_per_pose)
            if by_budget < n:
                n, limit = by_budget, "budget"
        return max(n, 0), limit

    def design_effects(self):
        """The current effects a plan can weigh: not those of a context known only when measuring
        (time, temperature, ...), which no pose chosen in advance informs."""
        from campaign.effects.base import make_effect

        robot = self.space.robot
        return tuple(e for e in self.run.effects if not make_effect(e, robot).context_keys)
