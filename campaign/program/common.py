"""What the language modules share: units, number formatting, parts, per-move speeds, and the
helpers of their structural checks (campaign.program.<language>.check)."""

from __future__ import annotations

import re

import numpy as np

#: length of the trigger pulse (s): long enough for a tracker's input to see it (a few ms at most
#: on the instruments' trigger inputs), short against the measuring time that follows
PULSE_S = 0.2


def unit_scale(prismatic, units: str) -> np.ndarray:
    """(N,) factors from SI (rad, m) to a format's units: ``deg`` formats write revolute joints in
    degrees and prismatic ones in mm (KRL, RAPID, LS, PDL2); ``rad`` formats write rad and m."""
    prismatic = np.asarray(prismatic, dtype=bool)
    if units == "deg":
        return np.where(prismatic, 1e3, 180.0 / np.pi)
    return np.ones(len(prismatic))


def in_units(inp, units: str) -> np.ndarray:
    """The stops' controller joints (n, N) in the format's units."""
    return inp.q_controller * unit_scale(inp.prismatic, units)


def fmt(v: float, decimals: int) -> str:
    """A fixed-point number without a negative zero."""
    s = f"{v:.{decimals}f}"
    return s[1:] if s.startswith("-") and float(s) == 0 else s


def parts(n: int, per_part: int) -> list:
    """Index ranges [(start, stop), ...] of ``n`` stops split into parts of at most ``per_part``."""
    return [(s, min(s + per_part, n)) for s in range(0, n, per_part)] or [(0, 0)]


def part_name(base: str, k: int, n_parts: int) -> str:
    """``base`` for a single part, ``base_<k+1>`` for part k of several."""
    return base if n_parts == 1 else f"{base}_{k + 1}"


def lead_speed(inp, k: int) -> tuple:
    """(v, a) of the leading axis for the move into stop k (controller convention, SI, scaled by
    ``inp.speed``): the leading axis moves farthest; the others move in proportion (a synchronised
    joint move), so its speed is the largest that keeps every joint within its own limit."""
    dq = np.abs(inp.q_controller[k] - inp.q_controller[k - 1]) if k else np.zeros(inp.q_controller.shape[1])
    v, a = inp.max_velocity, inp.max_acceleration
    lead = int(np.argmax(dq))
    if dq[lead] <= 0:
        return float(inp.speed * np.min(v)), float(inp.speed * np.min(a))
    moving = dq > 0
    ratio = dq[lead] / dq[moving]
    return float(inp.speed * np.min(v[moving] * ratio)), float(inp.speed * np.min(a[moving] * ratio))


def comment(stop) -> str:
    """The comment at a stop: its index, kind and pose id (ASCII, at most 32 characters)."""
    return f"stop {stop.stop} {stop.kind} {stop.pose_id}"[:32]


def check_trigger(name: str, n, low: int, high: int) -> None:
    from campaign.errors import ConfigError

    if n is not None and not low <= n <= high:
        raise ConfigError(f"--trigger-output {n}: {name} writes digital outputs {low}..{high}")


def check_axes(name: str, inp, most: int) -> None:
    """ConfigError when the robot has more joints than the format's joint target holds."""
    from campaign.errors import ConfigError

    if inp.q_controller.shape[1] > most:
        raise ConfigError(f"{name}: a joint target holds {most} axes, {inp.robot_name} has {inp.q_controller.shape[1]}")


def layout(mod, inp, fmt_name: str, most_axes: int, base: str, per_part: int) -> tuple:
    """A program's joints in the format's units (n, N), its parts' stop ranges and their names
    (``base``, or ``base_1``..); refuses a trigger output or a joint count the format lacks."""
    check_trigger(fmt_name, inp.trigger_output, *mod.TRIGGER_RANGE)
    check_axes(fmt_name, inp, most_axes)
    ranges = parts(len(inp.stops), per_part)
    return in_units(inp, mod.UNITS), ranges, [part_name(base, k, len(ranges)) for k in range(len(ranges))]


