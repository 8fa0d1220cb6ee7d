"""`campaign import --stream LOG --run RUN`: a tracker's log matched to RUN's program stops and
stored in the run's measurement log as `campaign run` stores a campaign.

The stops are RUN/program/stops.csv (`campaign program RUN --format csv`). The log is read in
blocks (campaign.program.stream.logread), its still windows found as it is read
(campaign.program.stream.windows), aligned to the measured stops (campaign.program.stream.align);
each confirmed window becomes a measured pose (reflectors by name in the log's frame, the pose by
Kabsch for three or more, like campaign.measure.driver), a drift stop a ``drift_check`` event, a
stop without a window a failed pose. RUN/import/stream_match.csv lists every stop up to the log's
end and every rejected window. A second log continues at the first stop the first did not reach.
"""

from __future__ import annotations

import csv
import io
from collections import Counter
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from campaign.errors import ConfigError, DataError
from campaign.tolerances import STREAM_FIT_RMS_MAX_M

MATCH_FILE = "stream_match.csv"
MATCH_HEADER = ("stop", "pose_id", "kind", "window_start_s", "window_end_s", "samples", "spread_mm", "status", "log")
#: meta key of the log: where the next log continues, and the logs imported
META_KEY = "stream_import"


@dataclass(frozen=True)
class StreamResult:
    """What an import of a log did: stops matched / skipped (no window) / incomplete (a reflector
    missing, or the reflectors not as the tool holds them) / unconfirmed (no neighbour confirms the
    window's distance), windows rejected, poses stored (measured, failed), drift checks, the log's
    samples, rate (Hz) and noise (m), and the next stop a further log starts at."""

    matched: int
    skipped: int
    incomplete: int
    unconfirmed: int
    rejected: int
    measured: int
    failed: int
    drift_checks: int
    samples: int
    rate_hz: float
    noise_m: float
    next_stop: int
    n_stops: int
    point_mode: bool
    match_csv: Path

    def summary(self, log, run) -> str:
        found = self.matched + self.skipped + self.incomplete + self.unconfirmed
        mode = "one record per stable point" if self.point_mode else \
            f"{self.rate_hz:.0f} Hz, noise {self.noise_m * 1e6:.1f} µm"
        return (f"{log}: matched {self.matched} of {found} stops reached ({self.skipped} without a still window, "
                f"{self.incomplete} with a reflector missing or misplaced, {self.unconfirmed} unconfirmed), "
                f"{self.rejected} windows rejected; {self.samples:,} samples ({mode}); stored {self.measured} "
                f"measured and {self.failed} failed poses, {self.drift_checks} drift checks in "
                f"{run}/measurements.sqlite; next stop {self.next_stop} of {self.n_stops}")


def nominal_points(robot, stops, codes_in_E) -> np.ndarray:
    """(n, k, 3) m: the nominal positions in F_I of the points ``codes_in_E`` (k, 3) in the tool
    frame at each stop."""
    from campaign.model.kinematics import forward
    from campaign.program.stops import stops_array

    T = forward(robot, stops_array(stops))
    P = np.asarray(codes_in_E, dtype=float)
    return np.einsum("nij,kj->nki", T[:, :3, :3], P) + T[:, None, :3, 3]


def import_stream(log, run_dir, *, length_unit: str = "m", frame: str = "robot", columns=None,
                  progress=None, targets=None) -> StreamResult:
    """Match the tracker log ``log`` to RUN's stops and store the result (module docstring).

    length_unit: "m" or "mm" of the log's x, y, z; frame: "robot" (the log is in the robot's base
    frame) or "tracker" (in the tracker's: calibrate identifies the tracker's pose); columns:
    {column in the file: name used}; progress: callable receiving the fraction read (0..1);
    targets: {the robot's reflector name: the log's name for it} (a tracker's software names its
    reflectors as its user did: SMR1, P1, ...)."""
    from campaign.run import RunFolder

    if frame not in ("robot", "tracker"):
        raise DataError(f"--frame must be robot or tracker, got {frame!r}")
    run = RunFolder(run_dir)
    if not run.path.is_dir():
        raise DataError(f"{run.path}: no such run folder")
    with run.lock("import --stream"):  # from the state read to the state written: one import at a time
        return _import_locked(run, log, length_unit, frame, columns, progress, targets)


