"""The measurement log of a run: ``runs/<name>/measurements.sqlite``.

One committed transaction per pose, so nothing measured is lost when a campaign stops.
Tables (units in the column names where they are not SI base units):

* ``meta(key, value)``: JSON values (``source``, ``robot``, ``T_LI`` as a 4x4 list, ...).
* ``poses``: one row per pose attempted to the end: ``pose_id`` (primary key), ``seq``
  (visiting order), ``status`` (``measured`` or ``failed``), ``reason``, ``time_s``
  (campaign clock, simulated or real), ``wall_time_unix_s``, commanded ``q1..q6`` (rad),
  encoder ``qe1..qe6`` (rad), derived pose of F_E in F_I ``x, y, z`` (m) and
  ``rx, ry, rz`` (rotation vector, rad), ``fit_rms_m`` (Kabsch residual), ``retries``,
  ``context`` (JSON object of extra named values).
* ``reflector_readings``: raw tracker coordinates in F_L per pose and reflector
  (``x_L_m, y_L_m, z_L_m``) with the tracker's status.
* ``events``: what happened besides the poses, in order (written by `campaign run`):
  ``kind`` (``session_start``, ``setup``, ``drift_check``, ``warning``, ``stop``,
  ``session_end``, ``retry_failed``), ``pose_id`` where it concerns one, ``time_s``
  (campaign clock), ``wall_time_unix_s`` and ``detail`` (a JSON object).
"""

from __future__ import annotations

import contextlib
import json
import sqlite3
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from campaign.errors import DataError, StorageError
from campaign.measure.data import MAX_STORED_POSE_ID, MeasuredPoses

SCHEMA = """
CREATE TABLE IF NOT EXISTS meta (key TEXT PRIMARY KEY, value TEXT NOT NULL);
CREATE TABLE IF NOT EXISTS poses (
    pose_id INTEGER PRIMARY KEY,
    seq INTEGER,
    status TEXT NOT NULL CHECK (status IN ('measured', 'failed')),
    reason TEXT,
    time_s REAL,
    wall_time_unix_s REAL,
    q1 REAL NOT NULL, q2 REAL NOT NULL, q3 REAL NOT NULL,
    q4 REAL NOT NULL, q5 REAL NOT NULL, q6 REAL NOT NULL,
    qe1 REAL, qe2 REAL, qe3 REAL, qe4 REAL, qe5 REAL, qe6 REAL,
    x REAL, y REAL, z REAL, rx REAL, ry REAL, rz REAL,
    fit_rms_m REAL,
    retries INTEGER NOT NULL DEFAULT 0,
    context TEXT NOT NULL DEFAULT '{}',
    q_json TEXT
);
CREATE TABLE IF NOT EXISTS reflector_readings (
    pose_id INTEGER NOT NULL REFERENCES poses(pose_id),
    name TEXT NOT NULL,
    x_L_m REAL, y_L_m REAL, z_L_m REAL,
    status TEXT NOT NULL,
    PRIMARY KEY (pose_id, name)
);
CREATE TABLE IF NOT EXISTS events (
    seq INTEGER PRIMARY KEY AUTOINCREMENT,
    kind TEXT NOT NULL,
    pose_id INTEGER,
    time_s REAL,
    wall_time_unix_s REAL NOT NULL,
    detail TEXT NOT NULL DEFAULT '{}'
);
"""

MEASUREMENTS_FILE = "measurements.sqlite"
#: seconds a write waits for another connection's lock before it fails with one line
BUSY_TIMEOUT_S = 30.0


@dataclass(frozen=True)
class PoseRecord:
    """Everything stored for one pose. Angles in rad, lengths in m, times in s."""

    pose_id: int
    status: str
    q: tuple
    seq: int | None = None
    reason: str | None = None
    time_s: float | None = None
    wall_time_unix_s: float | None = None
    q_encoder: tuple | None = None
    xyz: tuple | None = None
    rotvec: tuple | None = None
    fit_rms_m: float | None = None
    retries: int = 0
    context: dict = field(default_factory=dict)
    #: name -> ((x, y, z) in F_L, m, or None, status)
    reflectors: dict = field(default_factory=dict)


