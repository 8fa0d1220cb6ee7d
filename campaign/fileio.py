"""Reading and writing files so that a reader never sees half of one.

:func:`atomic_write` is the one write-to-partial-then-rename of the package: the text goes to
``NAME.partial`` beside the target and replaces it with one ``rename`` (atomic on POSIX), so
a crash, a full disk or Ctrl-C leaves either the old file or the new one. Errors name the
file and are :class:`campaign.errors.StorageError` (one line, never a traceback).
"""

from __future__ import annotations

import contextlib
import os
from pathlib import Path

import yaml

from campaign.errors import ConfigError, StorageError


def _storage_error(path, exc: OSError) -> StorageError:
    return StorageError(f"{path}: cannot write ({exc.strerror or exc}); the previous file, if any, is unchanged")


@contextlib.contextmanager
def atomic_open(path, mode: str = "w", **kwargs):
    """Open ``path.partial`` for writing; on a clean exit it replaces ``path``, on an error
    it is removed and ``path`` is left as it was. Yields the open file."""
    path = Path(path)
    tmp = path.with_name(path.name + ".partial")
    try:
        path.parent.mkdir(parents=True, exist_ok=True)
        fh = open(tmp, mode, **kwargs)
    except OSError as exc:
        raise _storage_error(path, exc) from None
    ok = False
    try:
        with fh:
            yield fh
        os.replace(tmp, path)
        ok = True
    except OSError as exc:
        raise _storage_error(path, exc) from None
    finally:
        if not ok:
            with contextlib.suppress(OSError):
                tmp.unlink()


def atomic_write(path, data) -> Path:
    """Write ``data`` (str or bytes) to ``path`` atomically; returns ``path``."""
    with atomic_open(path, "wb" if isinstance(data, bytes) else "w") as fh:
        fh.write(data)
    return Path(path)


def read_yaml_mapping(path, error=ConfigError) -> dict:
    """A YAML file whose top level is a mapping (an empty file is {}); ``error`` (an exception
    class) names the file on any failure."""
    path = Path(path)
    try:
        doc = yaml.safe_load(path.read_text())
    except OSError as exc:
        raise error(f"{path}: cannot read ({exc.strerror})") from None
    except UnicodeDecodeError:
        raise error(f"{path}: not a text file (not UTF-8)") from None
    except yaml.YAMLError as exc:
        raise error(f"{path}: not valid YAML ({str(exc).splitlines()[0]})") from None
    if doc is None:
        return {}
    if not isinstance(doc, dict):
        raise error(f"{path}: expected a mapping at the top level")
    return doc
