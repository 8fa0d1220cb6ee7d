"""The campaign driver: move → reached → measure the three reflectors → store → next.

The same code drives a real cell and the simulated one. Unattended: every request has a
timeout; a lost connection is re-opened with back-off and the request retried with the
same id (the peers answer a repeated id with their first reply); a pose whose measurement
keeps failing is stored as failed with its reason and the campaign goes on; an emergency
stop ends the campaign cleanly. Each pose is one committed SQLite transaction, so a
re-run resumes at the first pose without a stored outcome and never stores a pose twice.

Request ids are derived from the pose id and the attempt, so a re-run sends the same
requests as the first run did.
"""

from __future__ import annotations

import signal
import time
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from campaign.errors import CampaignError, DataError, PeerError, ProtocolError, RobotFault, TrackerTimeout
from campaign.measure import protocol as P
from campaign.measure.reflectors import frame_from_setup_points, pose_from_reflectors
from campaign.measure.store import PoseRecord, open_run
from campaign.model.rotations import matrix_to_rotvec
from campaign.progress import Progress

REFLECTORS = ("rrr1", "rrr2", "brr")
_SETUP_ID = 1 << 40
_DRIFT_ID = 1 << 41
_HEARTBEAT_ID = 1 << 42


@dataclass(frozen=True)
class RunOptions:
    timeout_s: float = 5.0
    move_timeout_s: float = 120.0
    retries: int = 3
    reconnect_attempts: int = 5
    backoff_s: float = 0.2
    drift_check_every: int = 500
    drift_threshold_mm: float = 0.05
    setup_repeats: int = 10

    @classmethod
    def from_config(cls, section: dict) -> "RunOptions":
        known = {k: section[k] for k in cls.__dataclass_fields__ if k in section}
        return cls(**known)


class Peer:
    """A client of one peer with reconnect, back-off and idempotent retries."""

    def __init__(self, host: str, port: int, name: str, opts: RunOptions, log):
        self.host, self.port, self.name, self.opts, self.log = host, int(port), name, opts, log
        self.conn = None
        self.reconnects = 0

    def _connect(self):
        delay = self.opts.backoff_s
        last = None
        for attempt in range(self.opts.reconnect_attempts):
            try:
                self.conn = P.Connection.connect(self.host, self.port, self.opts.timeout_s, self.name)
                return
            except PeerError as exc:
                last = exc
                time.sleep(delay)
                delay = min(delay * 2, 5.0)
        raise last

    def close(self):
        if self.conn is not None:
            self.conn.close()
            self.conn = None

    def request(self, msg, timeout_s: float):
        """Send ``msg`` and return the reply with its id; retried with the same id on failures."""
        last = None
        for attempt in range(self.opts.retries + 1):
            try:
                if self.conn is None:
                    if attempt:
                        self.reconnects += 1
                    self._connect()
                self.conn.send(msg)
                deadline = time.monotonic() + timeout_s
                while True:
                    reply = self.conn.receive(max(deadline - time.monotonic(), 1e-3))
                    if getattr(reply, "id", None) == msg.id:
                        return reply
                    if isinstance(reply, P.ErrorReply) and reply.id == 0:
                        raise ProtocolError(f"{self.name}: {reply.message}")
                    # a stale reply to an earlier request: keep reading
            except (PeerError, TrackerTimeout, ProtocolError) as exc:
                last = exc
                if attempt < self.opts.retries:
                    self.log(f"{exc}; retry {attempt + 1} of {self.opts.retries}")
                self.close()
                time.sleep(self.opts.backoff_s * (attempt + 1))
        raise PeerError(f"{self.name} {self.host}:{self.port}: no valid reply after {self.opts.retries + 1} attempts "
                        f"({last})")


def read_plan(run_dir):
    """(pose_ids (n,), q (n, 6), vias {pose_id: [q...]}) from RUN/plan/poses.csv and vias.csv."""
    plan = Path(run_dir) / "plan"
    path = plan / "poses.csv"
    if not path.is_file():
        raise DataError(f"{run_dir}: no plan/poses.csv (run `campaign plan --run {run_dir}` first)")
    lines = path.read_text().splitlines()
    if not lines or lines[0].strip() != "pose_id,q1,q2,q3,q4,q5,q6":
        raise DataError(f"{path}: header must be pose_id,q1,q2,q3,q4,q5,q6")
    ids, qs = [], []
    for k, line in enumerate(lines[1:], start=2):
        if not line.strip():
            continue
        cells = line.split(",")
        if len(cells) != 7:
            raise DataError(f"{path}: line {k} has {len(cells)} fields, expected 7")
        try:
            vals = [float(c) for c in cells]
        except ValueError:
            raise DataError(f"{path}: line {k}: not a number") from None
        if not np.all(np.isfinite(vals)) or vals[0] != int(vals[0]):
            raise DataError(f"{path}: line {k}: pose_id must be an integer and q finite")
        ids.append(int(vals[0]))
        qs.append(vals[1:])
    if len(set(ids)) != len(ids):
        raise DataError(f"{path}: duplicate pose_id")
    vias = {}
    vpath = plan / "vias.csv"
    if vpath.is_file():
        for line in vpath.read_text().splitlines()[1:]:
            if line.strip():
                c = [float(x) for x in line.split(",")]
                vias.setdefault(int(c[0]), []).append(c[1:])
    return np.array(ids, dtype=np.int64), np.array(qs, dtype=float).reshape(-1, 6), vias