class MeasurementStore:
    """A run's SQLite measurement log. Use as a context manager or call :meth:`close`."""

    def __init__(self, path, *, create: bool = True):
        self.path = Path(path)
        if not create and not self.path.is_file():
            raise DataError(f"{self.path}: no measurement log here")
        existing = self.path.is_file() and self.path.stat().st_size > 0
        try:
            self._db = sqlite3.connect(str(self.path), timeout=BUSY_TIMEOUT_S)
            if existing:  # before anything could write to it
                check_integrity(self._db, self.path)
            self._db.executescript(SCHEMA)
            cols = [r[1] for r in self._db.execute("PRAGMA table_info(poses)")]
            if "q_json" not in cols:  # a log written before robots with N != 6 joints
                with self._db:
                    self._db.execute("ALTER TABLE poses ADD COLUMN q_json TEXT")
        except sqlite3.OperationalError as exc:
            self._close_quietly()
            raise StorageError(f"{self.path}: cannot open the measurement log ({exc})") from None
        except sqlite3.DatabaseError as exc:
            self._close_quietly()
            raise DataError(f"{self.path}: not a measurement log ({exc})") from None
        except DataError:
            self._close_quietly()
            raise

    def _close_quietly(self):
        db = getattr(self, "_db", None)
        if db is not None:
            with contextlib.suppress(sqlite3.Error):
                db.close()

    def __enter__(self):
        return self

    def __exit__(self, *exc):
        self.close()

    def close(self):
        self._db.close()

    @contextlib.contextmanager
    def _writing(self, what: str):
        """One committed transaction; a storage failure (full disk, locked database, read-only
        file) rolls it back and becomes one StorageError line: everything committed before stays."""
        try:
            with self._db:
                yield self._db
        except sqlite3.IntegrityError:
            raise
        except sqlite3.DatabaseError as exc:
            raise StorageError(f"{self.path}: cannot store {what} ({exc}); everything stored before is kept, "
                               "re-run to resume once the cause is fixed") from None

    def use_wal(self) -> None:
        """Write-ahead logging: readers (calibrate, export) never block the driver's commits."""
        try:
            self._db.execute("PRAGMA journal_mode=WAL")
            self._db.execute("PRAGMA synchronous=NORMAL")
        except sqlite3.DatabaseError as exc:
            raise StorageError(f"{self.path}: cannot open the measurement log for writing ({exc})") from None

    # -- meta -------------------------------------------------------------------------
    def set_meta(self, key: str, value) -> None:
        with self._writing(f"meta '{key}'") as db:
            db.execute("INSERT OR REPLACE INTO meta(key, value) VALUES (?, ?)", (key, json.dumps(value)))

    def get_meta(self, key: str, default=None):
        row = self._db.execute("SELECT value FROM meta WHERE key = ?", (key,)).fetchone()
        return default if row is None else json.loads(row[0])

    def record_robot(self, robot) -> dict:
        """The robot the log was measured with (campaign.measure.robot_record): recorded now when
        the log has no record yet, else checked: a ConfigError line when ``robot`` is another."""
        from campaign.measure.robot_record import META_KEY, check_same_robot, robot_record

        recorded = self.get_meta(META_KEY)
        if recorded is None:
            recorded = robot_record(robot)
            self.set_meta(META_KEY, recorded)
            if self.get_meta("robot") is None:
                self.set_meta("robot", robot.name)
            return recorded
        check_same_robot(recorded, robot, self.path, "the configuration")
        return recorded

    # -- poses ------------------------------------------------------------------------
    def add_pose(self, rec: PoseRecord) -> None:
        """Store one pose in one committed transaction; a pose is never stored twice."""
        self.add_poses([rec])

    def add_poses(self, records) -> None:
        """Store several poses in one transaction (used by import)."""
        rows, refl = [], []
        for rec in records:
            if isinstance(rec.pose_id, bool) or not 0 <= rec.pose_id < MAX_STORED_POSE_ID \
                    or rec.pose_id != int(rec.pose_id):
                raise DataError(f"pose_id {rec.pose_id!r}: must be an integer in 0..{MAX_STORED_POSE_ID - 1}")
            if rec.status not in ("measured", "failed"):
                raise DataError(f"pose {rec.pose_id}: status must be 'measured' or 'failed', not {rec.status!r}")
            qe = rec.q_encoder if rec.q_encoder is not None and len(rec.q_encoder) == 6 else (None,) * 6
            xyz = tuple(_num(v) for v in rec.xyz) if rec.xyz is not None else (None,) * 3
            rv = tuple(_num(v) for v in rec.rotvec) if rec.rotvec is not None else (None,) * 3
            q = [float(v) for v in rec.q]
            # q1..q6 hold a 6-joint robot's values; any other joint count is kept whole in q_json
            q6, q_json = (q, None) if len(q) == 6 else ((q + [0.0] * 6)[:6], json.dumps(q))
            rows.append((int(rec.pose_id), rec.seq, rec.status, rec.reason, _num(rec.time_s), rec.wall_time_unix_s,
                         *q6, *qe, *xyz, *rv, rec.fit_rms_m, int(rec.retries),
                         json.dumps(rec.context, sort_keys=True), q_json))
            for name, (p, st) in rec.reflectors.items():
                p = p if p is not None else (None, None, None)
                refl.append((int(rec.pose_id), name, *p, st))
        what = f"pose {rows[0][0]}" if len(rows) == 1 else f"{len(rows)} poses"
        try:
            with self._writing(what) as db:
                db.executemany("INSERT INTO poses (pose_id, seq, status, reason, time_s, wall_time_unix_s, "
                               "q1, q2, q3, q4, q5, q6, qe1, qe2, qe3, qe4, qe5, qe6, x, y, z, rx, ry, rz, "
                               "fit_rms_m, retries, context, q_json) VALUES (" + ",".join("?" * 28) + ")", rows)
                db.executemany("INSERT INTO reflector_readings VALUES (?,?,?,?,?,?)", refl)
        except sqlite3.IntegrityError as exc:
            raise DataError(f"{self.path}: a pose is already stored ({exc})") from None

    def add_event(self, kind: str, detail: dict | None = None, *, pose_id: int | None = None,
                  time_s: float | None = None) -> None:
        """Append one event (its own committed transaction); ``time_s`` is the campaign clock."""
        import time

        with self._writing(f"event '{kind}'") as db:
            db.execute("INSERT INTO events(kind, pose_id, time_s, wall_time_unix_s, detail) VALUES (?,?,?,?,?)",
                       (kind, pose_id, time_s, time.time(), json.dumps(detail or {}, sort_keys=True)))

    def events(self, kind: str | None = None) -> list:
        """[(kind, pose_id, time_s, detail dict), ...] in the order they happened."""
        sql = "SELECT kind, pose_id, time_s, detail FROM events"
        rows = self._db.execute(sql + " WHERE kind = ? ORDER BY seq" if kind else sql + " ORDER BY seq",
                                (kind,) if kind else ()).fetchall()
        return [(k, p, t, json.loads(d)) for k, p, t, d in rows]

    def _setup_of(self, pose_ids, T_LI) -> np.ndarray:
        """T_LI (n, 4, 4) in force when each of ``pose_ids`` was measured: a run resumed on another
        cell measured that cell's own set-up (campaign.measure.driver); ``T_LI`` (meta) when the run
        has one set-up."""
        walls, setups = _setup_walls(self._db)
        if len(setups) < 2:
            return np.broadcast_to(np.asarray(T_LI, dtype=float), (len(pose_ids), 4, 4))
        when = dict(self._db.execute("SELECT pose_id, wall_time_unix_s FROM poses").fetchall())
        w = np.array([np.nan if when.get(int(p)) is None else when[int(p)] for p in pose_ids], dtype=float)
        at = np.clip(np.searchsorted(walls, np.nan_to_num(w, nan=-np.inf), side="right") - 1, 0, None)
        return setups[at]

    def forget_failed(self) -> list:
        """Delete the failed poses (one transaction) so a re-run measures them again; their ids."""
        with self._writing("the forgetting of failed poses") as db:
            ids = [r[0] for r in db.execute("SELECT pose_id FROM poses WHERE status = 'failed'")]
            db.execute("DELETE FROM reflector_readings WHERE pose_id IN "
                       "(SELECT pose_id FROM poses WHERE status = 'failed')")
            db.execute("DELETE FROM poses WHERE status = 'failed'")
        return ids

    def clock_s(self) -> float:
        """The campaign clock at the last thing stored (s; 0 for an empty log): a resumed
        campaign continues from here, so the clock never runs backwards."""
        times = [0.0, self._db.execute("SELECT MAX(time_s) FROM poses").fetchone()[0],
                 self._db.execute("SELECT MAX(time_s) FROM events").fetchone()[0],
                 self.get_meta("campaign_clock_s")]
        return float(max(t for t in times if t is not None))

    def stored_ids(self) -> set:
        """pose_ids with a stored outcome (measured or failed)."""
        return {r[0] for r in self._db.execute("SELECT pose_id FROM poses")}

    def counts(self) -> dict:
        return dict(self._db.execute("SELECT status, COUNT(*) FROM poses GROUP BY status").fetchall())

    def failures(self) -> list:
        return self._db.execute("SELECT pose_id, reason FROM poses WHERE status='failed' ORDER BY pose_id").fetchall()

    def load_measured(self, *, include_unusable: bool = False) -> MeasuredPoses:
        """All measured poses, ordered by pose_id, with the measurement kind and frame of the log
        (meta ``kind``, ``frame``, ``marker_positions``; default 6-D poses in the robot's frame).
        Raw-reflector poses with fewer than three reflectors seen (no pose) are left out unless
        ``include_unusable`` (`calibrate` identifies them from the reflectors' positions)."""
        cur = self._db.execute(
            "SELECT pose_id, time_s, q1, q2, q3, q4, q5, q6, x, y, z, rx, ry, rz, context, q_json "
            "FROM poses WHERE status = 'measured' ORDER BY pose_id")
        rows = cur.fetchall()
        if not rows:
            raise DataError(f"{self.path}: no measured poses")
        pid = np.array([r[0] for r in rows], dtype=np.int64)
        num = np.array([r[1:14] for r in rows], dtype=float)  # NULL (None) becomes NaN
        texts = [r[14] for r in rows]
        parsed = {t: json.loads(t) for t in set(texts)}  # most logs repeat a few contexts (often "{}")
        contexts = [parsed[t] for t in texts]
        keys = sorted(set().union(*contexts))
        context = {k: np.array([c.get(k, np.nan) for c in contexts], dtype=float) for k in keys}
        q = num[:, 1:7]
        if any(r[15] is not None for r in rows):
            q = np.array([json.loads(r[15]) if r[15] is not None else list(r[2:8]) for r in rows], dtype=float)
        kind = self.get_meta("kind", "pose")
        P_nom = self.get_meta("marker_positions")
        markers = None
        if kind == "markers":
            P_nom = np.asarray(P_nom, dtype=float)
            markers = np.full((len(pid), len(P_nom), 3), np.nan)
            index = {int(p): i for i, p in enumerate(pid)}
            # imported: readings m1..mk in the data's frame; measured by `campaign run` (two
            # reflectors): the tracker's targets by name, in F_L
            names = self.get_meta("marker_names")
            slot = {n: i for i, n in enumerate(names)} if names else \
                {f"m{i + 1}": i for i in range(len(P_nom))}
            for p, name, x, y, z in self._db.execute(
                    "SELECT pose_id, name, x_L_m, y_L_m, z_L_m FROM reflector_readings"):
                if p in index and name in slot and x is not None:
                    markers[index[p], slot[name]] = (x, y, z)
            T_LI = self.get_meta("T_LI")
            if names and T_LI is not None and self.get_meta("frame", "robot") == "robot":
                from campaign.measure.reflectors import invert, transform_points

                markers = transform_points(invert(self._setup_of(pid, T_LI)), markers)
            # a pose only where its rigid fit was (three or more seen): no rotation, no pose
            num[np.isnan(num[:, 10:13]).any(axis=1), 7:10] = np.nan
        poses = MeasuredPoses.from_vectors(pid, num[:, 0], q, num[:, 7:10], num[:, 10:13], context, kind=kind,
                                           frame=self.get_meta("frame", "robot"), markers=markers,
                                           marker_positions=None if P_nom is None else np.asarray(P_nom, dtype=float))
        usable = np.isfinite(poses.T_IE[:, :3, 3]).all(axis=1)
        if include_unusable or usable.all():
            return poses
        if not usable.any():
            raise DataError(f"{self.path}: no pose has three reflectors seen")
        return poses.subset(np.flatnonzero(usable))