def _import_locked(run, log, length_unit, frame, columns, progress, targets=None) -> StreamResult:
    """The import's steps: the stops and the robot, the log's layout, what each row measures, the
    still windows, their matches to the stops, the outcomes, stored."""
    from campaign.program.stream.logread import read_layout

    stops, robot = _stops_and_robot(run)
    layout = read_layout(log, length_unit=length_unit, columns=columns,
                         targets=log_target_names(robot, targets))
    state = _previous(run, frame, layout)
    first_stop = int(state.get("next_stop", 0))
    measured_idx = np.array([s.stop for s in stops if s.measured], dtype=int)
    first_m = int(np.searchsorted(measured_idx, first_stop))
    P_E, kind, names = measured_points(robot, layout)
    if layout.aliases:  # the log's own reflector names: which of the robot's each is
        P_E, names = assign_aliases(robot, layout, stops, measured_idx, first_m)
    windows, finder = find_windows(layout, P_E, progress)
    if layout.target_col is None:  # one point: which of the tool's (its reflectors, the origin) fits
        P_E, names = tracked_point(robot, stops, measured_idx, windows, first_m, finder.t_first)
    matches = match_stops(robot, stops, measured_idx, windows, P_E, first_m, finder.t_first)
    matches = check_placement(run, robot, stops, measured_idx, windows, matches, P_E, layout, first_stop, frame)
    rows, records, events = _outcomes(run, stops, measured_idx, matches, windows, P_E, names, kind, layout,
                                      finder, first_m, state)
    last = max([measured_idx[m.stop] for m in matches], default=first_stop - 1)
    next_stop = max(first_stop, int(last) + 1)
    match_csv = _store(run, records, events, rows, kind, frame, P_E, names, layout, finder, next_stop, state, robot)
    status = Counter(r[7] for r in rows)
    stored = Counter(r.status for r in records)
    return StreamResult(status["matched"], status["skipped"], status["incomplete"] + status["inconsistent"],
                        status["unconfirmed"], status["rejected"], stored["measured"], stored["failed"],
                        len(events), finder.samples, 1.0 / finder.dt_s if finder.dt_s else float("nan"),
                        finder.noise_m or float("nan"), next_stop, len(stops), bool(finder.point_mode), match_csv)


def _stops_and_robot(run) -> tuple:
    """(the run's stops, its robot with the reflectors a run measures), checked against each other."""
    from campaign.measure.driver import measured_robot
    from campaign.program.stops import stops_path

    stops = run_stops(run)
    robot = measured_robot(run.robot())
    if len(stops[0].q) != robot.n_joints:
        raise DataError(f"{stops_path(run.path)}: {len(stops[0].q)} joints, the run's robot {robot.name} "
                        f"has {robot.n_joints}")
    return stops, robot


def measured_points(robot, layout) -> tuple:
    """(P_E (k, 3) m: the points the log's reflector codes measure in the tool frame, the store's
    kind, their names): the robot's reflectors when the log names them (``target``: three or more a
    pose, two raw reflectors, one a point), else one point (kind "point"), first taken as the robot's
    single reflector or the tool frame's origin (as a one-reflector CSV import; :func:`tracked_point`
    then finds which it is)."""
    from campaign.measure.plausibility import measured_point

    names = tuple(r.name for r in robot.reflectors)
    if layout.target_col is not None:
        k = len(layout.targets) if layout.aliases else len(names)
        kind = "pose" if k >= 3 else "markers" if k == 2 else "point"
        return robot.reflector_positions_in_E[:k], kind, names[:k]
    return measured_point(robot, "point")[None], "point", (names[0] if len(names) == 1 else "tool",)


