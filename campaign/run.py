"""A run folder: one object that finds a run's configuration, robot, scene, effects,
measurement log and outputs. Every command and every library user goes through it.

Layout (DESIGN.md)::

    RUN/campaign.yaml          the run's configuration: robot (+ tool_frame, base_frame), scene, effects, ...
    RUN/plan/                  poses.csv, vias.csv, dropped.csv, summary.json, tour.png   (`campaign plan`)
    RUN/measurements.sqlite    the measurement log, with its robot's record                (`run`, `import`)
    RUN/calibration/           metrics.json, params.yaml, history.json, report.html        (`calibrate`)
    RUN/diagnose/              diagnosis.json, report.html                                 (`diagnose`)

RUN/plan, RUN/calibration and RUN/diagnose are links to one complete version each
(RUN/plans/<id>/, RUN/calibrations/<id>/, RUN/diagnoses/<id>/), replaced whole by
campaign.versioned (docs/files.md).
    RUN/sim/                   the simulated cell's own files (its truth: never read by plan/calibrate/diagnose)
    RUN/.lock                  held by the one command that writes into the run (RunFolder.lock)

A run remembers its robot in RUN/campaign.yaml; no command falls back to the default robot
for a run that records another.
"""

from __future__ import annotations

import contextlib
import fcntl
import functools
import json
import os
import sqlite3
import threading
import time
from pathlib import Path

from campaign.config import CampaignConfig, check_names, load_config, parse_config, write_run_config
from campaign.errors import ConfigError, DataError, RunBusy, RunHoldsMeasurements, StorageError
from campaign.fileio import atomic_write, read_yaml_mapping
from campaign.measure.store import MEASUREMENTS_FILE, read_only_log
from campaign.paths import DEFAULT_CONFIG

CONFIG_FILE = "campaign.yaml"
LOCK_FILE = ".lock"


def load_robot(spec, *, tool_frame=None, base_frame=None):
    """``RobotModel.load(spec, tool_frame=..., base_frame=...)`` (imported on first use)."""
    from campaign.model.robot import RobotModel

    return RobotModel.load(spec, tool_frame=tool_frame, base_frame=base_frame)


def same_robot(a, b) -> bool:
    """Two RobotModels of the same URDF with the same base and tool frames."""
    return (Path(a.urdf_path).resolve(), a.base_frame, a.tool_frame) == \
        (Path(b.urdf_path).resolve(), b.base_frame, b.tool_frame)


