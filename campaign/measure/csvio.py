"""The measured-pose CSV (DESIGN.md): read with validation, write.

Header ``pose_id,time_s,q1..q6,x,y,z,rx,ry,rz``; q in rad as commanded, ``x,y,z`` the
origin of F_E in F_I in m, ``rx,ry,rz`` the rotation vector of R_IE in rad. Extra named
numeric columns are kept as context. Every error names the file, the line and the column.
"""

from __future__ import annotations

import csv
import math
from pathlib import Path

import numpy as np

from campaign.errors import DataError
from campaign.fileio import atomic_open
from campaign.measure.data import CSV_COLUMNS, MAX_STORED_POSE_ID, MeasuredPoses
from campaign.tolerances import JOINT_LIMIT_SLACK, METRES_MAX_ABS, RADIANS_MAX_ABS, ROTVEC_NORM_SLACK


def read_numeric_table(path, required) -> tuple:
    """Read a CSV of numbers with a header; every cell finite.

    Returns (header, {column: values (n,)}, source line numbers (n,)). ``required`` columns
    must be present; every error names the file, and where it applies the line and column.
    """
    path = Path(path)
    try:
        text = path.read_text(encoding="utf-8-sig")
    except OSError as exc:
        raise DataError(f"{path}: cannot read ({exc.strerror})") from None
    except UnicodeDecodeError:
        raise DataError(f"{path}: not a UTF-8 text file") from None
    rows = list(csv.reader(text.splitlines()))
    if not rows:
        raise DataError(f"{path}: empty file (expected header {','.join(required)})")
    header = [h.strip() for h in rows[0]]
    missing = [c for c in required if c not in header]
    if missing:
        raise DataError(f"{path}: missing column(s) {', '.join(missing)} in the header")
    if len(set(header)) != len(header):
        dup = sorted({h for h in header if header.count(h) > 1})
        raise DataError(f"{path}: duplicate column(s) {', '.join(dup)}")
    body = [(i + 2, r) for i, r in enumerate(rows[1:]) if any(cell.strip() for cell in r)]
    if not body:
        raise DataError(f"{path}: no data rows")
    values = np.empty((len(body), len(header)))
    for k, (line, r) in enumerate(body):
        if len(r) != len(header):
            raise DataError(f"{path}: line {line} has {len(r)} fields, the header has {len(header)}")
        for j, cell in enumerate(r):
            try:
                v = float(cell)
            except ValueError:
                raise DataError(f"{path}: line {line}, column {header[j]}: '{cell.strip()}' is not a number") from None
            if not math.isfinite(v):
                raise DataError(f"{path}: line {line}, column {header[j]}: {cell.strip()} is not a finite number")
            values[k, j] = v
    col = {h: values[:, j] for j, h in enumerate(header)}
    return header, col, np.array([line for line, _ in body])


def read_measured_csv(path, robot=None) -> MeasuredPoses:
    """Read and validate a measured-pose CSV.

    With ``robot`` (a RobotModel), joint values are also checked against its limits.
    """
    path = Path(path)
    header, col, lines = read_numeric_table(path, CSV_COLUMNS)

    def fail(mask, name, what):
        k = int(np.argmax(mask))
        raise DataError(f"{path}: line {lines[k]}, column {name}: {col[name][k]:.6g} {what}")

    pid = col["pose_id"]
    if np.any(pid != np.round(pid)):
        fail(pid != np.round(pid), "pose_id", "is not an integer")
    out_of_range = (pid < 0) | (pid >= MAX_STORED_POSE_ID)
    if out_of_range.any():
        fail(out_of_range, "pose_id", f"is outside 0..{MAX_STORED_POSE_ID - 1} (pose ids are non-negative integers "
                                      "stored exactly)")
    uniq, counts = np.unique(pid, return_counts=True)
    if np.any(counts > 1):
        dup = uniq[counts > 1][0]
        where = lines[pid == dup]
        raise DataError(f"{path}: pose_id {int(dup)} appears twice (lines {where[0]} and {where[1]})")
    for name in ("q1", "q2", "q3", "q4", "q5", "q6"):
        big = np.abs(col[name]) > RADIANS_MAX_ABS
        if big.any():
            fail(big, name, "exceeds 2*pi: joint values must be in rad (this looks like degrees)")
    for name in ("x", "y", "z"):
        big = np.abs(col[name]) > METRES_MAX_ABS
        if big.any():
            fail(big, name, f"exceeds {METRES_MAX_ABS:g} m: positions must be in m (this looks like mm)")
    rv = np.stack([col["rx"], col["ry"], col["rz"]], axis=1)
    big = np.linalg.norm(rv, axis=1) > math.pi + ROTVEC_NORM_SLACK
    if big.any():
        k = int(np.argmax(big))
        raise DataError(f"{path}: line {lines[k]}, columns rx,ry,rz: rotation vector norm "
                        f"{np.linalg.norm(rv[k]):.6g} exceeds pi: must be in rad (this looks like degrees)")
    q = np.stack([col[f"q{i}"] for i in range(1, 7)], axis=1)
    if robot is not None:
        lo = q < robot.q_lower - JOINT_LIMIT_SLACK
        hi = q > robot.q_upper + JOINT_LIMIT_SLACK
        if (lo | hi).any():
            k, j = np.argwhere(lo | hi)[0]
            lim = robot.q_lower[j] if lo[k, j] else robot.q_upper[j]
            raise DataError(f"{path}: line {lines[k]}, column q{j + 1}: {q[k, j]:.6g} rad is outside "
                            f"the joint limit {lim:.6g} rad of {robot.name}")
    context = {h: col[h] for h in header if h not in CSV_COLUMNS}
    return MeasuredPoses.from_vectors(pid.astype(np.int64), col["time_s"], q,
                                      np.stack([col["x"], col["y"], col["z"]], axis=1), rv, context)


def write_measured_csv(path, poses: MeasuredPoses) -> None:
    """Write poses as a measured-pose CSV (context columns after the standard ones)."""
    path = Path(path)
    extra = sorted(poses.context)
    rv = poses.rotvec
    with atomic_open(path, "w", newline="") as fh:
        w = csv.writer(fh)
        w.writerow(list(CSV_COLUMNS) + extra)
        for i in range(len(poses)):
            row = [int(poses.pose_id[i]), repr(float(poses.time_s[i]))]
            row += [repr(float(v)) for v in poses.q[i]]
            row += [repr(float(v)) for v in poses.xyz[i]]
            row += [repr(float(v)) for v in rv[i]]
            row += [repr(float(poses.context[k][i])) for k in extra]
            w.writerow(row)
