"""`campaign auto`: a campaign that measures until it understands the robot.

The loop (DESIGN.md: plan → measure → calibrate → diagnose → decide → measure more):

1. plan the short campaign when the run has none (:func:`campaign.plan.pipeline.plan_campaign`),
   measure it, calibrate the current model, diagnose it;
2. decide from the diagnosis (:func:`decide`, a pure function of the diagnosis, the calibration
   and the rounds before) and do it:

   * a candidate effect is significant (the verdict, or the part of an "unexplained" it
     explains) → add it to RUN/campaign.yaml, calibrate again;
   * at the noise floor, but the model's parameters poorly determined (the predicted mean
     position error of the model against the truth above the target) → the next poses by the
     plan's optimal design for the current model (:func:`campaign.plan.extend.design_poses`);
   * "unexplained" → poses that reveal its structure: spread over the inputs it depends on
     (:func:`campaign.plan.extend.spread_poses`), or measured poses measured again later when
     it depends on time (:func:`campaign.plan.extend.remeasure_poses`);
   * nothing more to learn → stop, saying which and why: at the floor; unexplained and the new
     poses no longer change the verdict; the budget or the pose limit reached.

New poses are appended to RUN/plan/poses.csv and measured by the same driver (every pose
without a stored outcome); every calibration appends to RUN/calibration/history.json. The
loop's state lives in RUN/auto/state.json, written atomically after every step, and each step
is idempotent: a decision is written before it is carried out and carried out again on resume
(an effect added twice is added once, a pose the plan holds is not appended again, the driver
measures only poses without a stored outcome), so a killed `auto` resumes where it stopped,
losing nothing and measuring nothing twice; every decision follows deterministically from the
stored data.
"""

from __future__ import annotations

import html
import json
import time
from dataclasses import asdict, dataclass, field, replace
from pathlib import Path

import numpy as np

from campaign.errors import ConfigError, DataError, PeerError, RobotFault
from campaign.fileio import atomic_write
from campaign.run import RunFolder

AUTO_DIR = "auto"
STATE_FILE = "state.json"
STATE_VERSION = 1
#: without --max-poses: this many times the planned short campaign's poses at most
MAX_POSES_FACTOR = 2
#: poses per round that reveal the structure of an "unexplained" (a quarter of the default selection)
REVEAL_POSES = 30
#: poses per round of the optimal design at most (at least DESIGN_MIN_POSES)
DESIGN_MAX_POSES = 60
DESIGN_MIN_POSES = 8
#: rounds of revealing poses for one "unexplained" at most
REVEAL_ROUNDS = 3
#: without --target-mm: the model's own predicted error may be this share of the noise floor (its
#: held-out error is then about √(1 + share²) ≈ 1.1× the floor)
TARGET_FLOOR_SHARE = 0.5
#: the noise floor assumed for the target when the run has none (10 µm per reflector coordinate, 3 reflectors)
DEFAULT_FLOOR_MM = 0.0099
#: inputs of the model-free test that measuring again later reveals (not the joints)
TIME_INPUTS = ("time_s", "temperature_c")
#: a candidate that explains only part of an "unexplained" is added when it takes at least this share
#: of the held-out error away (on the folds): a few per cent are as often a wrong effect fitting a
#: little of a missing one (cyclic for a bearing run-out), which then stays in the model
MIN_PARTIAL_GAIN = 0.10
#: a floor known to worse than this (relative, 1 σ) does not decide "at the floor" alone: FLOOR_POSES
#: poses are measured FLOOR_TIMES times back to back first (once), for the noise itself
FLOOR_UNCERTAINTY_MAX = 0.1
FLOOR_POSES = 8
FLOOR_TIMES = 4


@dataclass(frozen=True)
class AutoOptions:
    """How far `auto` may go. budget_h: campaign hours (the run's clock: motion, settle, tracker);
    target_mm: the predicted mean position error of the model against the truth that counts as
    well determined (None: TARGET_FLOOR_SHARE of the noise floor); max_poses: planned poses at
    most (None: MAX_POSES_FACTOR times the short campaign's); grid_scale, select: the plan's
    ``--grid-scale`` and ``--select`` (None: the default short campaign; 0: every suitable pose)."""

    budget_h: float | None = None
    target_mm: float | None = None
    max_poses: int | None = None
    grid_scale: float = 1.0
    select: int | None = None

    def check(self) -> "AutoOptions":
        from campaign.config import check_int, check_number

        if self.budget_h is not None:
            check_number(self.budget_h, "--budget", low=0.0, low_open=True)
        if self.target_mm is not None:
            check_number(self.target_mm, "--target-mm", low=0.0, low_open=True)
        if self.max_poses is not None:
            check_int(self.max_poses, "--max-poses", low=1)
        check_number(self.grid_scale, "--grid-scale", low=0.0, low_open=True)
        if self.select is not None:
            check_int(self.select, "--select", low=0)
        return self


