"""FANUC TP as its ASCII form, LS: each part a program ``NAME.ls`` of ``J P[i]`` moves with the
positions in its ``/POS`` section as joint values.

Joints in degrees (mm for a linear axis; J1..J6, a 7th..9th joint as E1..E3 of group 1), exact
stops (``FINE``). Speed: ``J P[i] s%`` with s = ``--speed`` × 100 (percent of the axes' limits in
the controller's parameters, the datasheet limits robot.yaml states; the plan's Ruckig time of each
move is in the comment before it). A dwell is ``WAIT s(sec)``, a trigger ``DO[N]=PULSE,s sec``.

Limits (FANUC R-30iA/R-30iB controller operator's manuals, "program name" and "comment"): program
names at most 8 characters on older controllers (36 on R-30iB and later: we keep 8), upper-case
letters, digits and ``_``, starting with a letter; a comment line (``!``) at most 32 characters.
The number of lines and positions a TP program may hold is bounded by the controller's TP memory
(FANUC gives no single figure; large programs also load slowly through the ASCII loader), so we
split at MAX_STOPS_PER_PART stops (positions P[1..500], about 2,500 lines) a program; the program
``NAME`` calls the parts in order. Positions are written with 4 decimals: the pendant shows 3, but
the controller keeps 32-bit reals and the ASCII loader reads more digits (generated LS files carry
6); 3 would leave up to 0.0005° a joint, about 10 µm at the tool, the size of a tracker's noise.
"""

from __future__ import annotations

import re

import numpy as np

from campaign.program import common as C

EXTENSION = ".ls"
UNITS = "deg"
DECIMALS = 4
MAX_NAME = 8
MAX_COMMENT = 32
MAX_LINE = 255
MAX_STOPS_PER_PART = 500
TRIGGER_RANGE = (1, 4096)
_AXES = [f"J{j}" for j in range(1, 7)] + ["E1", "E2", "E3"]


def _names(base: str, n_parts: int) -> tuple:
    """(main name, [part names]) within MAX_NAME characters."""
    base = re.sub(r"[^A-Z0-9_]", "", base.upper().replace("CAL_", "CAL"))[:MAX_NAME] or "CAL"
    if n_parts == 1:
        return base, [base]
    width = len(str(n_parts))
    stem = base[:MAX_NAME - width - 1]
    return base, [f"{stem}_{k + 1:0{width}d}" for k in range(n_parts)]


def _attr(name: str, n_lines: int, comment: str) -> list:
    return ["/ATTR", "OWNER\t\t= MNEDITOR;", f'COMMENT\t\t= "{comment[:16]}";', "PROG_SIZE\t= 0;",
            f"FILE_NAME\t= {name};", "VERSION\t\t= 0;", f"LINE_COUNT\t= {n_lines};", "MEMORY_SIZE\t= 0;",
            "PROTECT\t\t= READ_WRITE;",
            "TCD:  STACK_SIZE\t= 0,", "      TASK_PRIORITY\t= 50,", "      TIME_SLICE\t= 0,",
            "      BUSY_LAMP_OFF\t= 0,", "      ABORT_REQUEST\t= 0,", "      PAUSE_REQUEST\t= 0;",
            "DEFAULT_GROUP\t= 1,*,*,*,*;", "CONTROL_CODE\t= 00000000 00000000;"]


def _program(name: str, mn: list, pos: list, comment: str) -> str:
    lines = [f"/PROG  {name}"] + _attr(name, len(mn), comment) + ["/MN"]
    # motion statements follow the line number directly, others after two blanks (as the LS files
    # a controller writes)
    lines += [f"{k:4d}:{stmt}    ;" if re.match(r"[JL] P\[", stmt) else f"{k:4d}:  {stmt} ;"
              for k, stmt in enumerate(mn, start=1)]
    lines += ["/POS"] + pos + ["/END"]
    return "\n".join(lines) + "\n"


def _position(i: int, values, prismatic) -> list:
    items = [f"{a}={C.fmt(v, DECIMALS):>10} {'mm' if p else 'deg'}" for a, v, p in zip(_AXES, values, prismatic)]
    rows = [",\t".join(items[r:r + 3]) for r in range(0, len(items), 3)]
    return [f"P[{i}]{{", "   GP1:", "\tUF : 0, UT : 1,", *("\t" + r + ("," if k < len(rows) - 1 else "")
                                                          for k, r in enumerate(rows)), "};"]


