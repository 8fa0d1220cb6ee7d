"""Output folders that change whole or not at all: ``RUN/calibration``, ``RUN/diagnose``, ``RUN/plan``.

Each is a symbolic link to one complete version of the stage's outputs::

    RUN/calibration  ->  calibrations/<calibration_id>/   (metrics.json, params.yaml, report.html, ...)
    RUN/diagnose     ->  diagnoses/<diagnosis_id>/         (diagnosis.json, report.html, ...)
    RUN/plan         ->  plans/<plan_id>/                  (poses.csv, summary.json, tour.png, ...)

A command writes its outputs into ``<store>/.<id>.partial/``, renames that folder to
``<store>/<id>/`` when every file is written, and then points the link at it by renaming a
new link over the old one. ``rename(2)`` is atomic on POSIX: a reader, and a process killed
at any instant (SIGKILL included), sees the previous version whole or the new one whole,
never a mix; until the last rename the previous version stays the one in use. Leftover
``.partial`` folders of a killed process are removed by the next command that writes the
same outputs (it holds the run's lock, so no other writer can own them). Nothing is copied:
a version is written once, in place, and published by two renames.

A reader that opens several files of one version resolves the link once
(:meth:`VersionedFolder.current`) and reads them all from that folder, so a version
published meanwhile cannot mix into what it reads. A folder of an older layout (a plain
``RUN/calibration/`` directory) is moved into the store as one version the first time a new
version is written (``<mtime>-legacy``); while that move is under way (between the two
renames) :meth:`current` finds it in the store.
"""

from __future__ import annotations

import contextlib
import os
import secrets
import shutil
import signal
import time
from dataclasses import dataclass
from pathlib import Path

from campaign.errors import StorageError

PARTIAL_SUFFIX = ".partial"


def new_id(when_unix_s: float | None = None) -> str:
    """A version id: UTC time to the second, then 6 random hex digits
    (``20261125T172155Z-3f9a1c``); ids sort by time."""
    stamp = time.strftime("%Y%m%dT%H%M%SZ", time.gmtime(time.time() if when_unix_s is None else when_unix_s))
    return f"{stamp}-{secrets.token_hex(3)}"


@dataclass(frozen=True)
class Version:
    """A version being written: its id and the folder its files go to (``<store>/.<id>.partial``)."""

    id: str
    path: Path


