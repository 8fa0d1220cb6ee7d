"""`campaign compensate RUN --program FILE --format F`: a robot program's targets filtered through
the calibration, every other character left as it was.

A **joint target** (controller convention and units) becomes the joints that bring the calibrated
robot to the pose the nominal robot reaches at the written joints:
q' = compensate(FK_nominal(q)) (campaign.identify.use.CalibratedRobot.compensate).
A **Cartesian target** T (the pose of the run's tool frame in its base frame, the program's
length unit and orientation convention) becomes the target the nominal controller must be given
so that the calibrated robot reaches T: the joints q with calibrated(q) = T, started from the
nominal inverse kinematics in the configuration the target writes where it can be read (KRL's T
bits, RAPID's quadrants of axes 1, 4, 6, FANUC's turns of J1, J4, J6; not what depends on the
arm's geometry: KRL's S, RAPID's cfx, FANUC's F/N U/D T/B), within it the solution reached from the
target before (a program's configuration is followed), then T' = FK_nominal(q), which the nominal
controller turns back into q. Configuration flags are kept as written.

Only the numbers of a target are replaced (each written with at least as many decimals as it
had, and the format's precision); what looks like a target but cannot be read is listed with its
line and left as it was. Targets outside the calibrated domain (a model is not known beyond its
data: the calibration's domain.json, campaign.identify.domain, at the corrected joints) are named,
as are targets the calibrated model could not reach (not converged: left as written).

Formats: ``urscript`` (``p[x, y, z, rx, ry, rz]`` in m and rotation vector; joint lists
``[q1, ..., qN]`` in rad), ``krl`` (.src or .dat: ``{A1 .., A6 ..}`` axis aggregates in deg and
``{X .., Y .., Z .., A .., B .., C ..}`` POS/E6POS aggregates in mm, R = Rz(A) Ry(B) Rx(C); FRAME
aggregates are frames, not targets), ``rapid`` (jointtarget ``[[rax_1..6], [eax_a..f]]`` in deg;
robtarget ``[[x, y, z], [q1..q4], conf, extax]`` in mm and a quaternion w, x, y, z), ``fanuc-ls``
(/POS positions: J1.. in deg, or X, Y, Z mm and W, P, R deg, R = Rz(R) Ry(P) Rx(W)), ``pdl2``
(``JNT(var, ...)`` deg; ``POS(x, y, z, e1, e2, e3, 'cnfg')`` mm and Z-Y-Z Euler deg),
``ros2-trajectory`` (every point's ``positions``, rad), ``csv`` (``j1..jN`` columns, rad).
"""

from __future__ import annotations

import re
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from campaign.errors import ConfigError, DataError

NUM = r"[-+]?(?:\d+\.?\d*|\.\d+)(?:[eE][-+]?\d+)?"
_NUM = re.compile(NUM)
FORMATS = ("urscript", "krl", "rapid", "fanuc-ls", "pdl2", "ros2-trajectory", "csv")


@dataclass
class Target:
    """One target of a program: ``spans`` [(start, end)] of its numbers in the text, ``values``
    as written, ``kind`` ``joint`` (values in the format's joint units, controller convention) or
    ``pose`` (``convention`` names how values give a pose), its ``line`` (1-based)."""

    kind: str
    spans: list
    values: list
    line: int
    convention: str = ""
    name: str = ""
    #: a Cartesian target's configuration as written, as a test of controller joints (N,) in
    #: degrees: KRL's T bits (the sign of each axis), RAPID's quadrants of axes 1, 4, 6, FANUC's
    #: turn numbers of J1, J4, J6; None when not given or not read
    config: object = None


@dataclass
class Unclear:
    line: int
    text: str
    why: str


@dataclass
class Scan:
    targets: list = field(default_factory=list)
    unclear: list = field(default_factory=list)


def _line_of(text: str, pos: int) -> int:
    return text.count("\n", 0, pos) + 1


def _numbers(text: str, start: int, end: int) -> tuple:
    """(spans, values) of the numbers in text[start:end]."""
    spans, vals = [], []
    for m in _NUM.finditer(text, start, end):
        spans.append((m.start(), m.end()))
        vals.append(float(m.group()))
    return spans, vals


# -- the formats' targets --------------------------------------------------------------------

def _unread(text: str, declaration: str, found_lines: set) -> list:
    """Lines declaring a target (regex ``declaration``) where no target value was read."""
    return [Unclear(k, ln.strip()[:60], "a target declaration whose value could not be read")
            for k, ln in enumerate(text.splitlines(), start=1)
            if re.search(declaration, ln, re.I) and k not in found_lines]


#: URScript calls a pose or a joint list is a target in (as their first argument or anywhere: a via)
UR_MOTIONS = ("movej", "movel", "movep", "movec", "servoj")
#: calls whose first argument is a pose the result is placed by (a base target), the others offsets
UR_POSE_OPS = ("pose_trans", "pose_add")


