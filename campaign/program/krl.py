"""KUKA KRL: each part a module, ``NAME.src`` (the moves) with ``NAME.dat`` (its E6AXIS targets).

Joints in degrees (mm for a linear axis), ``PTP`` to ``DECL E6AXIS`` targets of the .dat (A1..A6;
a 7th..12th joint as E1..E6), exact stops (no approximation). Speed: ``$VEL_AXIS[i]`` and
``$ACC_AXIS[i]`` in percent of the machine data's axis limits, ``--speed`` × 100 (the machine
data hold the robot's datasheet limits, the ones robot.yaml states; the plan's Ruckig time of
each move is in its comment). A dwell is ``WAIT SEC s``, a trigger ``PULSE($OUT[N], TRUE, s)``.

Limits (KUKA System Software programming manual for system integrators, "Names" / data lists):
names at most 24 characters, letters, digits, ``_`` and ``$``, not starting with a digit;
a module is a .src/.dat pair named like its files. The number of data a .dat can declare is
bounded by the controller's data memory, which KUKA does not state as one number; we split at
MAX_STOPS_PER_PART stops a module (a few hundred kB a .dat), and the main module ``NAME`` calls
the parts in order. Lines are kept below MAX_LINE characters. REAL is 32-bit: 4 decimals.
"""

from __future__ import annotations

import re
import sys

import numpy as np

from campaign.program import common as C

EXTENSION = ".src"
UNITS = "deg"
DECIMALS = 4
MAX_NAME = 24
MAX_LINE = 255
MAX_STOPS_PER_PART = 1000
TRIGGER_RANGE = (1, 4096)
_AXES = [f"A{j}" for j in range(1, 7)] + [f"E{j}" for j in range(1, 7)]


def _header() -> list:
    return ["&ACCESS RVP", "&REL 1"]


def _e6axis(values) -> str:
    vals = list(values) + [0.0] * (12 - len(values))
    return "{" + ",".join(f"{a} {C.fmt(v, DECIMALS)}" for a, v in zip(_AXES, vals)) + "}"


def render(inp, *, per_part: int = MAX_STOPS_PER_PART) -> list:
    base = inp.name.lower()[:MAX_NAME - 5]
    Q, ranges, names = C.layout(sys.modules[__name__], inp, "krl", 12, base, per_part)
    pct = C.fmt(max(1.0, inp.speed * 100.0), 1)
    files = []
    for (a, b), name in zip(ranges, names):
        src = _header() + [f"DEF {name}( )", f"; {inp.robot_name}: stops {a}..{b - 1} of {len(inp.stops)}, "
                           "joints in deg (controller convention); written by `campaign program --format krl`",
                           "  BAS(#INITMOV, 0)",
                           *(f"  $VEL_AXIS[{j}] = {pct}" for j in range(1, Q.shape[1] + 1)),
                           *(f"  $ACC_AXIS[{j}] = {pct}" for j in range(1, Q.shape[1] + 1))]
        dat = _header() + [f"DEFDAT {name}"]
        for k in range(a, b):
            s = inp.stops[k]
            src += [f"  ; {C.comment(s)}", f"  PTP XS{k}  ; Ruckig {inp.move_s[k]:.2f} s"]
            src += C.dwell_lines(s, inp, lambda t: f"  WAIT SEC {C.fmt(t, 3)}",
                                 lambda n: [f"  PULSE($OUT[{n}], TRUE, {C.PULSE_S})"])
            dat.append(f"  DECL E6AXIS XS{k}={_e6axis(Q[k])}")
        src.append("END")
        dat.append("ENDDAT")
        files += [(name + ".src", "\n".join(src) + "\n"), (name + ".dat", "\n".join(dat) + "\n")]
    if len(ranges) > 1:
        main = _header() + [f"DEF {base}( )", f"; the campaign in {len(ranges)} parts, run in order",
                            *(f"  {n}( )" for n in names), "END"]
        files = [(base + ".src", "\n".join(main) + "\n"), (base + ".dat", "\n".join(_header() + [f"DEFDAT {base}",
                                                                                        "ENDDAT"]) + "\n")] + files
    return files