@dataclass(frozen=True)
class VersionedFolder:
    """``root/name``, a link to the current version in ``root/store``.

    keep: how many versions to keep after publishing one (the new one and the ``keep - 1``
    before it; None: every version, e.g. diagnoses, so that an earlier report stays readable).
    """

    root: Path
    name: str
    store: str
    keep: int | None = 2

    @property
    def link(self) -> Path:
        return Path(self.root) / self.name

    @property
    def store_dir(self) -> Path:
        return Path(self.root) / self.store

    # -- reading ----------------------------------------------------------------------------
    def current(self) -> Path | None:
        """The folder of the current version, resolved (None when there is none): the link's
        target; a plain folder of the older layout; or, when the link is missing, the newest
        complete version of the store (a move of an older layout cut short)."""
        link = self.link
        if link.is_symlink():
            target = link.resolve()
            return target if target.is_dir() else None
        if link.is_dir():
            return link.resolve()
        done = self.versions()
        return self.store_dir.joinpath(done[-1]).resolve() if done else None

    def current_id(self) -> str | None:
        """The current version's id (its folder's name), None when there is none."""
        cur = self.current()
        return None if cur is None or cur.parent != self.store_dir.resolve() else cur.name

    def versions(self) -> list:
        """Ids of the complete versions in the store, oldest first."""
        try:
            names = os.listdir(self.store_dir)
        except OSError:
            return []
        return sorted(n for n in names if not n.startswith(".") and (self.store_dir / n).is_dir())

    # -- writing (the caller holds the run's lock) -----------------------------------------
    @contextlib.contextmanager
    def new_version(self, version_id: str | None = None):
        """Yield a :class:`Version` to write into; publish it when the block ends without an
        error; on an error (Ctrl-C included) remove it, leaving the current version as it was."""
        self.clean()
        vid = version_id or new_id()
        staging = self.store_dir / f".{vid}{PARTIAL_SUFFIX}"
        try:
            staging.mkdir(parents=True)
        except OSError as exc:
            raise StorageError(f"{staging}: cannot create ({exc.strerror or exc}); "
                               f"{self.link} is unchanged") from None
        ok = False
        try:
            yield Version(vid, staging)
            ok = True
        except (OSError, StorageError) as exc:  # a full disk, a file too large, ...: one line, the current version kept
            if isinstance(exc, StorageError):  # an atomic write inside the version (fileio): its OSError
                if getattr(exc, "cause_os_error", None) is None:
                    raise
                exc = exc.cause_os_error if exc.cause_os_error.filename else OSError(
                    exc.cause_os_error.errno, exc.cause_os_error.strerror, exc.filename)
            where = f" writing {Path(exc.filename).name}" if exc.filename else ""
            raise StorageError(f"{self.link}: cannot write the new version ({exc.strerror or exc}{where}); "
                               f"nothing of it was kept, the current one is unchanged") from None
        finally:
            if not ok:
                shutil.rmtree(staging, ignore_errors=True)
                with contextlib.suppress(OSError):
                    self.store_dir.rmdir()  # only when empty: a failed first version leaves no trace
        self.publish(Version(vid, staging))

    def publish(self, version: Version) -> Path:
        """Make a written version the current one (two renames, signals held back between
        them); then prune older versions (``keep``). Returns the link."""
        final = self.store_dir / version.id
        blocked = _block_signals()
        try:
            self._adopt_legacy()
            previous = self.current_id()
            try:
                os.rename(version.path, final)
                tmp_link = Path(self.root) / f".{self.name}.{version.id}.link"
                with contextlib.suppress(FileNotFoundError):
                    tmp_link.unlink()
                os.symlink(os.path.join(self.store, version.id), tmp_link)
                os.replace(tmp_link, self.link)
            except OSError as exc:
                shutil.rmtree(version.path, ignore_errors=True)
                raise StorageError(f"{self.link}: cannot publish the new version ({exc.strerror or exc}); "
                                   "the previous one is unchanged") from None
        finally:
            _unblock_signals(blocked)
        self._prune([previous, version.id])
        return self.link

    def clean(self) -> None:
        """Remove what a killed writer left: ``.partial`` folders and temporary links."""
        with contextlib.suppress(OSError):
            for name in os.listdir(self.store_dir):
                if name.startswith(".") and name.endswith(PARTIAL_SUFFIX):
                    shutil.rmtree(self.store_dir / name, ignore_errors=True)
        with contextlib.suppress(OSError):
            for name in os.listdir(self.root):
                if name.startswith(f".{self.name}.") and name.endswith(".link"):
                    with contextlib.suppress(OSError):
                        os.unlink(Path(self.root) / name)

    def _adopt_legacy(self) -> None:
        """A plain folder at ``link`` (the older layout) becomes a version of the store."""
        link = self.link
        if link.is_symlink() or not link.is_dir():
            return
        legacy = new_id(link.stat().st_mtime).rsplit("-", 1)[0] + "-legacy"
        self.store_dir.mkdir(parents=True, exist_ok=True)
        os.rename(link, self.store_dir / legacy)  # until the link exists, current() finds it here

    def _prune(self, recent) -> None:
        """Keep the ``keep`` most recent of ``recent`` (ids, oldest first; None skipped)."""
        if self.keep is None:
            return
        keep = {v for v in recent if v is not None}
        keep = set(sorted(keep, key=list(recent).index)[-self.keep:])
        for v in self.versions():
            if v not in keep:
                shutil.rmtree(self.store_dir / v, ignore_errors=True)


def _block_signals():
    """Hold back SIGINT and SIGTERM (main thread only), so that the renames of a publication
    run to their end; returns what to restore."""
    try:
        return signal.pthread_sigmask(signal.SIG_BLOCK, {signal.SIGINT, signal.SIGTERM})
    except (ValueError, OSError, AttributeError):
        return None


def _unblock_signals(previous) -> None:
    if previous is not None:
        signal.pthread_sigmask(signal.SIG_SETMASK, previous)


def calibration_folder(run_dir) -> VersionedFolder:
    """RUN/calibration -> calibrations/<calibration_id> (the current and the previous kept)."""
    return VersionedFolder(Path(run_dir), "calibration", "calibrations", keep=2)


def diagnosis_folder(run_dir) -> VersionedFolder:
    """RUN/diagnose -> diagnoses/<diagnosis_id> (every diagnosis kept: a report stays readable)."""
    return VersionedFolder(Path(run_dir), "diagnose", "diagnoses", keep=None)


def plan_folder(run_dir) -> VersionedFolder:
    """RUN/plan -> plans/<plan_id> (the current and the previous kept)."""
    return VersionedFolder(Path(run_dir), "plan", "plans", keep=2)