def _enclosing_call(text: str, pos: int) -> tuple:
    """(name, argument index) of the innermost call whose parenthesis is open at ``pos`` on its
    line, (None, 0) outside any call: ("set_tcp", 0) for the p[...] of ``set_tcp(p[...])``."""
    line_start = text.rfind("\n", 0, pos) + 1
    stack = []
    for m in re.finditer(r"([A-Za-z_]\w*)?\s*\(|\)|,|\[|\]", text[line_start:pos]):
        tok = m.group()
        if tok == ")" and stack:
            stack.pop()
        elif tok.endswith("("):
            stack.append([m.group(1), 0, 0])  # name, argument index, open brackets
        elif stack and tok in "[]":
            stack[-1][2] += 1 if tok == "[" else -1
        elif stack and tok == "," and stack[-1][2] == 0:
            stack[-1][1] += 1
    return (stack[-1][0], stack[-1][1]) if stack else (None, 0)


def _scan_urscript(text: str, n: int) -> Scan:
    out = Scan()
    for m in re.finditer(r"(p?)\[([^\[\]]*)\]", text):
        body = m.group(2)
        if not body.strip() or not re.fullmatch(rf"\s*{NUM}(\s*,\s*{NUM})*\s*", body):
            continue
        call, arg = _enclosing_call(text, m.start())
        if call is not None and call not in UR_MOTIONS and not (call in UR_POSE_OPS and arg == 0):
            continue  # an argument of set_tcp, force_mode, pose_trans's offset, ...: a tool, a wrench, an offset
        spans, vals = _numbers(text, m.start(2), m.end(2))
        line = _line_of(text, m.start())
        if m.group(1):
            if len(vals) == 6:
                out.targets.append(Target("pose", spans, vals, line, "m_rotvec"))
            else:
                out.unclear.append(Unclear(line, m.group(), f"a pose p[...] of {len(vals)} values, not 6"))
        elif len(vals) == n:
            out.targets.append(Target("joint", spans, vals, line))
        elif re.search(r"\b(movej|movel|movep|servoj|movec)\s*\(\s*$", text[max(0, m.start() - 40):m.start()]):
            out.unclear.append(Unclear(line, m.group(), f"a joint list of {len(vals)} values, the robot has {n}"))
    return out


def _krl_items(body: str, offset: int) -> dict:
    """{NAME: (span, value)} of an aggregate body ``NAME value, ...``."""
    items = {}
    for m in re.finditer(rf"([A-Za-z_]\w*)\s+({NUM})", body):
        items[m.group(1).upper()] = ((offset + m.start(2), offset + m.end(2)), float(m.group(2)))
    return items


def _kuka_turn(items):
    """KRL's T (turn) bits: bit j set when axis j + 1 is negative (KUKA's definition)."""
    if "T" not in items:
        return None
    bits = int(items["T"][1])
    return lambda q_deg: all(((q_deg[j] < 0) == bool(bits >> j & 1)) for j in range(min(6, len(q_deg))))


def _quadrants(cf: dict):
    """Axes {index: quadrant}: floor(angle / 90°) as RAPID's confdata; turns as FANUC's: {index: (turn,)}."""
    return lambda q_deg: all(np.floor(q_deg[j] / 90.0) == c for j, c in cf.items() if j < len(q_deg))


def _turns(turns: dict):
    return lambda q_deg: all(np.round(q_deg[j] / 360.0) == t for j, t in turns.items() if j < len(q_deg))


def _scan_krl(text: str, n: int) -> Scan:
    out = Scan()
    axes = [f"A{j}" for j in range(1, min(n, 6) + 1)] + [f"E{j}" for j in range(1, n - 5)]
    found_lines = set()
    for m in re.finditer(r"\{([^{}]*)\}", text):
        items = _krl_items(m.group(1), m.start(1))
        line = _line_of(text, m.start())
        start = text.rfind("\n", 0, m.start()) + 1
        head = text[start:m.start()].upper()
        if "A1" in items and not {"X", "Y", "Z"} & set(items):
            missing = [a for a in axes if a not in items]
            if missing:
                out.unclear.append(Unclear(line, m.group()[:60], f"an axis aggregate without {', '.join(missing)}"))
                continue
            out.targets.append(Target("joint", [items[a][0] for a in axes], [items[a][1] for a in axes], line))
            found_lines.add(line)
        elif {"X", "Y", "Z"} <= set(items):
            if re.search(r"\bFRAME\b|\$(BASE|TOOL|NULLFRAME)\b|BASE_DATA|TOOL_DATA", head):
                continue  # a frame (base, tool), not a target
            missing = [a for a in ("X", "Y", "Z", "A", "B", "C") if a not in items]
            if missing:
                out.unclear.append(Unclear(line, m.group()[:60], f"a position without {', '.join(missing)}"))
                continue
            keys = ("X", "Y", "Z", "A", "B", "C")
            out.targets.append(Target("pose", [items[a][0] for a in keys], [items[a][1] for a in keys], line,
                                      "mm_kuka_abc", config=_kuka_turn(items)))
            found_lines.add(line)
    out.unclear += _unread(text, r"^\s*DECL\s+(GLOBAL\s+)?(E6POS|POS|E6AXIS|AXIS)\s+\w+", found_lines)
    return out


