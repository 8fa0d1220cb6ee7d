"""A laser tracker's log read in blocks of bytes, so memory does not grow with the log.

The log is a delimited text file with a header line: a time column (``time_s``, s on any clock,
or ``time`` / ``timestamp`` in ISO 8601, or in s when it holds numbers), ``x, y, z`` and
optionally ``target`` (the reflector measured on that row, one of the robot's reflector names).
Other columns are ignored; ``columns`` maps a file's own names (``{column in the file: name
used}``, campaign.measure.csvio.parse_columns).
Rows with an empty or non-finite coordinate (the beam was lost), or an empty ``target``, are no
measurement of a reflector and are dropped.

A block of rows whose time and coordinates are numbers is parsed by numpy in C (loadtxt; a last
``target`` column by comparing each line's end with the names; ISO 8601 stamps of one form at once);
anything else (a malformed row, empty fields) goes line by line, and a bad value is one
:class:`DataError` naming the file, the row and the column.
"""

from __future__ import annotations

import io
import warnings
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from campaign.errors import DataError

#: bytes read at a time: large enough for numpy's parser to run at full speed, small enough that
#: a block's arrays (a few tens of MB) never matter
BLOCK_BYTES = 8 << 20
TIME_S_COLUMNS = ("time_s", "t_s")
TIME_ISO_COLUMNS = ("time", "timestamp", "datetime", "date_time")
DELIMITERS = (",", ";", "\t")


@dataclass(frozen=True)
class LogLayout:
    """Where a log keeps what is read: column indices, the time's form, the length unit."""

    path: Path
    delimiter: str
    header: tuple
    time_col: int
    time_iso: bool
    xyz_cols: tuple
    target_col: int | None
    #: the reflector names a ``target`` value may take, in code order (code = index)
    targets: tuple
    length_scale: float
    #: the header's row in the file (1-based; comment lines before it)
    header_row: int = 1
    #: ``targets`` are the log's own names (none of them the robot's), in order of appearance:
    #: campaign.program.stream.importer assigns them to the robot's reflectors
    aliases: bool = False

    @property
    def n_cols(self) -> int:
        return len(self.header)


@dataclass(frozen=True)
class LogChunk:
    """Consecutive measured rows: t (n,) s, p (n, 3) m in the log's frame, target (n,) int16
    (the reflector's code, 0 without a target column); ``rows`` the file rows read so far."""

    t: np.ndarray
    p: np.ndarray
    target: np.ndarray
    rows: int


def read_layout(path, *, length_unit: str = "m", columns: dict | None = None, targets=()) -> LogLayout:
    """The layout of the log ``path`` from its header line; DataError naming what is missing."""
    path = Path(path)
    if not path.is_file():
        raise DataError(f"{path}: no such log")
    line, header_row = "", 0
    with open(path, "rb") as f:
        for raw in f:  # comment lines (``#``) and blank lines before the header are the software's notes
            header_row += 1
            try:
                line = raw.decode("utf-8-sig").strip()
            except UnicodeDecodeError:
                raise DataError(f"{path}: row {header_row}: not text (expected a header line such as "
                                "time_s,x,y,z)") from None
            if line and not line.startswith("#"):
                break
            line = ""
    if not line:
        raise DataError(f"{path}: empty (expected a header line such as time_s,x,y,z)")
    delim = next((d for d in DELIMITERS if d in line), ",")
    header = tuple(h.strip() for h in line.split(delim))
    rename = dict(columns or {})
    missing_src = [c for c in rename if c not in header]
    if missing_src:
        raise DataError(f"{path}: --columns names {', '.join(missing_src)}, not in the header ({', '.join(header)})")
    names = [rename.get(h, h) for h in header]
    if len(set(names)) != len(names):
        dup = sorted({n for n in names if names.count(n) > 1})
        raise DataError(f"{path}: column {', '.join(dup)} appears twice in the header")

    def col(name):
        return names.index(name) if name in names else None

    time_col, iso = None, False
    for n in TIME_S_COLUMNS:
        if col(n) is not None:
            time_col = col(n)
            break
    if time_col is None:
        for n in TIME_ISO_COLUMNS:
            if col(n) is not None:
                time_col, iso = col(n), not _first_value_is_number(path, delim, col(n), header_row)
                break
    if time_col is None:
        raise DataError(f"{path}: no time column (time_s in s, or time/timestamp in ISO 8601) in the header "
                        f"({', '.join(header)}); map yours with --columns time_s=COLUMN")
    xyz = tuple(col(c) for c in "xyz")
    if None in xyz:
        miss = [c for c, i in zip("xyz", xyz) if i is None]
        raise DataError(f"{path}: no column {', '.join(miss)} in the header ({', '.join(header)}); "
                        "map yours with --columns x=COLUMN,...")
    if length_unit not in ("m", "mm"):
        raise DataError(f"--length-unit must be m or mm, got {length_unit!r}")
    target_col = col("target")
    targets = tuple(targets)
    aliases = False
    if target_col is not None and targets:
        seen = _first_targets(path, delim, target_col, header_row)
        if seen and not set(seen) & set(targets) and len(seen) <= len(targets):
            # the software's own names for the reflectors: which is which comes from the geometry
            targets, aliases = seen, True
    return LogLayout(path, delim, header, time_col, iso, xyz, target_col, targets,
                     1e-3 if length_unit == "mm" else 1.0, header_row, aliases)