def dwell_lines(stop, inp, wait, pulse, *, pulse_blocks: bool = False) -> list:
    """The statements of a stop's dwell: ``wait(seconds)`` and ``pulse(output)`` give a language's
    lines; a pulse that does not block (KRL, RAPID, LS, PDL2) runs during the wait after it."""
    first, pulsed, second = settle_and_measure(stop, inp.settle_s, inp.trigger_output)
    out = [wait(first)] if first > 0 else []
    if pulsed:
        out += pulse(inp.trigger_output)
        rest = second if pulse_blocks else second + PULSE_S
        if rest > 0:
            out.append(wait(rest))
    return out


def settle_and_measure(stop, settle_s: float, trigger) -> tuple:
    """(first wait s, pulse?, second wait s) at a stop: with a trigger the pulse comes once the
    robot has settled and the measuring time follows it; without, one wait of the whole dwell."""
    if trigger is None or not stop.measured:
        return stop.dwell_s, False, 0.0
    first = min(settle_s, stop.dwell_s)
    return first, True, max(stop.dwell_s - first - PULSE_S, 0.0)


# -- structural checks ----------------------------------------------------------------------

def line_problems(text: str, max_len: int, where: str) -> list:
    """Lines longer than ``max_len`` characters, or with characters outside printable ASCII."""
    out = []
    for k, line in enumerate(text.splitlines(), start=1):
        if len(line) > max_len:
            out.append(f"{where}: line {k} is {len(line)} characters long (limit {max_len})")
        if any(not (32 <= ord(c) < 127 or c == "\t") for c in line):
            out.append(f"{where}: line {k} has a character outside printable ASCII")
    return out


def identifier_problems(names, max_len: int, where: str, pattern: str = r"[A-Za-z][A-Za-z0-9_]*") -> list:
    out = []
    for name in names:
        if not re.fullmatch(pattern, name):
            out.append(f"{where}: identifier {name!r} is not a valid name")
        elif len(name) > max_len:
            out.append(f"{where}: identifier {name!r} is longer than {max_len} characters")
    return out


def block_problems(text: str, pairs, where: str, comment_re: str) -> list:
    """Blocks opened and closed in order: ``pairs`` [(opening regex, closing regex, name)], each
    matched at the start of a stripped line (comments removed)."""
    stack, out = [], []
    for k, raw in enumerate(text.splitlines(), start=1):
        line = re.sub(comment_re, "", raw).strip()
        for opening, closing, name in pairs:
            if re.match(closing, line, re.I):
                if not stack or stack[-1][0] != name:
                    out.append(f"{where}: line {k}: {name} closed without being opened")
                else:
                    stack.pop()
                break
            if re.match(opening, line, re.I):
                stack.append((name, k))
                break
    out += [f"{where}: line {k}: {name} opened and never closed" for name, k in stack]
    return out


def undeclared_targets(files, move_re, declared: set, what: str) -> list:
    """Moves (``move_re``'s group 1 names the target) whose target is not in ``declared`` (upper case)."""
    out = []
    for name, text in files:
        for k, line in enumerate(text.splitlines(), start=1):
            m = move_re.match(line)
            if m and m.group(1).upper() not in declared:
                out.append(f"{name}: line {k}: {what} target {m.group(1)} is not declared")
    return out


def limit_problems(values, robot, units: str, where: str, decimals: int) -> list:
    """Joint values (n, N) in a format's controller units that lie outside the robot's joint
    limits once converted to the model's convention (beyond the printed precision)."""
    values = np.asarray(values, dtype=float)
    if values.size == 0:
        return [f"{where}: no joint targets found"]
    if values.shape[1] != robot.n_joints:
        return [f"{where}: {values.shape[1]} joint values per target, {robot.name} has {robot.n_joints}"]
    scale = unit_scale(robot.prismatic, units)
    q = robot.to_model_q(values / scale)
    slack = 0.5 * 10.0 ** -decimals / scale * np.abs(robot.controller_matrix).sum(axis=1) \
        if robot.controller_matrix is not None else 0.5 * 10.0 ** -decimals / scale
    limited = np.array([t != "continuous" for t in robot.joint_types])
    bad = ((q < robot.q_lower - slack) | (q > robot.q_upper + slack)) & limited
    return [f"{where}: target {i + 1}, joint {j + 1} = {values[i, j]} {units} is outside the joint limits"
            for i, j in np.argwhere(bad)[:10]]
