"""URScript (Universal Robots): one ``def ... end`` program of ``movej`` moves in radians.

Joint moves ``movej([q1, ..., q6], a=A, v=V)``: V and A are the leading axis's speed (rad/s) and
acceleration (rad/s²), the largest that keep every joint within robot.yaml's limits at
``--speed`` (campaign.program.common.lead_speed); the plan's Ruckig time of the move is in the
comment. A dwell is ``sleep(s)``; a trigger ``set_standard_digital_out(N, True)`` for
PULSE_S. Size: the controller takes the program as one script (sent to the secondary interface,
port 30002, or loaded as a script file); no documented line or size limit, so it is not split.
Numbers: double precision; joints written with 9 decimals (1 nrad).
"""

from __future__ import annotations

import re

import numpy as np

from campaign.program import common as C

EXTENSION = ".script"
UNITS = "rad"
DECIMALS = 9
#: no line-length limit in the language; generated lines stay below this for readability
MAX_LINE = 200
#: the controller's standard digital outputs
TRIGGER_RANGE = (0, 7)


def render(inp) -> list:
    C.check_trigger("urscript", inp.trigger_output, *TRIGGER_RANGE)
    name = inp.name.lower()
    Q = C.in_units(inp, UNITS)
    out = [f"# {inp.robot_name}: {len(inp.stops)} stops, joints in rad (controller convention); "
           f"written by `campaign program --format urscript`",
           f"def {name}():"]
    for k, s in enumerate(inp.stops):
        v, a = C.lead_speed(inp, k)
        out.append(f"  # {C.comment(s)}")
        q = ", ".join(C.fmt(x, DECIMALS) for x in Q[k])
        out.append(f"  movej([{q}], a={C.fmt(a, 6)}, v={C.fmt(v, 6)})  # Ruckig {inp.move_s[k]:.2f} s")
        out += C.dwell_lines(s, inp, lambda t: f"  sleep({C.fmt(t, 3)})",
                             lambda n: [f"  set_standard_digital_out({n}, True)", f"  sleep({C.PULSE_S})",
                                        f"  set_standard_digital_out({n}, False)"], pulse_blocks=True)
    out.append("end")
    return [(name + EXTENSION, "\n".join(out) + "\n")]


_MOVEJ = re.compile(r"^\s*movej\(\s*\[([^\]]*)\]\s*(?:,\s*a\s*=\s*([-+0-9.eE]+))?\s*(?:,\s*v\s*=\s*([-+0-9.eE]+))?")


def _text(files) -> str:
    return "\n".join(t for _, t in files) if isinstance(files, list) else files


def read_moves(files) -> list:
    """[(q list, a or None, v or None), ...] of the movej lines, in order."""
    out = []
    for line in _text(files).splitlines():
        m = _MOVEJ.match(line)
        if m:
            out.append(([float(x) for x in m.group(1).split(",")], m.group(2) and float(m.group(2)),
                        m.group(3) and float(m.group(3))))
    return out


def read_joints(files) -> np.ndarray:
    """The movej targets (n, N), rad (controller convention)."""
    return np.array([q for q, _, _ in read_moves(files)], dtype=float)


def check(files, robot) -> list:
    """Structural problems of a URScript program (empty list: none)."""
    out = []
    for name, text in files:
        out += C.line_problems(text, MAX_LINE, name)
        out += C.block_problems(text, [(r"def\b|if\b|while\b|thread\b", r"end\b", "block")], name, r"#.*$")
        defs = re.findall(r"^def\s+(\w+)\(\)\s*:", text, re.M)
        if len(defs) != 1:
            out.append(f"{name}: expected one program (def NAME():), found {len(defs)}")
        out += C.identifier_problems(defs, 64, name)
        for k, line in enumerate(text.splitlines(), start=1):
            s = line.strip()
            if s.startswith("movej") and not _MOVEJ.match(line):
                out.append(f"{name}: line {k}: malformed movej")
            if s.startswith("sleep(") and not re.fullmatch(r"sleep\(\d+(\.\d+)?\)", s):
                out.append(f"{name}: line {k}: malformed sleep")
    moves = read_moves(files)
    bad = [k for k, (q, a, v) in enumerate(moves) if len(q) != robot.n_joints or not a or not v or a <= 0 or v <= 0]
    out += [f"movej {k + 1}: needs {robot.n_joints} joints and a, v > 0" for k in bad[:5]]
    if not bad and moves:
        Q = np.array([q for q, _, _ in moves])
        out += C.limit_problems(Q, robot, UNITS, files[0][0], DECIMALS)
        out += speed_problems(Q, [v for _, _, v in moves], [a for _, a, _ in moves], robot)
    return out


def speed_problems(Q, v_lead, a_lead, robot) -> list:
    """Moves whose leading-axis speed or acceleration drives some joint past its limit (rad)."""
    from campaign.program.generate import _limits_controller

    vmax, amax = _limits_controller(robot)
    out = []
    for k in range(1, len(Q)):
        dq = np.abs(Q[k] - Q[k - 1])
        if dq.max() <= 0:
            continue
        share = dq / dq.max()
        tol = 1 + 1e-5  # the 6 printed decimals
        if np.any(v_lead[k] * share > vmax * tol) or np.any(a_lead[k] * share > amax * tol):
            out.append(f"move {k + 1}: the leading axis's v={v_lead[k]} a={a_lead[k]} exceed a joint's limit")
    return out