def _scan_rapid(text: str, n: int) -> Scan:
    out = Scan()
    found_lines = set()
    rob = re.compile(rf"\[\s*\[({NUM}\s*,\s*{NUM}\s*,\s*{NUM})\]\s*,\s*\[({NUM}(?:\s*,\s*{NUM}){{3}})\]\s*,"
                     r"\s*\[([^\[\]]*)\]\s*,\s*\[[^\[\]]*\]\s*\]")
    for m in rob.finditer(text):
        s1, v1 = _numbers(text, m.start(1), m.end(1))
        s2, v2 = _numbers(text, m.start(2), m.end(2))
        line = _line_of(text, m.start())
        cf = [int(float(x)) for x in m.group(3).split(",")] if re.fullmatch(rf"\s*{NUM}(\s*,\s*{NUM}){{3}}\s*",
                                                                         m.group(3)) else None
        out.targets.append(Target("pose", s1 + s2, v1 + v2, line, "mm_quat",
                                  config=_quadrants({0: cf[0], 3: cf[1], 5: cf[2]}) if cf else None))
        found_lines.add(line)
    jt = re.compile(rf"\[\s*\[({NUM}(?:\s*,\s*{NUM}){{5}})\]\s*,\s*\[([^\[\]]*)\]\s*\]")
    for m in jt.finditer(text):
        s1, v1 = _numbers(text, m.start(1), m.end(1))
        line = _line_of(text, m.start())
        if n > 6:
            s2, v2 = _numbers(text, m.start(2), m.end(2))
            s1, v1 = s1 + s2[:n - 6], v1 + v2[:n - 6]
        out.targets.append(Target("joint", s1[:n], v1[:n], line))
        found_lines.add(line)
    out.unclear += _unread(text, r"\b(robtarget|jointtarget)\s+\w+\s*:=", found_lines)
    return out


def _scan_fanuc(text: str, n: int) -> Scan:
    out = Scan()
    if "/POS" not in text:
        return out
    base = text.index("/POS")
    axes = [f"J{j}" for j in range(1, min(n, 6) + 1)] + [f"E{j}" for j in range(1, n - 5)]
    for m in re.finditer(r"P\[(\d+)(?::[^\]]*)?\]\s*\{(.*?)\};", text[base:], re.S):
        s, e = base + m.start(2), base + m.end(2)
        body = text[s:e]
        gp = re.search(r"GP1\s*:(.*?)(?=GP\d\s*:|$)", body, re.S)
        line = _line_of(text, base + m.start())
        if not gp:
            out.unclear.append(Unclear(line, f"P[{m.group(1)}]", "no group 1 (GP1) in the position"))
            continue
        g0 = s + gp.start(1)
        vals = {a.upper(): ((g0 + v.start(2), g0 + v.end(2)), float(v.group(2)))
                for v in re.finditer(rf"\b(J\d|E\d|X|Y|Z|W|P|R)\s*=\s*({NUM})", gp.group(1))
                for a in [v.group(1)]}
        if "J1" in vals:
            if any(a not in vals for a in axes):
                out.unclear.append(Unclear(line, f"P[{m.group(1)}]", f"joint values J1..J{n} incomplete"))
                continue
            out.targets.append(Target("joint", [vals[a][0] for a in axes], [vals[a][1] for a in axes], line,
                                      name=f"P[{m.group(1)}]"))
        elif all(a in vals for a in ("X", "Y", "Z", "W", "P", "R")):
            keys = ("X", "Y", "Z", "W", "P", "R")
            cfg = re.search(r"CONFIG\s*:\s*'[^,']*,\s*(-?\d+)\s*,\s*(-?\d+)\s*,\s*(-?\d+)\s*'", gp.group(1))
            out.targets.append(Target("pose", [vals[a][0] for a in keys], [vals[a][1] for a in keys], line,
                                      "mm_fanuc_wpr", name=f"P[{m.group(1)}]",
                                      config=_turns({0: int(cfg.group(1)), 3: int(cfg.group(2)),
                                                     5: int(cfg.group(3))}) if cfg else None))
        else:
            out.unclear.append(Unclear(line, f"P[{m.group(1)}]", "neither J1..Jn nor X, Y, Z, W, P, R"))
        if re.search(r"GP[2-9]\s*:", body):
            out.unclear.append(Unclear(line, f"P[{m.group(1)}]", "groups 2.. (other motion groups) left as written"))
    return out


