"""The campaign driver: move → reached → measure the tool's reflectors → store → next.

The same code drives a real cell and the simulated one. Unattended: every request has a
timeout; a lost connection is re-opened with back-off and the request retried with the
same id (the peers answer a repeated id with their first reply); a pose whose measurement
keeps failing is stored as failed with its reason and the campaign goes on; a robot fault
that is not specific to the pose (an emergency stop, an unknown fault code), a peer that
cannot be reached at all, or too many failed poses in a row stop the campaign cleanly.
Each pose is one committed SQLite transaction, so a re-run resumes at the first pose
without a stored outcome and never stores a pose twice.

Request ids are derived from the pose id, the attempt and an epoch kept in the run's meta
(raised only by ``retry_failed``), so a re-run sends the same requests as the first run did.
docs/protocol.md gives the id layout.
"""

from __future__ import annotations

import signal
import time
from dataclasses import asdict, dataclass
from pathlib import Path

import numpy as np

from campaign.config import MAX_GRID_SIZE as MAX_POSE_ID  # pose ids are the plan's grid indices
from campaign.config import RunConfig
from campaign.errors import AuthError, DataError, Implausible, PeerError, ProtocolError, RobotFault
from campaign.measure import protocol as P
from campaign.measure.aims import AimPredictor
from campaign.measure.plausibility import check_tracker_readings
from campaign.measure.reflectors import frame_from_setup_points, invert, pose_from_reflectors, transform_points
from campaign.measure.store import PoseRecord, open_run
from campaign.model.rotations import matrix_to_rotvec
from campaign.progress import Progress

#: the default COMAU's reflectors; a run measures its robot's (robot.yaml's, else the default triad)
REFLECTORS = ("rrr1", "rrr2", "brr")
#: request ids: pose requests are ``pose_id * 64 + slot`` (slot 0 the move, 1.. the measure
#: attempts, 32.. the via moves); these bases lie above every pose id < 2**34
_SETUP_ID = 1 << 40
_DRIFT_ID = 1 << 41
_HEARTBEAT_ID = 1 << 42
_EPOCH_ID = 1 << 44
#: controller fault codes that concern only the requested pose: the pose is marked failed
#: and the campaign goes on. Any other code (``emergency_stop``, ...) stops the campaign.
POSE_FAULT_CODES = ("joint_limit", "move_rejected", "unreachable")


#: ``run.drift_check_every: auto``: the reference pose re-measured about this many times a campaign
#: (a drift figure for a short campaign too, campaign.measure.drift; 8 checks of ~25 s add ~5 % to
#: the default short campaign), and at least every DRIFT_CHECK_MAX_EVERY poses (a long one)
DRIFT_CHECKS_PER_CAMPAIGN = 8
DRIFT_CHECK_MAX_EVERY = 500


