"""The measured-pose CSV (DESIGN.md): read with validation (streamed, bounded memory), write.

Header ``[pose_id,][time_s,]q1..qN`` and the measurement columns, whose kind the header tells:
``x,y,z,rx,ry,rz`` (6-D: the origin of the tool frame in m and the rotation vector of its
orientation in rad), ``x,y,z`` (one reflector), or ``m1_x,m1_y,m1_z,...,mk_z`` (raw reflector
centres, m; an empty cell where the tracker missed one). q as commanded (rad, m for prismatic
joints). Without ``pose_id`` the rows are numbered 0..n-1 in file order (and import says so).
Frame: the robot's base (or the tracker's, ``--frame tracker``). ``--angle-unit deg`` and
``--length-unit mm`` convert on reading. Extra named numeric columns are kept as context.
Real files as they come (docs/csv_import.md): orientation as roll-pitch-yaw, KUKA's A, B, C or
quaternions (``--rotation``), another delimiter (``--delimiter``), other column names
(``--columns``), joint readings slightly past the URDF limits (``--limit-slack``).
Every error names the file, the line (1-based) and the column.
"""

from __future__ import annotations

import csv
import math
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from campaign.errors import DataError
from campaign.fileio import atomic_open
from campaign.measure.data import CSV_COLUMNS, MAX_STORED_POSE_ID, MeasuredPoses
from campaign.model.rotations import kuka_abc, matrix_to_rotvec, quaternion_to_matrix, rotvec_to_matrix, urdf_rpy
from campaign.tolerances import (DEGREES_EVIDENCE_ABS, JOINT_LIMIT_SLACK, METRES_MAX_ABS, QUATERNION_NORM_TOL,
                                 RADIANS_MAX_ABS, ROTVEC_NORM_SLACK)


#: rows parsed and validated together when streaming a CSV (bounds the reader's memory)
CHUNK_ROWS = 20000


def _open_text(path):
    try:
        fh = open(path, encoding="utf-8-sig", newline="")
        fh.read(1)
        fh.seek(0)
        return fh
    except OSError as exc:
        raise DataError(f"{path}: cannot read ({exc.strerror})") from None
    except UnicodeDecodeError:
        raise DataError(f"{path}: not a UTF-8 text file") from None


#: the delimiters `--delimiter` names: name -> character (``space``: any run of blanks or tabs)
DELIMITERS = {",": ",", "comma": ",", ";": ";", "semicolon": ";", "tab": "\t", "\t": "\t", "space": " ", " ": " ",
              "|": "|"}


def delimiter_char(name) -> str:
    """The delimiter character of ``--delimiter`` (``,`` ``;`` ``tab`` ``space`` ``|``); DataError otherwise."""
    if name is None:
        return ","
    if name not in DELIMITERS:
        raise DataError(f"--delimiter must be one of ',', ';', tab, space, '|', not {name!r}")
    return DELIMITERS[name]


def _delimiter_name(ch: str) -> str:
    return {"\t": "tab", " ": "space"}.get(ch, ch)


def _is_number(cell: str) -> bool:
    try:
        float(cell)
        return True
    except ValueError:
        return False


def _check_first_line(path, line: str, delimiter: str, header_given: bool = False) -> None:
    """A header separated by another delimiter, or no header at all (or one where ``--header``
    says there is none): one line naming it."""
    def split(ch):
        return line.split() if ch == " " else line.split(ch)

    fields = split(delimiter)
    if len(fields) <= 2:  # the chosen delimiter does not split the header: which one does?
        best = max((ch for ch in (",", ";", "\t", " ", "|") if ch != delimiter), key=lambda ch: len(split(ch)))
        if len(split(best)) > 2:
            head = (" and no header (line 1 holds numbers: name the columns with --header)"
                    if all(_is_number(c) for c in split(best)) and not header_given else "")
            raise DataError(f"{path}: line 1: not {'comma' if delimiter == ',' else _delimiter_name(delimiter)}"
                            f"-separated: looks like {_delimiter_name(best)!r}{head}; read it with "
                            f"--delimiter {_delimiter_name(best)!r} (docs/csv_import.md)")
    numbers = all(_is_number(c.strip()) for c in fields if c.strip()) and any(c.strip() for c in fields)
    if header_given and not numbers:
        raise DataError(f"{path}: line 1 is a header ({', '.join(c.strip() for c in fields[:4])}"
                        f"{', ...' if len(fields) > 4 else ''}) and --header names the columns too: drop --header")
    if numbers and not header_given:
        raise DataError(f"{path}: no header: line 1 holds numbers ({', '.join(c.strip() for c in fields[:4])}"
                        f"{', ...' if len(fields) > 4 else ''}); the first line must name the columns "
                        "(pose_id,time_s,q1..qN,x,y,z,rx,ry,rz; other names with --columns), or name them with "
                        "--header pose_id,q1,... (docs/csv_import.md)")


def _rename_header(path, header, rename, optional=None) -> list:
    """Header with ``rename`` ({name in the file: name used here}) applied; each must exist,
    except those mapped to a name the header already has (a file written by campaign itself) or
    for which ``optional`` (a callable) is true."""
    if not rename:
        return header
    missing = [src for src, name in rename.items()
               if src not in header and name not in header and not (optional and optional(name))]
    if missing:
        raise DataError(f"{path}: {getattr(rename, 'source', '--columns')} names column(s) {', '.join(missing)}, "
                        f"which the header does not have (it has {', '.join(header)})")
    return [rename.get(h, h) for h in header]


def missing_columns(path, missing, header, robot_name: str | None = None) -> DataError:
    """The error of required columns the header lacks: their names, and the ``--columns`` that
    maps a near-miss in the header (``Q1``, ``q_1``, ``X``); joints q1..qk of a robot with more
    (the last ones missing) are another robot's file."""
    qs = sorted(int(h[1:]) for h in header if h.startswith("q") and h[1:].isdigit())
    k = len(qs)
    wanted = sorted(int(m[1:]) for m in missing if m.startswith("q") and m[1:].isdigit())
    if k and qs == list(range(1, k + 1)) and wanted == list(range(k + 1, k + 1 + len(wanted))):
        return joint_count_error(path, k, k + len(wanted), robot_name)
    hint = near_miss_hint(missing, header) or (f" (a file naming them otherwise: --columns {missing[0]}=COLUMN,... "
                                               "or robot.yaml's columns:; docs/csv_import.md)")
    return DataError(f"{path}: missing column(s) {', '.join(missing)} in the header{hint}")


