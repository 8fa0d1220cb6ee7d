"""The stops of a planned campaign, in the order `campaign run` visits them: RUN/program/stops.csv.

A stop is a posture where the robot comes to rest. For each pose of ``RUN/plan/poses.csv`` (in
its order) the driver (campaign.measure.driver.run_campaign) moves through the via postures
``RUN/plan/vias.csv`` lists before that pose (kind ``via``: passed at rest, nothing measured),
then to the pose (kind ``pose``, ``validation`` when ``RUN/plan/validation.csv`` lists it,
``repeat`` when its id is a repeat id ``p + r·10⁹`` of ``RUN/plan/repeats.csv``), and after every
``drift_check_every``-th pose (campaign.measure.driver.drift_check_interval of the run's
``run.drift_check_every``; not after the last pose, nor after a pose whose drift motions the plan
found not clear, summary.json ``drift_monitor``) it goes back to the reference pose, the first
pose of the tour, and measures it again (kind ``drift``, pose_id the reference's).

The dwell at a measured stop is the time to settle and to measure every reflector:
``plan.settle_time_s + n_reflectors · plan.tracker_time_per_reflector_s`` of the run's
campaign.yaml (the plan's duration estimate, campaign.plan.pipeline, and the simulated cell,
campaign.sim.cell, take the same times). A via stop dwells 0 s: the robot stops there (every
move of a campaign is rest-to-rest, campaign.plan.timing) and goes on.

One difference from `campaign run`: the driver takes the first *measured* pose as its drift
reference; a program cannot know which poses will be measured, so it returns to the first one.
"""

from __future__ import annotations

import csv
import math
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from campaign.errors import DataError

KINDS = ("pose", "validation", "repeat", "drift", "via")
#: the kinds at which the tracker measures
MEASURED_KINDS = ("pose", "validation", "repeat", "drift")
PROGRAM_DIR = "program"
STOPS_FILE = "stops.csv"


@dataclass(frozen=True)
class Stop:
    """One stop of a program. stop: 0-based index in program order; pose_id: the plan's pose id
    (a via: the pose it leads to; a drift check: the reference pose); kind: one of KINDS;
    dwell_s: rest at the stop (s); q: (N,) joint vector in the model's convention (rad, m)."""

    stop: int
    pose_id: int
    kind: str
    dwell_s: float
    q: tuple

    @property
    def measured(self) -> bool:
        return self.kind in MEASURED_KINDS


def stops_path(run_dir) -> Path:
    """``RUN/program/stops.csv``."""
    return Path(run_dir) / PROGRAM_DIR / STOPS_FILE


def dwell_time_s(plan_config, n_reflectors: int) -> float:
    """Rest at a measured stop (s): settle, then each reflector measured in turn (PlanConfig)."""
    return float(plan_config.settle_time_s + n_reflectors * plan_config.tracker_time_per_reflector_s)


def order_stops(pose_ids, Q, vias, *, dwell_s: float, validation=(), repeats=(), drift_every: int = 0,
                no_drift_after=()) -> list:
    """The stops of a tour, as the driver visits them (module docstring).

    pose_ids (n,), Q (n, N) rad/m in visiting order; vias {pose_id: [q, ...]}; validation,
    repeats: pose ids of those kinds; drift_every: poses between drift checks (0: none);
    no_drift_after: pose ids after which the drift check is skipped."""
    from campaign.plan.selection import REPEAT_ID_STRIDE

    validation, repeats, no_drift_after = set(map(int, validation)), set(map(int, repeats)), set(map(int, no_drift_after))
    out = []

    def add(pid, kind, dwell, q):
        out.append(Stop(len(out), int(pid), kind, float(dwell), tuple(float(v) for v in q)))

    n = len(pose_ids)
    for k in range(n):
        pid = int(pose_ids[k])
        for qv in list(vias.get(pid, []))[:31]:  # the driver passes at most 31 vias (its request ids)
            add(pid, "via", 0.0, qv)
        kind = "repeat" if pid in repeats or pid >= REPEAT_ID_STRIDE else "validation" if pid in validation else "pose"
        add(pid, kind, dwell_s, Q[k])
        if drift_every and (k + 1) % drift_every == 0 and k + 1 < n and pid not in no_drift_after:
            add(pose_ids[0], "drift", dwell_s, Q[0])
    return out


def _id_column(path: Path) -> set:
    """The first column's integers of a plan's id list (validation.csv, repeats.csv), header skipped."""
    if not path.is_file():
        return set()
    ids = set()
    for k, line in enumerate(path.read_text().splitlines()[1:], start=2):
        if line.strip():
            try:
                ids.add(int(line.split(",")[0]))
            except ValueError:
                raise DataError(f"{path}: line {k}: pose_id must be an integer") from None
    return ids


