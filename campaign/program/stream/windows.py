"""Still windows in a tracker's log: where the tool stood still, found block by block.

A continuous log is cut into blocks of about STREAM_BLOCK_S; a block is still when the robust
spread of its positions (the norm of the per-axis median absolute deviations: a spike or two do
not move it) stays below STREAM_STILL_FACTOR times the log's own noise level, estimated from the
data (the STREAM_NOISE_QUANTILE quantile of the blocks' spreads: the still blocks are the quiet
ones). Still blocks that follow each other at one position make a window (also across a burst of
spikes up to STREAM_BURST_S); a change of reflector (``target``) between them continues the window
when the tool did not move in between (at most STREAM_SWITCH_BLOCKS moving blocks, or a short gap)
and the reflector lies from the others as the tool holds them; a reflector measured again after
another, or one the tracker's cycle measures before the last (the order of two whole windows in a
row that agree, a lead-in's reflector last: one the tracker followed in and measured again), starts
the next window (the reflectors' cycle of a stop repeated in place). A
window keeps, per reflector, the median of its samples (the position) and their robust standard
deviation (the spread, a quality figure). In a log of one reflector (no ``target``), a window
STREAM_SPLIT_FACTOR times as long as the typical recent one is cut into that many: stops at one
place one after another (a repeat measured back to back).

A log with one record per stable point (``point`` mode: records further apart in time than a
continuous log's) makes a window of each group of records at one position.
Memory: the samples of the open window only.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from campaign.tolerances import (STREAM_BLOCK_S, STREAM_BURST_S, STREAM_GAP_BLOCKS, STREAM_MIN_NOISE_M,
                                 STREAM_NOISE_QUANTILE, STREAM_POINT_MIN_DT_S, STREAM_POINT_STEP_M,
                                 STREAM_REFLECTOR_TOL_M, STREAM_RUN_GAP_SAMPLES, STREAM_SAME_PLACE_FACTOR, STREAM_SPLIT_AFTER_WINDOWS,
                                 STREAM_SPLIT_FACTOR, STREAM_SPLIT_RECENT_WINDOWS, STREAM_STILL_FACTOR,
                                 STREAM_SWITCH_BLOCKS, STREAM_SWITCH_S, STREAM_WINDOW_MAX_SAMPLES)

#: robust standard deviation from the median absolute deviation of a normal sample
MAD_TO_SIGMA = 1.4826


@dataclass
class Window:
    """One still window: t0, t1 (s, the log's clock), samples, and per reflector code its median
    position (3,) m, robust spread (m: the 3-D robust standard deviation) and sample count."""

    t0: float
    t1: float
    samples: int
    position: dict
    spread: dict
    counts: dict

    def spread_m(self) -> float:
        """The largest of its reflectors' spreads (m)."""
        return float(max(self.spread.values())) if self.spread else float("nan")


@dataclass
class _Open:
    t0: float
    t1: float
    parts: dict = field(default_factory=dict)  # code -> [arrays (k, 3)]
    ref: dict = field(default_factory=dict)  # code -> (3,) position of its first still block
    n: int = 0
    last_code: int = -1
    #: the reflector the tracker followed through the motion into the window (-1: none seen)
    entry: int = -1
    #: closed because its first reflector, the one followed in, was measured again: a lead-in
    lead_in: bool = False


def block_size(dt_s: float) -> int:
    """Samples per block at a sample interval ``dt_s`` (s): about STREAM_BLOCK_S, 5 to 50."""
    if not np.isfinite(dt_s) or dt_s <= 0:
        return 5
    return int(np.clip(round(STREAM_BLOCK_S / dt_s), 5, 50))


def block_spreads(p: np.ndarray, B: int) -> tuple:
    """(median (nb, 3), robust spread (nb,)) of consecutive blocks of B samples of p (n, 3)."""
    nb = len(p) // B
    blocks = p[:nb * B].reshape(nb, B, 3)
    med = np.median(blocks, axis=1)
    mad = np.median(np.abs(blocks - med[:, None, :]), axis=1)
    return med, np.sqrt(np.sum(mad * mad, axis=1))


def quick_block_spreads(p: np.ndarray, B: int, quiet_range: float) -> tuple:
    """:func:`block_spreads` where it matters: a block whose positions span at most ``quiet_range``
    (the norm of the per-axis ranges) has a robust spread of at most half that (a median absolute
    deviation is at most half the range), so its mean and that bound stand in for the medians; the
    others (moving, spiky) get the medians. Same stillness verdicts at ``quiet_range`` = 2 · tau."""
    nb = len(p) // B
    blocks = p[:nb * B].reshape(nb, B, 3)
    span = np.linalg.norm(blocks.max(axis=1) - blocks.min(axis=1), axis=1)
    med = blocks.mean(axis=1)
    s = 0.5 * span
    loud = np.flatnonzero(span > quiet_range)
    if len(loud):
        med[loud], s[loud] = block_spreads(blocks[loud].reshape(-1, 3), B)
    return med, s


def is_point_log(t) -> bool:
    """A log of stable points (one record per point) rather than a continuous one: its records
    are further apart in time than STREAM_POINT_MIN_DT_S (a continuous log samples at 10 Hz or
    more; a tracker takes longer than that to settle on a point and move to the next reflector)."""
    dt = np.diff(t)
    dt = dt[dt > 0]
    return bool(len(dt) == 0 or np.median(dt) > STREAM_POINT_MIN_DT_S)


class WindowFinder:
    """Feed :class:`~campaign.program.stream.logread.LogChunk` s in order (:meth:`feed`), then
    :meth:`finish`: the still windows in time order. The noise level and the block size come from
    the first chunk (a 100 Hz log's first block of bytes holds hours)."""

    def __init__(self, reflector_distances=None, *, split_long: bool = False):
        #: (k, k) m: the nominal distances between the reflectors (codes) on the tool, or None
        self.D = None if reflector_distances is None else np.asarray(reflector_distances, dtype=float)
        #: a log of one reflector: a window several typical windows long is that many stops at one
        #: place (a repeat measured back to back, with no reflectors' cycle to tell them apart)
        self.split_long = split_long
        self._lengths: list = []
        self._order = None  # reflector code -> its place in the tracker's cycle
        self._entry = -1  # the code of the moving block before the still run being added
        self._cycle = None  # the last whole window's cycle, until the next confirms it
        self._tail = -1  # the code of the last block fed when it was moving
        self.windows: list = []
        self.B = None
        self.tau = None
        self.noise_m = None
        self.dt_s = None
        self.point_mode = None
        self._carry = None
        self._open = None
        self._moving = 0  # moving blocks since the open window's last still block
        self.samples = 0
        self.t_first = None
        self.t_last = None

    # -- set-up from the first data ---------------------------------------------------------
    def _calibrate(self, t, p, g):
        self.point_mode = is_point_log(t)
        dt = np.diff(t)
        self.dt_s = float(np.median(dt[dt > 0])) if (dt > 0).any() else 1.0
        if self.point_mode:
            self.tau = STREAM_POINT_STEP_M
            self.noise_m = float("nan")
            return
        self.B = block_size(self.dt_s)
        _, s = block_spreads(p, self.B)
        same = _uniform(g, self.B)
        s = s[same] if same.any() else s
        level = float(np.quantile(s, STREAM_NOISE_QUANTILE)) if len(s) else 0.0
        # s is the norm of 3 per-axis MADs: a still block's s ≈ 0.6745·√3·σ
        self.noise_m = max(level / (0.6745 * np.sqrt(3.0)), STREAM_MIN_NOISE_M)
        self.tau = STREAM_STILL_FACTOR * self.noise_m

    # -- streaming ---------------------------------------------------------------------------
    def feed(self, chunk) -> None:
        t, p, g = chunk.t, chunk.p, chunk.target
        if len(t) == 0:
            return
        if self.t_first is None:
            self.t_first = float(t[0])
        self.t_last = float(t[-1])
        self.samples += len(t)
        if self.point_mode is None:
            self._calibrate(t, p, g)
        if self.point_mode:
            self._feed_points(t, p, g)
            return
        if self._carry is not None:
            ct, cp, cg = self._carry
            t, p, g = np.concatenate([ct, t]), np.concatenate([cp, p]), np.concatenate([cg, g])
        B = self.B
        new = run_starts(t, g, STREAM_RUN_GAP_SAMPLES * self.dt_s)
        start = run_blocks(new, len(g), B)
        # the last run may go on in the next chunk: its samples past its last whole block wait
        last = int(new[-1])
        rest = last + (len(t) - last) // B * B
        self._carry = (t[rest:], p[rest:], g[rest:])
        start = start[start + B <= rest]
        nb = len(start)
        if nb == 0:
            return
        at = start[:, None] + np.arange(B)
        med, s = quick_block_spreads(p[at].reshape(-1, 3), B, 2.0 * self.tau)
        tb = t[at]
        gap_s = STREAM_GAP_BLOCKS * B * self.dt_s
        # a block is still: quiet, one reflector, no gap inside
        still = (s <= self.tau) & (tb[:, -1] - tb[:, 0] <= gap_s)
        codes = g[start]
        idx = np.flatnonzero(still)
        if len(idx) == 0:
            self._moving += nb
        else:
            # runs of still blocks that follow each other (one reflector, at one place, no gap) go
            # to the window at once: one call a run, not a block
            new_run = np.ones(len(idx), dtype=bool)
            new_run[1:] = (np.diff(idx) > 1) | (codes[idx[1:]] != codes[idx[:-1]]) \
                | (np.linalg.norm(med[idx[1:]] - med[idx[:-1]], axis=1) > STREAM_SAME_PLACE_FACTOR * self.tau) \
                | (tb[idx[1:], 0] - tb[idx[:-1], -1] > gap_s)
            starts = np.flatnonzero(new_run)
            ends = np.append(starts[1:], len(idx)) - 1
            prev = -1
            for a, e in zip(idx[starts], idx[ends]):
                self._moving += a - prev - 1
                prev = e
                span = slice(start[a], start[e] + B)  # blocks a..e: one reflector's run, contiguous
                self._entry = (int(codes[a - 1]) if not still[a - 1] else -1) if a > 0 else self._tail
                self._still_block(a, tb[a, 0], tb[e, -1], int(codes[a]), med[a], np.column_stack((t[span], p[span])))
            self._moving += nb - 1 - prev
        self._tail = int(codes[-1]) if not still[-1] else -1
        w = self._open
        if w is not None and self._moving > STREAM_SWITCH_BLOCKS and tb[-1, -1] - w.t1 > STREAM_BURST_S:
            self._close()

    def _still_block(self, b, t0, t1, code, med, samples):
        w = self._open
        if w is not None:
            gap = t0 - w.t1
            near = code in w.ref and np.linalg.norm(med - w.ref[code]) <= STREAM_SAME_PLACE_FACTOR * self.tau
            quiet = self._moving == 0 and gap <= STREAM_GAP_BLOCKS * self.B * self.dt_s
            switch = code != w.last_code and code not in w.ref and \
                (self._moving <= STREAM_SWITCH_BLOCKS or gap <= STREAM_SWITCH_S) and gap <= STREAM_SWITCH_S \
                and self._on_the_same_tool(w, code, med)
            # a reflector measured again after another, or one the tracker's cycle measures before
            # the last: the next measurement (a repeat in place)
            again = code != w.last_code and (code in w.ref or self._before(code, w.last_code))
            # at its place again after a few moving blocks or a burst of spikes no longer than
            # STREAM_BURST_S: the tool did not move (it cannot leave and come back to within noise)
            back = near and (quiet or self._moving <= STREAM_SWITCH_BLOCKS or gap <= STREAM_BURST_S)
            if not again and (back or switch):
                self._extend(w, t1, code, med, samples)
                self._moving = 0
                return
            # its first reflector, followed in through the motion, measured again after the others:
            # the first part was the tracker holding it while the robot settled (a lead-in)
            w.lead_in = again and code == next(iter(w.ref)) and code == w.entry \
                and self._moving <= STREAM_SWITCH_BLOCKS
            self._close()
        self._open = _Open(t0=t0, t1=t1, entry=self._entry)
        self._extend(self._open, t1, code, med, samples)
        self._moving = 0

    def _before(self, a, b) -> bool:
        """Whether the tracker's cycle (the order of the reflectors in two whole windows in a row
        that agree) measures reflector ``a`` before ``b``; False before that order is known."""
        return self._order is not None and a in self._order and b in self._order and self._order[a] < self._order[b]

    def _on_the_same_tool(self, w, code, med) -> bool:
        """Whether reflector ``code`` at ``med`` lies from the window's other reflectors as the tool
        holds them (STREAM_REFLECTOR_TOL_M; always, without the nominal distances)."""
        if self.D is None:
            return True
        return all(abs(np.linalg.norm(med - p) - self.D[code, c]) <= STREAM_REFLECTOR_TOL_M for c, p in w.ref.items())

    def _extend(self, w, t1, code, med, samples):
        w.t1 = t1
        w.ref.setdefault(code, np.array(med))
        w.parts.setdefault(code, []).append(np.array(samples))
        w.n += len(samples)
        w.last_code = code
        if w.n > STREAM_WINDOW_MAX_SAMPLES:  # a long pause: every other sample is as good
            for c, parts in w.parts.items():
                allp = np.concatenate(parts)[::2]
                w.parts[c] = [allp]
            w.n = sum(len(v[0]) for v in w.parts.values())

    def _close(self):
        w, self._open = self._open, None
        if w is None:
            return
        samples = {code: np.concatenate(parts) for code, parts in w.parts.items()}  # (k, 4): t, x, y, z
        if self._order is None and self.D is not None and len(self.D) > 1 and len(samples) == len(self.D):
            cycle = list(samples)
            if w.lead_in:  # the cycle starts after the reflector followed in: it is measured last
                cycle = cycle[1:] + cycle[:1]
            # two whole windows in a row with one cycle: a lead-in whose repeat a gap took away, or a
            # stop with a reflector measured again, is not taken for the tracker's cycle
            if self._cycle == cycle:
                self._order = {code: k for k, code in enumerate(cycle)}
            self._cycle = cycle
        length = w.t1 - w.t0
        pieces = 1
        if self.split_long and len(samples) == 1 and len(self._lengths) >= STREAM_SPLIT_AFTER_WINDOWS:
            typical = float(np.median(self._lengths[-STREAM_SPLIT_RECENT_WINDOWS:]))
            if typical > 0 and length > STREAM_SPLIT_FACTOR * typical:
                pieces = int(round(length / typical))
        self._lengths.append(length)
        edges = np.linspace(w.t0, w.t1, pieces + 1)
        for k in range(pieces):
            position, spread, counts = {}, {}, {}
            for code, pts in samples.items():
                if pieces > 1:
                    pts = pts[(pts[:, 0] >= edges[k]) & ((pts[:, 0] < edges[k + 1]) | (k == pieces - 1))]
                if len(pts):
                    position[code], spread[code] = robust_mean(pts[:, 1:])
                    counts[code] = len(pts)
            if counts:
                self.windows.append(Window(float(edges[k]), float(edges[k + 1]), int(sum(counts.values())), position,
                                           spread, counts))

    def _feed_points(self, t, p, g):
        """One record per stable point: a record joins the open group when its reflector is new
        to the group (reflectors in turn, at the tool's distances) or repeats the last one at its
        place; else it starts a new group."""
        for k in range(len(t)):
            code = int(g[k])
            w = self._open
            if w is not None:
                # the same point again (not after another reflector: that is the next stop's cycle)
                same_place = code == w.last_code and np.linalg.norm(p[k] - w.ref[code]) <= self.tau
                if same_place or (code not in w.ref and t[k] - w.t1 <= STREAM_SWITCH_S * 5
                                  and self._on_the_same_tool(w, code, p[k])):
                    self._extend(w, float(t[k]), code, p[k], np.append(t[k], p[k])[None])
                    continue
                self._close()
            self._open = _Open(t0=float(t[k]), t1=float(t[k]))
            self._extend(self._open, float(t[k]), code, p[k], np.append(t[k], p[k])[None])

    def finish(self) -> list:
        if not self.point_mode and self._carry is not None and len(self._carry[0]) and self._open is not None:
            t, p, g = self._carry  # the last partial block: still when it is at the open window's place
            code = int(g[0])
            if (g == code).all() and code in self._open.ref and self._moving == 0:
                med = np.median(p, axis=0)
                if np.linalg.norm(med - self._open.ref[code]) <= self.tau:
                    self._extend(self._open, float(t[-1]), code, med, np.column_stack((t, p)))
        self._close()
        return self.windows


def run_starts(t, g, gap_s) -> np.ndarray:
    """The first sample of each run of one reflector without a time gap longer than ``gap_s`` (s)."""
    if len(g) == 0:
        return np.zeros(0, np.int64)
    return np.flatnonzero(np.r_[True, (g[1:] != g[:-1]) | (np.diff(t) > gap_s)])


def run_blocks(starts, n, B) -> np.ndarray:
    """The first sample of each block of B samples of n, the blocks laid from the start of each run
    (``starts``, :func:`run_starts`): a block never holds two reflectors or a gap, and a short run
    at a low rate is not cut by a block boundary laid from the log's start (8 samples of a reflector
    at 10 Hz make one block or none when blocks of 5 are laid from the start, always one when laid
    from the run's; 95 samples after a gap at 1,000 Hz, one block of 50 or none)."""
    if len(starts) == 0:
        return np.zeros(0, np.int64)
    e = np.r_[starts[1:], n]
    k = (e - starts) // B
    first = np.repeat(starts, k)
    return first + B * (np.arange(k.sum()) - np.repeat(np.cumsum(k) - k, k))


def _uniform(g, B) -> np.ndarray:
    nb = len(g) // B
    gb = g[:nb * B].reshape(nb, B)
    return gb.min(axis=1) == gb.max(axis=1)


def robust_mean(pts: np.ndarray) -> tuple:
    """(median (3,), robust 3-D standard deviation) of samples pts (k, 3), m: the median's and
    the MAD's breakdown point is one half, so spikes do not move them."""
    med = np.median(pts, axis=0)
    if len(pts) < 2:
        return med, 0.0
    mad = np.median(np.abs(pts - med), axis=0) * MAD_TO_SIGMA
    return med, float(np.sqrt(np.sum(mad * mad)))