def assign_aliases(robot, layout, stops, measured_idx, first_m) -> tuple:
    """(P_E (k, 3) m, names): the robot's reflectors the log's own k names stand for, in the log's
    code order: of every assignment, the one whose distances confirm the most matches over the
    still windows of the log's first block (each reflector's distances between stops differ)."""
    from itertools import permutations

    from campaign.program.stream.align import ALIGN_TIME_FIT_WINDOWS, align
    from campaign.program.stream.logread import iter_log
    from campaign.program.stream.windows import WindowFinder

    finder = WindowFinder()
    first = next(iter(iter_log(layout)), None)
    if first is None:
        raise DataError(f"{layout.path}: no measured rows (every x, y, z empty)")
    finder.feed(first)
    windows = finder.finish()[:ALIGN_TIME_FIT_WINDOWS]
    mstops = [stops[k] for k in measured_idx]
    dwell = np.array([s.dwell_s for s in mstops])
    E = robot.reflector_positions_in_E
    robot_names = tuple(r.name for r in robot.reflectors)
    best, best_n = None, -1
    for perm in permutations(range(len(E)), len(layout.targets)):
        P = nominal_points(robot, mstops, E[list(perm)])
        n = sum(m.confirmed for m in align(windows, P, dwell, first_stop=first_m, t_start=finder.t_first))
        if n > best_n:
            best, best_n = perm, n
    return E[list(best)], tuple(robot_names[i] for i in best)


def tracked_point(robot, stops, measured_idx, windows, first_m, t_first) -> tuple:
    """(P_E (1, 3) m, (its name,)): the point a log without ``target`` follows, among the robot's
    reflectors and the tool frame's origin (robot.yaml's single reflector, else the origin, first:
    it wins ties), the one whose distances confirm the most matches over the log's first
    ALIGN_TIME_FIT_WINDOWS windows (a wrong point's distances are off by centimetres)."""
    from campaign.measure.plausibility import measured_point
    from campaign.program.stream.align import ALIGN_TIME_FIT_WINDOWS, align

    first = measured_point(robot, "point")
    candidates = [(first, robot.reflectors[0].name if len(robot.reflectors) == 1 else "tool")]
    candidates += [(np.asarray(r.position_in_E, dtype=float), r.name) for r in robot.reflectors]
    candidates += [(np.zeros(3), "tool")]
    mstops = [stops[k] for k in measured_idx]
    dwell = np.array([s.dwell_s for s in mstops])
    part = windows[:ALIGN_TIME_FIT_WINDOWS]
    best, best_n, seen = candidates[0], -1, []
    for point, name in candidates:
        if any(np.allclose(point, p) for p in seen):
            continue
        seen.append(point)
        matches = align(part, nominal_points(robot, mstops, point[None]), dwell, first_stop=first_m, t_start=t_first)
        n = sum(m.confirmed for m in matches)
        if n > best_n:
            best, best_n = (point, name), n
    return best[0][None], (best[1],)


def find_windows(layout, P_E, progress=None) -> tuple:
    """(the log's still windows, the WindowFinder that read it: samples, rate, noise), the log read in
    blocks; DataError for a log without a measured row."""
    from campaign.program.stream.logread import iter_log
    from campaign.program.stream.windows import WindowFinder

    finder = WindowFinder(np.linalg.norm(P_E[:, None] - P_E[None], axis=-1), split_long=layout.target_col is None)
    for chunk in iter_log(layout, progress=progress):
        finder.feed(chunk)
    windows = finder.finish()
    if finder.samples == 0:
        raise DataError(f"{layout.path}: no measured rows (every x, y, z empty)")
    return windows, finder