def joint_count_error(path, in_file: int, n_joints: int, robot_name: str | None = None) -> DataError:
    """A file of joints q1..q<in_file> read for a robot of ``n_joints``: another robot's data."""
    robot = robot_name or "the robot"
    return DataError(f"{path}: the file has {in_file} joint columns (q1..q{in_file}), {robot} has {n_joints} "
                     f"(q1..q{n_joints}): another robot's data? (import --robot NAME|URDF, `campaign robots`; "
                     "predict and compensate: a run of that robot)")


def near_miss_hint(wanted, header) -> str:
    """`` (the file's own names: --columns q1=Q1,...)`` for the wanted names that a column of the
    header nearly spells (case, underscores, a close spelling); empty when none does."""
    import difflib

    left = [h for h in header if h not in _SPELLED]
    folded = {h.lower().replace("_", "").replace(" ", ""): h for h in left}
    near = []
    family = _named_family(wanted, left)
    for m in wanted:
        close = difflib.get_close_matches(m.lower(), [h.lower() for h in left], 1, 0.6)
        hit = (folded.get(m.lower().replace("_", "")) or family.get(m)
               or next((h for h in left if close and h.lower() == close[0]), None))
        if hit is not None:
            near.append(f"{m}={hit}")
    mm = " and --length-unit mm" if any("mm" in h.lower() for h in family.values() if h[:1].lower() in "xyz") else ""
    return (f" (the file's own names: --columns {','.join(near)}{mm}, or robot.yaml's columns:; docs/csv_import.md)"
            if near else "")


def _named_family(wanted, header) -> dict:
    """{wanted name: column} for names a header spells in a family of its own: joints as one prefix
    and their numbers (``joint1..joint6``, ``A1..A6``, ``axis_0..axis_5`` counted from 0), positions
    as the axis's letter with a unit or an index after it (``X_mm``, ``x [m]``)."""
    import re

    out = {}
    joints = sorted(int(m[1:]) for m in wanted if m.startswith("q") and m[1:].isdigit())
    if joints:
        by_prefix = {}
        for h in header:
            m = re.fullmatch(r"(.*?[^\d])(\d+)", h)
            if m:
                by_prefix.setdefault(m.group(1), {})[int(m.group(2))] = h
        for numbers in by_prefix.values():
            for base in (0, 1):  # joint1.. or joint0..
                if all(j - 1 + base in numbers for j in joints) and len(numbers) == len(joints):
                    out.update({f"q{j}": numbers[j - 1 + base] for j in joints})
                    break
            if out:
                break
    for w in ("x", "y", "z"):
        if w in wanted:
            hits = [h for h in header if re.fullmatch(rf"{w}[^a-z].*", h.lower())]
            if len(hits) == 1:
                out[w] = hits[0]
    return out


#: the names the measured-pose CSV spells itself (never a near-miss of another)
_SPELLED = {"pose_id", "time_s", "x", "y", "z", "rx", "ry", "rz", "a", "b", "c", "qw", "qx", "qy", "qz"}


def not_joint_name(name: str) -> bool:
    """True for a measured-pose CSV's names other than the joints' (pose id, time, measurement
    columns): what a file of joint coordinates may lack though robot.yaml maps it."""
    return name in _SPELLED or _may_be_empty(name)


def iter_numeric_chunks(path, required, *, may_be_empty=None, chunk_rows: int = CHUNK_ROWS, progress=None,
                        delimiter: str | None = None, rename=None, names=None, expected: str | None = None,
                        rename_optional=None, unused=None):
    """Stream a CSV of numbers with a header, ``chunk_rows`` rows at a time.

    Yields (header, values (m, columns) float64, source line numbers (m,), 1-based). ``required``
    columns must be present; every cell finite, except in columns for which ``may_be_empty``
    (a callable on the column name) is true, where an empty cell is NaN. ``progress``: called
    with the bytes read so far. delimiter: ``--delimiter``'s name (default comma; ``space``:
    any run of blanks). rename: {column in the file: name used} (``--columns``). names: the
    columns of a file without a header line (``--header``); expected: the header an empty file
    is told to have (default: the required columns); rename_optional: a callable, true for the
    names used whose mapped column may be absent (robot.yaml's measurement columns in a file of
    joints: :func:`not_joint_name`); unused: a callable, true for the columns the reader does not
    use (a measurement column in a file given to predict), whose cells are NaN unless they are
    finite numbers, never an error. A file without a header, or
    separated by another delimiter than asked, is one line naming it. Every error names the
    file, and where it applies the line and column.
    """
    path = Path(path)
    ch = delimiter_char(delimiter)
    fh = _open_text(path)
    with fh:
        lines_in = (",".join(ln.split()) for ln in fh) if ch == " " else fh
        reader = csv.reader(lines_in, delimiter="," if ch == " " else ch)
        try:
            first_raw = fh.readline()
            while first_raw and not first_raw.strip() and names is None:  # blank lines above the header
                first_raw = fh.readline()
            fh.seek(0)
            _check_first_line(path, first_raw.strip("\r\n"), ch, header_given=names is not None)
            first = next(reader, None) if names is None else list(names)
            while names is None and first is not None and not any(c.strip() for c in first):
                first = next(reader, None)
            if first is None:
                raise DataError(f"{path}: empty file (expected header {expected or ','.join(required)})")
            header = _rename_header(path, [h.strip() for h in first], rename, rename_optional)
            missing = [c for c in required if c not in header]
            if missing:
                raise missing_columns(path, missing, header)
            if len(set(header)) != len(header):
                dup = sorted({h for h in header if header.count(h) > 1})
                raise DataError(f"{path}: duplicate column(s) {', '.join(dup)}")
            empty_ok = [bool(may_be_empty and may_be_empty(h)) for h in header]
            skip = [bool(unused and unused(h)) for h in header]
            ncol = len(header)
            values = np.empty((chunk_rows, ncol))
            lines = np.empty(chunk_rows, dtype=np.int64)
            m = 0
            any_rows = False
            for r in reader:
                if not any(cell.strip() for cell in r):
                    continue
                line = reader.line_num
                if len(r) != ncol:
                    raise DataError(f"{path}: line {line} has {len(r)} fields, the header has {ncol}")
                row = values[m]
                for j, cell in enumerate(r):
                    try:
                        v = float(cell)
                    except ValueError:
                        if skip[j] or (empty_ok[j] and not cell.strip()):
                            row[j] = np.nan
                            continue
                        hint = " (a decimal comma? write decimal points)" if _is_number(cell.replace(",", ".")) \
                            else ""
                        raise DataError(f"{path}: line {line}, column {header[j]}: '{cell.strip()}' "
                                        f"is not a number{hint}") from None
                    if not math.isfinite(v) and not skip[j]:
                        raise DataError(f"{path}: line {line}, column {header[j]}: {cell.strip()} "
                                        "is not a finite number")
                    row[j] = v
                lines[m] = line
                m += 1
                if m == chunk_rows:
                    any_rows = True
                    yield header, values.copy(), lines.copy()
                    m = 0
                    if progress is not None:
                        progress(fh.buffer.tell() if hasattr(fh, "buffer") else 0)
            if m or not any_rows:
                if not m and not any_rows:
                    raise DataError(f"{path}: no data rows")
                yield header, values[:m].copy(), lines[:m].copy()
        except UnicodeDecodeError:
            raise DataError(f"{path}: not a UTF-8 text file") from None
        except csv.Error as exc:
            raise DataError(f"{path}: line {reader.line_num}: not valid CSV ({exc})") from None