def _scan_pdl2(text: str, n: int) -> Scan:
    out = Scan()
    for m in re.finditer(r"\bJNT\s*\(\s*\w+\s*,([^()]*)\)", text, re.I):
        spans, vals = _numbers(text, m.start(1), m.end(1))
        line = _line_of(text, m.start())
        if len(vals) < n or not re.fullmatch(rf"\s*{NUM}(\s*,\s*{NUM})*\s*(,\s*\d+\s*)?", m.group(1)):
            out.unclear.append(Unclear(line, m.group()[:60], f"JNT with other than {n} numbers"))
            continue
        out.targets.append(Target("joint", spans[:n], vals[:n], line))
    for m in re.finditer(rf"\bPOS\s*\(((?:\s*{NUM}\s*,){{5}}\s*{NUM})\s*(,\s*'[^']*')?\s*\)", text, re.I):
        spans, vals = _numbers(text, m.start(1), m.end(1))
        out.targets.append(Target("pose", spans, vals, _line_of(text, m.start()), "mm_zyz"))
    return out


def _scan_ros2(text: str, n: int) -> Scan:
    out = Scan()
    for m in re.finditer(r"positions\"?\s*:\s*\[([^\[\]]*)\]", text):
        spans, vals = _numbers(text, m.start(1), m.end(1))
        line = _line_of(text, m.start())
        if len(vals) == n:
            out.targets.append(Target("joint", spans, vals, line))
        else:
            out.unclear.append(Unclear(line, m.group()[:60], f"{len(vals)} positions, the robot has {n}"))
    return out


def _scan_csv(text: str, n: int) -> Scan:
    out = Scan()
    lines = text.splitlines(keepends=True)
    if not lines:
        return out
    head = [h.strip() for h in lines[0].strip().split(",")]
    want = [f"j{j}" for j in range(1, n + 1)]
    if any(w not in head for w in want):
        out.unclear.append(Unclear(1, lines[0].strip()[:60], f"no columns {','.join(want)}"))
        return out
    cols = [head.index(w) for w in want]
    pos = len(lines[0])
    for k, ln in enumerate(lines[1:], start=2):
        cells, starts, p = ln.rstrip("\r\n").split(","), [], pos
        for c in cells:
            starts.append(p)
            p += len(c) + 1
        try:
            vals = [float(cells[i]) for i in cols]
            spans = [(starts[i], starts[i] + len(cells[i])) for i in cols]
            out.targets.append(Target("joint", spans, vals, k))
        except (IndexError, ValueError):
            if ln.strip():
                out.unclear.append(Unclear(k, ln.strip()[:60], "a row without numbers in j1..jN"))
        pos += len(ln)
    return out


SCANNERS = {"urscript": (_scan_urscript, "rad"), "krl": (_scan_krl, "deg"), "rapid": (_scan_rapid, "deg"),
            "fanuc-ls": (_scan_fanuc, "deg"), "pdl2": (_scan_pdl2, "deg"), "ros2-trajectory": (_scan_ros2, "rad"),
            "csv": (_scan_csv, "rad")}
#: decimals written at least, by format (joint values; poses: length, angle/quaternion)
DECIMALS = {"urscript": (9, 7, 9), "krl": (4, 4, 5), "rapid": (4, 4, 8), "fanuc-ls": (4, 4, 4),
            "pdl2": (4, 4, 5), "ros2-trajectory": (9, 0, 0), "csv": (15, 0, 0)}


#: per format: (a motion statement whose group 1 is the target written, a target's definition in
#: the text by its name ``{name}``): a motion to a name the text does not define moves to a target
#: held elsewhere (another file, a register, a computation) that this file cannot rewrite
MOTIONS = {
    "krl": (r"^\s*(?:PTP|LIN|CIRC|SPTP|SLIN|SCIRC)\s+([A-Za-z_$][\w$]*(?:\s*\([^)]*\))?)",
            r"(?:DECL\s+(?:GLOBAL\s+)?\w+\s+{name}\s*=|^\s*{name}\s*=)"),
    "rapid": (r"^\s*Move\w*\s+(?:\\\w+\s*,?\s*)*([A-Za-z_]\w*(?:\s*\([^)]*\))?)",
              r"\b(?:robtarget|jointtarget)\s+{name}\s*:="),
    "urscript": (r"^\s*(?:movej|movel|movep|servoj)\s*\(\s*(?!p\s*\[)([A-Za-z_]\w*(?:\s*\([^)]*\))?)",
                 r"^\s*(?:global\s+)?{name}\s*=\s*p?\["),
    "pdl2": (r"^\s*MOVE(?:FLY)?\s+(?:JOINT\s+|LINEAR\s+|CIRCULAR\s+)?TO\s+([A-Za-z_$][\w$]*(?:\s*\([^)]*\))?)",
             r"(?:\bJNT\s*\(\s*{name}\s*,|^\s*{name}\s*:=\s*POS\s*\()"),
    "fanuc-ls": (r"^\s*\d+:\s*[JLC]\s+(PR\[[^\]]*\])", r"(?!)"),
}


