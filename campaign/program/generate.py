"""`campaign program`: the planned campaign as a program for the robot's controller.

:func:`build_program` reads the run's stops (campaign.program.stops), converts them to the
controller's joint convention (robot.yaml's ``controller:``: q_model = coupling · diag(sign) ·
q_controller + offset, campaign.model.robot.RobotModel.to_controller_q), and hands a
:class:`ProgramInput` to the module of the format asked for (one module per language,
:data:`FORMATS`), which returns the program's files. RUN/program/stops.csv is written with every
program: it is what a tracker's log is matched to (`campaign import --stream`).
"""

from __future__ import annotations

import importlib
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from campaign.errors import ConfigError, DataError

#: format name -> module under campaign.program (each has ``render(ProgramInput) -> [(name, text)]``,
#: ``EXTENSION``, ``read_joints(text or files) -> (n, N)`` in the format's units and ``check(files, ...)``)
FORMATS = {"csv": "campaign.program.csvprog"}


@dataclass(frozen=True)
class ProgramInput:
    """What a language module writes a program from.

    stops: the stops (campaign.program.stops.Stop, model convention); q_controller (n, N): the
    stops' joints in the controller's convention (rad, m); speed: fraction of the robot's joint
    speeds (0 < speed <= 1); max_velocity, max_acceleration (N,): the robot's limits in the
    controller's convention (rad/s, rad/s², from robot.yaml, as the plan's Ruckig timing uses them);
    move_s (n,): Ruckig's rest-to-rest time into each stop from the one before (s; 0 for the first);
    trigger_output: digital output pulsed at each measured stop, or None; name: program name (a
    valid identifier in every language: letters, digits, underscore, starting with a letter);
    robot_name; joint_names; lower, upper (N,): joint limits (model convention)."""

    stops: tuple
    q_controller: np.ndarray
    speed: float
    max_velocity: np.ndarray
    max_acceleration: np.ndarray
    move_s: np.ndarray
    trigger_output: int | None
    name: str
    robot_name: str
    joint_names: tuple
    prismatic: np.ndarray


def format_module(fmt: str):
    """The module of format ``fmt``; ConfigError naming the known ones otherwise."""
    if fmt not in FORMATS:
        raise ConfigError(f"--format {fmt!r}: unknown format (known: {', '.join(FORMATS)})")
    return importlib.import_module(FORMATS[fmt])


def program_name(run_dir) -> str:
    """An identifier every language accepts, from the run folder's name (at most 24 characters:
    FANUC's program names are the shortest limit we write, docs/programs.md)."""
    base = "".join(c if c.isalnum() else "_" for c in Path(run_dir).resolve().name.upper())
    base = base.strip("_") or "CAMPAIGN"
    if not base[0].isalpha():
        base = "C" + base
    return ("CAL_" + base)[:24] if not base.startswith("CAL") else base[:24]


def _limits_controller(robot) -> tuple:
    """The robot's speed and acceleration limits in the controller's convention (N,) each: a
    controller joint j moves the model joints through column j of the coupling matrix A, so
    its limit is the tightest of theirs divided by |A_ij| (the same limits keep every model joint
    within its own when a single controller joint moves)."""
    A = robot.controller_matrix
    v, a = np.asarray(robot.max_velocity, dtype=float), np.asarray(robot.max_acceleration, dtype=float)
    if A is None:
        return v.copy(), a.copy()
    absA = np.abs(A)
    with np.errstate(divide="ignore"):
        vc = np.min(np.where(absA > 0, v[:, None] / absA, np.inf), axis=0)
        ac = np.min(np.where(absA > 0, a[:, None] / absA, np.inf), axis=0)
    return vc, ac


def program_input(run_dir, *, speed: float = 1.0, trigger_output=None, stops=None, run=None) -> ProgramInput:
    """The :class:`ProgramInput` of a planned run (its stops, or ``stops`` given)."""
    from campaign.plan.timing import rest_to_rest_time
    from campaign.program.stops import plan_stops, stops_array
    from campaign.run import RunFolder

    if not (isinstance(speed, (int, float)) and 0 < speed <= 1):
        raise ConfigError(f"--speed must be a fraction in (0, 1] of the robot's joint speeds, got {speed!r}")
    if trigger_output is not None and not (isinstance(trigger_output, int) and 1 <= trigger_output <= 4096):
        raise ConfigError(f"--trigger-output must be a digital output number in 1..4096, got {trigger_output!r}")
    run = run or RunFolder(run_dir)
    stops = tuple(stops if stops is not None else plan_stops(run.path, run=run))
    robot = run.robot()
    Q = stops_array(stops)
    move_s = np.zeros(len(Q))
    if len(Q) > 1:
        move_s[1:] = rest_to_rest_time(robot, Q[:-1], Q[1:])
    v, a = _limits_controller(robot)
    return ProgramInput(stops=stops, q_controller=np.atleast_2d(robot.to_controller_q(Q)), speed=float(speed),
                        max_velocity=v, max_acceleration=a, move_s=move_s / speed, trigger_output=trigger_output,
                        name=program_name(run.path), robot_name=robot.name, joint_names=tuple(robot.joint_names),
                        prismatic=np.asarray(robot.prismatic, dtype=bool))


@dataclass(frozen=True)
class ProgramResult:
    """What `campaign program` wrote: the program's files, stops.csv, the number of stops."""

    files: tuple
    stops_csv: Path
    n_stops: int
    n_measured: int
    duration_s: float


def build_program(run_dir, fmt: str, *, out=None, speed: float = 1.0, trigger_output=None) -> ProgramResult:
    """Write the program of format ``fmt`` for the planned run ``run_dir`` and RUN/program/stops.csv.

    out: the program's file (a multi-part program: its first part, the others beside it with the
    same stem); default RUN/program/<name>.<ext>. Returns the files written."""
    from campaign.fileio import atomic_write
    from campaign.program.stops import PROGRAM_DIR, stops_path, write_stops_csv
    from campaign.run import RunFolder

    mod = format_module(fmt)
    run = RunFolder(run_dir)
    if not run.path.is_dir():
        raise DataError(f"{run.path}: no such run folder")
    if not run.poses_csv.is_file():
        raise DataError(f"{run.path}: no plan/poses.csv (run `campaign plan --run {run.path}` first)")
    inp = program_input(run.path, speed=speed, trigger_output=trigger_output, run=run)
    files = mod.render(inp)
    if out is None:
        folder, stem = run.path / PROGRAM_DIR, None
    else:
        out = Path(out)
        if out.is_dir():
            raise ConfigError(f"--out {out}: is a folder; give the program's file name")
        folder, stem = out.parent, out
    written = []
    for k, (name, text) in enumerate(files):
        if stem is not None:
            name = stem.name if k == 0 else _sibling(stem, files[0][0], name)
        written.append(atomic_write(folder / name, text))
    sp = write_stops_csv(stops_path(run.path), inp.stops)
    return ProgramResult(tuple(written), sp, len(inp.stops), sum(s.measured for s in inp.stops),
                         float(np.sum(inp.move_s) + sum(s.dwell_s for s in inp.stops)))


def _sibling(out: Path, first: str, name: str) -> str:
    """The name of a further part beside ``out``: the generated name with the generated first
    part's stem replaced by ``out``'s stem (KRL's .dat beside its .src, parts _2, _3, ...)."""
    first_stem = Path(first).stem
    return out.stem + name[len(first_stem):] if name.startswith(first_stem) else name