def read_numeric_table(path, required, *, may_be_empty=None, delimiter: str | None = None, rename=None,
                       rename_optional=None, unused=None, expected: str | None = None) -> tuple:
    """Read a whole CSV of numbers with a header; every cell finite.

    Returns (header, {column: values (n,)}, source line numbers (n,), 1-based). ``required``
    columns must be present; every error names the file, and where it applies the line and
    column. delimiter, rename, rename_optional, unused, expected: as :func:`iter_numeric_chunks`.
    """
    chunks = list(iter_numeric_chunks(path, required, may_be_empty=may_be_empty, delimiter=delimiter,
                                      rename=rename, rename_optional=rename_optional, unused=unused,
                                      expected=expected))
    header = chunks[0][0]
    values = np.concatenate([c[1] for c in chunks])
    lines = np.concatenate([c[2] for c in chunks])
    return header, {h: values[:, j] for j, h in enumerate(header)}, lines


def read_markers_file(path) -> np.ndarray:
    """``markers: [[x, y, z], ...]`` (m, tool frame, in the order m1..mk) from a YAML file: (k, 3)."""
    from campaign.fileio import read_yaml_mapping

    doc = read_yaml_mapping(path, DataError)
    mk = doc.get("markers")
    try:
        P = np.asarray(mk, dtype=float)
    except (TypeError, ValueError):
        P = None
    if P is None or P.ndim != 2 or P.shape[1] != 3 or len(P) < 1 or not np.all(np.isfinite(P)):
        raise DataError(f"{path}: field 'markers' must be a list of [x, y, z] (m, tool frame), one per reflector")
    return P


POSE_COLUMNS = ("x", "y", "z", "rx", "ry", "rz")

#: how a 6-D CSV writes the orientation (``--rotation``): name -> (columns, angles?, description)
ROTATIONS = {
    "rotvec": (("rx", "ry", "rz"), True, "rotation vectors (axis times angle)"),
    "rpy": (("rx", "ry", "rz"), True, "roll, pitch, yaw about the fixed x, y, z axes, R = Rz(yaw) Ry(pitch) "
                                      "Rx(roll) (URDF, ROS, Pinocchio)"),
    "abc": (("a", "b", "c"), True, "KUKA's A, B, C, R = Rz(A) Ry(B) Rx(C)"),
    "quat": (("qw", "qx", "qy", "qz"), False, "unit quaternions (w, x, y, z)"),
}


def rotation_matrices(rotation: str, values) -> np.ndarray:
    """Rotation matrices (n, 3, 3) from orientation columns (n, k) read as ``rotation``
    (:data:`ROTATIONS`; angles in rad)."""
    v = np.asarray(values, dtype=float)
    if rotation == "rotvec":
        return rotvec_to_matrix(v)
    if rotation == "rpy":
        return urdf_rpy(v[:, 0], v[:, 1], v[:, 2])
    if rotation == "abc":
        return kuka_abc(v[:, 0], v[:, 1], v[:, 2])
    return quaternion_to_matrix(v)


def rotation_readings_table() -> dict:
    """{name: (columns, values -> R, angles?)} of every ``--rotation`` (for the plausibility checks)."""
    return {name: (cols, (lambda v, r=name: rotation_matrices(r, v)), angles)
            for name, (cols, angles, _) in ROTATIONS.items()}


@dataclass(frozen=True)
class CsvLayout:
    """What a measured-pose CSV holds, from its header (and the robot's joint count)."""

    kind: str  # "pose", "point" or "markers"
    joints: tuple  # q1..qN
    n_markers: int
    context: tuple  # other columns
    has_time: bool
    rotation: str = "rotvec"  # how a 6-D CSV writes the orientation (ROTATIONS)
    has_pose_id: bool = True  # False: the rows are numbered 0..n-1 in file order (as predict numbers them)

    @property
    def rotation_columns(self) -> tuple:
        return ROTATIONS[self.rotation][0]

    @property
    def measure_columns(self) -> tuple:
        if self.kind == "pose":
            return POSE_COLUMNS[:3] + self.rotation_columns
        if self.kind == "point":
            return POSE_COLUMNS[:3]
        return tuple(f"m{i}_{a}" for i in range(1, self.n_markers + 1) for a in "xyz")


