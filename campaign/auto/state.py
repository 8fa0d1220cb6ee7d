"""The loop's data: its options, where it measures, a decision, a round, the result, and its state
on disk (RUN/auto/state.json, written atomically after every step)."""

from __future__ import annotations

import json
from dataclasses import asdict, dataclass, field
from pathlib import Path

from campaign.errors import ConfigError, DataError
from campaign.fileio import atomic_write
from campaign.run import RunFolder

AUTO_DIR = "auto"
STATE_FILE = "state.json"
STATE_VERSION = 1
#: without --max-poses: this many times the planned short campaign's poses at most
MAX_POSES_FACTOR = 2


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
    """What a round decided. kind: ``add_effect`` (``effect``), ``remove_effect`` (``effect`` taken
    out, or one of its joints: ``effects`` the model's effects after it; ``reason`` ``time`` for the
    effects of time with which the same poses still move), ``design``, ``reveal``, ``floor``
    or ``remeasure`` (``pose_ids`` to append and measure; ``reason`` ``probe`` for poses that
    test a structure found below the detection limit at the floor; ``separate`` for poses that separate two
    effects indistinguishable on one joint), or ``stop`` (``reason``: ``at_floor``, ``unexplained``,
    ``no_floor``, ``budget``, ``max_poses``, ``no_poses``, ``indistinguishable``); text: one line."""

    kind: str
    text: str
    effect: str | None = None
    pose_ids: tuple = ()
    reason: str | None = None
    effects: tuple = ()

    def as_json(self) -> dict:
        return {**asdict(self), "pose_ids": [int(p) for p in self.pose_ids], "effects": list(self.effects)}

    @classmethod
    def from_json(cls, doc) -> "Decision":
        return cls(doc["kind"], doc["text"], doc.get("effect"), tuple(int(p) for p in doc.get("pose_ids", ())),
                   doc.get("reason"), tuple(doc.get("effects", ())))


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

    def ratio_text(self, floor: str = "the floor") -> str:
        """The held-out mean against the floor in words: "= 1.08× the floor"; a floor of 0
        (noise-free data) has no ratio but is a floor, not a missing one."""
        if self.ratio is not None:
            return f"= {self.ratio:.2f}× {floor}"
        return "(the noise floor is 0)" if self.floor_mm == 0 else "(no noise floor)"

    def line(self) -> str:
        ratio = " " + self.ratio_text()
        return (f"round {self.number}: {self.poses} poses, {self.hours:.2f} h, {self.model}: test set "
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



@dataclass(frozen=True)
class Limits:
    max_poses: int
    budget_h: float | None
    target_mm: float | None



# -- the state on disk ----------------------------------------------------------------------------
def state_path(run: RunFolder) -> Path:
    return run.path / AUTO_DIR / STATE_FILE


def load_state(run: RunFolder) -> dict:
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


def calibrated_key(run: RunFolder, state: dict) -> dict:
    """What the loop's last calibration was of (``state["calibrated"]``): the effects, the stored
    poses and, when one was asked for, the cell segment (a new one is calibrated again)."""
    key = {"effects": list(run.effects), "poses": run.stored_pose_count()}
    if state.get("cell_segment") is not None:
        key["cell_segment"] = state["cell_segment"]
    return key


def save_state(run: RunFolder, state: dict) -> None:
    atomic_write(state_path(run), json.dumps(state, indent=2))