def match_stops(robot, stops, measured_idx, windows, P_E, first_m, t_first) -> list:
    """The windows' matches (campaign.program.stream.align.Match) to the measured stops
    ``measured_idx`` from the ``first_m``-th: their nominal points, dwells and motion times."""
    from campaign.program.stream.align import align

    mstops = [stops[k] for k in measured_idx]
    P = nominal_points(robot, mstops, P_E)
    dwell = np.array([s.dwell_s for s in mstops])
    try:
        motion = motion_times(robot, stops, measured_idx)
    except ConfigError:  # a robot without usable joint limits for Ruckig: distances and dwells alone
        motion = None
    return align(windows, P, dwell, first_stop=first_m, t_start=t_first, motion_s=motion)


def check_placement(run, robot, stops, measured_idx, windows, matches, P_E, layout, first_stop, frame) -> list:
    """Refuse, before anything is stored, a log that is not this run's: no window matched (another
    run's log, another length unit), or matches that do not lie together as the program's stops do
    (one rigid fit of every matched window to the stops' nominal points leaves a median residual
    over STREAM_PLACEMENT_MAX_M: an arm off nominal by a few mm leaves well under a millimetre; the
    distances between successive stops of another run's log can agree by chance, its places cannot);
    with ``frame`` "robot", a fit far from the identity (STREAM_ROBOT_FRAME_MAX_M at the stops): the
    log is in the tracker's frame. Returns ``matches`` with those lying off the fit by more than
    STREAM_PLACEMENT_MAX_M unconfirmed: a window matched to the wrong stop of a run of stops alike (a
    pose's wrist turned by 60 degrees a stop, repeats between them, beams lost) is stored nowhere."""
    from dataclasses import replace

    from campaign.measure.reflectors import kabsch, transform_points
    from campaign.tolerances import STREAM_PLACEMENT_MAX_M, STREAM_ROBOT_FRAME_MAX_M

    unit = "mm" if layout.length_scale == 1e-3 else "m"
    if first_stop >= len(stops):
        raise DataError(f"{run.path}: every stop of its program is imported already (next stop {first_stop} of "
                        f"{len(stops)}); {layout.path.name} is not imported again")
    ok = [m for m in matches if m.confirmed]
    if not any(len(windows[m.window].position) == len(P_E) for m in ok):  # none to store
        raise DataError(f"{layout.path}: none of its {len(windows)} still windows matches a stop of {run.path} "
                        f"from stop {first_stop} on (the log of another run? its positions not in --length-unit "
                        f"{unit}?); nothing stored")
    P = nominal_points(robot, [stops[measured_idx[m.stop]] for m in ok], P_E)
    A, B, of = [], [], []
    for m, pts in zip(ok, P):
        for c, pos in windows[m.window].position.items():
            if c < len(pts):
                A.append(pos)
                B.append(pts[c])
                of.append(m.window)
    if len(A) < 4:
        return matches
    A, B = np.array(A), np.array(B)
    T = kabsch(A, B[None])[0]
    res = np.linalg.norm(transform_points(T, A) - B, axis=1)
    keep = res <= max(3 * float(np.median(res)), 0.01)  # once more without the farthest
    if keep.sum() >= 4:
        T = kabsch(A[keep], B[keep][None])[0]
        res = np.linalg.norm(transform_points(T, A) - B, axis=1)
    median = float(np.median(res))
    if median > STREAM_PLACEMENT_MAX_M:
        raise DataError(f"{layout.path}: its {len(ok)} matched windows do not lie as the stops of {run.path} do (one "
                        f"rigid fit leaves {median * 1e3:.0f} mm median, this run's log a fraction of a mm): the log "
                        f"of another run or robot, or not in --length-unit {unit}? nothing stored")
    moved = float(np.median(np.linalg.norm(transform_points(T, A) - A, axis=1)))
    if frame == "robot" and moved > STREAM_ROBOT_FRAME_MAX_M:
        raise DataError(f"{layout.path}: its positions lie {moved * 1e3:.0f} mm (median) from where the stops are in "
                        "the robot's base frame: the log is in the tracker's frame (import it with --frame tracker); "
                        "nothing stored")
    off = {w for w, r in zip(of, res) if r > STREAM_PLACEMENT_MAX_M} if len(ok) >= 4 else set()
    return [replace(m, confirmed=False) if m.window in off else m for m in matches]