def _other_rotation(path, hs, rotation) -> None:
    """Orientation columns of another ``--rotation`` than asked: one line naming it."""
    for name, (cols, _, what) in ROTATIONS.items():
        if set(cols) <= hs and cols != ROTATIONS[rotation][0]:
            raise DataError(f"{path}: columns {','.join(cols)} look like {what}, and --rotation {rotation} reads "
                            f"{','.join(ROTATIONS[rotation][0])}: import with --rotation {name}"
                            + (" (or rotvec)" if name == "rpy" else "") + " (docs/csv_import.md)")


def csv_layout(path, header, n_joints: int | None, rotation: str = "rotvec", robot_name: str | None = None
               ) -> CsvLayout:
    """Detect the measurement kind from the header: ``x,y,z`` and the orientation columns of
    ``rotation`` (6-D; :data:`ROTATIONS`), ``m1_x,..`` (raw reflectors), ``x,y,z`` (one
    reflector). Joints ``q1..qN``. Orientation columns of another reading are named."""
    hs = set(header)
    qs = [h for h in header if h.startswith("q") and h[1:].isdigit()]
    N = n_joints if n_joints is not None else len(qs)
    joints = tuple(f"q{j}" for j in range(1, N + 1))
    extra = sorted(set(qs) - set(joints), key=lambda h: int(h[1:]))
    if extra:
        if sorted(int(h[1:]) for h in qs) == list(range(1, len(qs) + 1)):
            raise joint_count_error(path, len(qs), N, robot_name)
        raise DataError(f"{path}: column {extra[0]}: {robot_name or 'the robot'} has {N} joints (q1..q{N})")
    missing = [c for c in joints if c not in hs]
    if missing:
        raise missing_columns(path, missing, header, robot_name)
    rot_cols = ROTATIONS[rotation][0]
    if {"x", "y", "z", *rot_cols} <= hs:
        kind, k = "pose", 0
    elif "m1_x" in hs:
        kind, k = "markers", 0
        while f"m{k + 1}_x" in hs:
            k += 1
        for i in range(1, k + 1):
            for a in "xyz":
                if f"m{i}_{a}" not in hs:
                    raise DataError(f"{path}: reflector columns: m{i}_x is there, m{i}_{a} is missing")
    elif {"x", "y", "z"} <= hs:
        _other_rotation(path, hs, rotation)
        if hs & set(rot_cols):
            missing = [c for c in rot_cols if c not in hs]
            raise DataError(f"{path}: missing column(s) {', '.join(missing)} in the header (orientation columns "
                            f"{','.join(rot_cols)} go together)")
        kind, k = "point", 0
    else:
        hint = near_miss_hint([c for c in ("x", "y", "z") if c not in hs], header)
        raise DataError(f"{path}: no measurement columns: expected x,y,z,rx,ry,rz (6-D), x,y,z (one reflector) "
                        f"or m1_x,m1_y,m1_z,... (raw reflectors){hint}")
    layout = CsvLayout(kind, joints, k, (), "time_s" in hs, rotation)
    # in_domain, sigma_mm: what `export --csv` appends from a calibration, not a measurement's context
    known = {"pose_id", "time_s", *joints, *layout.measure_columns, *EXPORTED_DOMAIN_COLUMNS}
    return CsvLayout(kind, joints, k, tuple(h for h in header if h not in known), "time_s" in hs, rotation,
                     "pose_id" in hs)


class ColumnMap(dict):
    """{column in the file: name used}, and where the mapping was given (``source``: ``--columns``
    or a robot.yaml's ``columns:``), for the messages."""

    def __init__(self, mapping=(), source: str = "--columns"):
        super().__init__(mapping)
        self.source = source


def parse_columns(text) -> dict:
    """``--columns x=x1,y=y1,...`` (or robot.yaml's ``columns: {x: x1, ...}``) to {column in the
    file: name used}; ConfigError on a malformed mapping."""
    from campaign.errors import ConfigError

    if text is None or text == "" or text == {}:
        return {}
    if isinstance(text, dict):
        pairs = [(str(k), str(v)) for k, v in text.items()]
    else:
        pairs = []
        for item in str(text).split(","):
            name, eq, src = item.partition("=")
            if not eq or not name.strip() or not src.strip():
                raise ConfigError(f"--columns: expected NAME=COLUMN,... (e.g. x=X_mm,q1=J1), got {item.strip()!r}")
            pairs.append((name.strip(), src.strip()))
    out = {}
    for name, src in pairs:
        if src in out:
            raise ConfigError(f"--columns: column {src!r} is mapped twice")
        out[src] = name
    if len(set(out.values())) != len(out):
        dup = sorted({v for v in out.values() if list(out.values()).count(v) > 1})
        raise ConfigError(f"--columns: {', '.join(dup)} named twice")
    return out


@dataclass(frozen=True)
class ImportOptions:
    """How to read a measured-pose CSV: units, frame, nominal reflector positions, and the
    file's own conventions (docs/csv_import.md).

    rotation: :data:`ROTATIONS`; delimiter: ``--delimiter``'s name (None: comma); header: the
    column names of a file without a header line; columns:
    {column in the file: name used}; limit_slack_rad / limit_slack_m: how far past the URDF's
    joint limits a reading is accepted (revolute / prismatic joints)."""

    angle_unit: str = "rad"
    length_unit: str = "m"
    frame: str = "robot"
    markers: np.ndarray | None = None  # (k, 3) m in the tool frame, for raw reflectors
    rotation: str = "rotvec"
    delimiter: str | None = None
    columns: dict = None
    header: tuple | None = None  # the columns of a file without a header line (--header)
    limit_slack_rad: float = 0.0
    limit_slack_m: float = 0.0
    pose_ids: np.ndarray | None = None  # (n,) the rows' ids of a file without pose_id (the plan's: plan_pose_ids)

    def __post_init__(self):
        if self.angle_unit not in ("rad", "deg"):
            raise DataError(f"--angle-unit must be rad or deg, not {self.angle_unit!r}")
        if self.length_unit not in ("m", "mm"):
            raise DataError(f"--length-unit must be m or mm, not {self.length_unit!r}")
        if self.frame not in ("robot", "tracker"):
            raise DataError(f"--frame must be robot or tracker, not {self.frame!r}")
        if self.rotation not in ROTATIONS:
            raise DataError(f"--rotation must be one of {', '.join(ROTATIONS)}, not {self.rotation!r}")
        delimiter_char(self.delimiter)
        for v in (self.limit_slack_rad, self.limit_slack_m):
            if not (math.isfinite(v) and v >= 0):
                raise DataError(f"--limit-slack must be a finite number >= 0, not {v!r}")

    def slack(self, robot) -> np.ndarray:
        """Per joint, how far past its limit a reading is accepted (N,), rad or m."""
        return JOINT_LIMIT_SLACK + np.where(robot.prismatic, self.limit_slack_m, self.limit_slack_rad)