def render(inp, *, per_part: int = MAX_STOPS_PER_PART) -> list:
    C.check_trigger("fanuc-ls", inp.trigger_output, *TRIGGER_RANGE)
    C.check_axes("fanuc-ls", inp, 9)
    Q = C.in_units(inp, UNITS)
    ranges = C.parts(len(inp.stops), per_part)
    main, names = _names(inp.name, len(ranges))
    pct = int(max(1, min(100, round(inp.speed * 100))))
    files = []
    for (a, b), name in zip(ranges, names):
        mn, pos = [f"! stops {a}..{b - 1} of {len(inp.stops)}"[:MAX_COMMENT]], []
        for i, k in enumerate(range(a, b), start=1):
            s = inp.stops[k]
            mn += [f"! {C.comment(s)}"[:MAX_COMMENT + 2], f"J P[{i}] {pct}% FINE"]
            mn += C.dwell_lines(s, inp, lambda t: f"WAIT {t:.2f}(sec)", lambda n: [f"DO[{n}]=PULSE,{C.PULSE_S}sec"])
            pos += _position(i, Q[k], inp.prismatic)
        files.append((name + EXTENSION, _program(name, mn, pos, "campaign")))
    if len(ranges) > 1:
        files = [(main + EXTENSION, _program(main, [f"CALL {n}" for n in names], [], "campaign"))] + files
    return files


_MOTION = re.compile(r"^\s*\d+:\s*J\s+P\[(\d+)(?::[^\]]*)?\]")
_POS = re.compile(r"P\[(\d+)(?::[^\]]*)?\]\s*\{(.*?)\};", re.S)
_AXIS_VAL = re.compile(r"\b(J\d|E\d)\s*=\s*([-+0-9.]+)\s*(deg|mm)")


def positions(text: str) -> dict:
    """{index: {'J1': value, ...}} of an LS program's /POS section (joint positions only)."""
    body = text.split("/POS", 1)[1] if "/POS" in text else ""
    out = {}
    for m in _POS.finditer(body):
        vals = dict((a, float(v)) for a, v, _ in _AXIS_VAL.findall(m.group(2)))
        if vals:
            out[int(m.group(1))] = vals
    return out


def read_joints(files, n_joints: int | None = None) -> np.ndarray:
    """The J P[i] targets of the parts in order (n, N), deg/mm (controller convention)."""
    rows = []
    for _, text in files:
        pos = positions(text)
        mn = text.split("/MN", 1)[1].split("/POS", 1)[0] if "/MN" in text else ""
        for line in mn.splitlines():
            m = _MOTION.match(line)
            if m and int(m.group(1)) in pos:
                v = pos[int(m.group(1))]
                n = n_joints or sum(1 for a in _AXES[:6] if a in v)
                rows.append([v[a] for a in _AXES[:n]])
    return np.array(rows, dtype=float)


def check(files, robot) -> list:
    out = []
    for name, text in files:
        out += C.line_problems(text, MAX_LINE, name)
        head = re.match(r"/PROG\s+(\w+)", text)
        stem = name.rsplit(".", 1)[0]
        if not head or head.group(1) != stem:
            out.append(f"{name}: must open with /PROG {stem}")
        out += C.identifier_problems([stem], MAX_NAME, name, r"[A-Z][A-Z0-9_]*")
        for sec in ("/ATTR", "/MN", "/POS", "/END"):
            if text.count(sec) != 1:
                out.append(f"{name}: needs one {sec} section")
        if out:
            continue
        mn = text.split("/MN", 1)[1].split("/POS", 1)[0].strip().splitlines()
        for k, line in enumerate(mn, start=1):
            m = re.match(r"^\s*(\d+):\s*(.*?)\s*;\s*$", line)
            if not m or int(m.group(1)) != k:
                out.append(f"{name}: /MN line {k} must read '{k}:  ... ;'")
                continue
            stmt = m.group(2)
            if stmt.startswith("!") and len(stmt) - 1 > MAX_COMMENT:
                out.append(f"{name}: /MN line {k}: comment longer than {MAX_COMMENT} characters")
            j = re.match(r"J P\[(\d+)\] (\d+)% FINE$", stmt)
            if stmt.startswith("J ") and (not j or not 1 <= int(j.group(2)) <= 100):
                out.append(f"{name}: /MN line {k}: joint move must read 'J P[i] s% FINE' with s in 1..100")
        lc = re.search(r"LINE_COUNT\s*=\s*(\d+);", text)
        if not lc or int(lc.group(1)) != len(mn):
            out.append(f"{name}: LINE_COUNT does not match the {len(mn)} lines of /MN")
        pos = positions(text)
        used = [int(m.group(1)) for line in mn if (m := _MOTION.match(line))]
        missing = sorted(set(used) - set(pos))
        if missing:
            out.append(f"{name}: P[{missing[0]}] is used but not in /POS")
        if sorted(pos) != list(range(1, len(pos) + 1)):
            out.append(f"{name}: /POS positions must be numbered 1..n")
        if len(re.findall(r"\{", text)) != len(re.findall(r"\};", text)):
            out.append(f"{name}: a /POS block is not closed")
    if not out:
        out += C.limit_problems(read_joints(files, robot.n_joints), robot, UNITS, "fanuc-ls", DECIMALS)
    return out