def _setup_walls(db) -> tuple:
    """(wall times (k,), T_LI (k, 4, 4)) of the log's base-frame set-ups, in order."""
    rows = db.execute("SELECT wall_time_unix_s, detail FROM events WHERE kind = 'setup' ORDER BY seq").fetchall()
    rows = [(w, json.loads(d).get("T_LI")) for w, d in rows]
    rows = [(w, T) for w, T in rows if T is not None]
    return np.array([w for w, _ in rows], dtype=float), np.array([T for _, T in rows], dtype=float).reshape(-1, 4, 4)


def damaged_message(path, detail) -> str:
    """One line: the log is damaged, nothing was changed, what to do."""
    return (f"{path}: the measurement log is damaged (SQLite: {detail}); nothing was changed or rewritten: restore "
            f"it from a backup, or recover what is readable into a new log with "
            f"`sqlite3 {path} .recover | sqlite3 recovered.sqlite`")


def check_integrity(db, path) -> None:
    """DataError (one line, :func:`damaged_message`) when SQLite's ``PRAGMA integrity_check`` of
    the open connection ``db`` finds damage or cannot read the file at all (a page of random
    bytes: ``sqlite3.DatabaseError``). Reads only."""
    try:
        rows = db.execute("PRAGMA integrity_check").fetchall()
    except sqlite3.OperationalError as exc:
        if "locked" in str(exc) or "busy" in str(exc):
            raise StorageError(f"{path}: cannot open the measurement log ({exc})") from None
        raise DataError(damaged_message(path, exc)) from None
    except sqlite3.DatabaseError as exc:
        raise DataError(damaged_message(path, exc)) from None
    if rows != [("ok",)]:
        detail = str(rows[0][0]) if rows else "no answer"
        more = f" and {len(rows) - 1} more" if len(rows) > 1 else ""
        raise DataError(damaged_message(path, f"{detail}{more}"))