def _unresolved(text: str, fmt: str) -> list:
    """Motions to targets this text does not hold (MOTIONS): listed, as they cannot be rewritten here."""
    if fmt not in MOTIONS:
        return []
    motion, definition = MOTIONS[fmt]
    out = []
    for k, line in enumerate(text.splitlines(), start=1):
        m = re.match(motion, line, re.I)
        if not m:
            continue
        name = m.group(1)
        if "(" in name or "[" in name:
            why = ("a position register, held by the controller: compensate its value there" if fmt == "fanuc-ls"
                   else "a target computed when the program runs (left as written; its base targets are rewritten)")
        elif name.startswith("$") or re.search(definition.format(name=re.escape(name)), text, re.I | re.M):
            continue
        else:
            where = "its .dat" if fmt == "krl" else "the file that defines it"
            why = f"the target {name} is not defined in this file (compensate {where})"
        out.append(Unclear(k, line.strip()[:60], why))
    return out


def scan(text: str, fmt: str, n_joints: int) -> Scan:
    """The targets of a program text and what looked like a target but could not be read."""
    if fmt not in SCANNERS:
        raise ConfigError(f"--format {fmt!r}: compensate reads {', '.join(FORMATS)}")
    out = SCANNERS[fmt][0](text, n_joints)
    out.unclear += _unresolved(text, fmt)
    return out


# -- pose conventions ---------------------------------------------------------------------

def pose_to_T(values, convention: str) -> np.ndarray:
    """(4, 4) SI pose of a Cartesian target's values."""
    from campaign.model import rotations as R

    v = np.asarray(values, dtype=float)
    T = np.eye(4)
    if convention == "m_rotvec":
        T[:3, 3], T[:3, :3] = v[:3], R.rotvec_to_matrix(v[3:6])
        return T
    T[:3, 3] = v[:3] * 1e-3
    a = np.radians(v[3:6])
    if convention == "mm_kuka_abc":
        T[:3, :3] = R.kuka_abc(a[0], a[1], a[2])
    elif convention == "mm_fanuc_wpr":
        T[:3, :3] = R.urdf_rpy(a[0], a[1], a[2])
    elif convention == "mm_zyz":
        T[:3, :3] = R.zyz(a[0], a[1], a[2])
    elif convention == "mm_quat":
        T[:3, :3] = R.quaternion_to_matrix(v[3:7])
    else:
        raise ValueError(convention)
    return T


def T_to_pose(T, convention: str, like) -> list:
    """The values of ``convention`` for the pose T (4, 4) SI; ``like``: the values written before
    (the Euler angles' branch nearest them, a quaternion's sign)."""
    from campaign.model import rotations as R

    T = np.asarray(T, dtype=float)
    if convention == "m_rotvec":
        return [*T[:3, 3], *R.matrix_to_rotvec(T[:3, :3])]
    xyz = list(T[:3, 3] * 1e3)
    if convention == "mm_quat":
        q = R.matrix_to_quaternion(T[:3, :3])
        return xyz + list(q if np.dot(q, like[3:7]) >= 0 else -q)
    if convention == "mm_kuka_abc":
        c, b, a = R.urdf_rpy_from_matrix(T[:3, :3])
        ang = [a, b, c]
    elif convention == "mm_fanuc_wpr":
        ang = list(R.urdf_rpy_from_matrix(T[:3, :3]))
    else:
        ang = list(R.zyz_from_matrix(T[:3, :3]))
    deg = np.degrees(ang)
    old = np.asarray(like[3:6], dtype=float)
    deg = deg + 360.0 * np.round((old - deg) / 360.0)  # the branch nearest the written angles
    return xyz + list(deg)


# -- rewriting -------------------------------------------------------------------------------

def _decimals(token: str) -> int:
    return len(token.split(".", 1)[1]) if "." in token and "e" not in token.lower() else 0


def _write(text: str, spans, values, least: list) -> list:
    """[(start, end, new token)] for the values (each with the decimals it had, at least ``least``)."""
    out = []
    for (s, e), v, d in zip(spans, values, least):
        decimals = max(_decimals(text[s:e]), d)
        tok = f"{v:.{decimals}f}"
        if float(tok) == 0:
            tok = tok.lstrip("-")
        out.append((s, e, tok))
    return out