def plan_stops(run_dir, *, run=None) -> list:
    """The stops of the planned run ``run_dir`` (RUN/plan/ and RUN/campaign.yaml), in program order.

    ``run``: its :class:`campaign.run.RunFolder` when already open. DataError when the run has
    no plan or a planned pose lies outside the robot's joint limits."""
    from campaign.measure.driver import _unclear_drift_returns, drift_check_interval, measured_robot, read_plan
    from campaign.run import RunFolder

    run = run or RunFolder(run_dir)
    if not run.path.is_dir():
        raise DataError(f"{run.path}: no such run folder")
    ids, Q, vias = read_plan(run.path)
    robot = run.robot()
    if Q.shape[1] != robot.n_joints:
        raise DataError(f"{run.poses_csv}: {Q.shape[1]} joints, the run's robot {robot.name} has {robot.n_joints}")
    robot.check_joints(Q, field=str(run.poses_csv), pose_ids=ids)
    cfg = run.config
    dwell = dwell_time_s(cfg.plan, len(measured_robot(robot).reflectors))
    return order_stops(ids, Q, vias, dwell_s=dwell, validation=_id_column(run.plan_dir / "validation.csv"),
                       repeats=_id_column(run.plan_dir / "repeats.csv"),
                       drift_every=drift_check_interval(cfg.run.drift_check_every, len(ids)),
                       no_drift_after=_unclear_drift_returns(run.path))


def stops_header(n_joints: int) -> list:
    return ["stop", "pose_id", "kind", "dwell_s", *(f"q{j}" for j in range(1, n_joints + 1))]


def write_stops_csv(path, stops) -> Path:
    """Write ``stops`` as ``stop,pose_id,kind,dwell_s,q1..qN`` (rad, m; full precision), atomically."""
    from campaign.fileio import atomic_open

    stops = list(stops)
    if not stops:
        raise DataError(f"{path}: no stops to write")
    N = len(stops[0].q)
    with atomic_open(path, "w", newline="") as fh:
        w = csv.writer(fh, lineterminator="\n")
        w.writerow(stops_header(N))
        for s in stops:
            w.writerow([s.stop, s.pose_id, s.kind, repr(float(s.dwell_s)), *(repr(float(v)) for v in s.q)])
    return Path(path)


def read_stops_csv(path) -> list:
    """The stops of a stops.csv, checked: header ``stop,pose_id,kind,dwell_s,q1..qN``, stops
    numbered 0, 1, ... in order, kinds of KINDS, finite numbers, dwell >= 0. DataError naming
    the file and line otherwise."""
    path = Path(path)
    if not path.is_file():
        raise DataError(f"{path}: no such stops file (write it with `campaign program RUN --format csv`)")
    with open(path, newline="") as fh:
        rows = list(csv.reader(fh))
    if not rows:
        raise DataError(f"{path}: empty; header must be stop,pose_id,kind,dwell_s,q1..qN")
    head = [h.strip() for h in rows[0]]
    N = len(head) - 4
    if N < 1 or head != stops_header(N):
        raise DataError(f"{path}: header must be stop,pose_id,kind,dwell_s,q1..qN, got {','.join(head)}")
    out = []
    for k, row in enumerate(rows[1:], start=2):
        if not row or not "".join(row).strip():
            continue
        if len(row) != N + 4:
            raise DataError(f"{path}: line {k} has {len(row)} fields, expected {N + 4}")
        try:
            stop, pid = int(row[0]), int(row[1])
            dwell = float(row[3])
            q = tuple(float(v) for v in row[4:])
        except ValueError:
            raise DataError(f"{path}: line {k}: stop and pose_id must be integers, dwell_s and q numbers") from None
        kind = row[2].strip()
        if kind not in KINDS:
            raise DataError(f"{path}: line {k}: kind {kind!r} is not one of {', '.join(KINDS)}")
        if stop != len(out):
            raise DataError(f"{path}: line {k}: stop {stop}, expected {len(out)} (stops numbered in program order)")
        if not (math.isfinite(dwell) and dwell >= 0) or not np.all(np.isfinite(q)):
            raise DataError(f"{path}: line {k}: dwell_s must be a finite number >= 0 and q finite")
        out.append(Stop(stop, pid, kind, dwell, q))
    if not out:
        raise DataError(f"{path}: no stops")
    return out


def stops_array(stops) -> np.ndarray:
    """The stops' joint vectors, (n, N) rad/m."""
    return np.array([s.q for s in stops], dtype=float)