@dataclass(frozen=True)
class CellSource:
    """Where the poses are measured: the simulated cell (``sim``), a cell from adapters
    (``cell``: a SPEC of `campaign run --cell`), or a controller and a tracker (host, port)."""

    sim: bool = False
    cell: str | None = None
    controller: tuple | None = None
    tracker: tuple | None = None
    #: with ``cell``: the adapters' options file (`campaign run --cell SPEC --options FILE`)
    options: str | None = None

    def __post_init__(self):
        given = sum([bool(self.sim), self.cell is not None, self.controller is not None])
        if given != 1 or (self.controller is None) != (self.tracker is None):
            raise ConfigError("give one of --sim, --cell SPEC, or --controller HOST:PORT with --tracker HOST:PORT")
        if self.options is not None and self.cell is None:
            raise ConfigError("--options goes with --cell (the adapters' options)")

    def as_json(self) -> dict:
        return {"sim": self.sim, "cell": self.cell, "options": self.options,
                "controller": None if self.controller is None else list(self.controller),
                "tracker": None if self.tracker is None else list(self.tracker)}

    @classmethod
    def from_json(cls, doc) -> "CellSource":
        return cls(bool(doc.get("sim")), doc.get("cell"),
                   None if doc.get("controller") is None else (str(doc["controller"][0]), int(doc["controller"][1])),
                   None if doc.get("tracker") is None else (str(doc["tracker"][0]), int(doc["tracker"][1])),
                   doc.get("options"))

    def text(self) -> str:
        if self.sim:
            return "--sim"
        if self.cell is not None:
            return f"--cell {self.cell}" + (f" --options {self.options}" if self.options else "")
        return f"--controller {self.controller[0]}:{self.controller[1]} --tracker {self.tracker[0]}:{self.tracker[1]}"


@dataclass(frozen=True)
class Decision:
    """What a round decided. kind: ``add_effect`` (``effect``), ``design``, ``reveal``, ``floor``
    or ``remeasure`` (``pose_ids`` to append and measure; ``reason`` ``probe`` for poses that
    test a structure found below the detection limit at the floor), or ``stop`` (``reason``: ``at_floor``,
    ``unexplained``, ``no_floor``, ``budget``, ``max_poses``, ``no_poses``); text: one line."""

    kind: str
    text: str
    effect: str | None = None
    pose_ids: tuple = ()
    reason: str | None = None

    def as_json(self) -> dict:
        return {**asdict(self), "pose_ids": [int(p) for p in self.pose_ids]}

    @classmethod
    def from_json(cls, doc) -> "Decision":
        return cls(doc["kind"], doc["text"], doc.get("effect"), tuple(int(p) for p in doc.get("pose_ids", ())),
                   doc.get("reason"))


@dataclass(frozen=True)
class Round:
    """One round's numbers: poses measured so far, planned, campaign hours, the model (its stage
    name), the held-out (test set) mean position error and the noise floor (mm), the diagnosis's
    verdict and the inputs its model-free test found, and the decision."""

    number: int
    poses: int
    planned: int
    hours: float
    model: str
    effects: tuple
    heldout_mm: float
    floor_mm: float | None
    verdict: str | None
    at_floor: bool | None
    depends_on: tuple
    signature: str | None
    decision: Decision
    #: the model-free test's permutation importance per input (shares), {} without the test
    importance: dict = field(default_factory=dict)

    @property
    def ratio(self) -> float | None:
        return self.heldout_mm / self.floor_mm if self.floor_mm else None

    def line(self) -> str:
        ratio = f" = {self.ratio:.2f}× the floor" if self.ratio is not None else " (no noise floor)"
        return (f"round {self.number}: {self.poses} poses, {self.hours:.2f} h, {self.model}: held-out "
                f"{self.heldout_mm:.4f} mm{ratio} → {self.decision.text}")

    def as_json(self) -> dict:
        out = {k: v for k, v in asdict(self).items() if k != "decision"}
        out.update(effects=list(self.effects), depends_on=list(self.depends_on), ratio=self.ratio,
                   decision=self.decision.as_json())
        return out

    @classmethod
    def from_json(cls, doc) -> "Round":
        kw = {k: doc[k] for k in ("number", "poses", "planned", "hours", "model", "heldout_mm", "floor_mm",
                                  "verdict", "at_floor", "signature")}
        return cls(**kw, effects=tuple(doc["effects"]), depends_on=tuple(doc["depends_on"]),
                   decision=Decision.from_json(doc["decision"]), importance=dict(doc.get("importance") or {}))


