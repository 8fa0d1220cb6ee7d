"""ABB RAPID: each part a module (``NAME.mod``) of ``jointtarget`` data and ``MoveAbsJ`` moves.

Joints in degrees (mm for a linear axis; robax rax_1..rax_6, a 7th joint in eax_a, unused
external axes 9E9), exact stops (zone ``fine``). Speed: ``VelSet`` and ``AccSet`` at ``--speed``
× 100 %, and each move's time ``\\T`` is the plan's Ruckig time at that speed (the controller
moves no faster than its own axis limits when that time is too short). A dwell is ``WaitTime s``,
a trigger ``PulseDO\\PLength:=s, DO<N>`` (a digital output signal of that name must be configured).

Limits (ABB RAPID overview / technical reference manual, "Identifiers"): names at most 32
characters, letters, digits and ``_``, starting with a letter; one ``PROC main`` a task. A
module's size is bounded by the task's program memory, which ABB gives per controller, not per
module; we split at MAX_STOPS_PER_PART stops a module: module ``NAME`` holds ``main``, which
calls ``NAME_1`` .. ``NAME_k`` (each in its own module) in order. ``num`` is 32-bit: 4 decimals.
"""

from __future__ import annotations

import re
import sys

import numpy as np

from campaign.program import common as C

EXTENSION = ".mod"
UNITS = "deg"
DECIMALS = 4
MAX_NAME = 32
MAX_LINE = 255
MAX_STOPS_PER_PART = 1000
TRIGGER_RANGE = (0, 9999)


def _jointtarget(values) -> str:
    vals = list(values)
    rob, ext = vals[:6] + [0.0] * (6 - min(len(vals), 6)), vals[6:]
    ext = ext + [9e9] * (6 - len(ext))
    return ("[[" + ",".join(C.fmt(v, DECIMALS) for v in rob) + "],["
            + ",".join("9E9" if v == 9e9 else C.fmt(v, DECIMALS) for v in ext) + "]]")


def render(inp, *, per_part: int = MAX_STOPS_PER_PART) -> list:
    base = inp.name.upper()[:MAX_NAME - 5]
    Q, ranges, names = C.layout(sys.modules[__name__], inp, "rapid", 12, base, per_part)
    pct = C.fmt(max(1.0, inp.speed * 100.0), 1)
    files = []
    for (a, b), name in zip(ranges, names):
        proc = "main" if len(ranges) == 1 else name
        lines = [f"MODULE {name}",
                 f"  ! {inp.robot_name}: stops {a}..{b - 1} of {len(inp.stops)}, joints in deg (controller "
                 "convention); written by `campaign program --format rapid`"]
        lines += [f"  CONST jointtarget S{k}:={_jointtarget(Q[k])};" for k in range(a, b)]
        lines += [f"  PROC {proc}()", f"    VelSet {pct}, 5000;", f"    AccSet {pct}, 100;"]
        for k in range(a, b):
            s = inp.stops[k]
            t = f"\\T:={C.fmt(inp.move_s[k], 3)}" if inp.move_s[k] > 0 else ""
            lines += [f"    ! {C.comment(s)}", f"    MoveAbsJ S{k}\\NoEOffs, v1000{t}, fine, tool0;"]
            lines += C.dwell_lines(s, inp, lambda t: f"    WaitTime {C.fmt(t, 3)};",
                                   lambda n: [f"    PulseDO\\PLength:={C.PULSE_S}, DO{n};"])
        lines += ["  ENDPROC", "ENDMODULE"]
        files.append((name + EXTENSION, "\n".join(lines) + "\n"))
    if len(ranges) > 1:
        main = [f"MODULE {base}", f"  ! the campaign in {len(ranges)} parts, run in order", "  PROC main()",
                *(f"    {n};" for n in names), "  ENDPROC", "ENDMODULE"]
        files = [(base + EXTENSION, "\n".join(main) + "\n")] + files
    return files


_JT = re.compile(r"^\s*(?:LOCAL\s+)?(CONST|PERS|VAR)\s+jointtarget\s+(\w+)\s*:=\s*\[\s*\[([^\]]*)\]\s*,\s*\[([^\]]*)\]\s*\]",
                 re.I)
_MOVE = re.compile(r"^\s*MoveAbsJ\s+(\w+)", re.I)


def _floats(text: str) -> list:
    return [float(x) for x in text.split(",")]


def read_joints(files, n_joints: int | None = None) -> np.ndarray:
    """The MoveAbsJ targets in order (n, N), deg/mm (controller convention)."""
    decl = {}
    for _, text in files:
        for line in text.splitlines():
            m = _JT.match(line)
            if m:
                decl[m.group(2).upper()] = _floats(m.group(3)) + _floats(m.group(4))
    rows = []
    for _, text in files:
        for line in text.splitlines():
            m = _MOVE.match(line)
            if m and m.group(1).upper() in decl:
                v = decl[m.group(1).upper()]
                n = n_joints or 6
                rows.append(v[:6][:n] + v[6:6 + max(n - 6, 0)])
    return np.array(rows, dtype=float)


def check(files, robot) -> list:
    out = []
    decl, mains = set(), 0
    for name, text in files:
        out += C.line_problems(text, MAX_LINE, name)
        out += C.block_problems(text, [(r"MODULE\b", r"ENDMODULE\b", "MODULE"), (r"PROC\b", r"ENDPROC\b", "PROC"),
                                       (r"IF\b.*\bTHEN$", r"ENDIF\b", "IF"), (r"FOR\b", r"ENDFOR\b", "FOR"),
                                       (r"WHILE\b", r"ENDWHILE\b", "WHILE")], name, r"!.*$")
        mods = re.findall(r"^\s*MODULE\s+(\w+)", text, re.M | re.I)
        if len(mods) != 1 or mods[0].upper() != name.rsplit(".", 1)[0].upper():
            out.append(f"{name}: must hold one MODULE named like the file")
        procs = re.findall(r"^\s*PROC\s+(\w+)\s*\(", text, re.M | re.I)
        mains += sum(p.lower() == "main" for p in procs)
        out += C.identifier_problems(mods + procs, MAX_NAME, name)
        for k, line in enumerate(text.splitlines(), start=1):
            s = re.sub(r"!.*$", "", line).strip()
            if s and not s.endswith(";") and not re.match(r"(MODULE|ENDMODULE|PROC|ENDPROC)\b", s, re.I):
                out.append(f"{name}: line {k}: a statement must end with ';'")
            m = _JT.match(line)
            if m:
                decl.add(m.group(2).upper())
                out += C.identifier_problems([m.group(2)], MAX_NAME, name)
            m = re.search(r"\\T:=([-0-9.eE]+)", s)
            if m and float(m.group(1)) <= 0:
                out.append(f"{name}: line {k}: \\T must be > 0")
    if mains != 1:
        out.append(f"rapid: {mains} PROC main, a task needs exactly one")
    out += C.undeclared_targets(files, _MOVE, decl, "MoveAbsJ")
    out += C.limit_problems(read_joints(files, robot.n_joints), robot, UNITS, "rapid", DECIMALS)
    return out
