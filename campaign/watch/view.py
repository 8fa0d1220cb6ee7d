"""What the live page shows, read from a run folder without ever getting in the writer's way.

The measurement log is opened read-only, one short connection per refresh and only when its files
changed, through the log's one read-only reader (campaign.measure.store.read_only_log), which writes
nothing into the run folder: the driver writes it in WAL mode, where a reader never blocks a commit.
A damaged log (SQLite's integrity check, once per file) makes the state ``damaged`` and a note names
the file. Whether a command is writing the run is read from the kernel's table of file
locks (``/proc/locks``), so the watcher never takes the run's lock itself, not even for a
moment (a ``flock`` probe could make a `campaign run` starting at that instant refuse as busy);
elsewhere than Linux it falls back to such a probe (:meth:`RunFolder.lock_holder`).

Times: ``time_s`` is the campaign clock (s), ``wall_time_unix_s`` the wall clock; positions in m
inside, errors in mm at the edges (``*_mm``).
"""

from __future__ import annotations

import json
import math
import os
import threading
import time
from pathlib import Path

from campaign.errors import CampaignError, DataError, StorageError
from campaign.measure.store import read_only_log
from campaign.run import RunFolder

#: commands whose lock on the run means poses are being measured
MEASURING_COMMANDS = ("run", "auto")
#: the states of a run (DESIGN.md, `campaign watch`), and ``damaged``: the log cannot be read
STATES = ("planned", "running", "finished", "interrupted", "damaged")
#: shortest time between two reads of the log (s): any number of clients share one read (a page polls
#: every second; the log is read again only when its files changed)
MIN_REFRESH_S = 0.25
#: the report pages the page links to when present, in RUN (label, path)
REPORTS = (("calibration report", "calibration/report.html"), ("diagnosis report", "diagnose/report.html"),
           ("ISO 9283 report", "iso9283/report.html"), ("auto report", "auto/report.html"),
           ("plan tour", "plan/tour.png"))
#: the folders of RUN the page may serve files from (the reports and what they show)
SERVED_FOLDERS = ("calibration", "calibrations", "diagnose", "diagnoses", "iso9283", "iso9283s", "auto", "plan",
                  "plans")

_POSE_COLUMNS = ("pose_id", "seq", "status", "reason", "time_s", "wall_time_unix_s", "x", "y", "z", "fit_rms_m",
                 "retries", "q1", "q2", "q3", "q4", "q5", "q6", "q_json", "context")


def finite(v):
    """``v`` as a float, None when missing or not finite (strict JSON has no NaN)."""
    if v is None:
        return None
    v = float(v)
    return v if math.isfinite(v) else None


def strict_json(doc) -> bytes:
    """UTF-8 strict JSON (ValueError on NaN or infinity, which :func:`finite` keeps out)."""
    return json.dumps(doc, allow_nan=False, separators=(",", ":")).encode()


def run_folder_error(path) -> str | None:
    """Why ``path`` is no run folder to watch (one line), None when it is one: a folder with a
    campaign.yaml, a plan, a measurement log or auto's state (what `plan`, `import`, `run` and
    `auto` write first)."""
    path = Path(path)
    if not path.exists():
        return f"{path}: no such run folder"
    if not path.is_dir():
        return f"{path}: not a folder (give a run folder, as for `campaign run`)"
    run = RunFolder(path)
    if not any(p.is_file() for p in (run.config_path, run.poses_csv, run.measurements_path,
                                     path / "auto" / "state.json")):
        return (f"{path}: not a run folder (no campaign.yaml, plan/poses.csv nor measurements.sqlite); plan it "
                f"with `campaign plan --run {path}`, or `campaign auto {path} --sim --watch` plans, measures and "
                "serves the page")
    return None