def log_target_names(robot, targets) -> tuple:
    """The names the log gives the robot's reflectors, in the robot's order: ``targets`` {reflector:
    the log's name} renames some or all of them; DataError naming an unknown reflector or a name
    given twice."""
    names = tuple(r.name for r in robot.reflectors)
    targets = dict(targets or {})
    unknown = [n for n in targets if n not in names]
    if unknown:
        raise DataError(f"--targets: {', '.join(unknown)} is not one of the robot's reflectors ({', '.join(names)}); "
                        f"give REFLECTOR=LOG_NAME,... e.g. {names[0]}=SMR1")
    out = tuple(targets.get(n, n) for n in names)
    if len(set(out)) != len(out):
        raise DataError(f"--targets: two reflectors with one name in the log ({', '.join(out)})")
    return out


def motion_times(robot, stops, measured_idx) -> np.ndarray:
    """(m,) s: the nominal time (Ruckig's rest-to-rest motions at the robot's limits, and the
    dwells of vias) from the measured stop before each measured stop ``measured_idx`` to it (0 for
    the first)."""
    from campaign.plan.timing import rest_to_rest_time
    from campaign.program.stops import stops_array

    Q = stops_array(stops)
    step = np.concatenate([[0.0], rest_to_rest_time(robot, Q[:-1], Q[1:])])
    step += np.array([0.0] + [s.dwell_s if s.kind == "via" else 0.0 for s in stops[:-1]])  # rest at vias
    cum = np.cumsum(step)
    return np.diff(cum[measured_idx], prepend=cum[measured_idx[0]])


def run_stops(run) -> list:
    """The run's program stops: RUN/program/stops.csv, else (no program written yet) the stops of
    its plan (campaign.program.stops.plan_stops: what `campaign program` would write)."""
    from campaign.program.stops import plan_stops, read_stops_csv, stops_path

    path = stops_path(run.path)
    if path.is_file() or not run.poses_csv.is_file():
        if not path.is_file():
            raise DataError(f"{path}: no such stops file and no plan (write it with `campaign program RUN "
                            "--format csv` after `campaign plan`)")
        return read_stops_csv(path)
    return plan_stops(run.path, run=run)


def _previous(run, frame, layout) -> dict:
    """What earlier stream imports into this run recorded (empty for a new run); refuses a run
    whose log holds measurements of another kind or frame."""
    from campaign.measure.store import MeasurementStore

    if not run.measurements_path.is_file():
        return {}
    with MeasurementStore(run.measurements_path, create=False) as store:
        state = store.get_meta(META_KEY)
        recorded_frame = store.get_meta("frame", "robot")
    if state is None:
        raise DataError(f"{run.path}: already holds measurements that no stream import stored; import the log "
                        "into a new run folder (with its plan and program)")
    if recorded_frame != frame:
        raise DataError(f"{run.path}: the earlier logs were in the {recorded_frame}'s frame; import {layout.path} "
                        f"with --frame {recorded_frame}")
    return state