@dataclass(frozen=True)
class ProgramCompensation:
    """What `campaign compensate --program` did. text: the new program; joints, poses: targets
    rewritten; unclear: [(line, text, why)] left as written; outside: [(line, why)] targets outside
    the calibrated domain (rewritten) or not reached (left)."""

    text: str
    joints: int
    poses: int
    unclear: tuple
    outside: tuple
    stage: str
    #: the lines of the targets outside the calibrated domain (`--strict` refuses them)
    outside_domain: tuple = ()


def measured_ranges(run_dir, robot):
    """(lo, hi) (N,) model joints the run measured, or None without measurements."""
    from campaign.run import RunFolder

    run = RunFolder(run_dir)
    if not run.measurements_path.is_file():
        return None
    with run.store() as store:
        q = store.load_measured().q
    return (q.min(axis=0), q.max(axis=0)) if len(q) else None


def _outside_domain(cal, run_dir, checked) -> list:
    """[(line, why)] of the targets outside the calibrated domain: the calibration's domain.json
    (campaign.identify.domain: joint ranges with a margin, the nearest measured pose, pairs of
    joints) at the corrected joints, as `compensate --csv` tests them; for a calibration made before
    domain.json, the joint ranges the run measured at the nominal joints (what the program asks)."""
    if not checked:
        return []
    targets = [t for t, _, _ in checked]
    names = [f"q{j + 1}" for j in range(cal.robot.n_joints)]
    stored = getattr(cal, "stored_domain", None)
    if stored is not None:
        why = stored.domain.why_outside(np.array([qc for _, qc, _ in checked]), names)
        return [(t.line, f"{t.name or 'target'}: outside the calibrated domain: {w}")
                for t, w in zip(targets, why) if w]
    ranges = measured_ranges(run_dir, cal.robot)
    if ranges is None:
        return []
    lo, hi = ranges
    out = []
    for t, _, q in checked:
        bad = np.flatnonzero((q < lo - 1e-9) | (q > hi + 1e-9))
        if len(bad):
            j = bad[0]
            out.append((t.line, f"{t.name or 'target'}: {names[j]} at {q[j]:.4f} is outside the measured range "
                                f"{lo[j]:.4f}..{hi[j]:.4f} (rad or m; the calibration has no domain.json)"))
    return out


def _acceptable(t, robot, step, residual, converged, q_new, outside) -> bool:
    """Whether a target's corrected joints q_new (N,) are written; what is not, is named. They are
    when no joint moves more than PROGRAM_BEST_EFFORT_STEP_RAD for them (corrections are of the size
    of the robot's errors; a larger step is another configuration, or the solver wandering beside a
    singularity, where the program's clearances were planned for the written joints) and they lie
    within the joint limits. A target the model does not reach exactly (beyond the real robot's
    reach, beside a singularity) gets the solver's last iterate, never farther from it than the
    written joints (the solver takes only improving steps), named with how near it comes."""
    from campaign.tolerances import PROGRAM_BEST_EFFORT_STEP_RAD

    what = t.name or ("joint target" if t.kind == "joint" else "Cartesian target")
    mm, mrad = np.linalg.norm(residual[:3]) * 1e3, np.linalg.norm(residual[3:]) * 1e3
    big = int(np.argmax(np.abs(step)))
    if abs(step[big]) > PROGRAM_BEST_EFFORT_STEP_RAD:
        unit, f = ("mm", 1e3) if robot.prismatic[big] else ("deg", 180.0 / np.pi)
        reached = "" if converged else f", {mm:.3f} mm off"
        outside.append((t.line, f"{what}: the correction would move q{big + 1} by {step[big] * f:.1f} {unit}{reached} "
                                "(another configuration, beyond the real robot's reach or beside a singularity; "
                                "left as written)"))
        return False
    j = _beyond_limits(robot, q_new)
    if j is not None:
        outside.append((t.line, f"{what}: corrected, {_limit_words(robot, q_new, j)} (left as written)"))
        return False
    if not converged:
        outside.append((t.line, f"{what}: reached to within {mm:.3f} mm, {mrad:.3f} mrad only (beyond the real "
                                "robot's reach or beside a singularity; rewritten, nearer than as written)"))
    return True


#: joint targets solved together (one progress step)
BLOCK = 500


def _beyond_limits(robot, q, slack=0.0) -> int | None:
    """The first joint (0-based) of q (N,) past its limit by more than ``slack`` (N,) or None."""
    limited = np.array([t != "continuous" for t in robot.joint_types], dtype=bool)
    bad = np.flatnonzero(((q < robot.q_lower - slack) | (q > robot.q_upper + slack)) & limited)
    return int(bad[0]) if len(bad) else None


