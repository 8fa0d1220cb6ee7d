"""What the live page shows, read from a run folder without ever getting in the writer's way.

The measurement log is opened read-only (SQLite URI ``mode=ro``), one short connection per
refresh, and only when its files changed: the driver writes it in WAL mode, where a reader never
blocks a commit. Whether a command is writing the run is read from the kernel's table of file
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
import sqlite3
import threading
import time
from pathlib import Path

from campaign.errors import CampaignError
from campaign.run import RunFolder

#: commands whose lock on the run means poses are being measured
MEASURING_COMMANDS = ("run", "auto")
#: the states of a run (DESIGN.md, `campaign watch`)
STATES = ("planned", "running", "finished", "interrupted")
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
    for line in table.splitlines():
        parts = line.split()
        if len(parts) < 6 or "->" in parts or parts[1] != "FLOCK":  # "->": a waiter, not the holder
            continue
        try:
            major, minor, inode = parts[5].split(":")
            same = int(inode) == st.st_ino and os.makedev(int(major, 16), int(minor, 16)) == st.st_dev
        except ValueError:
            continue
        if same:
            try:
                return json.loads(run.lock_path.read_text() or "{}")
            except (OSError, ValueError):
                return {}
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
        self._events: list = []
        self._meta: dict = {}
        self._planned = (None, 0, ())
        self._calibration = (None, None)
        self._calibrated = None
        self._residuals: dict = {}
        self._nominal: dict = {}
        self._robot = None
        self._notes: list = []
        self.reads = 0

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
        """Read the log again when it changed (and MIN_REFRESH_S has passed since the last read)."""
        with self._guard:
            now = time.monotonic()
            if not force and now - self._read_at < MIN_REFRESH_S:
                return
            self._read_at = now
            self._read_plan()
            stamp = self._files_stamp()
            if stamp != self._stamp:
                self._read_log()
                self._stamp = stamp
            self._read_calibration()

    def _read_plan(self):
        path = self.run.poses_csv
        try:
            st = path.stat()
        except OSError:
            self._planned = (None, 0, ())
            return
        key = (st.st_ino, st.st_mtime_ns, st.st_size)
        if self._planned[0] == key:
            return
        ids = []
        try:
            for line in path.read_text().splitlines()[1:]:
                head = line.split(",", 1)[0].strip()
                if head:
                    ids.append(int(float(head)))
        except (OSError, ValueError):
            return  # a plan being rewritten: the previous one stays until it reads whole
        self._planned = (key, len(ids), tuple(ids))

    def _read_log(self):
        path = self.run.measurements_path
        if not path.is_file():
            self._rows, self._events, self._meta = [], [], {}
            return
        try:
            db = sqlite3.connect(path.resolve().as_uri() + "?mode=ro", uri=True, timeout=1.0,
                                 check_same_thread=False)
        except sqlite3.Error:
            return
        try:
            tables = {r[0] for r in db.execute("SELECT name FROM sqlite_master WHERE type = 'table'")}
            if "poses" not in tables:
                return
            rows = db.execute(f"SELECT {', '.join(_POSE_COLUMNS)} FROM poses ORDER BY seq, pose_id").fetchall()
            events = db.execute("SELECT kind, pose_id, time_s, wall_time_unix_s, detail FROM events ORDER BY seq"
                                ).fetchall() if "events" in tables else []
            meta = dict(db.execute("SELECT key, value FROM meta").fetchall()) if "meta" in tables else {}
        except sqlite3.Error:
            return  # busy or being created: the previous read stays until the next refresh
        finally:
            db.close()
        self.reads += 1
        self._rows = [dict(zip(_POSE_COLUMNS, r)) for r in rows]
        self._events = [(k, p, t, w, _loads(d, {})) for k, p, t, w, d in events]
        self._meta = {k: _loads(v, None) for k, v in meta.items() if k in ("frame", "kind", "campaign_clock_s",
                                                                            "T_LI", "robot")}
        self._update_residuals()

    # -- residuals ----------------------------------------------------------------------------------
    def _robot_model(self):
        if self._robot is None:
            try:
                from campaign.measure.driver import measured_robot

                self._robot = measured_robot(self.run.robot())
            except CampaignError as exc:
                self._robot = False
                self._notes.append(f"no residuals: {exc}")
        return self._robot or None

    def _tool_point(self, robot):
        """The point the log's x, y, z measure, in F_E (m): E's origin for 6-D poses, the first
        reflector otherwise."""
        import numpy as np

        if self._meta.get("kind", "pose") == "pose":
            return np.zeros(3)
        P = robot.reflector_positions_in_E
        return np.asarray(P[0] if len(P) else np.zeros(3), dtype=float)

    def _q(self, rows, n_joints):
        import numpy as np

        return np.array([json.loads(r["q_json"]) if r["q_json"] else [r[f"q{j}"] for j in range(1, 7)]
                         for r in rows], dtype=float).reshape(len(rows), -1)[:, :n_joints]

    def _update_residuals(self):
        """Nominal positions (m, of every stored pose: where failures happen too) and the
        nominal model's error (mm) of the measured ones; new poses only."""
        import numpy as np

        from campaign.model.kinematics import forward

        new = [r for r in self._rows if r["pose_id"] not in self._nominal]
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
            self._notes.append(f"no nominal positions: {exc}")
            return
        for r, pos in zip(new, p):
            self._nominal[r["pose_id"]] = pos

    def _read_calibration(self):
        """The current calibration's residuals of the measured poses (mm): all again when the
        calibration changes, the new poses only otherwise."""
        from campaign.versioned import calibration_folder

        try:
            folder = calibration_folder(self.run.path).current()
        except (CampaignError, OSError):
            folder = None
        metrics = (folder / "metrics.json") if folder else self.run.calibration_dir / "metrics.json"
        try:
            key = (str(metrics.resolve()), metrics.stat().st_mtime_ns)
        except OSError:
            self._calibration, self._residuals, self._calibrated = (None, None), {}, None
            return
        if self._calibration[0] != key:
            self._calibration, self._residuals, self._calibrated = (key, None), {}, None
            robot = self._robot_model()
            if robot is None or self._meta.get("frame", "robot") != "robot":
                return
            try:
                from campaign.identify.use import CalibratedRobot

                self._calibrated = CalibratedRobot(self.run.path)
            except (CampaignError, ValueError, KeyError, OSError) as exc:
                self._notes.append(f"no calibrated residuals: {' '.join(str(exc).split())}")
                return
            self._calibration = (key, self._calibrated.stage)
        if self._calibrated is None:
            return
        todo = [r for r in self._rows if r["status"] == "measured" and r["x"] is not None
                and r["pose_id"] not in self._residuals]
        if not todo:
            return
        import numpy as np

        from campaign.effects.base import effect_context

        robot = self._robot_model()
        try:
            keys = sorted({k for r in todo for k in _loads(r["context"], {})})
            ctx = {k: np.array([_loads(r["context"], {}).get(k, np.nan) for r in todo], dtype=float) for k in keys}
            ctx = effect_context(ctx, [r["time_s"] if r["time_s"] is not None else np.nan for r in todo])
            T = self._calibrated.predict(self._q(todo, robot.n_joints), ctx)
            p = T[:, :3, :3] @ self._tool_point(robot) + T[:, :3, 3]
        except (CampaignError, ValueError, KeyError) as exc:
            self._notes.append(f"no calibrated residuals: {' '.join(str(exc).split())}")
            self._calibrated = None
            return
        xyz = np.array([[r["x"], r["y"], r["z"]] for r in todo], dtype=float)
        for r, e in zip(todo, np.linalg.norm(p - xyz, axis=1) * 1e3):
            self._residuals[r["pose_id"]] = finite(e)

    # -- the answers ---------------------------------------------------------------------------------
    def state(self, measured_or_failed: int, planned: int) -> str:
        holder = lock_holder(self.run)
        if holder is not None and holder.get("command") in MEASURING_COMMANDS:
            return "running"
        auto = self._auto_state()
        if auto is not None:
            return "finished" if auto.get("finished") else "interrupted"
        if measured_or_failed == 0 and not any(e[0] == "session_start" for e in self._events):
            return "planned"
        planned_ids = set(self._planned[2])
        stored = {r["pose_id"] for r in self._rows}
        return "finished" if planned_ids <= stored else "interrupted"

    def _auto_state(self) -> dict | None:
        try:
            doc = json.loads((self.run.path / "auto" / "state.json").read_text())
        except (OSError, ValueError):
            return None
        return doc if isinstance(doc, dict) else None

    def _clock_s(self) -> float:
        times = [r["time_s"] for r in self._rows] + [e[2] for e in self._events] + [self._meta.get("campaign_clock_s")]
        times = [t for t in times if isinstance(t, (int, float)) and math.isfinite(t)]
        return max(times, default=0.0)

    def _per_pose_s(self) -> float | None:
        """Campaign seconds per stored pose over the current (or last) session."""
        starts = [e[3] for e in self._events if e[0] == "session_start"]
        since = starts[-1] if starts else -math.inf
        rows = [r for r in self._rows if r["time_s"] is not None and (r["wall_time_unix_s"] or math.inf) >= since]
        if len(rows) < 2:
            return None
        t = sorted(r["time_s"] for r in rows)
        return (t[-1] - t[0]) / (len(t) - 1)

    def drift(self) -> dict:
        checks = [(t, d.get("drift_mm"), bool(d.get("over_threshold"))) for k, _, t, _, d in self._events
                  if k == "drift_check"]
        values = [finite(v) for _, v, _ in checks if finite(v) is not None]
        stored = [d.get("threshold_mm") for k, _, _, _, d in self._events if k == "drift_check"]
        stored = [finite(v) for v in stored if v is not None]
        return {"checks": len(checks), "last_mm": finite(checks[-1][1]) if checks else None,
                "max_mm": max(values) if values else None,
                "threshold_mm": stored[-1] if stored else self.drift_threshold_mm(),
                "over_threshold": sum(o for _, _, o in checks)}

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
            measured = sum(r["status"] == "measured" for r in self._rows)
            failed = len(self._rows) - measured
            planned = self._planned[1] or len(self._rows)
            state = self.state(measured + failed, planned)
            remaining = max(len(set(self._planned[2]) - {r["pose_id"] for r in self._rows}), 0)
            per_pose = self._per_pose_s()
            eta = 0.0 if remaining == 0 else (remaining * per_pose if per_pose is not None else None)
            return {"measured": measured, "failed": failed, "planned": planned, "eta_s": finite(eta), "state": state,
                    "campaign_h": finite(self._clock_s() / 3600.0),
                    "last_pose": self._rows[-1]["pose_id"] if self._rows else None, "drift": self.drift()}

    def poses(self, start: int = 0) -> list:
        """Every stored pose from position ``start`` (in visiting order), as JSON-ready dicts:
        status, reason, campaign time (s), wall time, measured position (m), nominal position
        (m) and the nominal and calibrated models' position errors (mm)."""
        self.refresh()
        with self._guard:
            out = []
            for r in self._rows[max(int(start), 0):]:
                nom = self._nominal.get(r["pose_id"])
                xyz = [finite(r[c]) for c in ("x", "y", "z")]
                has_xyz = r["status"] == "measured" and None not in xyz
                err = None
                if nom is not None and has_xyz and self._meta.get("frame", "robot") == "robot":
                    err = finite(1e3 * math.dist(nom, xyz))
                out.append({"pose_id": r["pose_id"], "seq": r["seq"], "status": r["status"], "reason": r["reason"],
                            "time_s": finite(r["time_s"]), "wall_time_unix_s": finite(r["wall_time_unix_s"]),
                            "xyz_m": xyz if has_xyz else None,
                            "nominal_xyz_m": [finite(v) for v in nom] if nom is not None else None,
                            "fit_rms_mm": finite(r["fit_rms_m"] * 1e3) if r["fit_rms_m"] is not None else None,
                            "retries": r["retries"], "error_nominal_mm": err,
                            "error_calibrated_mm": self._residuals.get(r["pose_id"])})
            return out

    def details(self) -> dict:
        """What changes rarely: the run, the drift checks, warnings and stops, auto's rounds, the
        calibration the residuals are against, the reports present, notes."""
        self.refresh()
        with self._guard:
            events = [{"kind": k, "pose_id": p, "time_s": finite(t), "wall_time_unix_s": finite(w),
                       "detail": _jsonable(d)} for k, p, t, w, d in self._events
                      if k in ("drift_check", "warning", "stop", "session_start", "session_end", "retry_failed",
                               "drift_check_skipped")]
            auto = self._auto_state()
            rounds = []
            if auto is not None:
                for r in auto.get("rounds") or []:
                    d = r.get("decision") or {}
                    rounds.append({"number": r.get("number"), "poses": r.get("poses"), "hours": finite(r.get("hours")),
                                   "model": r.get("model"), "heldout_mm": finite(r.get("heldout_mm")),
                                   "floor_mm": finite(r.get("floor_mm")), "verdict": r.get("verdict"),
                                   "decision": d.get("text"), "kind": d.get("kind")})
            reports = [{"label": label, "href": f"run/{rel}"} for label, rel in REPORTS
                       if (self.run.path / rel).is_file()]
            per_pose = self._per_pose_s()
            walls = [r["wall_time_unix_s"] for r in self._rows[-50:] if r["wall_time_unix_s"] is not None]
            wall_rate = (len(walls) - 1) / (walls[-1] - walls[0]) * 3600 if len(walls) > 2 and walls[-1] > walls[0] \
                else None
            holder = lock_holder(self.run)
            nxt = next((p for p in self._planned[2] if p not in {r["pose_id"] for r in self._rows}), None)
            robot = self._robot or None
            up = None
            if robot is not None:
                g = [float(v) for v in robot.gravity_in_root]
                norm = math.hypot(*g)
                up = [-v / norm for v in g] if norm > 0 else None
            return {"run": self.run.path.name, "path": str(self.run.path), "robot": self._meta.get("robot"),
                    "up": up,
                    "frame": self._meta.get("frame", "robot"), "kind": self._meta.get("kind", "pose"),
                    "holder": holder, "next_pose": nxt, "events": events,
                    "drift_threshold_mm": self.drift_threshold_mm(),
                    "rate_poses_per_campaign_h": finite(3600.0 / per_pose) if per_pose else None,
                    "rate_poses_per_wall_h": finite(wall_rate),
                    "calibration_stage": self._calibration[1],
                    "auto": None if auto is None else {"rounds": rounds, "finished": _jsonable(auto.get("finished")),
                                                       "pending": (auto.get("pending") or {}).get("text")},
                    "reports": reports, "notes": list(dict.fromkeys(self._notes))[-5:]}

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