def _outcomes(run, stops, measured_idx, matches, windows, P_E, names, kind, layout, finder, first_m, state):
    """(stream_match rows, PoseRecords, DriftReadings) of the stops from ``first_m`` (index among
    the measured stops) to the last one matched."""
    from campaign.measure.driver import _derive
    from campaign.measure.store import PoseRecord

    by_stop = {m.stop: m for m in matches}
    matched_windows = {m.window for m in matches}
    last = max(by_stop, default=first_m - 1)
    log_name = str(layout.path.name)
    clock0 = float(state.get("clock_s", 0.0))
    t_first = finder.t_first
    rows, records, events = [], [], []
    seq0 = int(state.get("seq", 0))
    eye = np.eye(4)
    for mi in range(first_m, last + 1):
        s = stops[measured_idx[mi]]
        m = by_stop.get(mi)
        w = windows[m.window] if m is not None else None
        status, reason = "matched", None
        if m is None:
            status, reason = "skipped", f"no still window in {log_name} (a lost beam?)"
        elif not m.confirmed:
            status, reason = "unconfirmed", (f"{log_name}: the window at {w.t0:.3f} s is not confirmed by its "
                                             "neighbours' distances")
        elif len(w.position) < len(P_E):
            missing = [names[c] for c in range(len(P_E)) if c not in w.position]
            status, reason = "incomplete", f"{log_name}: reflector {', '.join(missing)} not measured in the window"
        if status == "matched":
            P_L = np.array([w.position[c] for c in range(len(P_E))])
            xyz, rotvec, rms = _derive(eye, P_E, P_L)
            if rms is not None and rms > STREAM_FIT_RMS_MAX_M:
                status, reason = "inconsistent", (f"{log_name}: the window's reflectors are {rms * 1e3:.2f} mm rms "
                                                  "from the tool's layout")
        t_s = None if w is None else clock0 + 0.5 * (w.t0 + w.t1) - t_first
        rows.append([s.stop, s.pose_id, s.kind, "" if w is None else f"{w.t0:.6f}", "" if w is None else f"{w.t1:.6f}",
                     0 if w is None else w.samples, "" if w is None else f"{w.spread_m() * 1e3:.6f}", status, log_name])
        if s.kind == "drift":  # stored as `campaign run` stores its drift checks (_store)
            events.append(DriftReading(s.stop, s.pose_id, s.q, xyz if status == "matched" else None, t_s,
                                       seq0 + len(records)))
            continue
        seq = seq0 + len(records)
        if status == "matched":
            refl = {names[c]: (tuple(map(float, w.position[c])), "ok") for c in range(len(P_E))}
            records.append(PoseRecord(s.pose_id, "measured", s.q, seq=seq, time_s=t_s, xyz=xyz, rotvec=rotvec,
                                      fit_rms_m=rms, reflectors=refl))
        else:
            records.append(PoseRecord(s.pose_id, "failed", s.q, seq=seq, time_s=t_s, reason=reason))
    for i, w in enumerate(windows):
        if i not in matched_windows:
            rows.append(["", "", "", f"{w.t0:.6f}", f"{w.t1:.6f}", w.samples, f"{w.spread_m() * 1e3:.6f}",
                         "rejected", log_name])
    return rows, records, events


@dataclass(frozen=True)
class DriftReading:
    """A drift stop's outcome: its stop, reference pose id and q, the tool point it read (3,) m in
    the log's frame or None, its campaign time (s), the poses stored before it."""

    stop: int
    pose_id: int
    q: tuple
    xyz: tuple | None
    time_s: float | None
    n_stored: int


