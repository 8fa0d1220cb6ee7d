"""Reading and writing files so that a reader never sees half of one.

:func:`atomic_write` is the one write-to-partial-then-rename of the package: the text goes to
``NAME.partial`` beside the target and replaces it with one ``rename`` (atomic on POSIX), so
a crash, a full disk or Ctrl-C leaves either the old file or the new one. Errors name the
file and are :class:`campaign.errors.StorageError` (one line, never a traceback).

:func:`strict_json` is the one JSON writer of the package: every JSON file and every
``--json`` output is strict JSON (RFC 8259: no ``NaN``, no ``Infinity``), a value that is not a
finite number written as ``null`` with its reason beside it (docs/files.md).
"""

from __future__ import annotations

import contextlib
import json
import math
import os
from pathlib import Path

import yaml

from campaign.errors import ConfigError, StorageError


def _storage_error(path, exc: OSError) -> StorageError:
    err = StorageError(f"{path}: cannot write ({exc.strerror or exc}); the previous file, if any, is unchanged")
    err.cause_os_error = exc  # a version being written (versioned.py) says it as the version's failure
    err.filename = str(path)
    return err


def check_writable_file(path, what: str | None = None, example: str = "out") -> Path:
    """``path`` as a Path, or a StorageError when it names a directory (a file's name is needed:
    nothing is written, no ``.partial`` left); ``what``: the option that named it; ``example``:
    a file name to suggest inside that directory."""
    path = Path(path)
    if path.is_dir():
        given = f"{what} {path}" if what else str(path)
        raise StorageError(f"{given}: is a directory; name the file to write (e.g. {path / example})")
    return path


@contextlib.contextmanager
def atomic_open(path, mode: str = "w", **kwargs):
    """Open ``path.partial`` for writing; on a clean exit it replaces ``path``, on an error
    it is removed and ``path`` is left as it was (a directory at ``path``: a StorageError before
    anything is opened). Yields the open file."""
    path = check_writable_file(path)
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


#: the key beside a mapping's values that were not finite numbers: {key: why it is null}
NULL_REASONS_KEY = "null_reasons"


def _non_finite_reason(value: float) -> str:
    what = "not a number (NaN)" if math.isnan(value) else f"{'+' if value > 0 else '-'}infinity"
    return f"{what}: not computable from these data"


def finite_json(obj):
    """``obj`` with every float that is not finite (NaN, ±inf) replaced by None; in a mapping
    the reason goes beside it, under ``null_reasons`` ({key: reason}). numpy scalars and arrays
    become plain numbers and lists; tuples become lists."""
    if isinstance(obj, bool) or obj is None or isinstance(obj, (str, int)):
        return obj
    if isinstance(obj, float):
        return obj if math.isfinite(obj) else None
    if isinstance(obj, dict):
        out, reasons = {}, {}
        for key, value in obj.items():
            if isinstance(value, float) and not math.isfinite(value) or _is_np_nonfinite(value):
                reasons[str(key)] = _non_finite_reason(float(value))
                out[key] = None
            else:
                out[key] = finite_json(value)
        if reasons:
            out[NULL_REASONS_KEY] = {**(out.get(NULL_REASONS_KEY) or {}), **reasons}
        return out
    if isinstance(obj, (list, tuple)):
        return [finite_json(v) for v in obj]
    tolist = getattr(obj, "tolist", None)  # numpy scalars and arrays
    if tolist is not None:
        return finite_json(tolist())
    return obj


def _is_np_nonfinite(value) -> bool:
    import numbers

    return isinstance(value, numbers.Real) and not isinstance(value, (bool, int, float)) and \
        not math.isfinite(float(value))


def strict_json(obj, *, indent=2, **kwargs) -> str:
    """``obj`` as strict JSON text (:func:`finite_json` first, then ``allow_nan=False``, so a
    value that slipped through raises rather than writes ``NaN``)."""
    return json.dumps(finite_json(obj), allow_nan=False, indent=indent, **kwargs)


def atomic_write_json(path, obj) -> Path:
    """Write ``obj`` as strict JSON (:func:`strict_json`) to ``path`` atomically."""
    return atomic_write(path, strict_json(obj) + "\n")


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