@dataclass(frozen=True)
class RunResult:
    measured: int
    failed: int
    stored_before: int
    stopped: str | None
    simulated_duration_s: float
    wall_s: float
    drift_warnings: int


def run_campaign(run_dir, robot, controller, tracker, opts: RunOptions = RunOptions(), *, progress=False,
                 log=None, max_poses=None) -> RunResult:
    """Measure every planned pose of ``run_dir`` that has no stored outcome yet.

    controller, tracker: (host, port). Returns counts and the campaign clock at the end.
    """
    run_dir = Path(run_dir)
    say = log or (lambda msg: None)
    ids, Q, vias = read_plan(run_dir)
    robot.check_joints(Q, field=f"{run_dir}/plan/poses.csv")
    stop = {"flag": None}
    old_handler = None

    def on_sigint(signum, frame):
        stop["flag"] = "interrupted (Ctrl-C): stopped after the current pose"

    try:
        old_handler = signal.signal(signal.SIGINT, on_sigint)
    except ValueError:  # not in the main thread
        old_handler = None
    ctrl = Peer(*controller, "controller", opts, say)
    trk = Peer(*tracker, "tracker", opts, say)
    t_wall = time.perf_counter()
    clock = 0.0
    drift_warnings = 0
    with open_run(run_dir, create=True) as store:
        store._db.execute("PRAGMA journal_mode=WAL")
        store._db.execute("PRAGMA synchronous=NORMAL")
        done = store.stored_ids()
        stored_before = len(done)
        # base-frame set-up: T_LI from the set-up points, measured once and kept
        T_LI = store.get_meta("T_LI")
        if T_LI is None:
            pts = {t: [] for t in P.SETUP_TARGETS}
            for k in range(opts.setup_repeats):
                reply = trk.request(P.Measure(_SETUP_ID + k, P.SETUP_TARGETS), opts.timeout_s)
                for r in reply.readings:
                    if r.status == "ok" and r.target in pts:
                        pts[r.target].append(r.xyz_m)
            if any(len(v) == 0 for v in pts.values()):
                raise PeerError("tracker: the base-frame set-up points could not be measured")
            T_LI = frame_from_setup_points(*[np.mean(pts[t], axis=0) for t in P.SETUP_TARGETS])
            store.set_meta("T_LI", [[float(v) for v in row] for row in T_LI])
            store.set_meta("setup_points_L", {t: np.mean(v, axis=0).tolist() for t, v in pts.items()})
        T_LI = np.array(T_LI, dtype=float)
        P_E = robot.reflector_positions_in_E
        todo = [k for k in range(len(ids)) if int(ids[k]) not in done]
        if max_poses is not None:
            todo = todo[:max_poses]
        bar = Progress("measuring", len(todo), progress, " poses")
        n_ok = n_fail = 0
        reference = None
        stopped = None
        try:
            for n, k in enumerate(todo):
                pid = int(ids[k])
                q = Q[k]
                rec, clock = _measure_pose(pid, n, q, vias.get(pid, []), ctrl, trk, opts, T_LI, P_E, say)
                store.add_pose(rec)
                if rec.status == "measured":
                    n_ok += 1
                    if reference is None:
                        reference = (q, np.array(rec.xyz))
                else:
                    n_fail += 1
                if reference is not None and opts.drift_check_every and n and n % opts.drift_check_every == 0:
                    drift = _drift_check(n, reference, ctrl, trk, opts, T_LI, P_E)
                    if drift is not None and drift * 1e3 > opts.drift_threshold_mm:
                        drift_warnings += 1
                        say(f"warning: drift check after {n} poses: reference pose moved {drift * 1e3:.3f} mm "
                            f"(threshold {opts.drift_threshold_mm} mm)")
                    store.set_meta(f"drift_check_{n}", {"drift_mm": None if drift is None else drift * 1e3,
                                                        "time_s": clock})
                bar.update(1, extra=f"ok {n_ok} failed {n_fail} sim {clock / 3600:.1f} h")
                if stop["flag"]:
                    stopped = stop["flag"]
                    break
        except RobotFault as exc:
            stopped = f"robot fault: {exc}"
        finally:
            bar.close()
            ctrl.close()
            trk.close()
            if old_handler is not None:
                signal.signal(signal.SIGINT, old_handler)
            store.set_meta("campaign_clock_s", clock)
    return RunResult(n_ok, n_fail, stored_before, stopped, clock, time.perf_counter() - t_wall, drift_warnings)