def _first_targets(path, delim, column, header_row, max_bytes: int = 1 << 20) -> tuple:
    """The distinct non-empty values of the target ``column`` in the log's first ``max_bytes``, in
    order of appearance."""
    seen = {}
    with open(path, "rb") as f:
        for _ in range(header_row):
            f.readline()
        data = f.read(max_bytes)
        lines = data.decode("utf-8", errors="replace").splitlines()
        for raw in lines if len(data) < max_bytes else lines[:-1]:  # not a line cut by the read
            cells = raw.strip().split(delim)
            if len(cells) > column and cells[column].strip():
                seen.setdefault(cells[column].strip(), None)
    return tuple(seen)


def _first_value_is_number(path, delim, column, header_row) -> bool:
    """Whether the first data row's ``column`` is a number (a ``time`` column in s, not ISO 8601)."""
    with open(path, "rb") as f:
        for _ in range(header_row):
            f.readline()
        for raw in f:
            line = raw.decode("utf-8", errors="replace").strip()
            if line:
                try:
                    float(line.split(delim)[column])
                    return True
                except (ValueError, IndexError):
                    return False
    return False


def iter_log(layout: LogLayout, *, block_bytes: int = BLOCK_BYTES, progress=None):
    """The log's measured rows as :class:`LogChunk` s, in file order. ``progress``: callable
    receiving the fraction of the file read (0..1)."""
    size = max(layout.path.stat().st_size, 1)
    done = 0
    row = layout.header_row
    with open(layout.path, "rb") as f:
        for _ in range(layout.header_row):
            done += len(f.readline())
        tail = b""
        while True:
            data = f.read(block_bytes)
            if not data:
                break
            done += len(data)
            data = tail + data
            cut = data.rfind(b"\n")
            if cut < 0:
                tail = data
                continue
            tail, data = data[cut + 1:], data[:cut + 1]
            chunk = _parse(layout, data, row)
            row += data.count(b"\n")
            if chunk is not None:
                yield chunk
            if progress is not None:
                progress(done / size)
        if tail.strip():
            chunk = _parse(layout, tail + b"\n", row)
            if chunk is not None:
                yield chunk
    if progress is not None:
        progress(1.0)


def _parse(layout: LogLayout, data: bytes, row0: int) -> LogChunk | None:
    """One block of whole lines (row0: the file row before its first line)."""
    if b"\r" in data:
        data = data.replace(b"\r", b"")
    fast = _parse_numeric(layout, data)
    if fast is None:
        t, vals, g = _parse_lines(layout, data, row0)
    else:
        t, vals, g = fast
    p = vals * layout.length_scale
    ok = np.isfinite(p).all(axis=1) & np.isfinite(t) & (g >= 0)
    rows = row0 + data.count(b"\n")
    if not ok.all():
        t, p, g = t[ok], p[ok], g[ok]
    if len(t) == 0:
        return None
    return LogChunk(t, np.ascontiguousarray(p), g, rows)