def lock_holder(run: RunFolder) -> dict | None:
    """Who holds RUN/.lock now (``{"pid", "command", "since_unix_s"}``) or None, read from
    /proc/locks without touching the lock; elsewhere a brief non-blocking probe."""
    try:
        st = os.stat(run.lock_path)
    except OSError:
        return None
    try:
        with open("/proc/locks") as f:
            table = f.read()
    except OSError:
        return run.lock_holder()
    try:
        holder = json.loads(run.lock_path.read_text() or "{}")
    except (OSError, ValueError):
        holder = {}
    for line in table.splitlines():
        parts = line.split()
        if len(parts) < 6 or "->" in parts or parts[1] != "FLOCK":  # "->": a waiter, not the holder
            continue
        try:
            major, minor, inode = parts[5].split(":")
            if int(inode) != st.st_ino:
                continue
            # the file's device, or (where a layered file system shows another device number
            # there) the process the lock file names
            if os.makedev(int(major, 16), int(minor, 16)) == st.st_dev or int(parts[4]) == holder.get("pid"):
                return holder
        except ValueError:
            continue
    return None


class RunView:
    """A run folder as the live page sees it: :meth:`status`, :meth:`poses`, :meth:`details`.
    Thread-safe; reads are shared by all clients and repeated at most every MIN_REFRESH_S."""

    def __init__(self, run_dir):
        self.run = RunFolder(run_dir)
        self._guard = threading.Lock()
        self._read_at = -math.inf
        self._stamp = None
        self._rows: list = []
        self._ids: set = set()
        self._max_seq = None
        self._events: list = []
        self._event_seq = 0
        self._meta: dict = {}
        self._planned = (None, 0, ())
        self._calibration = (None, None)
        #: calibrations read so far: a page re-reads the calibrated residuals when it changes (a new
        #: calibration of the same stage gives other residuals under the same name)
        self._calibration_count = 0
        self._calibrated = None
        #: the tracker's pose against the robot's base (4, 4) that the current calibration found,
        #: for a run measured in the tracker's frame; None otherwise
        self._T_L_I = None
        self._residual_from = 0
        self._residuals: dict = {}
        self._nominal: dict = {}
        self._robot = None
        self._notes: dict = {}  # what could not be shown and why, once each, in order
        self._summary = None
        self._tally = _Tally()
        self._todo = (None, [], 0)
        self._state = "planned"
        self._holder = None
        #: why the log cannot be read (a damaged file: one line naming it), else None
        self.log_error = None
        self._checked_inode = None  # the log file whose integrity was checked
        #: reads of the log: whole ("full") and of what was appended since the last ("appended")
        self.reads = {"full": 0, "appended": 0}

    def _note(self, text: str) -> None:
        self._notes[" ".join(str(text).split())] = None

    def prepare(self) -> None:
        """Load what the first poses will need (the robot, the kinematics) now, before a run is
        watched, rather than during it."""
        if self.run.has_config:
            with self._guard:
                self._robot_model()
                import campaign.model.kinematics  # noqa: F401

    # -- reading ----------------------------------------------------------------------------------
    def _files_stamp(self):
        out = []
        for suffix in ("", "-wal"):
            try:
                st = os.stat(f"{self.run.measurements_path}{suffix}")
                out.append((st.st_ino, st.st_mtime_ns, st.st_size))
            except OSError:
                out.append(None)
        return tuple(out)

    def refresh(self, *, force: bool = False) -> None:
        """Read the log again when it changed (and MIN_REFRESH_S has passed since the last read),
        and who writes the run."""
        with self._guard:
            now = time.monotonic()
            if not force and now - self._read_at < MIN_REFRESH_S:
                return
            self._read_at = now
            changed = self._read_plan()
            stamp = self._files_stamp()
            if stamp != self._stamp:
                changed = True
                if self._read_log():
                    self._stamp = stamp
            changed |= self._read_calibration()
            if changed or self._summary is None:
                self._summary = self._summarise()
            self._holder = lock_holder(self.run)
            self._state = self._run_state()

    def _read_plan(self) -> bool:
        path = self.run.poses_csv
        try:
            st = path.stat()
        except OSError:
            changed = self._planned[0] is not None
            self._planned = (None, 0, ())
            return changed
        key = (st.st_ino, st.st_mtime_ns, st.st_size)
        if self._planned[0] == key:
            return False
        ids = []
        try:
            for line in path.read_text().splitlines()[1:]:
                head = line.split(",", 1)[0].strip()
                if head:
                    ids.append(int(float(head)))
        except (OSError, ValueError):
            return False  # a plan being rewritten: the previous one stays until it reads whole
        self._planned = (key, len(ids), tuple(ids))
        return True

    def _read_log(self) -> bool:
        """Read what the log gained since the last read (all of it when rows were removed or
        came out of visiting order); False when it could not be read now."""
        path = self.run.measurements_path
        if not path.is_file():
            self._rows, self._ids, self._max_seq, self._events, self._event_seq, self._meta = [], set(), None, [], 0, {}
            self._tally = _Tally()
            return True
        try:
            inode = path.stat().st_ino
        except OSError:
            return False
        try:
            with read_only_log(path, check=inode != self._checked_inode, timeout_s=1.0) as db:
                self._checked_inode = inode
                got = self._query(db)
        except StorageError:
            return False  # busy or being created: what was read stays until the next refresh
        except DataError as exc:  # damaged: said on the page and as the state, nothing written
            self.log_error = " ".join(str(exc).split())
            self._note(self.log_error)
            return True  # read again when the file changes
        self.log_error = None
        if got is None:
            return False
        new, events, meta, appended = got
        rows = [dict(zip(_POSE_COLUMNS, r)) for r in new]
        new_events = [(k, p, t, w, _loads(d, {})) for _, k, p, t, w, d in events]
        if appended:
            self.reads["appended"] += 1
            self._rows += rows
            self._events += new_events
            self._ids.update(r["pose_id"] for r in rows)
        else:
            self.reads["full"] += 1
            self._rows, self._events, self._ids = rows, new_events, {r["pose_id"] for r in rows}
            self._tally = _Tally()
        seqs = [r["seq"] for r in rows if r["seq"] is not None] + ([self._max_seq] if appended else [])
        self._max_seq = max((q for q in seqs if q is not None), default=None)
        self._event_seq = max((e[0] for e in events), default=self._event_seq if appended else 0)
        self._meta = {k: _loads(v, None) for k, v in meta.items() if k in ("frame", "kind", "campaign_clock_s",
                                                                            "robot")}
        self._tally.add(rows, new_events)
        self._update_residuals(rows)
        return True

    def _query(self, db):
        """(rows, events, meta, appended) of one read transaction of the open log ``db``: what it
        gained since the last read (all of it unless ``appended``), None before it has a poses table."""
        tables = {r[0] for r in db.execute("SELECT name FROM sqlite_master WHERE type = 'table'")}
        if "poses" not in tables:
            return None
        with db:  # one read transaction: the count and the rows of one state of the log
            db.execute("BEGIN")
            count = db.execute("SELECT COUNT(*) FROM poses").fetchone()[0]
            cols = ", ".join(_POSE_COLUMNS)
            new = db.execute(f"SELECT {cols} FROM poses WHERE seq > ? ORDER BY seq, pose_id",
                             (-1 if self._max_seq is None else self._max_seq,)).fetchall()
            appended = count == len(self._rows) + len(new) and not any(r[0] in self._ids for r in new)
            if not appended:
                new = db.execute(f"SELECT {cols} FROM poses ORDER BY seq, pose_id").fetchall()
            events = db.execute("SELECT seq, kind, pose_id, time_s, wall_time_unix_s, detail FROM events "
                                "WHERE seq > ? ORDER BY seq", (self._event_seq if appended else 0,)
                                ).fetchall() if "events" in tables else []
            meta = dict(db.execute("SELECT key, value FROM meta").fetchall()) if "meta" in tables else {}
        return new, events, meta, appended

    # -- residuals ----------------------------------------------------------------------------------
    def _robot_model(self):
        if self._robot is None:
            try:
                from campaign.measure.driver import measured_robot

                self._robot = measured_robot(self.run.robot())
            except CampaignError as exc:
                self._robot = False
                self._note(f"no residuals: {exc}")
        return self._robot or None

    def _tool_point(self, robot, *, calibrated: bool = False):
        """The point the log's x, y, z measure, in the tool frame F_E of ``robot`` (m): E's origin
        for 6-D poses and raw reflectors (the log stores the pose the reflectors were fitted to);
        for one-reflector data where calibrate takes them (robot.yaml's single reflector, else E's
        origin: plausibility.measured_point), which is the calibrated robot's own tool frame
        (``calibrated``: its origin)."""
        import numpy as np

        from campaign.measure.plausibility import measured_point

        if self._meta.get("kind", "pose") != "point" or calibrated:
            return np.zeros(3)
        return np.asarray(measured_point(robot, "point"), dtype=float)

    def _q(self, rows, n_joints):
        import numpy as np

        return np.array([json.loads(r["q_json"]) if r["q_json"] else [r[f"q{j}"] for j in range(1, 7)]
                         for r in rows], dtype=float).reshape(len(rows), -1)[:, :n_joints]

    def _update_residuals(self, rows):
        """Nominal positions (m) of the poses just read that have none yet (of every stored pose:
        where failures happen too); /api/poses gives the nominal model's error from them."""
        from campaign.model.kinematics import forward

        new = [r for r in rows if r["pose_id"] not in self._nominal]
        if not new:
            return
        robot = self._robot_model()
        if robot is None:
            return
        try:
            q = self._q(new, robot.n_joints)
            T = forward(robot, q)
            p = T[:, :3, :3] @ self._tool_point(robot) + T[:, :3, 3]
        except (CampaignError, ValueError) as exc:
            self._note(f"no nominal positions: {exc}")
            return
        for r, pos in zip(new, p):
            self._nominal[r["pose_id"]] = pos

    def _read_calibration(self) -> bool:
        """The current calibration's residuals of the measured poses (mm): all again when the
        calibration changes, the new poses only otherwise. True when something changed."""
        from campaign.versioned import calibration_folder

        try:
            folder = calibration_folder(self.run.path).current()
        except (CampaignError, OSError):
            folder = None
        metrics = (folder / "metrics.json") if folder else self.run.calibration_dir / "metrics.json"
        try:
            key = (str(metrics.resolve()), metrics.stat().st_mtime_ns)
        except OSError:
            changed = self._calibration[0] is not None
            self._calibration, self._residuals, self._calibrated = (None, None), {}, None
            return changed
        if self._calibration[0] != key:
            self._calibration, self._residuals, self._calibrated = (key, None), {}, None
            self._T_L_I = None
            robot = self._robot_model()
            if robot is None or not self._rows:
                self._calibration = (None, None)  # tried again once there are poses
                return True
            if self._meta.get("frame", "robot") == "tracker":
                self._T_L_I = _tracker_pose(metrics)  # where calibrate found the tracker
                if self._T_L_I is None:
                    self._note(f"no residuals: the run is measured in the tracker's frame and {metrics} holds no "
                               "tracker pose (tracker.T_L_I)")
                    return True
            try:
                from campaign.identify.use import CalibratedRobot

                self._calibrated = CalibratedRobot(self.run.path)
            except (CampaignError, ValueError, KeyError, OSError) as exc:
                self._note(f"no calibrated residuals: {' '.join(str(exc).split())}")
                return True
            self._calibration = (key, self._calibrated.stage)
            self._calibration_count += 1
            self._residual_from = 0
        if self._calibrated is None:
            return False
        todo = [r for r in self._rows[self._residual_from:] if r["status"] == "measured" and r["x"] is not None
                and r["pose_id"] not in self._residuals]
        self._residual_from = len(self._rows)
        if not todo:
            return False
        import numpy as np

        from campaign.effects.base import effect_context

        robot = self._robot_model()
        try:
            keys = sorted({k for r in todo for k in _loads(r["context"], {})})
            ctx = {k: np.array([_loads(r["context"], {}).get(k, np.nan) for r in todo], dtype=float) for k in keys}
            ctx = effect_context(ctx, [r["time_s"] if r["time_s"] is not None else np.nan for r in todo])
            T = self._calibrated.predict(self._q(todo, robot.n_joints), ctx)
            p = T[:, :3, :3] @ self._tool_point(robot, calibrated=True) + T[:, :3, 3]
            if self._T_L_I is not None:  # measured in the tracker's frame: the model's points taken there
                p = p @ self._T_L_I[:3, :3].T + self._T_L_I[:3, 3]
        except (CampaignError, ValueError, KeyError) as exc:
            self._note(f"no calibrated residuals: {' '.join(str(exc).split())}")
            self._calibrated = None
            return True
        xyz = np.array([[r["x"], r["y"], r["z"]] for r in todo], dtype=float)
        for r, e in zip(todo, np.linalg.norm(p - xyz, axis=1) * 1e3):
            self._residuals[r["pose_id"]] = finite(e)
        return True

    # -- the answers ---------------------------------------------------------------------------------
    def _summarise(self) -> dict:
        """What status and details show, from the tallies kept as the log is read (no pass over
        every pose per request, nor per read)."""
        t, rows = self._tally, self._rows
        key, planned_ids = self._planned[0], self._planned[2]
        if self._todo[0] != key or len(self._ids) < self._todo[2]:  # a new plan, or poses forgotten
            self._todo = (key, [p for p in planned_ids if p not in self._ids], len(self._ids))
        else:  # the poses stored since leave the list; the plan's order is kept
            todo = self._todo[1]
            if len(self._ids) != self._todo[2]:
                todo = [p for p in todo if p not in self._ids]
            self._todo = (key, todo, len(self._ids))
        todo = self._todo[1]
        clock = max(t.clock_s, finite(self._meta.get("campaign_clock_s")) or 0.0)
        per_pose = (t.session_max - t.session_min) / (t.session_n - 1) if t.session_n > 1 else None
        walls = [r["wall_time_unix_s"] for r in rows[-50:] if r["wall_time_unix_s"] is not None]
        wall_rate = (len(walls) - 1) / (walls[-1] - walls[0]) * 3600 if len(walls) > 2 and walls[-1] > walls[0] \
            else None
        threshold = t.drift_threshold if t.drift_threshold is not None else self.drift_threshold_mm()
        drift = {"checks": t.drift_checks, "last_mm": t.drift_last, "max_mm": t.drift_max,
                 "threshold_mm": threshold, "over_threshold": t.drift_over}
        return {"measured": t.measured, "failed": len(rows) - t.measured, "planned": len(planned_ids) or len(rows),
                "todo": len(todo), "next_pose": todo[0] if todo else None, "per_pose_s": per_pose,
                "wall_rate": wall_rate, "clock_s": clock, "last_pose": rows[-1]["pose_id"] if rows else None,
                "drift": drift, "sessions": t.sessions}

    def _run_state(self) -> str:
        """planned | running | finished | interrupted (DESIGN.md, `campaign watch`); damaged when the
        log cannot be read (:attr:`log_error` says why, naming the file): no count of it can be told."""
        if self.log_error is not None:
            return "damaged"
        s = self._summary
        if self._holder is not None and self._holder.get("command") in MEASURING_COMMANDS:
            return "running"
        auto = self._auto_state()
        if auto is not None:
            return "finished" if auto.get("finished") else "interrupted"
        if s["measured"] + s["failed"] == 0 and not s["sessions"]:
            return "planned"
        return "finished" if s["todo"] == 0 else "interrupted"

    def _auto_state(self) -> dict | None:
        try:
            doc = json.loads((self.run.path / "auto" / "state.json").read_text())
        except (OSError, ValueError):
            return None
        return doc if isinstance(doc, dict) else None

    def drift_threshold_mm(self):
        """The configured threshold (mm), None when ``auto`` (from the noise floor, stored with
        each check) or unreadable."""
        try:
            value = self.run.config.run.drift_threshold_mm
        except CampaignError:
            return None
        return None if value == "auto" else finite(value)

    def status(self) -> dict:
        """The eight fields of ``/api/status`` (DESIGN.md, `campaign watch`)."""
        self.refresh()
        with self._guard:
            s = self._summary
            eta = 0.0 if s["todo"] == 0 else (s["todo"] * s["per_pose_s"] if s["per_pose_s"] is not None else None)
            return {"measured": s["measured"], "failed": s["failed"], "planned": s["planned"], "eta_s": finite(eta),
                    "state": self._state, "campaign_h": finite(s["clock_s"] / 3600.0), "last_pose": s["last_pose"],
                    "drift": dict(s["drift"])}

    def poses(self, start: int = 0) -> list:
        """Every stored pose from position ``start`` (in visiting order), as JSON-ready dicts:
        status, reason, campaign time (s), wall time, measured position (m), nominal position
        (m) and the nominal and calibrated models' position errors (mm)."""
        self.refresh()
        with self._guard:
            # a run measured in the tracker's frame is compared with the nominal model once a
            # calibration found the tracker (the nominal points taken into its frame)
            to_measured = None if self._meta.get("frame", "robot") == "robot" else self._T_L_I
            comparable = to_measured is not None or self._meta.get("frame", "robot") == "robot"
            out = []
            for r in self._rows[max(int(start), 0):]:
                nom = self._nominal.get(r["pose_id"])
                xyz = [finite(r[c]) for c in ("x", "y", "z")]
                has_xyz = r["status"] == "measured" and None not in xyz
                err = None
                if nom is not None and has_xyz and comparable:
                    there = nom if to_measured is None else to_measured[:3, :3] @ nom + to_measured[:3, 3]
                    err = finite(1e3 * math.dist(there, xyz))
                out.append({"pose_id": r["pose_id"], "seq": r["seq"], "status": r["status"], "reason": r["reason"],
                            "time_s": finite(r["time_s"]), "wall_time_unix_s": finite(r["wall_time_unix_s"]),
                            "xyz_m": xyz if has_xyz else None,
                            "nominal_xyz_m": [finite(v) for v in nom] if nom is not None else None,
                            "fit_rms_mm": finite(r["fit_rms_m"] * 1e3) if r["fit_rms_m"] is not None else None,
                            "retries": r["retries"], "error_nominal_mm": err,
                            "error_calibrated_mm": self._residuals.get(r["pose_id"])})
            return out

    def details(self) -> dict:
        """What the page shows beside the counts: the run, the drift checks, warnings and stops,
        auto's rounds, the calibration the residuals are against, the reports present, notes."""
        self.refresh()
        with self._guard:
            s = self._summary
            events = [{"kind": k, "pose_id": p, "time_s": finite(t), "wall_time_unix_s": finite(w),
                       "detail": _jsonable(d)} for k, p, t, w, d in self._events
                      if k in ("drift_check", "warning", "stop", "session_start", "session_end", "retry_failed",
                               "drift_check_skipped")]
            auto = self._auto_state()
            rounds = []
            for r in (auto or {}).get("rounds") or []:
                d = r.get("decision") or {}
                rounds.append({"number": r.get("number"), "poses": r.get("poses"), "hours": finite(r.get("hours")),
                               "model": r.get("model"), "heldout_mm": finite(r.get("heldout_mm")),
                               "floor_mm": finite(r.get("floor_mm")), "verdict": r.get("verdict"),
                               "decision": d.get("text"), "kind": d.get("kind")})
            reports = [{"label": label, "href": f"run/{rel}"} for label, rel in REPORTS
                       if (self.run.path / rel).is_file()]
            up = None
            if self._robot:
                g = [float(v) for v in self._robot.gravity_in_root]
                norm = math.hypot(*g)
                up = [-v / norm for v in g] if norm > 0 else None
            per_pose = s["per_pose_s"]
            return {"run": self.run.path.name, "path": str(self.run.path), "robot": self._meta.get("robot"),
                    "up": up, "frame": self._meta.get("frame", "robot"), "kind": self._meta.get("kind", "pose"),
                    "state": self._state, "holder": self._holder, "next_pose": s["next_pose"], "events": events,
                    "drift_threshold_mm": s["drift"]["threshold_mm"],
                    "rate_poses_per_campaign_h": finite(3600.0 / per_pose) if per_pose else None,
                    "rate_poses_per_wall_h": finite(s["wall_rate"]),
                    "calibration_stage": self._calibration[1],
                    "calibration_id": f"{self._calibration_count}:{self._calibration[1]}"
                                      if self._calibration[1] else None,
                    "auto": None if auto is None else {"rounds": rounds, "finished": _jsonable(auto.get("finished")),
                                                       "pending": (auto.get("pending") or {}).get("text")},
                    "reports": reports, "notes": list(self._notes)[-5:]}

    def served_file(self, rel: str) -> Path | None:
        """RUN/``rel`` when it is a file in one of SERVED_FOLDERS (links resolved: inside RUN), else None."""
        parts = Path(rel).parts
        if not parts or parts[0] not in SERVED_FOLDERS or any(p in ("..", "") for p in parts):
            return None
        root = self.run.path.resolve()
        try:
            path = (self.run.path / rel).resolve()
        except (OSError, RuntimeError):
            return None
        if root not in path.parents or not path.is_file():
            return None
        return path