class RunFolder:
    """The run folder at ``path``.

    config: a campaign.yaml (path or :class:`CampaignConfig`) to use instead of
    RUN/campaign.yaml (``campaign run --config``); by default RUN/campaign.yaml, or, for a
    folder without one, the embedded default configuration.
    """

    def __init__(self, path, *, config=None):
        self.path = Path(path)
        self._config_override = config
        self._checked = False  # the log's integrity (campaign.measure.store.check_integrity)

    def __repr__(self) -> str:
        return f"RunFolder({str(self.path)!r})"

    # -- where things are -------------------------------------------------------------------
    @property
    def config_path(self) -> Path:
        return self.path / CONFIG_FILE

    @property
    def measurements_path(self) -> Path:
        return self.path / MEASUREMENTS_FILE

    @property
    def plan_dir(self) -> Path:
        return self.path / "plan"

    @property
    def poses_csv(self) -> Path:
        return self.plan_dir / "poses.csv"

    @property
    def calibration_dir(self) -> Path:
        return self.path / "calibration"

    @property
    def diagnose_dir(self) -> Path:
        return self.path / "diagnose"

    @property
    def sim_dir(self) -> Path:
        return self.path / "sim"

    @property
    def lock_path(self) -> Path:
        return self.path / LOCK_FILE

    @property
    def has_config(self) -> bool:
        return self.config_path.is_file()

    # -- what the run is made of --------------------------------------------------------------
    @functools.cached_property
    def config(self) -> CampaignConfig:
        """The validated configuration (every bad value one ConfigError line, before any work)."""
        if isinstance(self._config_override, CampaignConfig):
            return self._config_override
        if self._config_override is not None:
            return load_config(self._config_override)
        if self.has_config:
            cfg = load_config(self.config_path)
            if read_yaml_mapping(self.config_path).get("robot") is None:  # e.g. an emptied file
                cfg = self._recorded_robot_config(cfg)
            return cfg
        cfg = load_config(DEFAULT_CONFIG)
        self._check_recorded_robot(cfg)
        return cfg

    def _check_recorded_robot(self, cfg):
        """A folder without campaign.yaml whose log records another robot must not get the default."""
        recorded = self.meta("robot")
        if recorded is None:
            return
        default = load_robot(cfg.robot_spec)
        if recorded != default.name:
            raise ConfigError(f"{self.path}: its measurements record robot {recorded!r} but it has no {CONFIG_FILE}; "
                              f"write one with `robot: <name or path>`")

    def _recorded_robot_config(self, cfg):
        """``cfg`` for the robot the measurement log records (campaign.measure.robot_record),
        when it records one; else ``cfg`` as it is."""
        from campaign.measure.robot_record import META_KEY

        recorded = self.meta(META_KEY)
        if not recorded or not recorded.get("spec"):
            return cfg
        return cfg.with_robot(recorded["spec"], recorded.get("tool_frame"), recorded.get("base_frame"))

    @functools.cached_property
    def _robot(self):
        from campaign.measure.robot_record import META_KEY, check_same_robot

        cfg = self.config
        robot = load_robot(cfg.robot_spec, tool_frame=cfg.tool_frame, base_frame=cfg.base_frame)
        # the configuration names the robot the log was measured with, or the command is refused
        check_same_robot(self.meta(META_KEY), robot, self.measurements_path, cfg.path)
        return robot

    def robot(self):
        """The run's RobotModel: ``RobotModel.load(cfg.robot, tool_frame=..., base_frame=...)``,
        the robot path relative to the run's campaign.yaml."""
        return self._robot

    def check_recorded_robot(self) -> None:
        """ConfigError when a configuration given in place of RUN/campaign.yaml (``config=``)
        names another robot or frame than the one the run records."""
        if self._config_override is None or not self.has_config:
            return
        recorded = RunFolder(self.path)
        if not same_robot(self.robot(), recorded.robot()):
            raise ConfigError(f"{self.config.path}: robot {self.config.robot!r} is not the robot "
                              f"{recorded.config.robot!r} that {self.config_path} records")

    def scene(self):
        """The run's cell (campaign.plan.scene.Scene) in the run's robot's base frame F_I
        (:meth:`~campaign.plan.scene.Scene.placed`)."""
        from campaign.plan.scene import load_scene

        return load_scene(self.config.scene_path).placed(self.robot())

    @property
    def effects(self) -> tuple:
        """Effects enabled for calibration in the run's campaign.yaml; user effect files
        (``path/file.py:ClassName``) made absolute against that file's folder."""
        from campaign.effects.base import check_effect_joints, resolve_effect_spec, split_joints

        specs = tuple(resolve_effect_spec(e, self.config.dir) for e in self.config.effects)
        for spec in specs:  # a joint the robot lacks: the file and field named, like every other entry
            base, joints = split_joints(spec)
            if joints is not None:
                try:
                    check_effect_joints(joints, self.robot(), base)
                except ConfigError as exc:
                    raise ConfigError(f"{self.config.path}: effects: {exc}") from None
        return specs

    def last_calibration(self) -> dict | None:
        """What the run's current calibration fitted, read from its params.yaml (not from
        campaign.yaml, which a `calibrate --effects` does not change): {"calibration_id",
        "effects": (spec, ...), "path", "excluded_pose_ids": the reading faults it left out}; None when
        the run is not calibrated."""
        from campaign.versioned import calibration_folder

        path = (calibration_folder(self.path).current() or self.calibration_dir) / "params.yaml"
        if not path.is_file():
            return None
        params = read_yaml_mapping(path, DataError)
        block = params.get("effects") or {}
        if not isinstance(block, dict):
            raise DataError(f"{path}: effects: expected a mapping of effect names, got {block!r}")
        specs = tuple(str((v.get("spec") if isinstance(v, dict) else None) or k) for k, v in block.items())
        left_out = params.get("excluded_pose_ids") or []
        if not isinstance(left_out, list) or not all(isinstance(i, int) for i in left_out):
            raise DataError(f"{path}: excluded_pose_ids: expected a list of pose ids, got {left_out!r}")
        return {"calibration_id": params.get("calibration_id"), "effects": specs, "path": path,
                "excluded_pose_ids": tuple(left_out)}

    # -- the measurement log ------------------------------------------------------------------
    def store(self, *, create: bool = False):
        """The run's MeasurementStore (``create``: make the folder and the log if missing)."""
        from campaign.measure.store import open_run

        return open_run(self.path, create=create)

    @contextlib.contextmanager
    def _read_only_db(self):
        """A read-only connection to the log, or None when there is none (never creates files:
        campaign.measure.store.read_only_log)."""
        if not self.measurements_path.is_file():
            yield None
            return
        # once per RunFolder: a damaged log is one line, never rewritten
        with read_only_log(self.measurements_path, check=not self._checked) as db:
            self._checked = True
            yield db

    def stored_pose_count(self) -> int:
        """Poses with a stored outcome (measured or failed); 0 without a log."""
        with self._read_only_db() as db:
            if db is None or not _has_table(db, "poses"):
                return 0
            return int(db.execute("SELECT COUNT(*) FROM poses").fetchone()[0])

    def meta(self, key, default=None):
        """A value of the log's meta table (read-only), ``default`` when absent."""
        with self._read_only_db() as db:
            if db is None or not _has_table(db, "meta"):
                return default
            row = db.execute("SELECT value FROM meta WHERE key = ?", (key,)).fetchone()
            return default if row is None else json.loads(row[0])

    def cell_segments(self):
        """Which stored poses were measured on which recorded cell
        (campaign.measure.cell_identity.CellSegments; one segment for a run measured on one cell,
        imported, or without a log)."""
        from campaign.measure.cell_identity import cell_segments

        with self._read_only_db() as db:
            if db is None:
                return cell_segments(sqlite3.connect(":memory:"))
            recorded = db.execute("SELECT value FROM meta WHERE key = 'cell'").fetchone() \
                if _has_table(db, "meta") else None
            return cell_segments(db, None if recorded is None else json.loads(recorded[0]))

    def clock_s(self) -> float:
        """The campaign clock at the last thing stored (s; 0 without a log): a resumed campaign
        starts here, so the clock never runs backwards, even after the driver was killed."""
        if not self.measurements_path.is_file():
            return 0.0
        with self.store() as store:
            return store.clock_s()

    def refuse_if_measured(self, action: str, advice: str) -> None:
        """RunHoldsMeasurements (one line) when the log holds any pose: ``action`` would lose
        them; ``advice`` says what to do instead."""
        n = self.stored_pose_count()
        if n:
            raise RunHoldsMeasurements(f"{self.path} holds {n:,} measured poses; {action} would replace them, "
                                       f"so it refuses: {advice}")

    # -- one writer at a time ----------------------------------------------------------------
    def lock(self, command: str):
        """A context manager holding RUN/.lock (``flock``) for the block.

        Every command that writes into the run (plan, run, import, calibrate, diagnose, demo)
        holds it, so two of them never interleave their writes: a second one is refused at
        once, before it does any work, with one RunBusy line ``run RUN is busy: <command> pid
        N since <time>; ...``. The lock goes with its process: released on any exit, even
        kill -9, so a lock whose holder died is stale and the next command takes it over.
        Re-entrant within one process (the demo holds it while its steps take it again).
        When the block fails, the lock file is left as it was (removed again, with the run
        folder if that is empty, when this call created them), so a failed command leaves
        the folder unchanged."""
        return _hold(self.path, self.lock_path, f"run {self.path}", command)

    def sim_lock(self, command: str = "sim"):
        """A context manager holding RUN/sim/.lock, the simulated cell's own part of the run
        (RUN/sim/truth.yaml, estops.json), for the cell's lifetime: one cell per run, while
        a driver (``campaign run RUN --controller ...``) holds RUN/.lock beside it. As
        :meth:`lock` otherwise."""
        return _hold(self.sim_dir, self.sim_dir / LOCK_FILE, f"the simulated cell of run {self.path}", command)

    def lock_holder(self, *, sim: bool = False) -> dict | None:
        """Who holds RUN/.lock (``sim``: RUN/sim/.lock) now: ``{"pid", "command",
        "since_unix_s"}``, or None when no live process holds it (a lock file left by a dead
        process is stale and counts as free)."""
        try:
            fd = os.open(self.sim_dir / LOCK_FILE if sim else self.lock_path, os.O_RDWR)
        except OSError:
            return None
        try:
            try:
                fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
            except BlockingIOError:
                return _read_holder(fd)
            fcntl.flock(fd, fcntl.LOCK_UN)
            return None
        finally:
            os.close(fd)

    # -- writing the run's configuration --------------------------------------------------------
    def write_config(self, cfg: CampaignConfig) -> Path:
        """Make ``cfg`` (paths made absolute) the run's campaign.yaml."""
        path = write_run_config(cfg, self.path)
        self.__dict__.pop("config", None)
        self.__dict__.pop("_robot", None)
        return path

    def record_robot(self, spec: str, *, tool_frame=None, base_frame=None) -> Path:
        """Write RUN/campaign.yaml for a folder without one, recording its robot (import)."""
        doc = {"robot": str(spec), "tool_frame": tool_frame, "base_frame": base_frame, "effects": []}
        cfg = parse_config(doc, self.config_path)
        return self.write_config(cfg)

    def add_effects(self, names) -> tuple:
        """Enable effects in RUN/campaign.yaml (kept in order, no duplicates; a joint-indexed effect
        already there gets the new joints added to its list); the new list.

        The rest of the file is kept as it is (only its ``effects:`` key changes)."""
        names = check_names(list(names), "effects")
        if not self.has_config:
            raise ConfigError(f"{self.config_path}: no such file (the run has no configuration to add effects to)")
        from campaign.effects.base import merge_effects

        cfg = parse_config(read_yaml_mapping(self.config_path), self.config_path)  # refuse an invalid file
        return self.set_effects(merge_effects(cfg.effects, names, self.robot()))

    def set_effects(self, names) -> tuple:
        """Write exactly ``names`` as the effects of RUN/campaign.yaml (an effect taken out of the
        model, or a joint out of its list); the rest of the file is kept. Returns them."""
        names = check_names(list(names), "effects")
        if not self.has_config:
            raise ConfigError(f"{self.config_path}: no such file (the run has no configuration to set effects in)")
        from campaign.effects.base import effect_yaml

        doc = read_yaml_mapping(self.config_path)
        parse_config(doc, self.config_path)
        doc["effects"] = [effect_yaml(e) for e in names]
        parse_config(doc, self.config_path)
        import yaml

        atomic_write(self.config_path, yaml.safe_dump(doc, sort_keys=False))
        self.__dict__.pop("config", None)
        return names