def read_only_uri(path) -> str:
    """The SQLite URI that reads the log at ``path`` without writing anything beside it. ``mode=ro``
    alone does not: on a log in WAL mode whose writer has closed (no ``-wal`` file), a reader creates
    ``-wal`` and ``-shm`` and, read-only, cannot remove them. Such a log is read ``immutable`` (all of it
    is in the file); a log with a ``-wal`` (a writer at work, or killed) is read ``mode=ro``, through it."""
    path = Path(path)
    uri = path.resolve().as_uri() + "?mode=ro"
    try:
        with open(path, "rb") as f:
            header = f.read(100)
    except OSError:
        return uri
    wal_mode = len(header) == 100 and header[:16] == b"SQLite format 3\x00" and header[18:20] == b"\x02\x02"
    return uri + "&immutable=1" if wal_mode and not Path(f"{path}-wal").exists() else uri


@contextlib.contextmanager
def read_only_log(path, *, check: bool = False, timeout_s: float = 5.0):
    """A read-only connection to the measurement log at ``path`` that writes nothing into its folder
    (:func:`read_only_uri`); ``check``: SQLite's integrity check first (:func:`check_integrity`).
    StorageError (one line) when it cannot be opened or read now (busy; a writer started during an
    immutable read), DataError when it is no log or damaged. The one reader of the log for those who
    must not write it: RunFolder's questions, `campaign watch`."""
    uri = read_only_uri(path)
    try:
        db = sqlite3.connect(uri, uri=True, timeout=timeout_s)
    except sqlite3.Error as exc:
        raise StorageError(f"{path}: cannot open ({exc})") from None
    try:
        if check:
            check_integrity(db, path)
        yield db
    except sqlite3.OperationalError as exc:
        raise StorageError(f"{path}: cannot read ({exc})") from None
    except sqlite3.DatabaseError as exc:
        if uri.endswith("immutable=1") and Path(f"{path}-wal").exists():  # a writer began meanwhile
            raise StorageError(f"{path}: changed while read ({exc})") from None
        raise DataError(f"{path}: not a measurement log ({exc})") from None
    finally:
        db.close()