def _parse_numeric(layout: LogLayout, data: bytes):
    """numpy's C parser (loadtxt) on a block of whole lines whose time and x, y, z are numbers, the
    target column (when it is the last) decoded by comparing each line's end with the reflector
    names; None when the block is anything else (then it is read line by line)."""
    n_lines = data.count(b"\n")
    if b"\n\n" in data or data.startswith(b"\n") or n_lines == 0:
        return None  # an empty line: the line reader knows what it means
    cols = [*layout.xyz_cols] if layout.time_iso else [layout.time_col, *layout.xyz_cols]
    buf = data
    g = np.zeros(n_lines, dtype=np.int16)
    if layout.target_col is not None:
        if layout.target_col == layout.n_cols - 1:
            g = _target_codes(np.frombuffer(data, dtype=np.uint8), layout)
            if g is None:
                return None
        else:  # names to their codes, then a number like the others
            d = layout.delimiter.encode()
            for code, name in enumerate(layout.targets):
                nb, cb = name.encode(), str(code).encode()
                buf = (b"\n" + buf).replace(b"\n" + nb + d, b"\n" + cb + d)[1:] if layout.target_col == 0 \
                    else buf.replace(d + nb + d, d + cb + d)
            cols.append(layout.target_col)
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        try:
            a = np.loadtxt(io.BytesIO(buf), delimiter=layout.delimiter, usecols=cols, dtype=float, ndmin=2,
                           comments=None, encoding="utf-8")
        except (ValueError, Warning):
            return None
    if a.shape[0] != n_lines:
        return None
    if layout.time_iso:
        t = _iso_block(layout, buf, n_lines)
        if t is None:
            return None
        a = np.column_stack([t, a])
    if a.shape[1] == 5:
        codes = a[:, 4]
        if not np.isin(codes, np.arange(len(layout.targets))).all():
            return None
        g = codes.astype(np.int16)
    return a[:, 0].copy(), a[:, 1:4].copy(), g


def _iso_block(layout: LogLayout, buf: bytes, n_lines: int):
    """The block's ISO 8601 time stamps as s since 1970 (UTC when they say their offset), all at
    once when they share one form (``Z``, one ``+HH:MM`` or none); None otherwise."""
    try:
        stamps = np.loadtxt(io.BytesIO(buf), delimiter=layout.delimiter, usecols=[layout.time_col], dtype="U40",
                            comments=None, encoding="utf-8", ndmin=1)
    except ValueError:
        return None
    if len(stamps) != n_lines:
        return None
    stamps = np.char.strip(stamps)
    first = str(stamps[0])
    offset = 0.0
    if first.endswith(("Z", "z")):
        suffix = first[-1]
    elif len(first) > 6 and first[-6] in "+-" and first[-3] == ":" and first[-5:-3].isdigit() and first[-2:].isdigit():
        suffix = first[-6:]
        offset = (1.0 if suffix[0] == "+" else -1.0) * (int(suffix[1:3]) * 3600 + int(suffix[4:6]) * 60)
    else:
        suffix = ""
    if suffix:
        if not np.char.endswith(stamps, suffix).all():
            return None
        lengths = np.char.str_len(stamps)
        stamps = np.array([s[:-len(suffix)] for s in stamps]) if (lengths != lengths[0]).any() \
            else stamps.astype(f"U{int(lengths[0]) - len(suffix)}")
    try:
        return np.char.replace(stamps, " ", "T").astype("datetime64[ns]").astype("int64") * 1e-9 - offset
    except ValueError:
        return None