@dataclass(frozen=True)
class AutoResult:
    """The story: every round, the final decision (kind ``stop``) and the verdict in words."""

    run_dir: Path
    rounds: tuple
    final: Decision
    verdict_text: str
    report_path: Path | None = None


# -- the state on disk ----------------------------------------------------------------------------
def state_path(run: RunFolder) -> Path:
    return run.path / AUTO_DIR / STATE_FILE


def _load_state(run: RunFolder) -> dict:
    path = state_path(run)
    if not path.is_file():
        return {"version": STATE_VERSION, "cell": None, "options": {}, "plan": None, "rounds": [], "pending": None,
                "calibrated": None, "finished": None}
    try:
        state = json.loads(path.read_text())
        if state.get("version") != STATE_VERSION or not isinstance(state.get("rounds"), list):
            raise ValueError("unknown version")
        return state
    except (ValueError, OSError) as exc:
        raise DataError(f"{path}: not a state of `campaign auto` ({exc}); move it away to start the loop "
                        "afresh") from None


def _save_state(run: RunFolder, state: dict) -> None:
    atomic_write(state_path(run), json.dumps(state, indent=2))


# -- the loop --------------------------------------------------------------------------------------
def auto(run_dir, cell: CellSource | None = None, options: AutoOptions | None = None, *, say=None,
         progress: bool = False, report: bool = True) -> AutoResult:
    """Run the loop on ``run_dir`` until there is nothing more to learn (module docstring).

    cell: where to measure (None: the one the run's earlier `auto` used); options: limits (None
    fields: those stored by an earlier `auto` of this run, else the defaults); say: a callable
    receiving the story, one line at a time (None: silent); progress: progress bars on stderr;
    report: write the calibration report and RUN/auto/report.html at the end. Holds the run's
    lock throughout."""
    say = say or (lambda line: None)
    run = RunFolder(run_dir)
    with run.lock("auto"):
        state = _load_state(run)
        cell = _resolve_cell(run, state, cell)
        opts = _resolve_options(state, options)
        state["cell"], state["options"] = cell.as_json(), asdict(opts)
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
        if state["finished"] is not None:
            if not _reopen(run, state, limits):
                return _result(run, state, say, report=False)
            say(f"continuing: {state['reopened']}")
        loop = _Loop(run, state, cell, limits, say, progress)
        loop.go()
        return _result(run, state, say, report=report)


def _resolve_cell(run, state, cell):
    if cell is not None:
        return cell
    if state.get("cell"):
        return CellSource.from_json(state["cell"])
    raise ConfigError(f"{run.path}: no earlier `campaign auto` to resume: say where to measure (--sim, --cell SPEC, "
                      "or --controller HOST:PORT --tracker HOST:PORT)")


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
        say(f"plan: the run's own plan, {summary['tour']['poses']} poses")
    else:
        what = ("every suitable pose" if opts.select == 0 else
                f"the {opts.select} most informative poses" if opts.select else "the default short campaign")
        scale = "" if opts.grid_scale == 1 else f" --grid-scale {opts.grid_scale:g}"
        say(f"plan: {what} (as `campaign plan --run {run.path}{scale}`)")
        selection = SelectionOptions(n=opts.select, effects=run.effects).check() if opts.select else None
        summary = plan_campaign(None, run.path, grid_scale=opts.grid_scale, progress=progress, selection=selection,
                                all_poses=opts.select == 0)
    est = summary.get("estimated_campaign", {})
    state["plan"] = {"poses": int(summary["tour"]["poses"]), "estimated_h": float(est.get("total_s", 0.0)) / 3600}
    say(f"plan: {state['plan']['poses']} poses, estimated {state['plan']['estimated_h']:.2f} h")
    _save_state(run, state)


@dataclass(frozen=True)
class Limits:
    max_poses: int
    budget_h: float | None
    target_mm: float | None


def _limits(state, opts) -> Limits:
    max_poses = opts.max_poses if opts.max_poses is not None else MAX_POSES_FACTOR * int(state["plan"]["poses"])
    return Limits(max_poses, opts.budget_h, opts.target_mm)