def _marker_positions(path, layout, robot, options):
    if layout.kind != "markers":
        return None
    # any number of reflectors: calibrate identifies raw reflectors from their positions (fewer
    # than three give no pose, and need none)
    P = options.markers
    src = "--markers"
    if P is None and robot is not None and len(robot.reflectors):
        P, src = robot.reflector_positions_in_E, f"robot.yaml of {robot.name}"
    if P is None:
        raise DataError(f"{path}: raw reflector columns m1..m{layout.n_markers} need their nominal positions "
                        "in the tool frame: --markers FILE (markers: [[x, y, z], ...], m) or reflectors in robot.yaml")
    if len(P) != layout.n_markers:
        raise DataError(f"{path}: {layout.n_markers} reflectors in the header, {len(P)} nominal positions in {src}")
    return np.asarray(P, dtype=float)


def _convert(path, layout, header, values, lines, robot, options, P_nom, first_row: int = 0):
    """One chunk of rows to SI arrays, validated. Returns a dict of arrays. first_row: how many
    data rows came before this chunk (the pose ids of a file without ``pose_id``)."""
    col = {h: values[:, j] for j, h in enumerate(header)}
    if not layout.has_pose_id:
        col["pose_id"] = (np.arange(first_row, first_row + len(values), dtype=float) if options.pose_ids is None
                          else np.asarray(options.pose_ids[first_row:first_row + len(values)], dtype=float))

    def fail(mask, name, what, v=None):
        k = int(np.argmax(mask))
        val = col[name][k] if v is None else v[k]
        raise DataError(f"{path}: line {lines[k]}, column {name}: {val:.6g} {what}")

    pid = col["pose_id"]
    if np.any(pid != np.round(pid)):
        fail(pid != np.round(pid), "pose_id", "is not an integer")
    out_of_range = (pid < 0) | (pid >= MAX_STORED_POSE_ID)
    if out_of_range.any():
        fail(out_of_range, "pose_id", f"is outside 0..{MAX_STORED_POSE_ID - 1} (pose ids are non-negative integers "
                                      "stored exactly)")
    deg = options.angle_unit == "deg"
    mm = options.length_unit == "mm"
    a_scale = np.pi / 180.0 if deg else 1.0
    l_scale = 1e-3 if mm else 1.0
    N = len(layout.joints)
    prismatic = robot.prismatic if robot is not None else np.zeros(N, dtype=bool)
    q = np.stack([col[c] for c in layout.joints], axis=1) * np.where(prismatic, l_scale, a_scale)
    check_joint_units(path, q, np.stack([col[c] for c in layout.joints], axis=1), lines, robot, deg)
    past = None
    if robot is not None:
        q = robot.to_model_q(q)
        limited = np.array([t != "continuous" for t in robot.joint_types], dtype=bool)
        slack = options.slack(robot)
        lo = (q < robot.q_lower - slack) & limited
        hi = (q > robot.q_upper + slack) & limited
        if (lo | hi).any():
            k, j = np.argwhere(lo | hi)[0]
            lim = robot.q_lower[j] if lo[k, j] else robot.q_upper[j]
            u = robot.joint_units[j]
            raise DataError(f"{path}: line {lines[k]}, column q{j + 1}: {q[k, j]:.6g} {u} is outside "
                            f"the joint limit {lim:.6g} {u} of {robot.name}"
                            + limit_hint(robot, q, options))
        excess = np.maximum(robot.q_lower - JOINT_LIMIT_SLACK - q, q - robot.q_upper - JOINT_LIMIT_SLACK) * limited
        if (excess > 0).any():
            k, j = np.unravel_index(int(np.argmax(excess)), excess.shape)
            lim = robot.q_lower[j] if q[k, j] < robot.q_lower[j] else robot.q_upper[j]
            past = PastLimits(int((excess > 0).sum()), int(lines[k]), f"q{j + 1}", float(q[k, j]), float(lim),
                              robot.joint_units[j])
    n = len(pid)
    xyz = np.full((n, 3), np.nan)
    rv = np.full((n, 3), np.nan)
    markers = None
    if layout.kind in ("pose", "point"):
        xyz = np.stack([col["x"], col["y"], col["z"]], axis=1) * l_scale
        for a, name in enumerate("xyz"):
            big = np.abs(xyz[:, a]) > METRES_MAX_ABS
            if big.any():
                fail(big, name, f"exceeds {METRES_MAX_ABS:g} m: positions must be in m (this looks like mm; "
                                "--length-unit mm)", xyz[:, a])
    if layout.kind == "pose":
        rv = _orientation(path, layout, col, lines, a_scale, robot, q, options)
    if layout.kind == "markers":
        from campaign.measure.reflectors import fit_markers

        k = layout.n_markers
        markers = np.stack([np.stack([col[f"m{i}_{a}"] for a in "xyz"], axis=1) for i in range(1, k + 1)],
                           axis=1) * l_scale
        part = np.isnan(markers).any(axis=2) & ~np.isnan(markers).all(axis=2)
        if part.any():
            r, i = np.argwhere(part)[0]
            raise DataError(f"{path}: line {lines[r]}, reflector m{i + 1}: x, y, z must be all given or all empty")
        big = np.abs(np.nan_to_num(markers)) > METRES_MAX_ABS
        if big.any():
            r, i, a = np.argwhere(big)[0]
            raise DataError(f"{path}: line {lines[r]}, column m{i + 1}_{'xyz'[a]}: {markers[r, i, a]:.6g} m exceeds "
                            f"{METRES_MAX_ABS:g} m (this looks like mm; --length-unit mm)")
        T, _ = fit_markers(P_nom, markers)
        xyz = T[:, :3, 3]
        ok = np.isfinite(T[:, 0, 0])
        rv[ok] = matrix_to_rotvec(T[ok, :3, :3])
    t = col["time_s"] if layout.has_time else np.full(n, np.nan)
    return {"pose_id": pid.astype(np.int64), "time_s": t, "q": q, "xyz": xyz, "rotvec": rv, "markers": markers,
            "context": {h: col[h] for h in layout.context}, "lines": lines, "past_limits": past}