def drift_check_interval(every, n_poses: int) -> int:
    """Stored poses between drift checks: ``every`` as configured (0: none), or for ``"auto"``
    n_poses / DRIFT_CHECKS_PER_CAMPAIGN, at most DRIFT_CHECK_MAX_EVERY."""
    if every != "auto":
        return int(every)
    return int(min(DRIFT_CHECK_MAX_EVERY, max(1, n_poses // (DRIFT_CHECKS_PER_CAMPAIGN + 1) + 1)))


class PeerUnreachable(PeerError):
    """A peer could not be connected to after every reconnect attempt; the campaign stops."""


class AuthFailed(PeerUnreachable):
    """The peer and the driver disagree about authenticated frames (a token on one side only);
    retrying cannot help, the campaign stops."""


@dataclass(frozen=True)
class RunOptions(RunConfig):
    """How the driver waits and retries: the validated ``run:`` section of campaign.yaml
    (campaign.config.RunConfig) and what campaign.yaml does not set. Times in s."""

    setup_repeats: int = 10
    #: the stated tracker noise (``tracker: {noise_m}``, m), for the drift check's threshold
    tracker_noise_m: float | None = None
    #: stop the campaign when this many poses in a row fail (something systematic is wrong)
    max_consecutive_failures: int = 50

    @classmethod
    def from_config(cls, section) -> "RunOptions":
        """From the validated ``run:`` section (RunConfig) or a mapping of its keys."""
        if not isinstance(section, dict):
            section = asdict(section)
        return cls(**{k: section[k] for k in cls.__dataclass_fields__ if k in section})


class Peer:
    """A client of one peer with reconnect, back-off and idempotent retries; ``key``: the shared
    secret of authenticated frames (campaign.measure.auth.read_token) or None."""

    def __init__(self, host: str, port: int, name: str, opts: RunOptions, log, key: bytes | None = None):
        self.host, self.port, self.name, self.opts, self.log = host, int(port), name, opts, log
        self.key = key
        self.conn = None
        self.reconnects = 0
        self._heartbeats = 0

    def _connect(self):
        delay = self.opts.backoff_s
        last = None
        for attempt in range(max(self.opts.reconnect_attempts, 1)):
            if attempt:
                time.sleep(delay)
                delay = min(delay * 2, 5.0)
            try:
                self.conn = P.Connection.connect(self.host, self.port, self.opts.timeout_s, self.name, self.key)
                return
            except AuthError as exc:
                raise AuthFailed(f"{exc}; the driver has --token-file, the peer must be served with the same") from None
            except PeerError as exc:
                last = exc
        raise PeerUnreachable(str(last))

    def close(self):
        if self.conn is not None:
            self.conn.close()
            self.conn = None

    def request(self, msg, timeout_s: float):
        """Send ``msg`` and return the reply with its id; retried with the same id on failures.

        Raises PeerUnreachable when the peer cannot be connected to, PeerError when no
        valid reply came after ``retries + 1`` attempts.
        """
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
                    if isinstance(reply, P.Hello):
                        raise AuthFailed(f"{self.name} {self.host}:{self.port}: the peer authenticates its frames; "
                                         "give its shared secret (campaign run --token-file FILE)")
                    if getattr(reply, "id", None) == msg.id:
                        return reply
                    if isinstance(reply, P.ErrorReply) and reply.id == 0:
                        raise ProtocolError(f"{self.name}: {reply.message}")
                    # a stale reply to an earlier request: keep reading
            except PeerUnreachable:
                raise
            except (PeerError, ProtocolError) as exc:
                last = exc
                self.close()
                if attempt < self.opts.retries:
                    self.log(f"{exc}; retry {attempt + 1} of {self.opts.retries}")
                    time.sleep(self.opts.backoff_s * (attempt + 1))
        raise PeerError(f"{self.name} {self.host}:{self.port}: no valid reply after {self.opts.retries + 1} attempts "
                        f"({last})")

    def heartbeat(self) -> "P.HeartbeatAck":
        """Ask the peer who it is; PeerError when it is not the peer this client expects."""
        self._heartbeats += 1
        ack = self.request(P.Heartbeat(_HEARTBEAT_ID + (time.time_ns() // 1000 + self._heartbeats) % (1 << 40)),
                           self.opts.timeout_s)
        if not isinstance(ack, P.HeartbeatAck):
            raise PeerError(f"{self.name} {self.host}:{self.port}: answered '{ack.type}' to a heartbeat")
        if ack.peer != self.name:
            raise PeerError(f"{self.name} {self.host}:{self.port}: the peer there is a {ack.peer!r}, not the "
                            f"{self.name} (are --controller and --tracker swapped?)")
        return ack


def read_plan(run_dir, poses_csv=None):
    """(pose_ids (n,), q (n, N) rad, vias {pose_id: [q...]}) from RUN/plan/poses.csv and vias.csv
    (header ``pose_id,q1..qN``, N from the header: the caller checks it against the robot).

    ``poses_csv`` replaces RUN/plan/poses.csv (vias are then not read).
    """
    plan = Path(run_dir) / "plan"
    path = Path(poses_csv) if poses_csv is not None else plan / "poses.csv"
    if not path.is_file():
        if poses_csv is not None:
            raise DataError(f"{path}: no such pose list")
        raise DataError(f"{run_dir}: no plan/poses.csv (run `campaign plan --run {run_dir}` first)")
    lines = path.read_text().splitlines()
    head = lines[0].strip().split(",") if lines else []
    N = len(head) - 1
    if N < 1 or head != ["pose_id"] + [f"q{j}" for j in range(1, N + 1)]:
        raise DataError(f"{path}: header must be pose_id,q1,q2,q3,q4,q5,q6 (pose_id,q1..qN for a chain of N joints)")
    ids, qs = [], []
    for k, line in enumerate(lines[1:], start=2):
        if not line.strip():
            continue
        cells = line.split(",")
        if len(cells) != N + 1:
            raise DataError(f"{path}: line {k} has {len(cells)} fields, expected {N + 1}")
        try:
            vals = [float(c) for c in cells]
        except ValueError:
            raise DataError(f"{path}: line {k}: not a number") from None
        if not np.all(np.isfinite(vals)) or vals[0] != int(vals[0]):
            raise DataError(f"{path}: line {k}: pose_id must be an integer and q finite")
        if not 0 <= vals[0] < MAX_POSE_ID:
            raise DataError(f"{path}: line {k}: pose_id {int(vals[0])} outside 0..{MAX_POSE_ID - 1}")
        ids.append(int(vals[0]))
        qs.append(vals[1:])
    if not ids:
        raise DataError(f"{path}: no poses")
    if len(set(ids)) != len(ids):
        raise DataError(f"{path}: duplicate pose_id")
    vias = {}
    vpath = plan / "vias.csv"
    if poses_csv is None and vpath.is_file():
        for k, line in enumerate(vpath.read_text().splitlines()[1:], start=2):
            if line.strip():
                try:
                    c = [float(x) for x in line.split(",")]
                except ValueError:
                    c = []
                if len(c) != N + 1 or not np.all(np.isfinite(c)) or c[0] != int(c[0]):
                    raise DataError(f"{vpath}: line {k}: expected before_pose_id,q1..q{N} as finite numbers")
                vias.setdefault(int(c[0]), []).append(c[1:])
    return np.array(ids, dtype=np.int64), np.array(qs, dtype=float).reshape(-1, N), vias


def measured_robot(robot):
    """The robot with the reflectors a run measures (robot.yaml's, else the default triad): three
    or more give each pose by Kabsch, one its position (one-reflector data, kind "point"), two
    are stored as raw reflector data (kind "markers": their positions, no pose), which
    `calibrate` identifies from the reflectors' positions."""
    return robot.with_default_reflectors()


def _derive(T_LI, P_E, P_L):
    """What the reflectors measured in F_L (k, 3) give in F_I: (xyz (3,) m, rotvec (3,) rad or None,
    fit rms m or None). Three or more: the pose of F_E by Kabsch; one: its position alone; two: no
    pose, xyz the first reflector's position (the drift check's; the data are the raw positions)."""
    if len(P_E) < 3:
        xyz = transform_points(invert(T_LI), np.asarray(P_L, dtype=float)[None])[0, 0]
        return tuple(map(float, xyz)), None, None
    T_IE, rms = pose_from_reflectors(T_LI, P_E, np.asarray(P_L, dtype=float)[None])
    return (tuple(map(float, T_IE[0, :3, 3])), tuple(map(float, matrix_to_rotvec(T_IE[0, :3, :3]))),
            float(rms[0]))


@dataclass(frozen=True)
class RunResult:
    """The outcome of one `campaign run` session. ``stopped_kind``: None (every pose has an
    outcome or ``max_poses`` was reached), ``interrupted``, ``robot_fault``, ``unreachable``
    ``failures`` (too many failed poses in a row) or ``implausible`` (a pose's readings no tracker
    measuring in metres gives: campaign.measure.plausibility.check_tracker_readings); ``stopped``
    says why in words."""

    measured: int
    failed: int
    stored_before: int
    stopped: str | None
    simulated_duration_s: float
    wall_s: float
    drift_warnings: int
    stopped_kind: str | None = None
    remaining: int = 0


def run_campaign(run_dir, robot, controller, tracker, opts: RunOptions = RunOptions(), *, progress=False,
                 log=None, max_poses=None, poses_csv=None, retry_failed=False, verbose=False, plan=None,
                 frame: str = "robot", key: bytes | None = None, cell_identity: dict | None = None,
                 allow_other_cell: bool = False) -> RunResult:
    """Measure every planned pose of ``run_dir`` that has no stored outcome yet.

    controller, tracker: (host, port). ``progress`` draws a bar on stderr; ``log`` receives
    warnings (one line each), and with ``verbose`` every retry too. ``retry_failed`` forgets
    the failed poses first so they are measured again. ``poses_csv`` replaces
    RUN/plan/poses.csv; ``plan``: the (ids, q, vias) of :func:`read_plan` when already read.
    ``key``: the shared secret when the peers authenticate frames (`campaign serve --token-file`).
    ``cell_identity``: the cell measured on (campaign.measure.cell_identity), recorded in the log;
    another cell than the log's is refused unless ``allow_other_cell``.
    Each measure request carries the aims (campaign.measure.aims).
    Returns counts and the campaign clock (s) at the end, which continues from the last
    stored time. The caller holds the run's lock (campaign.measure.session). Ctrl-C
    (SIGINT) stops after the current pose; a second one stops at once (the pose in flight is
    not stored).
    """
    run_dir = Path(run_dir)
    say = log or (lambda msg: None)
    ids, Q, vias = plan if plan is not None else read_plan(run_dir, poses_csv)
    robot.check_joints(Q, field=str(poses_csv or f"{run_dir}/plan/poses.csv"), pose_ids=ids)
    stop = {"flag": None}
    old_handler = None

    def on_sigint(signum, frame):
        if stop["flag"]:
            raise KeyboardInterrupt
        stop["flag"] = "interrupted (Ctrl-C): stopped after the current pose"

    try:
        old_handler = signal.signal(signal.SIGINT, on_sigint)
    except ValueError:  # not in the main thread
        old_handler = None
    t_wall = time.perf_counter()
    clock = 0.0
    drift_warnings = 0
    ctrl = trk = None
    try:
        with open_run(run_dir, create=True) as store:
            store.use_wal()
            store.record_robot(robot)  # the robot these measurements belong to (checked when recorded)
            epoch = int(store.get_meta("id_epoch", 0))
            if retry_failed:
                forgotten = store.forget_failed()
                if forgotten:
                    epoch += 1
                    store.set_meta("id_epoch", epoch)
                    store.add_event("retry_failed", {"pose_ids": forgotten, "id_epoch": epoch})
            base = epoch * _EPOCH_ID
            done = store.stored_ids()
            stored_before = len(done)
            chatter = say if verbose else (lambda msg: None)
            ctrl = Peer(*controller, "controller", opts, chatter, key)
            trk = Peer(*tracker, "tracker", opts, chatter, key)
            ctrl.heartbeat()
            trk.heartbeat()
            if cell_identity is not None:
                from campaign.measure.cell_identity import record_cell, recorded_cell, refuse_other_cell

                refuse_other_cell(run_dir, recorded_cell(store), cell_identity, allow_other_cell)
                record_cell(store, cell_identity, allowed=allow_other_cell)
            store.add_event("session_start", {"controller": f"{ctrl.host}:{ctrl.port}",
                                              "tracker": f"{trk.host}:{trk.port}", "stored_before": stored_before,
                                              "planned": len(ids), "cell": cell_identity})
            recorded = store.get_meta("frame")
            if recorded is not None and recorded != frame:
                from campaign.errors import ConfigError

                raise ConfigError(f"{run_dir}: measured so far in the {recorded}'s frame; resume with --frame {recorded}")
            if frame == "tracker":
                # poses stay in the tracker's frame F_L (no base-frame set-up); calibrate identifies
                # the tracker's pose with the model
                if recorded is None:
                    store.set_meta("frame", "tracker")
                T_LI = np.eye(4).tolist()
            else:
                T_LI = store.get_meta("T_LI")
                if T_LI is not None and cell_identity is not None and not _setup_is_of(store, cell_identity):
                    say(f"another cell ({cell_identity['spec']}) than the base-frame set-up was measured on: its "
                        "own set-up is measured (another tracker placement is another frame)")
                    T_LI = None
            if T_LI is None:
                T_LI = _setup(store, trk, opts, base, cell_identity)
            T_LI = np.array(T_LI, dtype=float)
            geometry = ("robot.yaml's reflectors" if robot.reflectors else
                        "the default triad: robot.yaml names no reflectors")
            robot = measured_robot(robot)
            P_E = robot.reflector_positions_in_E
            targets = tuple(r.name for r in robot.reflectors)
            aim = AimPredictor(robot, targets, P_E, None if frame == "tracker" else T_LI)
            if len(P_E) == 1 and store.get_meta("kind") is None:
                store.set_meta("kind", "point")  # one reflector: positions only (calibrate fits them there)
            if len(P_E) == 2 and store.get_meta("kind") is None:
                # two reflectors: no pose; their raw positions (the readings of these targets, in F_L)
                store.set_meta("kind", "markers")
                store.set_meta("marker_positions", np.asarray(P_E, dtype=float).tolist())
                store.set_meta("marker_names", list(targets))
            todo = [k for k in range(len(ids)) if int(ids[k]) not in done]
            remaining_total = len(todo)
            if max_poses is not None:
                todo = todo[:max_poses]
            clock = store.clock_s()
            result = _loop(store, ids, Q, vias, todo, ctrl, trk, opts, T_LI, P_E, base, stop, say, progress,
                           stored_before, clock, targets, aim,
                           unclear_drift_returns=set() if poses_csv is not None else _unclear_drift_returns(run_dir),
                           geometry=geometry)
            n_ok, n_fail, clock, drift_warnings, stopped, kind = result
            if kind not in ("unreachable", "robot_fault"):
                try:  # the clock after the last measurement's tracker time
                    clock = max(clock, trk.heartbeat().time_s)
                except PeerError:
                    pass
            store.set_meta("campaign_clock_s", clock)
            store.add_event("session_end", {"measured": n_ok, "failed": n_fail, "stopped": stopped,
                                            "reconnects": ctrl.reconnects + trk.reconnects}, time_s=clock)
    finally:
        for peer in (ctrl, trk):
            if peer is not None:
                peer.close()
        if old_handler is not None:
            signal.signal(signal.SIGINT, old_handler)
    return RunResult(n_ok, n_fail, stored_before, stopped, clock, time.perf_counter() - t_wall, drift_warnings,
                     kind, remaining_total - n_ok - n_fail)


def _setup_is_of(store, identity) -> bool:
    """Whether the run's base-frame set-up (meta ``T_LI``) was measured on the cell ``identity``: the
    cell recorded with it (meta ``setup_cell``), else (a set-up from before that was recorded) the
    run's first recorded cell; True when neither is known."""
    from campaign.measure.cell_identity import same_cell

    setup = store.get_meta("setup_cell")
    if setup is None:
        setup = (store.get_meta("cells") or [None])[0]
    return setup is None or same_cell(setup, identity)


def _setup(store, trk, opts, base, cell=None):
    """Base-frame set-up: the three set-up points, each averaged over repeats → T_LI, kept in meta
    with the cell it was measured on (``cell``, meta ``setup_cell``). A run's later set-up (on
    another cell) asks with request ids of its own (peers answer a repeated id with its first reply)."""
    pts = {t: [] for t in P.SETUP_TARGETS}
    first = base + _SETUP_ID + 1024 * len(store.events("setup"))
    for k in range(opts.setup_repeats):
        reply = trk.request(P.Measure(first + k, P.SETUP_TARGETS), opts.timeout_s)
        if not isinstance(reply, P.Measurement):
            why = f": {reply.message}" if isinstance(reply, P.ErrorReply) else ""
            raise PeerError(f"tracker: answered '{reply.type}' to the set-up measurement{why}")
        for r in reply.readings:
            if r.status == "ok" and r.target in pts:
                pts[r.target].append(r.xyz_m)
    if any(len(v) == 0 for v in pts.values()):
        missing = ", ".join(t for t, v in pts.items() if not v)
        raise PeerError(f"tracker: the base-frame set-up points could not be measured ({missing})")
    means = [np.mean(pts[t], axis=0) for t in P.SETUP_TARGETS]
    wrong = check_tracker_readings(means, None, P.SETUP_TARGETS)  # their range (their spacing is unknown)
    if wrong:
        raise Implausible(f"base-frame set-up: {wrong}")
    T_LI = frame_from_setup_points(*means)
    T_LI = [[float(v) for v in row] for row in T_LI]
    store.set_meta("setup_points_L", {t: np.mean(v, axis=0).tolist() for t, v in pts.items()})
    # the tracker's noise per reflector coordinate from the set-up's repeats (pooled over the points
    # and the coordinates): the drift check's threshold before the campaign's own repeats are measured
    dev = np.concatenate([np.asarray(v) - np.mean(v, axis=0) for v in pts.values()])
    dof = 3 * (len(dev) - len(pts))
    if dof > 0:
        store.set_meta("setup_noise_m", {"sigma": float(np.sqrt(np.sum(dev ** 2) / dof)), "dof": int(dof)})
    if cell is not None:
        store.set_meta("setup_cell", cell)
    store.set_meta("T_LI", T_LI)  # last: its presence marks the set-up as done
    store.add_event("setup", {"T_LI": T_LI, "readings": {t: len(v) for t, v in pts.items()},
                              **({} if cell is None else {"cell": cell.get("fingerprint")})})
    return T_LI


def _unclear_drift_returns(run_dir) -> set:
    """Pose ids after which the plan found the drift check's direct motions (to the reference
    pose and on to the next pose) not clear (RUN/plan/summary.json ``drift_monitor``): the driver
    skips those checks rather than move through a collision."""
    import json

    try:
        doc = json.loads((Path(run_dir) / "plan" / "summary.json").read_text())
        return {int(p) for p in (doc.get("drift_monitor") or {}).get("not_clear_after_pose_ids", [])}
    except (OSError, ValueError, TypeError):
        return set()


def _loop(store, ids, Q, vias, todo, ctrl, trk, opts, T_LI, P_E, base, stop, say, progress, stored_before,
          clock_start=0.0, targets=REFLECTORS, aim=None, unclear_drift_returns=frozenset(),
          geometry="robot.yaml's reflectors"):
    bar = Progress("measuring", len(todo), progress, " poses")
    n_ok = n_fail = drift_warnings = in_a_row = 0
    clock = clock0 = clock_start
    stopped = kind = None
    reference = store.get_meta("drift_reference")
    readings = [] if reference is None else _reference_readings(store, reference)
    try:
        for n, k in enumerate(todo):
            pid = int(ids[k])
            rec, c = _measure_pose(pid, stored_before + n, Q[k], vias.get(pid, []), ctrl, trk, opts, T_LI, P_E, base,
                                   targets, aim)
            wrong = None if rec.status != "measured" else check_tracker_readings(
                [rec.reflectors[t][0] for t in targets], P_E, targets, geometry)
            if wrong:  # hours of cell time at stake: stop now, this pose not stored
                stopped, kind = f"pose {pid}: {wrong} (this pose is not stored)", "implausible"
                break
            store.add_pose(rec)
            clock = max(clock, c)
            if n == 0:
                clock0 = clock
            if rec.status == "measured":
                n_ok += 1
                in_a_row = 0
                if reference is None:
                    reference = {"pose_id": pid, "q": list(map(float, Q[k])), "xyz": list(rec.xyz)}
                    store.set_meta("drift_reference", reference)
                    readings = [reference["xyz"]]
            else:
                n_fail += 1
                in_a_row += 1
            n_stored = stored_before + n + 1
            every = drift_check_interval(opts.drift_check_every, len(ids))
            due = reference is not None and every and n_stored % every == 0 and n + 1 < len(todo)
            if due and pid in unclear_drift_returns:
                store.add_event("drift_check_skipped", {"after_pose_id": pid, "why": "the plan found the motions "
                                "to the reference pose and back not clear (summary.json drift_monitor)"},
                                time_s=clock)
                due = False
            if due:
                xyz, c = _drift_check(base + _DRIFT_ID + 4 * k, reference, ctrl, trk, opts, T_LI, P_E, targets, aim)
                clock = max(clock, c)
                warned = _record_drift_check(store, reference, xyz, readings, opts, P_E, n_stored, pid, clock, say)
                drift_warnings += warned
            per_pose = (clock - clock0) / n if n else 0.0
            bar.update(1, extra=f"ok {n_ok} failed {n_fail} | sim {clock / 3600:.1f} h, "
                                f"~{per_pose * (len(todo) - n - 1) / 3600:.1f} h to go")
            if opts.max_consecutive_failures and in_a_row >= opts.max_consecutive_failures:
                stopped, kind = (f"{in_a_row} poses in a row failed (last: {rec.reason}); "
                                 "check the cell, then re-run (`--retry-failed` measures them again)"), "failures"
                break
            if stop["flag"]:
                stopped, kind = stop["flag"], "interrupted"
                break
    except RobotFault as exc:
        stopped, kind = f"robot fault: {exc}", "robot_fault"
    except PeerUnreachable as exc:
        stopped, kind = f"peer unreachable: {exc}", "unreachable"
    finally:
        bar.close()
    if stopped:
        store.add_event("stop", {"reason": stopped, "kind": kind}, time_s=clock)
    return n_ok, n_fail, clock, drift_warnings, stopped, kind


def _move(ctrl, msg, opts):
    reply = ctrl.request(msg, opts.move_timeout_s)
    if isinstance(reply, P.Fault):
        if reply.code not in POSE_FAULT_CODES:
            raise RobotFault(f"{reply.code}: {reply.message}")
        return None, f"robot fault {reply.code}: {reply.message}"
    if not isinstance(reply, P.Reached):
        why = f": {reply.message}" if isinstance(reply, P.ErrorReply) else ""
        return None, f"controller answered '{reply.type}' to a move{why}"
    return reply, None


def _measure_pose(pid, seq, q, vias, ctrl, trk, opts, T_LI, P_E, base, targets=REFLECTORS, aim=None):
    """One pose, start to stored record. Returns (PoseRecord, campaign clock s). ``aim``: the
    AimPredictor whose aims the measure requests carry (and which learns from the result)."""
    retries = 0
    clock = 0.0
    rid = base + pid * 64
    try:
        for v, qv in enumerate(vias[:31]):
            reply, err = _move(ctrl, P.Move(rid + 32 + v, tuple(map(float, qv))), opts)
            if err:
                return PoseRecord(pid, "failed", tuple(q), seq=seq, reason=f"via {v}: {err}"), clock
        reply, err = _move(ctrl, P.Move(rid, tuple(map(float, q))), opts)
        if err:
            return PoseRecord(pid, "failed", tuple(q), seq=seq, reason=err), clock
        q_enc = reply.q_encoder
        clock = reply.time_s
        last_reason = None
        for attempt in range(opts.retries + 1):
            if attempt:
                retries += 1
            m = trk.request(P.Measure(rid + 1 + attempt, targets, aim(q) if aim is not None else None), opts.timeout_s)
            if not isinstance(m, P.Measurement):
                last_reason = f"tracker answered '{m.type}'" + (f": {m.message}" if isinstance(m, P.ErrorReply) else "")
                continue
            clock = m.time_s
            by = {r.target: r for r in m.readings}
            bad = [f"{t}: {by[t].status if t in by else 'missing'}" for t in targets
                   if t not in by or by[t].status != "ok"]
            if bad:
                last_reason = "; ".join(bad)
                continue
            P_L = np.array([by[t].xyz_m for t in targets])
            xyz, rotvec, rms = _derive(T_LI, P_E, P_L)
            if aim is not None:
                aim.learn(q, P_L)
            return PoseRecord(pid, "measured", tuple(q), seq=seq, time_s=clock, wall_time_unix_s=time.time(),
                              q_encoder=tuple(q_enc), xyz=xyz, rotvec=rotvec, fit_rms_m=rms, retries=retries,
                              context={} if m.temperature_c is None else {"temperature_c": m.temperature_c},
                              reflectors={t: (by[t].xyz_m, by[t].status) for t in targets}), clock
        return PoseRecord(pid, "failed", tuple(q), seq=seq, time_s=clock, wall_time_unix_s=time.time(),
                          q_encoder=tuple(q_enc), retries=retries,
                          reason=f"tracker after {opts.retries + 1} attempts: {last_reason}"), clock
    except (RobotFault, PeerUnreachable):
        raise
    except PeerError as exc:
        return PoseRecord(pid, "failed", tuple(q), seq=seq, time_s=clock or None, wall_time_unix_s=time.time(),
                          retries=retries, reason=str(exc)), clock


def _reference_readings(store, reference) -> list:
    """The reference pose's readings so far (resumed runs too): its first, then every drift check's;
    of a run resumed on another cell (campaign.measure.cell_identity), only those on this one (the
    cell's readings are in another frame: a step between cells is no drift)."""
    from campaign.measure.cell_identity import cell_segments, segment_events

    segments = cell_segments(store._db)
    now = segments.session_segments[-1] if segments.session_segments else 0
    first = [reference["xyz"]] if int(segments.of([reference["pose_id"]])[0]) == now else []
    return first + [d["xyz_m"] for seg, _, d in segment_events(store._db, "drift_check", segments)
                    if seg == now and isinstance(d, dict) and d.get("xyz_m")]


def _record_drift_check(store, reference, xyz, readings, opts, P_E, n_stored, pid, clock, say) -> int:
    """Store a drift check's reading ``xyz`` (m, or None when it could not be measured) as a
    ``drift_check`` event: its position, its distance from the reference's first reading
    (``drift_mm``) and from the mean of its earlier ``readings`` (``moved_mm``, appended to), and
    the warning's threshold (``run.drift_threshold_mm``, "auto": from the noise floor so far).
    1 when it warned (a ``warning`` event and a line), else 0."""
    detail = {"reference_pose_id": reference["pose_id"], "drift_mm": None, "over_threshold": False}
    if xyz is None:
        store.add_event("drift_check", detail, pose_id=pid, time_s=clock)
        return 0
    if not readings:  # the first reading on another cell (a resumed run): nothing to compare it with
        detail.update(xyz_m=[float(v) for v in xyz], first_on_cell=True)
        store.add_event("drift_check", detail, pose_id=pid, time_s=clock)
        readings.append(list(map(float, xyz)))
        return 0
    earlier = np.asarray(readings, dtype=float)
    moved_m = float(np.linalg.norm(xyz - earlier.mean(axis=0)))
    threshold_m, why = _drift_threshold_m(store, opts, P_E, len(earlier))
    over = moved_m > threshold_m
    detail.update(drift_mm=float(np.linalg.norm(xyz - earlier[0])) * 1e3, xyz_m=[float(v) for v in xyz],
                  moved_mm=moved_m * 1e3, threshold_mm=threshold_m * 1e3, threshold_from=why, over_threshold=over)
    store.add_event("drift_check", detail, pose_id=pid, time_s=clock)
    readings.append(list(map(float, xyz)))
    if not over:
        return 0
    msg = (f"warning: drift check after {n_stored} poses: reference pose {reference['pose_id']} moved "
           f"{moved_m * 1e3:.3g} mm from the mean of its {len(earlier)} earlier reading"
           f"{'s' if len(earlier) > 1 else ''} (threshold {threshold_m * 1e3:.3g} mm, {why})")
    store.add_event("warning", {"message": msg}, pose_id=pid, time_s=clock)
    say(msg)
    return 1


def _drift_threshold_m(store, opts, P_E, n_earlier) -> tuple:
    """(the drift check's warning threshold m, where it came from): ``run.drift_threshold_mm``
    when a number, else beyond the noise of what is stored so far (campaign.measure.drift
    .moved_threshold_m, warning_sigma_m), else tolerances.DRIFT_WARNING_FALLBACK_MM."""
    from campaign.measure.drift import moved_threshold_m, warning_sigma_m
    from campaign.tolerances import DRIFT_WARNING_ALPHA, DRIFT_WARNING_FALLBACK_MM

    if opts.drift_threshold_mm != "auto":
        return float(opts.drift_threshold_mm) * 1e-3, "run.drift_threshold_mm"
    try:
        poses = store.load_measured()
        ok = np.isfinite(poses.xyz).all(axis=1)
        poses = poses.subset(np.flatnonzero(ok))
    except DataError:
        poses = None
    setup = store.get_meta("setup_noise_m")
    sigma = warning_sigma_m(poses, opts.tracker_noise_m, P_E, None if setup is None else setup["sigma"])
    if sigma is None:
        return DRIFT_WARNING_FALLBACK_MM * 1e-3, "no noise known yet"
    return (moved_threshold_m(sigma, n_earlier),
            f"the noise exceeds it once in {1 / DRIFT_WARNING_ALPHA:.0f} checks")


def _drift_check(rid, reference, ctrl, trk, opts, T_LI, P_E, targets=REFLECTORS, aim=None):
    """Re-measure the reference pose: (its derived position (3,) m or None when it could not be
    measured, campaign clock s)."""
    clock = 0.0
    try:
        reply, err = _move(ctrl, P.Move(rid, tuple(map(float, reference["q"]))), opts)
        if err:
            return None, clock
        clock = reply.time_s
        m = trk.request(P.Measure(rid + 1, targets, aim(reference["q"]) if aim is not None else None), opts.timeout_s)
        if not isinstance(m, P.Measurement):
            return None, clock
        clock = m.time_s
        by = {r.target: r for r in m.readings}
        if any(t not in by or by[t].status != "ok" for t in targets):
            return None, clock
        xyz, _, _ = _derive(T_LI, P_E, np.array([by[t].xyz_m for t in targets]))
        return np.array(xyz, dtype=float), clock
    except (RobotFault, PeerUnreachable):
        raise
    except PeerError:
        return None, clock