def _reopen(run, state, limits) -> bool:
    """Whether a finished loop goes on: its effects were changed in campaign.yaml since (a user
    effect added), or it stopped at a limit that is now larger."""
    last = Round.from_json(state["rounds"][-1])
    reason = state["finished"]["reason"]
    why = None
    if tuple(run.effects) != tuple(last.effects):
        why = f"the effects in {run.config_path} changed since ({', '.join(run.effects) or 'none'})"
    elif reason == "max_poses" and limits.max_poses > last.planned:
        why = f"--max-poses {limits.max_poses} allows more poses"
    elif reason == "budget" and (limits.budget_h is None or limits.budget_h > last.hours):
        why = "the budget allows more hours"
    if why is None:
        return False
    state["finished"], state["pending"], state["reopened"] = None, None, why
    return True


class _Loop:
    def __init__(self, run, state, cell, limits, say, progress):
        self.run, self.state, self.cell, self.limits, self.say, self.progress = run, state, cell, limits, say, progress
        self._space = None

    @property
    def space(self):
        if self._space is None:
            from campaign.plan.extend import plan_space

            self._space = plan_space(self.run)
        return self._space

    def save(self):
        _save_state(self.run, self.state)

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
                self.state["finished"] = {"reason": rnd.decision.reason, "time_unix_s": time.time()}
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
        elif d.pose_ids:
            from campaign.plan.extend import append_tour

            ext = append_tour(self.run, self.space, d.pose_ids, offset_repeats=d.kind == "remeasure")
            if ext.added or ext.dropped:
                self.say(f"  plan: {len(ext.added)} poses appended to {self.run.poses_csv}"
                         + (f" ({ext.via_poses} via poses)" if ext.via_poses else "")
                         + (f"; {len(ext.dropped)} dropped (no collision-free motion)" if ext.dropped else ""))

    def measure(self):
        from campaign.measure.session import measure_run

        c = self.cell
        # the library call of `campaign run RUN --sim | --cell SPEC [--options FILE] | --controller --tracker`
        res = measure_run(self.run.path, sim=c.sim, cell=c.cell, options=c.options, controller=c.controller,
                          tracker=c.tracker, progress=self.progress, log=lambda msg: self.say(f"  {msg}"))
        if res.measured or res.failed:
            self.say(f"  measured {res.measured} poses" + (f", {res.failed} failed" if res.failed else "")
                     + f"; campaign clock {res.simulated_duration_s / 3600:.2f} h")
        if res.stopped_kind == "interrupted":
            raise KeyboardInterrupt
        if res.stopped_kind == "robot_fault":
            raise RobotFault(f"campaign stopped: {res.stopped}; everything measured is stored, run `campaign auto "
                             f"{self.run.path}` again to resume")
        if res.stopped:
            raise PeerError(f"campaign stopped: {res.stopped}; everything measured is stored, run `campaign auto "
                            f"{self.run.path}` again to resume")

    def calibrate(self) -> dict:
        from campaign.identify.calibrate import calibrate

        effects = list(self.run.effects)
        key = {"effects": effects, "poses": self.run.stored_pose_count()}
        metrics_path = self.run.calibration_dir / "metrics.json"
        if self.state.get("calibrated") != key or not metrics_path.is_file():
            result = calibrate(self.run.path, ann=False, report=False)
            self.state["calibrated"] = key
            self.save()
            self.say(f"  calibrate: {result.order[-1]} on {int((~result.is_test).sum())} training poses")
        return json.loads(metrics_path.read_text())

    def diagnose(self):
        from campaign.diagnose.engine import diagnose
        from campaign.diagnose.report import write_diagnosis

        d = diagnose(self.run.path)
        write_diagnosis(d, report=False)
        verdict = {None: "nothing left to find" if d.at_floor else "nothing found", "unexplained": "unexplained"}
        self.say(f"  diagnose: {verdict.get(d.verdict, 'add ' + str(d.verdict))}"
                 + (f" (depends on {_inputs_text(d.depends_on)})" if d.verdict == "unexplained" and d.depends_on
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
        depends_on = tuple(diagnosis.depends_on)
        weak = weak_structure_inputs(diagnosis) if diagnosis.verdict is None else []
        if not depends_on and weak:
            depends_on = tuple(weak)
            if before and before[-1].decision.reason == "probe":  # the same weak structure twice: both tests' ranking
                both = {k: importance.get(k, 0.0) + before[-1].importance.get(k, 0.0) for k in importance}
                depends_on = tuple(k for k in sorted(both, key=lambda k: -both[k])
                                   if k in weak or k in before[-1].depends_on)
        if not depends_on and diagnosis.verdict == "unexplained":  # the inputs an earlier test of this model named
            same = [r for r in before if r.effects == tuple(self.run.effects) and r.depends_on]
            depends_on = same[-1].depends_on if same else ()
        p_time = time_change_p(self.run, diagnosis.floor) if depends_on and depends_on[0] in TIME_INPUTS else None
        if p_time is not None and p_time >= TIME_ALPHA:
            # measured again after a pause, the poses agree within the noise: time is not the cause (the tour
            # orders poses, so time stands in for the joints the tour sweeps); the joints it depends on remain
            depends_on = tuple(i for i in depends_on if i not in TIME_INPUTS)
            sig = None
        base = Round(len(before) + 1, self.measured_count(), len(ids), self.run.clock_s() / 3600, model,
                     tuple(self.run.effects), float(metrics["stages"][model]["test"]["position_mm"]["mean"]), floor,
                     diagnosis.verdict, diagnosis.at_floor, depends_on, sig, Decision("stop", ""), importance)
        return replace(base, decision=decide(diagnosis, base, before, self.limits, self))

    # -- what decide asks about the run --------------------------------------------------------
    def planned(self):
        from campaign.measure.driver import read_plan

        ids, Q, _ = read_plan(self.run.path)
        return ids, Q

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


# -- deciding --------------------------------------------------------------------------------------
def decide(diagnosis, rnd: Round, before: list, limits: Limits, loop) -> Decision:
    """The next step from a diagnosis (module docstring, 2.). ``before``: the earlier rounds;
    ``loop`` answers what the run holds (planned poses, training poses, the room the limits leave)
    and chooses poses. Deterministic: the same stored data give the same decision."""
    best = diagnosis.ranking[0] if diagnosis.ranking and diagnosis.ranking[0].significant else None
    if best is not None and diagnosis.verdict == "unexplained" and best.gain < MIN_PARTIAL_GAIN:
        best = None  # a small part of an unexplained error: the effect that explains it is more likely missing
    if best is not None and diagnosis.verdict is not None:
        part = "" if diagnosis.verdict == best.effect else ", which explains part of what is left"
        return Decision("add_effect", f"add {best.effect}{part} (held-out on the folds "
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
            return Decision("stop", "stop: no missing effect found, but the run has no noise floor to say how close "
                                    "the model is to the noise", reason="no_floor")
        weak = weak_structure_inputs(diagnosis)
        if weak and floor_round is None:
            s = diagnosis.structure
            what = (f"the model-free test finds {100 * s.heldout_gain:.0f} % of the held-out error on "
                    f"{_inputs_text(list(rnd.depends_on) or weak)} (p = {s.p_value:.2g}), below what the floor's "
                    "uncertainty lets it call significant")
            if before and before[-1].decision.reason == "probe":
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
    if diagnosis.structure_significant and rnd.depends_on:
        top = rnd.depends_on[0]
        last = before[-1] if before else None
        if reveals and last is not None and last.verdict == "unexplained" and last.depends_on[:1] == (top,):
            return Decision("stop", f"stop: unexplained, and {reveals * REVEAL_POSES if reveals else 0} poses chosen "
                                    f"to reveal it did not change the verdict (depends on {top} first)",
                            reason="unexplained")
        if reveals >= REVEAL_ROUNDS:
            return Decision("stop", f"stop: unexplained after {reveals} rounds of poses chosen to reveal it",
                            reason="unexplained")
        n, limit = loop.room(REVEAL_POSES)
        if n <= 0:
            return _limit_stop(limit, rnd)
        d = _reveal(list(rnd.depends_on), diagnosis.signature, loop, n)
        if d is None:
            return Decision("stop", "stop: unexplained, and no suitable pose is left to measure", reason="no_poses")
        return replace(d, text=f"unexplained, depends on {_inputs_text(rnd.depends_on)}: {d.text}")
    # above the floor, and nothing says on what the rest depends
    if floor_round is not None:
        return floor_round
    d = _design_or_stop(rnd, limits, loop, target, at_floor=False)
    if d.kind != "stop" or reveals:
        return d
    n, limit = loop.room(REVEAL_POSES)
    if n <= 0:
        return _limit_stop(limit, rnd)
    from campaign.plan.extend import spread_poses

    ids_train, _ = loop.training()
    ids, _ = loop.planned()
    pose_ids = spread_poses(loop.space, ids_train, ids, [f"q{j + 1}" for j in range(loop.space.robot.n_joints)], n)
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

    floor, ratio = diagnosis.floor, diagnosis.model_to_noise
    if not floor.known or ratio is None or floor.relative_uncertainty <= FLOOR_UNCERTAINTY_MAX:
        return None
    if any(r.decision.kind == "floor" for r in before):
        return None
    n, _ = loop.room(FLOOR_POSES * FLOOR_TIMES)
    n = min(n, loop.room(10 ** 9)[0] // 2)  # half of what the limits leave at most: the model may need the rest
    if n < 2 * FLOOR_TIMES:
        return None
    ids_train, _ = loop.training()
    ids, _ = loop.planned()
    chosen, _, _ = design_poses(loop.space, ids_train, ids, loop.design_effects(), n_max=n // FLOOR_TIMES)
    pose_ids = tuple(int(p) + r * REPEAT_ID_STRIDE for p in chosen for r in range(FLOOR_TIMES))
    return Decision("floor", f"the floor is known only to ±{100 * floor.relative_uncertainty:.0f} % "
                             f"(held-out {ratio:.2f}× it on the folds): "
                             f"measure {len(chosen)} informative poses {FLOOR_TIMES} times back to back, for the noise",
                    pose_ids=pose_ids)


#: significance of the change of poses measured again after a pause (:func:`time_change_p`)
TIME_ALPHA = 0.01


def time_change_p(run: RunFolder, floor) -> float | None:
    """p-value of "the poses measured again later (remeasure rounds: the same joints but for
    1 µrad) moved by no more than the noise": the differences d of their measured positions from
    their first measurement against the floor's σ per coordinate, Σ (d / (√2 σ))² ~ χ²(3n). None
    without such pairs or without a floor."""
    from scipy import stats

    from campaign.plan.extend import REMEASURE_OFFSET_RAD
    from campaign.plan.selection import REPEAT_ID_STRIDE

    if not floor.known or floor.sigma_position_m is None or not np.all(np.asarray(floor.sigma_position_m) > 0):
        return None
    with run.store() as store:
        poses = store.load_measured()
    first = {int(p): k for k, p in enumerate(poses.pose_id) if p < REPEAT_ID_STRIDE}
    z = []
    for k, pid in enumerate(poses.pose_id):
        b, r = int(pid % REPEAT_ID_STRIDE), int(pid // REPEAT_ID_STRIDE)
        if r == 0 or b not in first:
            continue
        dq = poses.q[k] - poses.q[first[b]]
        if not (np.all(np.abs(dq[:-1]) == 0) and abs(abs(dq[-1]) - r * REMEASURE_OFFSET_RAD) < 1e-9):
            continue  # a repeat for the floor (identical joints), not a pose measured again later
        z.append((poses.xyz[k] - poses.xyz[first[b]]) / (np.sqrt(2.0) * np.asarray(floor.sigma_position_m)))
    if not z:
        return None
    z = np.asarray(z)
    return float(stats.chi2.sf(float(np.sum(z ** 2)), z.size))


#: a structure the model-free test finds at the floor with p below this (and a positive gain) is
#: tested with more poses before auto calls it the floor; after them it must reach diagnose's ALPHA
PROBE_ALPHA = 0.1


def weak_structure_inputs(diagnosis, alpha: float = PROBE_ALPHA) -> list:
    """The inputs (by permutation importance) of a structure the model-free test finds by its
    p-value (p < ``alpha``, a positive held-out gain) but does not call significant: below the
    detection limit that the floor's uncertainty sets at the floor. Empty otherwise."""
    from campaign.diagnose.engine import MIN_IMPORTANCE_SHARE

    s = diagnosis.structure
    if s is None or diagnosis.structure_significant or not (s.p_value < alpha and s.heldout_gain > 0):
        return []
    return s.depends_on(MIN_IMPORTANCE_SHARE)


def _reveal(inputs, signature, loop, n: int) -> Decision | None:
    """``n`` poses that reveal a structure depending on ``inputs``: measured poses again now when
    time (or temperature) comes first, else new poses spread over the joints among the inputs (and
    the gravity load when the signature says it grows with it). None when no pose is left."""
    ids_train, times = loop.training()
    if inputs and inputs[0] in TIME_INPUTS:
        from campaign.plan.extend import remeasure_poses

        pose_ids = remeasure_poses(loop.space, ids_train, times, n)
        return Decision("remeasure", f"measure {len(pose_ids)} of the oldest poses again now",
                        pose_ids=tuple(int(p) for p in pose_ids))
    from campaign.plan.extend import spread_poses

    chosen = [i for i in inputs if i not in TIME_INPUTS]
    if signature is not None and any(k != "time_s" for k in signature.growth):
        chosen.append("gravity load")
    ids, _ = loop.planned()
    pose_ids = spread_poses(loop.space, ids_train, ids, chosen, n)
    if len(pose_ids) == 0:
        return None
    return Decision("reveal", f"measure {len(pose_ids)} poses spread over {', '.join(chosen) or 'the joints'}",
                    pose_ids=tuple(int(p) for p in pose_ids))


def _design_or_stop(rnd, limits, loop, target, *, at_floor: bool) -> Decision:
    from campaign.plan.extend import design_poses

    ids_train, _ = loop.training()
    ids, _ = loop.planned()
    n, limit = loop.room(DESIGN_MAX_POSES)
    effects = loop.design_effects()
    _, predicted, _ = design_poses(loop.space, ids_train, ids, effects, n_max=0)
    what = "at the measurement noise" if at_floor else "above the floor, and nothing says why"
    if predicted <= target:
        if at_floor:
            return Decision("stop", f"stop: at the measurement noise, and the model well determined (predicted "
                                    f"error {1e3 * predicted:.1f} µm ≤ target {1e3 * target:.1f} µm)",
                            reason="at_floor")
        return Decision("stop", f"stop: {what}; the model is well determined (predicted error "
                                f"{1e3 * predicted:.1f} µm)",
                        reason="unexplained")
    if n < DESIGN_MIN_POSES:
        if at_floor:
            return Decision("stop", f"stop: at the measurement noise; the model's predicted error "
                                    f"{1e3 * predicted:.1f} "
                                    f"µm is above the target {1e3 * target:.1f} µm, but the "
                                    f"{'budget' if limit == 'budget' else 'pose limit'} allows no more poses",
                            reason="at_floor")
        return _limit_stop(limit, rnd)
    chosen, _, after = design_poses(loop.space, ids_train, ids, effects, n_max=n, target_mm=target,
                                    n_min=DESIGN_MIN_POSES)
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


def _reveal_rounds(before) -> int:
    """Rounds just before this one that measured poses to reveal an "unexplained" (consecutive)."""
    n = 0
    for r in reversed(before):
        if r.decision.kind not in ("reveal", "remeasure"):
            break
        n += 1
    return n


def _inputs_text(inputs) -> str:
    inputs = ["time" if i == "time_s" else i for i in inputs]
    return inputs[0] if len(inputs) == 1 else ", ".join(inputs[:-1]) + " and " + inputs[-1]


# -- the end ---------------------------------------------------------------------------------------
def verdict_text(run: RunFolder, state: dict) -> str:
    """The final verdict and what the user can do next, in a few lines."""
    last = Round.from_json(state["rounds"][-1])
    reason = (state.get("finished") or {}).get("reason")
    ratio = f"{last.ratio:.2f}× the noise floor" if last.ratio is not None else "no noise floor"
    head = f"{last.model} on {last.poses} poses ({last.hours:.2f} h): held-out mean {last.heldout_mm:.4f} mm = {ratio}"
    if reason == "at_floor":
        return (f"verdict: at the measurement noise: nothing left to find. {head}.\n"
                f"  the model: {run.calibration_dir}/params.yaml; use it with `campaign predict {run.path}` or "
                f"`campaign compensate {run.path}`, or export it: `campaign export {run.path} --urdf OUT.urdf`")
    if reason == "unexplained":
        dep = last.signature or (f"depends on {_inputs_text(last.depends_on)}" if last.depends_on else
                                 "no input found on which it depends")
        joints = [i for i in last.depends_on if i.startswith("q")]
        hint = (f"an effect that depends on {_inputs_text(joints)}" if joints else
                "an effect of time (drift, warm-up)" if set(last.depends_on) & set(TIME_INPUTS) else "an effect")
        return (f"verdict: unexplained — systematic error remains that no candidate explains: {dep}. {head}.\n"
                f"  next: write {hint} (docs/effects.md, 'Writing an effect'), add it to {run.config_path} "
                f"(effects: [..., your_file.py:YourEffect]) and run `campaign auto {run.path}` again")
    if reason in ("budget", "max_poses"):
        what = "budget" if reason == "budget" else "pose limit"
        return (f"verdict: stopped at the {what} with the model {last.model} ({last.verdict or 'at the floor'} in the "
                f"last diagnosis). {head}.\n  next: run `campaign auto {run.path} "
                f"{'--budget HOURS' if reason == 'budget' else '--max-poses N'}` with a larger limit to go on")
    if reason == "no_floor":
        return (f"verdict: no missing effect found. {head}.\n  next: state the tracker's noise "
                f"(`tracker: {{noise_m: ...}}` in {run.config_path}) or measure repeats, and run auto again")
    return f"verdict: {last.decision.text}. {head}."


def _result(run, state, say, *, report: bool) -> AutoResult:
    rounds = tuple(Round.from_json(r) for r in state["rounds"])
    text = verdict_text(run, state)
    page = None
    if report:
        page = write_auto_report(run, state, text)
    say(text)
    return AutoResult(run.path, rounds, rounds[-1].decision, text, page)


def write_auto_report(run: RunFolder, state: dict, text: str) -> Path:
    """RUN/calibration/report.html of the final model (calibrated again, with its report, when the
    last round's calibration wrote none; with the neural compensator after the long campaign,
    ``--select 0``, when it has the training poses for one) and RUN/auto/report.html: the story,
    one line per round, and the held-out error over the rounds against the noise floor
    (auto/rounds.png)."""
    from campaign.identify.calibrate import calibrate

    page = run.calibration_dir / "report.html"
    if not page.is_file() or page.stat().st_mtime < (run.calibration_dir / "metrics.json").stat().st_mtime:
        long = (state.get("options") or {}).get("select") == 0
        calibrate(run.path, ann="auto" if long else False, report=True)
        state["calibrated"] = {"effects": list(run.effects), "poses": run.stored_pose_count()}
        _save_state(run, state)
    rounds = [Round.from_json(r) for r in state["rounds"]]
    out = run.path / AUTO_DIR
    img = plot_rounds(rounds, out / "rounds.png")
    parts = ["<!doctype html><meta charset='utf-8'><title>campaign auto</title>",
             "<style>body{font-family:sans-serif;max-width:1100px;margin:2em auto;padding:0 1em}"
             "pre{background:#f6f6f6;padding:1em;white-space:pre-wrap}img{max-width:100%}</style>",
             f"<h1>campaign auto: {html.escape(run.path.name)}</h1>",
             "<h2>The rounds</h2>", f"<pre>{html.escape(chr(10).join(r.line() for r in rounds))}</pre>",
             "<h2>The verdict</h2>", f"<pre>{html.escape(text)}</pre>"]
    if img:
        parts += ["<h2>The error over the rounds</h2>", f"<img src='{img.name}'>"]
    parts += ["<p>the final model's report: <a href='../calibration/report.html'>calibration/report.html</a>; "
              "the last diagnosis: <a href='../diagnose/diagnosis.json'>diagnose/diagnosis.json</a></p>"]
    return atomic_write(out / "report.html", "\n".join(parts))


def plot_rounds(rounds, path: Path):
    """The held-out mean position error after each round (log scale) with the noise floor, each
    point labelled with the model and the poses measured; None without rounds."""
    if not rounds:
        return None
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(figsize=(9, 4.2))
    x = [r.number for r in rounds]
    ax.plot(x, [r.heldout_mm for r in rounds], "o-", label="held-out mean ‖Δt‖ (test set)")
    floors = [r.floor_mm for r in rounds]
    if any(f for f in floors):
        ax.plot(x, [f if f else float("nan") for f in floors], ":", color="C3", label="noise floor (repeats)")
    for r in rounds:
        ax.annotate(f"{r.model.replace('geometric', 'geo')}\n{r.poses} poses", (r.number, r.heldout_mm),
                    textcoords="offset points", xytext=(0, 8), ha="center", fontsize=7)
    ax.set_yscale("log")
    values = [r.heldout_mm for r in rounds] + [f for f in floors if f]
    ax.set_ylim(min(values) / 2, max(values) * 3)
    ax.set_xlim(0.5, len(rounds) + 0.5)
    ax.set_xticks(x)
    ax.set_xlabel("round")
    ax.set_ylabel("held-out mean ‖Δt‖ [mm]")
    ax.set_title("campaign auto: the error over the rounds")
    ax.legend(fontsize=8)
    fig.tight_layout()
    path.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(path, dpi=110)
    plt.close(fig)
    return path


__all__ = ["AutoOptions", "AutoResult", "CellSource", "Decision", "Round", "auto", "decide", "verdict_text"]