class _Tally:
    """Running sums over the poses and events read so far (campaign clock in s, drift in mm)."""

    def __init__(self):
        self.measured = self.sessions = self.drift_checks = self.drift_over = 0
        self.clock_s = 0.0
        self.session_since = -math.inf
        self.session_n, self.session_min, self.session_max = 0, math.inf, -math.inf
        self.drift_last = self.drift_max = None
        #: the threshold the driver applied at the last check (mm; it follows the noise floor under
        #: ``run.drift_threshold_mm: auto``), None before a check that stores it
        self.drift_threshold = None

    def add(self, rows, events) -> None:
        for kind, _, t, wall, detail in events:
            if t is not None and math.isfinite(t):
                self.clock_s = max(self.clock_s, t)
            if kind == "session_start":  # the rate is the current session's
                self.sessions += 1
                self.session_since = wall if wall is not None else -math.inf
                self.session_n, self.session_min, self.session_max = 0, math.inf, -math.inf
            elif kind == "drift_check":
                self.drift_checks += 1
                self.drift_over += bool(detail.get("over_threshold"))
                self.drift_last = finite(detail.get("drift_mm"))
                if finite(detail.get("threshold_mm")) is not None:
                    self.drift_threshold = finite(detail.get("threshold_mm"))
                if self.drift_last is not None:
                    self.drift_max = max(self.drift_max or 0.0, self.drift_last)
        for r in rows:
            self.measured += r["status"] == "measured"
            t = r["time_s"]
            if t is None or not math.isfinite(t):
                continue
            self.clock_s = max(self.clock_s, t)
            if (r["wall_time_unix_s"] if r["wall_time_unix_s"] is not None else math.inf) >= self.session_since:
                self.session_n += 1
                self.session_min, self.session_max = min(self.session_min, t), max(self.session_max, t)


def _tracker_pose(metrics: Path):
    """metrics.json's ``tracker.T_L_I`` (4, 4): the pose of the robot's base frame in the tracker's
    frame that calibrate found for data measured in the tracker's frame; None when absent."""
    import numpy as np

    try:
        T = np.asarray(json.loads(metrics.read_text())["tracker"]["T_L_I"], dtype=float)
    except (OSError, ValueError, KeyError, TypeError):
        return None
    return T if T.shape == (4, 4) and np.isfinite(T).all() else None


def _loads(text, default):
    try:
        return json.loads(text) if text else default
    except (TypeError, ValueError):
        return default


def _jsonable(doc):
    """``doc`` with every non-finite float made None (strict JSON)."""
    if isinstance(doc, float):
        return finite(doc)
    if isinstance(doc, dict):
        return {str(k): _jsonable(v) for k, v in doc.items()}
    if isinstance(doc, (list, tuple)):
        return [_jsonable(v) for v in doc]
    return doc