def check_joint_units(path, q, written, lines, robot=None, read_in_deg: bool = False) -> None:
    """Joint readings in another unit than read: a revolute joint beyond 2*pi and its limits
    (degrees read as rad), a prismatic one beyond METRES_MAX_ABS (mm read as m). q (n, N) as
    read (rad, m); written (n, N) as the file writes them; lines (n,) the file's line numbers.
    DataError naming the line, the column and the option; import, predict and compensate alike."""
    N = q.shape[1]
    prismatic = robot.prismatic if robot is not None else np.zeros(N, dtype=bool)
    limited = (np.array([t != "continuous" for t in robot.joint_types], dtype=bool) if robot is not None
               else np.zeros(N, dtype=bool))
    revolute = ~prismatic
    # degrees read as rad: some joint's readings beyond DEGREES_EVIDENCE_ABS; below, a limited joint a
    # little past 2*pi is past its limit (an offset, another robot), which the limit check says
    deg_like = bool(revolute.any() and np.abs(written[:, revolute]).max() > DEGREES_EVIDENCE_ABS)
    for j in range(N):
        if not prismatic[j] and (read_in_deg or (limited[j] and not deg_like)):
            continue  # in degrees already, or no sign of degrees: past the limits is the limit check's to say
        if prismatic[j]:
            big, what, v = np.abs(q[:, j]) > METRES_MAX_ABS, ("m: a prismatic joint's value must be in m (this looks "
                                                              "like mm; --length-unit mm)"), q[:, j]
        else:
            bound = RADIANS_MAX_ABS
            if robot is not None and robot.joint_types[j] != "continuous":
                bound = max(bound, abs(robot.q_lower[j]) + 1e-6, abs(robot.q_upper[j]) + 1e-6)
            big = np.abs(q[:, j]) > bound
            what = "exceeds 2*pi and the joint's limits: joint values must be in rad (this looks like degrees; " \
                   "--angle-unit deg)"
            v = q[:, j] if read_in_deg else written[:, j]
        if big.any():
            k = int(np.argmax(big))
            raise DataError(f"{path}: line {lines[k]}, column q{j + 1}: {v[k]:.6g} {what}")


def limit_hint(robot, q, options) -> str:
    """What joint readings q (n, N, model convention) past the limits mean, by the largest excess
    of any joint: far past (FAR_PAST_LIMIT_*), another robot's data (a forgotten ``--robot``);
    else readings slightly past, the ``--limit-slack`` in force or the option to give."""
    from campaign.tolerances import FAR_PAST_LIMIT_M, FAR_PAST_LIMIT_RAD

    limited = np.array([t != "continuous" for t in robot.joint_types], dtype=bool)
    excess = np.max(np.maximum(robot.q_lower - q, q - robot.q_upper) * limited, axis=0)  # (N,)
    far = excess / np.where(robot.prismatic, FAR_PAST_LIMIT_M, FAR_PAST_LIMIT_RAD)
    j = int(np.argmax(far))
    past = f"{excess[j] * 1e3:.3g} mm" if robot.prismatic[j] else f"{math.degrees(excess[j]):.3g} deg"
    if far[j] > 1:
        return (f" (q{j + 1} reads up to {past} past a limit: no reading slightly past, but data of another robot, "
                f"unit or joint convention; the file is read as {robot.name}'s: --robot NAME|URDF (`campaign "
                "robots`), --angle-unit, robot.yaml's controller)")
    given = np.where(robot.prismatic, options.limit_slack_m, options.limit_slack_rad)[j]
    if given:
        slack = f"{given * 1e3:.6g} mm" if robot.prismatic[j] else f"{math.degrees(given):.6g} deg"
        return f" ({past} past at most, more than the --limit-slack in force: {slack})"
    return f" (up to {past} past: readings slightly past a limit: --limit-slack DEG_OR_MM)"


@dataclass(frozen=True)
class PastLimits:
    """Joint readings accepted past the URDF's limits (``--limit-slack``): how many, and the largest."""

    count: int
    line: int
    column: str
    value: float
    limit: float
    unit: str

    def worse(self, other: "PastLimits | None") -> "PastLimits":
        """The two counts together, with the larger excess of the two."""
        if other is None:
            return self
        big = self if abs(self.value - self.limit) >= abs(other.value - other.limit) else other
        return PastLimits(self.count + other.count, big.line, big.column, big.value, big.limit, big.unit)

    def text(self, robot_name: str) -> str:
        return (f"{self.count} joint reading(s) past the URDF limits of {robot_name} accepted (--limit-slack); "
                f"the largest: line {self.line}, {self.column} = {self.value:.6g} {self.unit} "
                f"(limit {self.limit:.6g} {self.unit})")


def orientation_values(layout, col, a_scale) -> np.ndarray:
    """The orientation columns (n, k) as written, angles scaled to rad."""
    v = np.stack([col[c] for c in layout.rotation_columns], axis=1)
    return v * a_scale if ROTATIONS[layout.rotation][1] else v