def open_run(run_dir, *, create: bool = False) -> MeasurementStore:
    """The measurement log of a run folder."""
    run_dir = Path(run_dir)
    if not create and not (run_dir / MEASUREMENTS_FILE).is_file():
        raise DataError(f"{run_dir}: no {MEASUREMENTS_FILE} (run `campaign run` or `campaign import` first)")
    run_dir.mkdir(parents=True, exist_ok=True)
    return MeasurementStore(run_dir / MEASUREMENTS_FILE)


def import_csv(csv_path, run_dir, robot=None) -> int:
    """Create ``run_dir/measurements.sqlite`` from a measured-pose CSV. Returns the pose count.

    The CSV is validated whole before anything is written (see :func:`write_imported`).
    `campaign import` goes through :func:`campaign.measure.importer.import_run`, which also
    records the run's robot and holds the run's lock.
    """
    from campaign.measure.csvio import read_measured_csv

    poses = read_measured_csv(csv_path, robot)
    return write_imported(poses, run_dir, source={"kind": "import", "csv": str(Path(csv_path).resolve())},
                          robot=robot)


def write_imported(poses, run_dir, *, source: dict, robot=None) -> int:
    """Create ``run_dir/measurements.sqlite`` holding ``poses`` (MeasuredPoses). The log is
    written to a temporary file and moved into place, so a failure (a full disk included)
    leaves the run folder as it was. Refuses a folder that already holds a log."""
    run_dir = Path(run_dir)
    target = run_dir / MEASUREMENTS_FILE
    if target.exists():
        raise DataError(f"{run_dir}: already holds {MEASUREMENTS_FILE}; import into a new run folder")
    chunks = [poses] if isinstance(poses, MeasuredPoses) else poses
    tmp = run_dir / (MEASUREMENTS_FILE + ".partial")
    n = 0
    try:
        run_dir.mkdir(parents=True, exist_ok=True)
        tmp.unlink(missing_ok=True)
        with MeasurementStore(tmp) as store:
            store.set_meta("source", source)
            if robot is not None:
                store.record_robot(robot)
            for part in chunks:
                if n == 0:
                    store.set_meta("kind", part.kind)
                    store.set_meta("frame", part.frame)
                    if part.marker_positions is not None:
                        store.set_meta("marker_positions", np.asarray(part.marker_positions).tolist())
                store.add_poses(_records(part, n))
                n += len(part)
        tmp.replace(target)
    except OSError as exc:
        raise StorageError(f"{target}: cannot write ({exc.strerror or exc}); nothing was imported") from None
    finally:
        tmp.unlink(missing_ok=True)
    return n


def _num(v):
    """None for a missing value (NaN), else float."""
    return None if v is None or not np.isfinite(v) else float(v)


def _records(poses: MeasuredPoses, seq0: int) -> list:
    rv = poses.rotvec if poses.has_orientation else np.full((len(poses), 3), np.nan)
    out = []
    for i in range(len(poses)):
        refl = {}
        if poses.markers is not None:
            for k, p in enumerate(poses.markers[i]):
                refl[f"m{k + 1}"] = (tuple(map(float, p)), "ok") if np.isfinite(p).all() else (None, "missed")
        out.append(PoseRecord(pose_id=int(poses.pose_id[i]), seq=seq0 + i, status="measured", q=tuple(poses.q[i]),
                              time_s=float(poses.time_s[i]), xyz=tuple(poses.xyz[i]), rotvec=tuple(rv[i]),
                              context={k: float(v[i]) for k, v in poses.context.items()}, reflectors=refl))
    return out
