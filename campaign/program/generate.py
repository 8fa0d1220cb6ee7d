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
FORMATS = {"urscript": "campaign.program.urscript", "krl": "campaign.program.krl", "rapid": "campaign.program.rapid",
           "fanuc-ls": "campaign.program.fanuc_ls", "pdl2": "campaign.program.pdl2",
           "ros2-trajectory": "campaign.program.ros2", "csv": "campaign.program.csvprog"}


@dataclass(frozen=True)
class ProgramInput:
    """What a language module writes a program from.

    stops: the stops (campaign.program.stops.Stop, model convention); q_controller (n, N): the
    stops' joints in the controller's convention (rad, m); speed: fraction of the robot's joint
    speeds (0 < speed <= 1); max_velocity, max_acceleration (N,): the robot's limits in the
    controller's convention (rad/s, rad/s², from robot.yaml, as the plan's Ruckig timing uses them);
    move_s (n,): Ruckig's rest-to-rest time into each stop from the one before (s; 0 for the first);
    trigger_output: digital output pulsed at each measured stop once the robot has settled, or
    None; name: program name (letters, digits, underscore, starting with a letter; each language
    shortens it to its own limit); robot_name; joint_names; prismatic (N,) bool; settle_s: the
    settle time at the start of each dwell (s, plan.settle_time_s)."""

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
    settle_s: float = 0.0
    #: (k, dt_s) -> (times (m,) s from the move's start, positions, velocities, accelerations (m, N)):
    #: samples of the Ruckig move into stop k at ``speed``, controller convention (or None)
    sampler: object = None
    #: the suffix of --out (a format may write another flavour for it, e.g. ROS 2 JSON)
    out_suffix: str = ""


def format_module(fmt: str):
    """The module of format ``fmt``; ConfigError naming the known ones otherwise."""
    if fmt not in FORMATS:
        raise ConfigError(f"--format {fmt!r}: unknown format (known: {', '.join(FORMATS)})")
    return importlib.import_module(FORMATS[fmt])


def program_name(run_dir=None, stem: str | None = None) -> str:
    """An identifier every language accepts (letters, digits, ``_``, starting with a letter):
    ``stem`` (--out's) made one, else ``CAL_<run folder's name>``; each language shortens it to
    its own limit (docs/programs.md)."""
    raw = stem if stem is not None else Path(run_dir).resolve().name
    base = "".join(c if c.isalnum() and c.isascii() else "_" for c in raw).strip("_") or "CAMPAIGN"
    if stem is None and not base.upper().startswith("CAL"):
        base = "CAL_" + base
    if not base[0].isalpha():
        base = "P" + base
    return base[:32]


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


def _sampler(robot, Q, speed):
    """The ProgramInput.sampler of the stops Q (n, N) model convention (rad, m)."""
    from campaign.plan.timing import ruckig_trajectory

    def sample(k, dt_s):
        T, traj = ruckig_trajectory(robot, Q[k - 1], Q[k])
        times = np.arange(dt_s, T / speed - 1e-9, dt_s)
        P, V, A = [], [], []
        for t in times:
            p, v, a = traj.at_time(t * speed)
            P.append(p), V.append(np.asarray(v) * speed), A.append(np.asarray(a) * speed ** 2)
        P = np.atleast_2d(robot.to_controller_q(np.array(P).reshape(-1, Q.shape[1])))
        lin = np.linalg.inv(robot.controller_matrix) if robot.controller_matrix is not None else np.eye(Q.shape[1])
        V, A = np.array(V).reshape(-1, Q.shape[1]) @ lin.T, np.array(A).reshape(-1, Q.shape[1]) @ lin.T
        return times, P, V, A
    return sample


def program_input(run_dir, *, speed: float = 1.0, trigger_output=None, stops=None, run=None,
                  out_suffix: str = "", name: str | None = None) -> ProgramInput:
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
                        name=name or program_name(run.path), robot_name=robot.name, joint_names=tuple(robot.joint_names),
                        prismatic=np.asarray(robot.prismatic, dtype=bool),
                        settle_s=float(run.config.plan.settle_time_s), sampler=_sampler(robot, Q, float(speed)),
                        out_suffix=out_suffix)


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

    out: the program's file: its folder holds the files, its stem names the program (as far as the
    language's rules allow: KRL and RAPID name modules like their files, FANUC in 8 upper-case
    characters); default RUN/program/cal_<run>.<ext>. Returns the files written."""
    from campaign.fileio import atomic_write
    from campaign.program.stops import PROGRAM_DIR, stops_path, write_stops_csv
    from campaign.run import RunFolder

    mod = format_module(fmt)
    run = RunFolder(run_dir)
    if not run.path.is_dir():
        raise DataError(f"{run.path}: no such run folder")
    if not run.poses_csv.is_file():
        raise DataError(f"{run.path}: no plan/poses.csv (run `campaign plan --run {run.path}` first)")
    if out is not None and Path(out).is_dir():
        raise ConfigError(f"--out {out}: is a folder; give the program's file name")
    inp = program_input(run.path, speed=speed, trigger_output=trigger_output, run=run,
                        out_suffix=Path(out).suffix if out is not None else "",
                        name=program_name(stem=Path(out).stem) if out is not None else None)
    files = mod.render(inp)
    folder = run.path / PROGRAM_DIR if out is None else Path(out).parent
    written = [atomic_write(folder / name, text) for name, text in files]
    sp = write_stops_csv(stops_path(run.path), inp.stops)
    return ProgramResult(tuple(written), sp, len(inp.stops), sum(s.measured for s in inp.stops),
                         float(np.sum(inp.move_s) + sum(s.dwell_s for s in inp.stops)))