def _target_codes(arr: np.ndarray, layout: LogLayout):
    """Each line's reflector code from its last field (the name ends the line, spaces before it
    allowed; -1 for an empty field), (n_lines,) int16; None when a line ends in none of the names."""
    nl = np.flatnonzero(arr == 10)
    codes = np.full(len(nl), -1, dtype=np.int16)
    before = (ord(layout.delimiter), ord(" "))
    for code, name in enumerate(sorted(layout.targets, key=len, reverse=True)):
        nb = name.encode()
        at = nl - len(nb)
        if len(at) == 0 or at.min() < 1:
            return None
        ok = (codes < 0) & np.isin(arr[at - 1], before)
        for i, ch in enumerate(nb):
            ok &= arr[at + i] == ch
        codes[ok] = layout.targets.index(name)
    empty = arr[nl - 1] == ord(layout.delimiter)  # no reflector named (in motion): the row is dropped
    return None if ((codes < 0) & ~empty).any() else codes


def _parse_lines(layout: LogLayout, data: bytes, row0: int):
    """Line by line: empty coordinates are NaN (no measurement); anything unreadable is one error."""
    path, delim = layout.path, layout.delimiter
    t, vals, g = [], [], []
    code = {name: k for k, name in enumerate(layout.targets)}
    iso = []
    for k, raw in enumerate(data.decode("utf-8", errors="replace").split("\n")):
        line = raw.strip()
        if not line:
            continue
        row = row0 + k + 1
        cells = line.split(delim)
        if len(cells) != layout.n_cols:
            raise DataError(f"{path}: row {row} has {len(cells)} fields, expected {layout.n_cols} "
                            f"({','.join(layout.header)})")
        xyz = []
        for c in layout.xyz_cols:
            cell = cells[c].strip()
            try:
                xyz.append(float(cell) if cell else np.nan)
            except ValueError:
                raise DataError(f"{path}: row {row}, column {layout.header[c]}: not a number ({cell!r})") from None
        tc = cells[layout.time_col].strip()
        if layout.time_iso:
            iso.append((row, tc))
            t.append(0.0)
        else:
            try:
                t.append(float(tc))
            except ValueError:
                raise DataError(f"{path}: row {row}, column {layout.header[layout.time_col]}: not a time in s "
                                f"({tc!r}; ISO 8601 time stamps go in a column named time or timestamp)") from None
        if layout.target_col is not None:
            name = cells[layout.target_col].strip()
            if not name:  # no reflector named (the tracker in motion, say): no measurement of one
                g.append(-1)
                vals.append(xyz)
                continue
            if name not in code:
                whose = "the log's first reflectors" if layout.aliases else "the robot's reflectors"
                raise DataError(f"{path}: row {row}, column {layout.header[layout.target_col]}: {name!r} is not one "
                                f"of {whose} ({', '.join(layout.targets)}); name the log's reflectors with "
                                "--targets REFLECTOR=NAME,...")
            g.append(code[name])
        else:
            g.append(0)
        vals.append(xyz)
    t = np.array(t, dtype=float)
    if layout.time_iso and iso:
        t = iso_seconds(path, layout.header[layout.time_col], iso)
    return t, np.array(vals, dtype=float).reshape(-1, 3), np.array(g, dtype=np.int16)


def iso_seconds(path, column, cells) -> np.ndarray:
    """ISO 8601 time stamps [(row, text), ...] as s since 1970 (UTC when the stamp says its
    offset, ``Z`` or ``+HH:MM``; else the stamps' own local clock)."""
    texts, offsets = [], []
    for row, s in cells:
        off = 0.0
        if s.endswith(("Z", "z")):
            s = s[:-1]
        elif len(s) > 6 and s[-6] in "+-" and s[-3] == ":" and "T" in s[:-6] + " ":
            try:
                sign = 1.0 if s[-6] == "+" else -1.0
                off = sign * (int(s[-5:-3]) * 3600 + int(s[-2:]) * 60)
            except ValueError:
                raise DataError(f"{path}: row {row}, column {column}: not an ISO 8601 time ({s!r})") from None
            s = s[:-6]
        texts.append(s.replace(" ", "T", 1))
        offsets.append(off)
    try:
        stamps = np.array(texts, dtype="datetime64[ns]")
    except ValueError:
        for (row, s), text in zip(cells, texts):
            try:
                np.datetime64(text, "ns")
            except ValueError:
                raise DataError(f"{path}: row {row}, column {column}: not an ISO 8601 time ({s!r})") from None
        raise
    return stamps.astype("int64") * 1e-9 - np.array(offsets)
