"""COMAU PDL2: each part a program ``NAME.pdl`` setting one JOINTPOS with ``JNT`` and moving to it.

Joints in degrees (mm for a linear axis), in the controller's convention (robot.yaml's
``controller:`` coupling applied: e.g. an arm whose controller counts joint 3 from joint 2),
exact stops (``$TERM_TYPE := FINE``). Speed: ``$PROG_SPD_OVR``, ``$PROG_ACC_OVR`` and
``$PROG_DEC_OVR`` at ``--speed`` × 100 % of the arm's limits (the plan's Ruckig time of each move
is in its comment). A dwell is ``DELAY ms``, a trigger ``PULSE $DOUT[N] FOR ms``.

Limits (COMAU PDL2 programming language manual, "identifiers" and "program structure"):
identifiers are letters, digits and ``_`` starting with a letter; we keep names within
MAX_NAME characters, which the controller's file names also accept; ``PROGRAM name`` ..
``BEGIN`` .. ``END name``. A program's size is bounded by the controller's memory for compiled
code (.cod), which COMAU states per controller; we split at MAX_STOPS_PER_PART stops a program:
NAME_1, NAME_2, ... run in order (each starts where the one before ended). REAL is 32-bit:
4 decimals.
"""

from __future__ import annotations

import re

import numpy as np

from campaign.program import common as C

EXTENSION = ".pdl"
UNITS = "deg"
DECIMALS = 4
MAX_NAME = 16
MAX_LINE = 255
MAX_STOPS_PER_PART = 1000
TRIGGER_RANGE = (1, 4096)


def render(inp, *, per_part: int = MAX_STOPS_PER_PART) -> list:
    C.check_trigger("pdl2", inp.trigger_output, *TRIGGER_RANGE)
    C.check_axes("pdl2", inp, 10)
    Q = C.in_units(inp, UNITS)
    ranges = C.parts(len(inp.stops), per_part)
    base = inp.name.lower()[:MAX_NAME - 1 - len(str(len(ranges)))] if len(ranges) > 1 else inp.name.lower()[:MAX_NAME]
    pct = int(max(1, min(100, round(inp.speed * 100))))
    files = []
    for k_part, (a, b) in enumerate(ranges):
        name = C.part_name(base, k_part, len(ranges))
        lines = [f"PROGRAM {name} PROG_ARM = 1",
                 f"-- {inp.robot_name}: stops {a}..{b - 1} of {len(inp.stops)}, joints in deg (controller "
                 "convention); written by `campaign program --format pdl2`",
                 "VAR", "  jp : JOINTPOS FOR ARM[1]", "BEGIN",
                 f"  $PROG_SPD_OVR := {pct}", f"  $PROG_ACC_OVR := {pct}", f"  $PROG_DEC_OVR := {pct}",
                 "  $TERM_TYPE := FINE"]
        for k in range(a, b):
            s = inp.stops[k]
            vals = ", ".join(C.fmt(v, DECIMALS) for v in Q[k])
            lines += [f"  -- {C.comment(s)}", f"  JNT(jp, {vals})", f"  MOVE JOINT TO jp  -- Ruckig {inp.move_s[k]:.2f} s"]
            lines += C.dwell_lines(s, inp, lambda t: f"  DELAY {int(round(t * 1000))}",
                                   lambda n: [f"  PULSE $DOUT[{n}] FOR {int(round(C.PULSE_S * 1000))}"])
        lines.append(f"END {name}")
        files.append((name + EXTENSION, "\n".join(lines) + "\n"))
    return files


_JNT = re.compile(r"^\s*JNT\s*\(\s*(\w+)\s*,([^)]*)\)", re.I)


def read_joints(files, n_joints: int | None = None) -> np.ndarray:
    """The JNT targets moved to, in order (n, N), deg/mm (controller convention)."""
    rows = []
    for _, text in files:
        current = {}
        for line in text.splitlines():
            m = _JNT.match(line)
            if m:
                current[m.group(1).lower()] = [float(x) for x in m.group(2).split(",")]
            mv = re.match(r"^\s*MOVE\s+JOINT\s+TO\s+(\w+)", line, re.I)
            if mv and mv.group(1).lower() in current:
                v = current[mv.group(1).lower()]
                rows.append(v[:n_joints] if n_joints else v)
    return np.array(rows, dtype=float)


def check(files, robot) -> list:
    out = []
    for name, text in files:
        before = len(out)
        stem = name.rsplit(".", 1)[0]
        out += C.line_problems(text, MAX_LINE, name)
        lines = [re.sub(r"--.*$", "", ln).strip() for ln in text.splitlines()]
        body = [ln for ln in lines if ln]
        head = re.match(r"PROGRAM\s+(\w+)", body[0] if body else "", re.I)
        if not head or head.group(1).lower() != stem.lower():
            out.append(f"{name}: must open with PROGRAM {stem}")
        if not body or body[-1].lower() != f"end {stem.lower()}":
            out.append(f"{name}: must close with END {stem}")
        if sum(ln.upper() == "BEGIN" for ln in body) != 1:
            out.append(f"{name}: needs one BEGIN")
        out += C.identifier_problems([stem], MAX_NAME, name)
        out += C.block_problems(text, [(r"IF\b.*\bTHEN$", r"ENDIF\b", "IF"), (r"FOR\b", r"ENDFOR\b", "FOR"),
                                       (r"WHILE\b", r"ENDWHILE\b", "WHILE")], name, r"--.*$")
        declared = {m.group(1).lower() for ln in lines if (m := re.match(r"(\w+)\s*:\s*JOINTPOS\b", ln, re.I))}
        begin = next((i for i, ln in enumerate(lines) if ln.upper() == "BEGIN"), len(lines))
        for k, ln in enumerate(lines[begin + 1:], start=begin + 2):
            m = _JNT.match(ln) or re.match(r"MOVE\s+JOINT\s+TO\s+(\w+)", ln, re.I)
            if m and m.group(1).lower() not in declared:
                out.append(f"{name}: line {k}: {m.group(1)} is not declared as a JOINTPOS")
            if _JNT.match(ln) and len(_JNT.match(ln).group(2).split(",")) != robot.n_joints:
                out.append(f"{name}: line {k}: JNT needs {robot.n_joints} axis values")
            d = re.match(r"DELAY\s+(\S+)$", ln, re.I)
            if d and not d.group(1).isdigit():
                out.append(f"{name}: line {k}: DELAY takes whole milliseconds")
        if len(out) > before:
            continue
    out += C.limit_problems(read_joints(files, robot.n_joints), robot, UNITS, "pdl2", DECIMALS)
    return out