def _has_table(db, name) -> bool:
    return db.execute("SELECT 1 FROM sqlite_master WHERE type = 'table' AND name = ?", (name,)).fetchone() is not None


def busy_message(label: str, holder: dict) -> str:
    """``run RUN is busy: <command> pid N since <local time>; ...`` (one line)."""
    since = holder.get("since_unix_s")
    when = time.strftime("%Y-%m-%d %H:%M:%S", time.localtime(since)) if isinstance(since, (int, float)) else "?"
    return (f"{label} is busy: {holder.get('command', '?')} pid {holder.get('pid', '?')} since {when}; "
            "one command writes a run at a time: wait for it to finish or stop it")


#: locks this process holds: resolved lock path -> [fd, depth] (re-entrant within a process)
_HELD: dict = {}
_HELD_GUARD = threading.Lock()


@contextlib.contextmanager
def _hold(folder: Path, lock_path: Path, label: str, command: str):
    """Hold the flock on ``lock_path`` (in ``folder``) for the block (see RunFolder.lock)."""
    key = str(lock_path.resolve())
    with _HELD_GUARD:
        held = _HELD.get(key)
        if held is not None:
            held[1] += 1
    if held is not None:
        try:
            yield
        finally:
            with _HELD_GUARD:
                held[1] -= 1
        return
    made_dirs = [d for d in (folder, *folder.parents) if not d.exists()]
    fd, made_file, previous = _acquire(folder, lock_path, label, command)
    with _HELD_GUARD:
        _HELD[key] = [fd, 1]
    ok = False
    try:
        yield
        ok = True
    finally:
        with _HELD_GUARD:
            del _HELD[key]
        if not ok and made_file:
            with contextlib.suppress(OSError):
                lock_path.unlink()
            for d in made_dirs:  # innermost first; only empty ones go
                with contextlib.suppress(OSError):
                    d.rmdir()
        elif not ok:  # the lock file as it was (the last holder's record)
            with contextlib.suppress(OSError):
                os.ftruncate(fd, 0)
                os.pwrite(fd, previous, 0)
        os.close(fd)  # releases the flock