def _orientation(path, layout, col, lines, a_scale, robot, q, options) -> np.ndarray:
    """Rotation vectors (n, 3) rad of a 6-D chunk read as ``layout.rotation``, validated."""
    v = orientation_values(layout, col, a_scale)
    cols = ",".join(layout.rotation_columns)
    if layout.rotation == "rotvec":
        big = np.linalg.norm(v, axis=1) > math.pi + ROTVEC_NORM_SLACK
        if big.any():
            k = int(np.argmax(big))
            raise DataError(f"{path}: line {lines[k]}, columns {cols}: rotation vector norm "
                            f"{np.linalg.norm(v[k]):.6g} exceeds pi: {_reading_hint(robot, q, v, layout, options)}")
        return v
    if layout.rotation == "quat":
        norm = np.linalg.norm(v, axis=1)
        bad = np.abs(norm - 1) > QUATERNION_NORM_TOL
        if bad.any():
            k = int(np.argmax(bad))
            raise DataError(f"{path}: line {lines[k]}, columns {cols}: quaternion norm {norm[k]:.6g} is not 1 "
                            "(columns qw,qx,qy,qz: w first)")
    else:
        big = np.abs(v) > RADIANS_MAX_ABS
        if big.any():
            k, a = np.argwhere(big)[0]
            raise DataError(f"{path}: line {lines[k]}, column {layout.rotation_columns[a]}: {v[k, a]:.6g} rad exceeds "
                            "2*pi: angles must be in rad (this looks like degrees; --angle-unit deg)")
    return matrix_to_rotvec(rotation_matrices(layout.rotation, v))


def _reading_hint(robot, q, values, layout, options) -> str:
    """What a rotation-vector norm above pi means: the reading of the columns (and their unit)
    that agrees with the nominal orientations, tested with the nominal model, else degrees."""
    default = "must be in rad (this looks like degrees; --angle-unit deg)"
    if robot is None or options.frame not in ("robot", "tracker"):
        return default
    from campaign.measure.plausibility import rotation_readings
    from campaign.tolerances import ORIENTATION_SPREAD_MAX_RAD

    scales = (1.0, math.pi / 180) if options.angle_unit == "rad" else (1.0, 180 / math.pi)
    ranked = rotation_readings(robot, q, values, layout.rotation_columns, rotation_readings_table(), scales)
    spread, name, scale = ranked[0]
    if not np.isfinite(spread) or spread > ORIENTATION_SPREAD_MAX_RAD:
        return default + "; no reading of the columns agrees with the nominal orientations (--rotation rotvec|rpy)"
    unit = options.angle_unit if scale == 1.0 else ("deg" if options.angle_unit == "rad" else "rad")
    if name == layout.rotation:
        return (f"must be in rad: read in {unit}, the columns agree with the nominal orientations to "
                f"{spread * 1e3:.1f} mrad (--angle-unit {unit})")
    flags = f"--rotation {name}" + ("" if unit == options.angle_unit else f" with the columns in {unit}")
    return (f"not rotation vectors: read as {ROTATIONS[name][2]} ({unit}), the columns agree with the nominal "
            f"orientations to {spread * 1e3:.1f} mrad: {flags} (docs/csv_import.md)")


def _may_be_empty(h: str) -> bool:
    return h.startswith("m") and "_" in h and h[1:h.index("_")].isdigit()


@dataclass(frozen=True)
class CsvReading:
    """A validated measured-pose CSV, ready to stream: its layout, the raw reflectors' nominal
    positions (or None), the joint readings accepted past the limits (or None), and
    ``chunks``, a generator of MeasuredPoses (one pass)."""

    layout: CsvLayout
    marker_positions: np.ndarray | None
    past_limits: PastLimits | None
    chunks: object
    n_rows: int = 0
    plan_match: str | None = None  # how the rows of a file without pose_id were given the plan's ids

    @property
    def numbered(self) -> str | None:
        """The sentence saying the rows were numbered (a file without ``pose_id``), or None."""
        if self.layout.has_pose_id:
            return None
        if self.plan_match:
            return f"no pose_id column: the {self.n_rows} rows {self.plan_match}"
        return (f"no pose_id column: the {self.n_rows} rows are numbered 0..{self.n_rows - 1} in file order "
                "as pose_id")

    def __iter__(self):  # (layout, marker positions, chunks), as before
        return iter((self.layout, self.marker_positions, self.chunks))


def _chunk_poses(path, layout, hdr, vals, lns, robot, options, P_nom, first_row=0):
    c = _convert(path, layout, hdr, vals, lns, robot, options, P_nom, first_row)
    return c, MeasuredPoses.from_vectors(c["pose_id"], c["time_s"], c["q"], c["xyz"], c["rotvec"], c["context"],
                                         kind=layout.kind, frame=options.frame, markers=c["markers"],
                                         marker_positions=P_nom)


def iter_measured_chunks(path, robot=None, options: ImportOptions | None = None, *, progress=None,
                         chunk_rows: int = CHUNK_ROWS) -> CsvReading:
    """Validate a measured-pose CSV whole (streaming, bounded memory: a chunk of rows and the
    pose ids), then stream it again as MeasuredPoses chunks. Returns a :class:`CsvReading`
    (which unpacks as (layout, marker nominal positions or None, generator)). ``progress``:
    called with the fraction done (0..1) over both passes."""
    path = Path(path)
    options = options or ImportOptions()
    size = max(path.stat().st_size, 1) if path.is_file() else 1

    def report(offset, half):
        if progress is not None:
            progress(min(1.0, 0.5 * half + 0.5 * offset / size))

    read = dict(may_be_empty=_may_be_empty, chunk_rows=chunk_rows, delimiter=options.delimiter,
                rename=options.columns, names=options.header, expected=expected_header(robot, options))
    it = iter_numeric_chunks(path, (), progress=lambda b: report(b, 0), **read)
    header, values, lines = next(it)
    layout = csv_layout(path, header, robot.n_joints if robot is not None else None, options.rotation,
                        robot.name if robot is not None else None)
    P_nom = _marker_positions(path, layout, robot, options)
    ids, id_lines = [], []
    past = None
    rows = 0
    for hdr, vals, lns in _chain_first((header, values, lines), it):
        c = _convert(path, layout, hdr, vals, lns, robot, options, P_nom, rows)
        rows += len(vals)
        ids.append(c["pose_id"])
        id_lines.append(lns)
        if c["past_limits"] is not None:
            past = c["past_limits"].worse(past)
    report(size, 0)
    pid = np.concatenate(ids)
    lines_all = np.concatenate(id_lines)
    del ids, id_lines
    order = np.argsort(pid, kind="stable")
    dup = np.flatnonzero(pid[order][1:] == pid[order][:-1])
    if len(dup):
        a, b = order[dup[0]], order[dup[0] + 1]
        raise DataError(f"{path}: pose_id {int(pid[a])} appears twice (lines {min(lines_all[a], lines_all[b])} "
                        f"and {max(lines_all[a], lines_all[b])})")
    del pid, lines_all, order

    def chunks():
        done = 0
        for hdr, vals, lns in iter_numeric_chunks(path, (), progress=lambda b: report(b, 1), **read):
            yield _chunk_poses(path, layout, hdr, vals, lns, robot, options, P_nom, done)[1]
            done += len(vals)
        report(size, 1)

    return CsvReading(layout, P_nom, past, chunks(), rows)