def _limit_words(robot, q, j) -> str:
    unit, f = ("mm", 1e3) if robot.prismatic[j] else ("deg", 180.0 / np.pi)
    lim = robot.q_lower[j] if q[j] < robot.q_lower[j] else robot.q_upper[j]
    return f"q{j + 1} = {q[j] * f:.3f} {unit} is past its limit {lim * f:.3f} {unit}"


def compensate_program(run_dir, text: str, fmt: str, *, stage=None, calibrated=None, slack=None,
                       progress: bool = False) -> ProgramCompensation:
    """Rewrite the targets of a program ``text`` of format ``fmt`` through the calibration of
    ``run_dir`` (module docstring). ``slack`` (N,) rad/m: how far past the joint limits a written
    joint target is still read (campaign.identify.use.run_joint_slack; default: what the run's import
    accepted); beyond, and where the corrected joints would pass a limit, a target is named and left
    as written. ``progress``: a bar on stderr."""
    from campaign.progress import Progress

    from campaign.identify.use import CalibratedRobot
    from campaign.model.kinematics import forward
    from campaign.program.common import unit_scale

    cal = calibrated or CalibratedRobot(run_dir, stage=stage)
    robot = cal.robot
    if slack is None:
        from campaign.identify.use import run_joint_slack

        slack = run_joint_slack(run_dir, robot)[0]
    if cal.context_keys:
        raise ConfigError(f"the calibrated model ({cal.stage}) needs per-pose context ({', '.join(cal.context_keys)}) "
                          "that a program does not give; compensate with --stage geometric or a stage without it")
    found = scan(text, fmt, robot.n_joints)
    least_joint, least_len, least_ang = DECIMALS[fmt]
    scale = unit_scale(robot.prismatic, SCANNERS[fmt][1])
    edits, outside = [], []
    joints = [t for t in found.targets if t.kind == "joint"]
    poses = [t for t in found.targets if t.kind == "pose"]

    checked = []  # (target, its corrected joints (N,), its nominal joints (N,)): the domain test at the end

    def note_domain(t, q_corrected, q_nominal):
        checked.append((t, q_corrected, q_nominal))

    n_joint = n_pose = 0
    solved = {}
    bar = Progress("compensating", len(found.targets), progress, " targets")
    if joints:
        q_ctrl = np.array([t.values for t in joints], dtype=float) / scale
        q = np.atleast_2d(robot.to_model_q(q_ctrl))
        q_new, ok, res = np.empty_like(q), np.empty(len(q), dtype=bool), np.empty((len(q), 6))
        for a in range(0, len(q), BLOCK):
            q_new[a:a + BLOCK], res[a:a + BLOCK], ok[a:a + BLOCK] = cal.compensate(forward(robot, q[a:a + BLOCK]),
                                                                                   q[a:a + BLOCK])
            bar.update(len(q[a:a + BLOCK]))
        new_ctrl = np.atleast_2d(robot.to_controller_q(q_new)) * scale
        for k, (t, qn, qc, good) in enumerate(zip(joints, q_new, new_ctrl, ok)):
            solved[id(t)] = q[k]
            what = t.name or "joint target"
            j = _beyond_limits(robot, q[k], slack)
            if j is not None:
                outside.append((t.line, f"{what}: {_limit_words(robot, q[k], j)} (left as written)"))
                continue
            note_domain(t, qn, q[k])
            if not _acceptable(t, robot, qn - q[k], res[k], good, qn, outside):
                continue
            edits += _write(text, t.spans, qc, [least_joint] * len(qc))
            n_joint += 1
    previous = robot.q_mid.copy()
    for t in sorted(found.targets, key=lambda t: t.spans[0][0]):  # program order: a pose's branch follows
        if t.kind == "joint":
            previous = solved[id(t)]
            continue
        q_t = _compensate_pose(text, t, cal, previous, edits, outside, note_domain, (least_len, least_ang))
        if q_t is not None:
            previous, n_pose = q_t, n_pose + 1
        bar.update(1)
    bar.close()
    domain = _outside_domain(cal, run_dir, checked)
    outside += domain
    new = text
    for s, e, tok in sorted(edits, reverse=True):
        new = new[:s] + tok + new[e:]
    unclear = tuple((u.line, u.text, u.why) for u in sorted(found.unclear, key=lambda u: u.line))
    return ProgramCompensation(new, n_joint, n_pose, unclear, tuple(sorted(outside)), cal.stage,
                               tuple(sorted(line for line, _ in domain)))