_DECL = re.compile(r"^\s*DECL\s+(E6AXIS|AXIS)\s+(\w+)\s*=\s*\{([^}]*)\}", re.I)
_PTP = re.compile(r"^\s*PTP\s+(\w+)", re.I)


def axis_values(body: str) -> dict:
    """{'A1': value, ...} of an AXIS/E6AXIS/E6POS aggregate's body ``A1 0.0,A2 ...``."""
    out = {}
    for item in body.split(","):
        parts = item.split()
        if len(parts) == 2:
            out[parts[0].upper()] = parts[1]
    return out


def read_joints(files, n_joints: int | None = None) -> np.ndarray:
    """The PTP targets of the .src files in order (n, N), deg/mm (controller convention); N:
    ``n_joints`` or the A axes declared."""
    decl = {}
    for name, text in files:
        if name.lower().endswith(".dat"):
            for line in text.splitlines():
                m = _DECL.match(line)
                if m:
                    decl[m.group(2).upper()] = axis_values(m.group(3))
    rows = []
    for name, text in files:
        if name.lower().endswith(".src"):
            for line in text.splitlines():
                m = _PTP.match(line)
                if m and m.group(1).upper() in decl:
                    v = decl[m.group(1).upper()]
                    n = n_joints or sum(1 for a in _AXES[:6] if a in v)
                    rows.append([float(v[a]) for a in _AXES[:n]])
    return np.array(rows, dtype=float)


def check(files, robot) -> list:
    out = []
    decl = set()
    pairs = [(r"DEF\b", r"END\b", "DEF"), (r"DEFDAT\b", r"ENDDAT\b", "DEFDAT"), (r"IF\b", r"ENDIF\b", "IF"),
             (r"FOR\b", r"ENDFOR\b", "FOR"), (r"WHILE\b", r"ENDWHILE\b", "WHILE")]
    stems = {}
    for name, text in files:
        stem, ext = name.rsplit(".", 1)
        stems.setdefault(stem, set()).add(ext.lower())
        out += C.line_problems(text, MAX_LINE, name)
        out += C.block_problems(text, [(o, c, n) for o, c, n in pairs if n != "DEF" or ext.lower() == "src"], name,
                                r";.*$")
        head = re.findall(r"^\s*(DEF|DEFDAT)\s+(\w+)", text, re.M | re.I)
        want = "DEFDAT" if ext.lower() == "dat" else "DEF"
        if [h[0].upper() for h in head[:1]] != [want] or (head and head[0][1].lower() != stem.lower()):
            out.append(f"{name}: must open with {want} {stem}")
        out += C.identifier_problems([h[1] for h in head], MAX_NAME, name, r"[A-Za-z_$][A-Za-z0-9_$]*")
        for line in text.splitlines():
            m = _DECL.match(line)
            if m:
                decl.add(m.group(2).upper())
                out += C.identifier_problems([m.group(2)], MAX_NAME, name, r"[A-Za-z_$][A-Za-z0-9_$]*")
        for k, line in enumerate(text.splitlines(), start=1):
            m = re.match(r"^\s*\$(VEL|ACC)_AXIS\[(\d+)\]\s*=\s*([-0-9.]+)", line)
            if m and not 0 < float(m.group(3)) <= 100:
                out.append(f"{name}: line {k}: ${m.group(1)}_AXIS must be a percentage in (0, 100]")
    for stem, exts in stems.items():
        if exts != {"src", "dat"}:
            out.append(f"{stem}: a KRL module is a .src/.dat pair, found {', '.join(sorted(exts))}")
    out += C.undeclared_targets(files, _PTP, decl, "PTP")
    out += C.limit_problems(read_joints(files, robot.n_joints), robot, UNITS, "krl", DECIMALS)
    return out