def expected_header(robot=None, options: ImportOptions | None = None) -> str:
    """The header a measured-pose CSV has, in words (for an empty file's error)."""
    N = robot.n_joints if robot is not None else 6
    rot = ",".join(ROTATIONS[(options or ImportOptions()).rotation][0])
    return (f"[pose_id,][time_s,]q1,...,q{N}, then x,y,z,{rot} (6-D), x,y,z (one reflector) or m1_x,m1_y,m1_z,... "
            "(raw reflectors)")


def read_check_sample(path, robot, options: ImportOptions | None = None, *, rows: int = 2000) -> tuple:
    """The first ``rows`` rows of a measured-pose CSV (already validated by
    :func:`iter_measured_chunks`) for the plausibility checks: (MeasuredPoses, orientation
    columns (n, k) as written, angles in rad, or None)."""
    options = options or ImportOptions()
    hdr, vals, lns = next(iter_numeric_chunks(path, (), may_be_empty=_may_be_empty, chunk_rows=rows,
                                              delimiter=options.delimiter, rename=options.columns,
                                              names=options.header))
    layout = csv_layout(path, hdr, robot.n_joints, options.rotation, robot.name)
    P_nom = _marker_positions(path, layout, robot, options)
    c, poses = _chunk_poses(path, layout, hdr, vals, lns, robot, options, P_nom)
    if layout.kind != "pose":
        return poses, None
    a_scale = np.pi / 180.0 if options.angle_unit == "deg" else 1.0
    return poses, orientation_values(layout, {h: vals[:, j] for j, h in enumerate(hdr)}, a_scale)


def _chain_first(first, rest):
    yield first
    yield from rest


def concat_poses(parts) -> MeasuredPoses:
    """One MeasuredPoses from chunks (same kind and frame)."""
    parts = list(parts)
    p0 = parts[0]
    cat = np.concatenate
    return MeasuredPoses(cat([p.pose_id for p in parts]), cat([p.time_s for p in parts]), cat([p.q for p in parts]),
                         cat([p.T_IE for p in parts]), {k: cat([p.context[k] for p in parts]) for k in p0.context},
                         p0.T_LI, p0.kind, p0.frame,
                         None if p0.markers is None else cat([p.markers for p in parts]), p0.marker_positions)


def read_measured_csv(path, robot=None, options: ImportOptions | None = None) -> MeasuredPoses:
    """Read and validate a measured-pose CSV whole (kind from the header; see ImportOptions).

    With ``robot`` (a RobotModel), the joint count and limits are checked, and joint values
    converted by robot.yaml's controller convention.
    """
    return concat_poses(iter_measured_chunks(path, robot, options).chunks)


#: columns `export --csv` appends from the run's calibration (campaign.identify.use.DOMAIN_COLUMNS);
#: `import` reads past them
EXPORTED_DOMAIN_COLUMNS = ("in_domain", "sigma_mm")


def write_measured_csv(path, poses: MeasuredPoses, robot=None, appended: dict | None = None) -> None:
    """Write poses as a measured-pose CSV: ``pose_id,time_s,q1..qN`` then the measurement columns
    of their kind (``x,y,z,rx,ry,rz``, ``x,y,z`` or ``m1_x,..``, an empty cell where a reflector
    was missed), then the context columns, then ``appended`` ({column: (n,) cells as written}). SI
    units; with ``robot``, joint values in its controller's convention (robot.yaml's ``controller``),
    as they were imported."""
    path = Path(path)
    appended = appended or {}
    extra = sorted(poses.context)
    q = poses.q if robot is None else robot.to_controller_q(poses.q)
    N = q.shape[1]
    has_time = bool(np.isfinite(poses.time_s).any())
    head = ["pose_id"] + (["time_s"] if has_time else []) + [f"q{j}" for j in range(1, N + 1)]
    if poses.kind == "markers":
        k = poses.markers.shape[1]
        head += [f"m{i}_{a}" for i in range(1, k + 1) for a in "xyz"]
    else:
        head += list(POSE_COLUMNS if poses.kind == "pose" else POSE_COLUMNS[:3])
    rv = poses.rotvec if poses.kind == "pose" else None

    def num(v):
        return "" if not np.isfinite(v) else repr(float(v))

    with atomic_open(path, "w", newline="") as fh:
        w = csv.writer(fh)
        w.writerow(head + extra + list(appended))
        for i in range(len(poses)):
            row = [int(poses.pose_id[i])] + ([repr(float(poses.time_s[i]))] if has_time else [])
            row += [repr(float(v)) for v in q[i]]
            if poses.kind == "markers":
                row += [num(v) for v in poses.markers[i].reshape(-1)]
            else:
                row += [repr(float(v)) for v in poses.xyz[i]]
                if rv is not None:
                    row += [repr(float(v)) for v in rv[i]]
            row += [repr(float(poses.context[k][i])) for k in extra]
            row += [appended[k][i] for k in appended]
            w.writerow(row)