def _acquire(folder: Path, lock_path: Path, label: str, command: str):
    """(fd holding the flock on ``lock_path``, whether this call created the file, the file's
    previous bytes); RunBusy when another process holds it."""
    try:
        folder.mkdir(parents=True, exist_ok=True)
    except OSError as exc:
        raise StorageError(f"{folder}: cannot create the run folder ({exc.strerror})") from None
    for _ in range(100):
        made = False
        try:
            try:
                fd = os.open(lock_path, os.O_RDWR | os.O_CREAT | os.O_EXCL, 0o644)
                made = True
            except FileExistsError:
                fd = os.open(lock_path, os.O_RDWR)
        except FileNotFoundError:
            continue  # removed between the two opens: try again
        except OSError as exc:
            raise StorageError(f"{lock_path}: cannot open the run lock ({exc.strerror})") from None
        try:
            fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
        except BlockingIOError:
            holder = _read_holder(fd)
            os.close(fd)
            raise RunBusy(busy_message(label, holder)) from None
        try:  # the file may have been removed by a failing holder while we waited: lock the one on disk
            same = os.stat(lock_path).st_ino == os.fstat(fd).st_ino
        except FileNotFoundError:
            same = False
        if not same:
            os.close(fd)
            continue
        previous = os.pread(fd, 4096, 0)
        info = json.dumps({"pid": os.getpid(), "command": command, "since_unix_s": time.time()})
        os.ftruncate(fd, 0)
        os.pwrite(fd, info.encode(), 0)
        return fd, made, previous
    raise StorageError(f"{lock_path}: the run lock keeps disappearing")


def _read_holder(fd) -> dict:
    try:
        return json.loads(os.pread(fd, 4096, 0).decode() or "{}")
    except (OSError, ValueError):
        return {}


__all__ = ["RunFolder", "busy_message", "load_robot", "same_robot", "CONFIG_FILE", "MEASUREMENTS_FILE"]