def _drift_checks(store, run, readings, records, P_E) -> int:
    """Store the drift stops' readings as `campaign run` stores its drift checks
    (campaign.measure.driver._record_drift_check: ``drift_check`` events, warnings over the run's
    threshold). The reference is the log's ``drift_reference`` or, the first time, the drift stops'
    pose as measured (the program returns to the tour's first pose), else the first drift reading.
    Returns the warnings."""
    from dataclasses import replace

    from campaign.measure.driver import RunOptions, _record_drift_check

    cfg = run.config
    opts = replace(RunOptions.from_config(cfg.run), tracker_noise_m=cfg.tracker.noise_m)
    reference = store.get_meta("drift_reference")
    earlier = [] if reference is None else [reference["xyz"]] + [
        d["xyz_m"] for _, _, _, d in store.events("drift_check") if isinstance(d, dict) and d.get("xyz_m")]
    measured = {r.pose_id: r.xyz for r in records if r.status == "measured"}
    warned = 0
    for d in readings:
        if reference is None:
            first = measured.get(d.pose_id) or d.xyz
            if first is None:
                store.add_event("drift_check", {"reference_pose_id": d.pose_id, "drift_mm": None,
                                                "over_threshold": False}, pose_id=d.pose_id, time_s=d.time_s)
                continue
            reference = {"pose_id": d.pose_id, "q": list(map(float, d.q)), "xyz": list(map(float, first))}
            store.set_meta("drift_reference", reference)
            earlier = [reference["xyz"]]
            if d.pose_id not in measured:  # this reading is the reference's first
                continue
        xyz = None if d.xyz is None else np.asarray(d.xyz, dtype=float)
        warned += _record_drift_check(store, reference, xyz, earlier, opts, P_E, d.n_stored, d.pose_id, d.time_s,
                                      lambda msg: None)
    return warned


def _store(run, records, events, rows, kind, frame, P_E, names, layout, finder, next_stop, state, robot) -> Path:
    """Write the poses and events (one transaction for the poses), the meta and stream_match.csv."""
    from campaign.fileio import atomic_write
    from campaign.measure.store import MeasurementStore

    twice = sorted(i for i, n in Counter(r.pose_id for r in records).items() if n > 1)
    if twice:
        dup = twice
        raise DataError(f"{run.path}/program/stops.csv: pose_id {dup[0]} is measured at two stops; a run "
                        "stores a pose once (a repeat has an id of its own)")
    match_csv = run.path / "import" / MATCH_FILE
    new = not run.measurements_path.is_file()
    target = run.measurements_path
    path = target.with_name(target.name + ".partial") if new else target
    if new:
        path.unlink(missing_ok=True)
    try:
        with MeasurementStore(path) as store:
            if new:
                store.set_meta("source", {"kind": "stream", "length_unit": "mm" if layout.length_scale != 1 else "m",
                                          "logs": []})
                store.record_robot(robot)
                store.set_meta("frame", frame)
                store.set_meta("T_LI", np.eye(4).tolist())
                store.set_meta("kind", kind)
                if kind == "markers":
                    store.set_meta("marker_positions", np.asarray(P_E, dtype=float).tolist())
                    store.set_meta("marker_names", list(names))
            else:
                stored = store.stored_ids() & {r.pose_id for r in records}
                if stored:
                    raise DataError(f"{run.path}: pose {min(stored)} is already stored; {layout.path} "
                                    "repeats stops an earlier log imported")
            if records:
                store.add_poses(records)
            _drift_checks(store, run, events, records, P_E)
            src = store.get_meta("source", {})
            src.setdefault("logs", []).append(str(layout.path.resolve()))
            store.set_meta("source", src)
            clock = max([state.get("clock_s", 0.0)] + [r.time_s for r in records if r.time_s is not None]
                        + [e.time_s for e in events if e.time_s is not None])
            store.set_meta("campaign_clock_s", clock)
            store.add_event("stream_import", {"log": str(layout.path.resolve()), "samples": finder.samples,
                                              "next_stop": next_stop}, time_s=clock)
            seq = int(state.get("seq", 0)) + len(records)
            store.set_meta(META_KEY, {"next_stop": next_stop, "clock_s": clock + 1.0, "seq": seq})
        if new:
            path.replace(target)
    finally:
        if new:
            path.unlink(missing_ok=True)
    text = io.StringIO()
    w = csv.writer(text, lineterminator="\n")
    old = match_csv.read_text() if match_csv.is_file() and not new else ""
    if not old:
        w.writerow(MATCH_HEADER)
    w.writerows(rows)
    match_csv.parent.mkdir(parents=True, exist_ok=True)
    atomic_write(match_csv, old + text.getvalue())
    return match_csv