def _move(ctrl, msg, opts):
    reply = ctrl.request(msg, opts.move_timeout_s)
    if isinstance(reply, P.Fault):
        if reply.code == "emergency_stop":
            raise RobotFault(f"{reply.code}: {reply.message}")
        return None, f"robot fault {reply.code}: {reply.message}"
    if not isinstance(reply, P.Reached):
        return None, f"controller answered '{reply.type}' to a move"
    return reply, None


def _measure_pose(pid, n, q, vias, ctrl, trk, opts, T_LI, P_E, say):
    """One pose, start to stored record. Returns (PoseRecord, campaign clock)."""
    retries = 0
    clock = 0.0
    try:
        for v, qv in enumerate(vias):
            reply, err = _move(ctrl, P.Move(pid * 64 + 32 + v, tuple(map(float, qv))), opts)
            if err:
                return PoseRecord(pid, "failed", tuple(q), seq=n, reason=f"via {v}: {err}"), clock
        reply, err = _move(ctrl, P.Move(pid * 64, tuple(map(float, q))), opts)
        if err:
            return PoseRecord(pid, "failed", tuple(q), seq=n, reason=err), clock
        q_enc = reply.q_encoder
        clock = reply.time_s
        last_reason = None
        for attempt in range(opts.retries + 1):
            m = trk.request(P.Measure(pid * 64 + 1 + attempt, REFLECTORS), opts.timeout_s)
            if not isinstance(m, P.Measurement):
                last_reason = f"tracker answered '{m.type}'"
                continue
            clock = m.time_s
            by = {r.target: r for r in m.readings}
            bad = [f"{t}: {by[t].status if t in by else 'missing'}" for t in REFLECTORS
                   if t not in by or by[t].status != "ok"]
            if bad:
                last_reason = "; ".join(bad)
                retries += 1
                continue
            P_L = np.array([by[t].xyz_m for t in REFLECTORS])
            T_IE, rms = pose_from_reflectors(T_LI, P_E, P_L[None])
            return PoseRecord(pid, "measured", tuple(q), seq=n, time_s=clock, wall_time_unix_s=time.time(),
                              q_encoder=tuple(q_enc), xyz=tuple(T_IE[0, :3, 3]),
                              rotvec=tuple(matrix_to_rotvec(T_IE[0, :3, :3])), fit_rms_m=float(rms[0]),
                              retries=retries,
                              reflectors={t: (by[t].xyz_m, by[t].status) for t in REFLECTORS}), clock
        return PoseRecord(pid, "failed", tuple(q), seq=n, time_s=clock, retries=retries,
                          reason=f"tracker after {opts.retries + 1} attempts: {last_reason}"), clock
    except RobotFault:
        raise
    except PeerError as exc:
        return PoseRecord(pid, "failed", tuple(q), seq=n, time_s=clock, retries=retries, reason=str(exc)), clock


def _drift_check(n, reference, ctrl, trk, opts, T_LI, P_E):
    """Re-measure the reference pose; the distance (m) of its derived position from the first time."""
    q, xyz0 = reference
    try:
        reply, err = _move(ctrl, P.Move(_DRIFT_ID + n * 4, tuple(map(float, q))), opts)
        if err:
            return None
        m = trk.request(P.Measure(_DRIFT_ID + n * 4 + 1, REFLECTORS), opts.timeout_s)
        by = {r.target: r for r in m.readings}
        if any(t not in by or by[t].status != "ok" for t in REFLECTORS):
            return None
        T_IE, _ = pose_from_reflectors(T_LI, P_E, np.array([[by[t].xyz_m for t in REFLECTORS]]))
        return float(np.linalg.norm(T_IE[0, :3, 3] - xyz0))
    except PeerError:
        return None


class SimulatedCell:
    """The simulated cell as a child process of the driver; it exits when the driver dies."""

    def __init__(self, config_path, run_dir):
        import json
        import subprocess
        import sys

        self.proc = subprocess.Popen(
            [sys.executable, "-m", "campaign.sim.cell", "--config", str(config_path), "--run", str(run_dir),
             "--watch-stdin"], stdin=subprocess.PIPE, stdout=subprocess.PIPE, stderr=subprocess.PIPE)
        line = self.proc.stdout.readline().decode()
        try:
            info = json.loads(line)
        except json.JSONDecodeError:
            err = self.proc.stderr.read().decode().strip().splitlines()
            self.stop()
            raise PeerError(f"the simulated cell did not start: {err[-1] if err else 'no output'}") from None
        if "error" in info:
            self.stop()
            raise CampaignError(f"simulated cell: {info['error']}")
        self.host = info["host"]
        self.controller = (self.host, info["controller"])
        self.tracker = (self.host, info["tracker"])
        self.truth_path = info["truth"]

    def stop(self):
        try:
            if self.proc.stdin:
                self.proc.stdin.close()
            self.proc.wait(timeout=10)
        except Exception:
            self.proc.kill()

    def __enter__(self):
        return self

    def __exit__(self, *exc):
        self.stop()