def nominal_solutions(robot, T, previous, config=None, n_starts: int = 24):
    """Nominal IK solutions of T (4, 4) within the joint limits, nearest ``previous`` (N,) first;
    ``config``: a test of controller joints in degrees (the configuration a program wrote). The
    solution reached from ``previous`` is taken when it passes (a program's next target lies in
    its branch); otherwise ``n_starts`` more starts are solved."""
    from campaign.model.ik import nominal_ik

    def passing(q, ok):
        inside = np.all((q >= robot.q_lower - 1e-9) & (q <= robot.q_upper + 1e-9), axis=1)
        q = q[ok & inside]
        if config is not None and len(q):
            deg = np.atleast_2d(robot.to_controller_q(q)) * np.where(robot.prismatic, 1e3, 180.0 / np.pi)
            q = q[[bool(config(d)) for d in deg]]
        return q

    q = passing(*nominal_ik(robot, T[None], np.asarray(previous, dtype=float)[None], max_iter=100)[::2])
    if len(q):
        return q
    rng = np.random.default_rng(0)
    starts = rng.uniform(robot.q_lower, robot.q_upper, size=(40 * n_starts, robot.n_joints))
    if config is not None:  # starts in the configuration written (its signs, quadrants, turns)
        deg = np.atleast_2d(robot.to_controller_q(starts)) * np.where(robot.prismatic, 1e3, 180.0 / np.pi)
        starts = starts[[bool(config(d)) for d in deg]]
    starts = np.vstack([robot.q_mid, starts[:n_starts]])
    q = passing(*nominal_ik(robot, np.repeat(T[None], len(starts), axis=0), starts, max_iter=100)[::2])
    return q[np.argsort(np.linalg.norm(q - previous, axis=1))] if len(q) else q


def _compensate_pose(text, t, cal, previous, edits, outside, note_domain, least):
    """Rewrite one Cartesian target (module docstring); its calibrated joints, or None (listed)."""
    from campaign.model.kinematics import forward

    robot = cal.robot
    T = pose_to_T(t.values, t.convention)
    sols = nominal_solutions(robot, T, previous, t.config)
    what = t.name or "Cartesian target"
    if not len(sols):
        why = " in the configuration written" if t.config is not None else ""
        outside.append((t.line, f"{what}: the nominal robot does not reach it{why} (left as written)"))
        return None
    q, res, ok = cal.compensate(T[None], sols[:1])
    note_domain(t, q[0], sols[0])
    if not _acceptable(t, robot, q[0] - sols[0], res[0], ok[0], q[0], outside):
        return None
    values = T_to_pose(forward(robot, q)[0], t.convention, t.values)
    dec = [least[0]] * 3 + [least[1]] * (len(values) - 3)
    edits += _write(text, t.spans, values, dec)
    return q[0]


def compensate_program_file(run_dir, program, fmt: str, *, out=None, stage=None, slack=None, strict: bool = False,
                            progress: bool = False, calibrated=None) -> tuple:
    """Read ``program``, rewrite it (:func:`compensate_program`), write ``out`` (default: beside
    it, ``<stem>_compensated<suffix>``; never the program itself). ``strict``: DataError, nothing
    written, when a target lies outside the calibrated domain. Returns (out path, result)."""
    from campaign.fileio import atomic_write

    program = Path(program)
    if not program.is_file():
        raise DataError(f"{program}: no such program file")
    text, encoding, newline = read_program_text(program)
    out = Path(out) if out is not None else program.with_name(program.stem + "_compensated" + program.suffix)
    if out.resolve() == program.resolve():
        raise ConfigError(f"--out {out}: is the program itself; write the filtered program to another file")
    res = compensate_program(run_dir, text, fmt, stage=stage, slack=slack, progress=progress, calibrated=calibrated)
    if not res.joints and not res.poses and not res.unclear and not res.outside:
        raise DataError(f"{program}: no {fmt} targets found (is --format right?)")
    if strict and res.outside_domain:
        lines = res.outside_domain
        raise DataError(f"{program}: {len(lines)} target(s) outside the calibrated domain with --strict (line "
                        f"{', '.join(map(str, lines[:10]))}{', ...' if len(lines) > 10 else ''}): nothing written")
    atomic_write(out, res.text.replace("\n", newline).encode(encoding))
    return out, res


def read_program_text(program: Path) -> tuple:
    """(text with "\n" line ends, its encoding, its line end): a controller's file is written back
    as it came (a KUKA .dat with CRLF and a comment in Windows-1252, "Schwei\xdfnaht", stays so;
    read as UTF-8 with universal newlines, every line of it changed, or it was "not a text file")."""
    raw = program.read_bytes()
    if b"\0" in raw:
        raise DataError(f"{program}: not a text file")
    for encoding in ("utf-8", "cp1252", "latin-1"):
        try:
            text = raw.decode(encoding)
            break
        except UnicodeDecodeError:
            continue
    newline = "\r\n" if "\r\n" in text and text.count("\r\n") == text.count("\n") else "\n"
    return text.replace("\r\n", "\n"), encoding, newline
