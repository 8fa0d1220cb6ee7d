"""The ``csv`` program: one row per stop, ``stop,pose_id,kind,dwell_s,j1..jN`` with the joints in
the controller's convention (rad, m), for controllers and tools that import a joint table.
(RUN/program/stops.csv, written beside every program, holds the same stops in the model's
convention, q1..qN.)"""

from __future__ import annotations

import csv
import io

import numpy as np

EXTENSION = ".csv"
UNITS = "rad"
#: full precision (repr): read back exactly
DECIMALS = 15


def render(inp) -> list:
    if inp.trigger_output is not None:
        from campaign.errors import ConfigError

        raise ConfigError("--trigger-output: a csv joint table carries no digital outputs")
    N = inp.q_controller.shape[1]
    buf = io.StringIO()
    w = csv.writer(buf, lineterminator="\n")
    w.writerow(["stop", "pose_id", "kind", "dwell_s", *(f"j{j}" for j in range(1, N + 1))])
    for s, q in zip(inp.stops, inp.q_controller):
        w.writerow([s.stop, s.pose_id, s.kind, repr(float(s.dwell_s)), *(repr(float(v)) for v in q)])
    return [(inp.name.lower() + EXTENSION, buf.getvalue())]


def read_joints(files) -> np.ndarray:
    """The joint targets of a csv program (n, N), controller convention, rad/m."""
    text = files[0][1] if isinstance(files, list) else files
    rows = list(csv.reader(io.StringIO(text)))
    head = rows[0]
    cols = [i for i, h in enumerate(head) if h.startswith("j") and h[1:].isdigit()]
    return np.array([[float(r[i]) for i in cols] for r in rows[1:] if r], dtype=float)


def check(files, robot) -> list:
    """Header ``stop,pose_id,kind,dwell_s,j1..jN``, one row a stop numbered in order, known kinds,
    dwell >= 0, joints within the limits."""
    from campaign.program import common as C
    from campaign.program.stops import KINDS

    name, text = files[0]
    rows = list(csv.reader(io.StringIO(text)))
    N = robot.n_joints
    want = ["stop", "pose_id", "kind", "dwell_s", *(f"j{j}" for j in range(1, N + 1))]
    if not rows or rows[0] != want:
        return [f"{name}: header must be {','.join(want)}"]
    out = []
    for k, r in enumerate(rows[1:]):
        if len(r) != len(want) or r[0] != str(k) or r[2] not in KINDS or float(r[3]) < 0:
            out.append(f"{name}: line {k + 2}: expected stop {k}, a kind of {', '.join(KINDS)}, dwell_s >= 0")
            break
    return out or C.limit_problems(read_joints(text), robot, UNITS, name, DECIMALS)
