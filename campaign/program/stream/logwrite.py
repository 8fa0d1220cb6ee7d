"""A tracker's log written fast: rows ``time_s,x,y,z[,target]`` formatted by numpy in fixed-width
fields (the number right-aligned after spaces), millions of rows a second; what
campaign.program.stream.logread reads back (in m, or mm with ``scale`` 1000)."""

from __future__ import annotations

import numpy as np

LOG_HEADER = "time_s,x,y,z"


def fixed_width_t(v, int_digits: int, decimals: int) -> np.ndarray:
    """Numbers v (n,) as right-aligned ASCII fields, transposed: (1 + int_digits + 1 + decimals, n)
    uint8, each column ``-12.345600`` padded with spaces on the left. Values beyond the width
    are a ValueError."""
    v = np.asarray(v, dtype=float)
    scaled = np.round(np.abs(v) * 10 ** decimals).astype(np.int64)
    if len(v) and scaled.max(initial=0) >= 10 ** (int_digits + decimals):
        raise ValueError(f"a value ({np.abs(v).max()}) needs more than {int_digits} integer digits")
    width = int_digits + decimals + 2
    out = np.empty((width, len(v)), dtype=np.uint8)
    out[0] = ord(" ")
    out[1 + int_digits] = ord(".")
    ip, fp = np.divmod(scaled, np.int64(10 ** decimals))
    # digits from the least significant, dividing by the scalar 10 (fast) in 32 bits where they fit
    for x, rows in ((fp, range(width - 1, 1 + int_digits, -1)), (ip, range(int_digits, 0, -1))):
        x = x.astype(np.int32) if x.max(initial=0) < 2 ** 31 else x
        for r in rows:
            x, d = np.divmod(x, 10)
            out[r] = d
            out[r] += ord("0")
    # integer digits before the number's first one are blanks (the units digit always shows)
    shown = np.zeros(len(v), dtype=bool)
    blanks = np.zeros(len(v), dtype=np.int64)
    for r in range(1, int_digits):
        shown |= out[r] != ord("0")
        out[r][~shown] = ord(" ")
        blanks += ~shown
    neg = np.flatnonzero((v < 0) & (scaled > 0))
    out[blanks[neg], neg] = ord("-")  # just before the first digit shown (row 0 when none is blank)
    return out


def format_rows(t, P, target=None, names=(), *, scale: float = 1.0, time_digits: int = 7, length_digits: int = 5,
                time_decimals: int = 4, length_decimals: int = 6) -> bytes:
    """The log's rows for t (n,) s, P (n, 3) m (written times ``scale``: 1000 for mm) and, when
    given, target (n,) codes into ``names`` (written last, right-aligned after spaces the reader ignores)."""
    n = len(t)
    comma = np.full((1, n), ord(","), dtype=np.uint8)
    parts = [fixed_width_t(t, time_digits, time_decimals)]
    for k in range(3):
        parts += [comma, fixed_width_t(P[:, k] * scale, length_digits, length_decimals)]
    if target is not None:
        width = max(len(s) for s in names)
        table = np.full((width + 1, len(names)), ord(" "), dtype=np.uint8)
        table[0] = ord(",")
        for c, name in enumerate(names):  # right-aligned: the name ends the line
            table[width + 1 - len(name):, c] = np.frombuffer(name.encode(), dtype=np.uint8)
        parts.append(table[:, np.asarray(target, dtype=np.int64)])
    parts.append(np.full((1, n), ord("\n"), dtype=np.uint8))
    return np.ascontiguousarray(np.vstack(parts).T).tobytes()


def log_header(with_target: bool) -> str:
    return LOG_HEADER + (",target" if with_target else "") + "\n"
