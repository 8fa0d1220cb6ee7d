"""Stage 3: order the suitable poses into a short tour in Ruckig travel time, and sample its motions.

Travel times come from campaign.plan.timing (Ruckig's time-optimal, jerk-limited, phase-
synchronised rest-to-rest durations, tabulated per joint for grid poses: :class:`GridTimes`).
With phase synchronisation the motion is a straight line in joint space; segments are
re-checked by sampling that line at ≤ 1° of joint motion (:func:`segment_samples`, the tests
compare with Ruckig's own trajectory).
"""

from __future__ import annotations

import operator

import numpy as np

from campaign.plan.timing import GridTimes


def axis_tables(times: GridTimes, C):
    """Per joint i, the table (cells_i, n) of travel times (s) of that joint alone from each of
    its cell values to each pose of C (n, N): the time from cell vector c to every pose is then
    the elementwise maximum of the N rows ``tables[i][c[i]]`` (contiguous rows, no gathers)."""
    return [lut[np.abs(np.arange(len(lut))[:, None] - C[None, :, i])] for i, lut in enumerate(times.lut)]


def nearest_neighbour(times: GridTimes, C, start: int = 0, near=None):
    """Greedy tour over cell vectors C (n, N) from pose ``start``; returns the visiting order (n,).

    At each step the nearest unvisited pose in travel time (ties: the lowest index). The
    per-joint time tables are compacted to the unvisited poses whenever half of them are gone.
    ``near``: :func:`neighbour_lists` (n, k), the same tour in less time: an unvisited pose of
    the current pose's list nearer than the list's farthest is the nearest of all (every pose
    nearer than that is in the list); only when there is none are all poses compared."""
    n = len(C)
    order = np.empty(n, dtype=np.int64)
    alive = np.arange(n)  # pose indices of the tables' columns
    tables = axis_tables(times, C)
    visited = np.zeros(n)  # +inf on visited columns
    cur = start
    row = np.empty(n)
    seen = bytearray(n)
    if near is not None and near.shape[1] > 0:
        t_near = times.pair(C[:, None, :], C[near])
        lists = [list(zip(t, p)) for t, p in zip(t_near.tolist(), near.tolist())]
        farthest = t_near.max(axis=1).tolist()
    else:
        lists = None
    for k in range(n):
        order[k] = cur
        seen[cur] = 1
        if k == n - 1:
            break
        col = int(np.searchsorted(alive, cur))
        visited[col] = np.inf
        if 2 * (n - k - 1) < len(alive) and len(alive) > 256:  # compact to the unvisited columns
            keep = np.isfinite(visited)
            alive, visited = alive[keep], visited[keep]
            tables = [T[:, keep] for T in tables]
            row = np.empty(len(alive))
        if lists is not None:
            best = min((tj for tj in lists[cur] if not seen[tj[1]] and tj[0] < farthest[cur]), default=None)
            if best is not None:
                cur = int(best[1])
                continue
        c = C[cur]
        np.add(tables[0][c[0]], visited, out=row)
        for i in range(1, len(tables)):
            np.maximum(row, tables[i][c[i]], out=row)
        cur = int(alive[int(np.argmin(row))])
    return order


#: candidates per pose that the k-d tree proposes to :func:`neighbour_lists` (their travel times decide)
NEAR_CANDIDATES = 48


def neighbour_lists(times: GridTimes, C, k: int = 8, block: int = 256):
    """The k nearest poses in travel time of each pose of C (n, N), itself excluded: (n, k) indices.

    Exact, without the n × n times: a k-d tree over the cells scaled by each joint's time for one
    cell proposes :data:`NEAR_CANDIDATES` poses (largest scaled difference); their travel times
    pick the k nearest. The travel time is at most T only inside the box of half-widths
    ``w_i(T)`` cells (the most cells joint i moves in T), so the proposal is complete when its
    farthest candidate lies beyond that box's scaled half-width for T the k-th time; the poses
    where it does not are computed against every pose (``block`` at a time)."""
    from scipy.spatial import cKDTree

    n = len(C)
    k = min(k, n - 1)
    near = np.empty((n, max(k, 0)), dtype=np.int64)
    if k <= 0:
        return near
    m = min(n - 1, max(NEAR_CANDIDATES, 4 * k))
    unit = np.array([lut[1] if len(lut) > 1 else 1.0 for lut in times.lut])  # s per cell
    unit = np.where(unit > 0, unit, 1.0)
    X = C * unit
    todo = np.arange(n)
    if m < n - 1:
        dist, idx = cKDTree(X).query(X, k=m + 1, p=np.inf)
        t = times.pair(C[:, None, :], C[idx])  # (n, m + 1) s
        t[idx == np.arange(n)[:, None]] = np.inf
        part = np.argpartition(t, k - 1, axis=1)[:, :k]
        near[:] = np.take_along_axis(idx, part, axis=1)
        t_k = np.take_along_axis(t, part, axis=1).max(axis=1)
        # the box of travel time t_k, scaled: its half-width per joint, the largest over joints
        reach = np.max(np.stack([unit[i] * (np.searchsorted(lut, t_k, side="right") - 1)
                                 for i, lut in enumerate(times.lut)]), axis=0)
        todo = np.flatnonzero(~(dist[:, -1] > reach + 1e-12 * np.maximum(reach, 1.0)))
    if len(todo):
        tables = axis_tables(times, C)
        for s in range(0, len(todo), block):
            rows = todo[s : s + block]
            t = tables[0][C[rows, 0]]
            for i in range(1, len(tables)):
                np.maximum(t, tables[i][C[rows, i]], out=t)
            t[np.arange(len(rows)), rows] = np.inf
            near[rows] = np.argpartition(t, k - 1, axis=1)[:, :k]
    return near


def _pair_time_function(times: GridTimes, C):
    """A plain-Python travel time t(a, b) (s) between poses a, b of C (n, N): scalar lookups
    without numpy's per-call overhead, for the local search's many single pairs."""
    cells = C.tolist()
    luts = [lut.tolist() for lut in times.lut]
    if len(luts) != 6:
        lookup, sub = list.__getitem__, operator.sub

        def pair_time(a, b):  # the lookups in C's map loops, no generator frames
            return max(map(lookup, luts, map(abs, map(sub, cells[a], cells[b]))))

        return pair_time
    l0, l1, l2, l3, l4, l5 = luts

    def pair_time6(a, b):  # unrolled: the local search's inner loop for a six-joint arm
        ca, cb = cells[a], cells[b]
        return max(l0[abs(ca[0] - cb[0])], l1[abs(ca[1] - cb[1])], l2[abs(ca[2] - cb[2])],
                   l3[abs(ca[3] - cb[3])], l4[abs(ca[4] - cb[4])], l5[abs(ca[5] - cb[5])])

    return pair_time6


def two_opt(times: GridTimes, C, order, neighbours: int = 8, passes: int = 3, near=None):
    """2-opt on an open path with candidate lists of the nearest poses in travel time.

    For each edge (a, b) of the path and each candidate c near a (later on the path, with
    successor d), reverse b…c when t(a,b) + t(c,d) > t(a,c) + t(b,d) (first improvement).
    The first pose stays first. ``near``: precomputed :func:`neighbour_lists`."""
    order = np.array(order)
    n = len(order)
    if n < 4:
        return order
    if near is None:
        near = neighbour_lists(times, C, neighbours)
    near = near.tolist()
    dist = _pair_time_function(times, C)
    pos = np.empty(n, dtype=np.int64)
    for p in range(passes):
        pos[order] = np.arange(n)
        seq = order.tolist()
        where = pos.tolist()
        improved = 0
        for i in range(n - 1):
            a, b = seq[i], seq[i + 1]
            d_ab = dist(a, b)
            for c in near[a]:
                j = where[c]
                if j <= i + 1 or j >= n - 1:
                    continue
                d = seq[j + 1]
                gain = d_ab + dist(c, d) - dist(a, c) - dist(b, d)
                if gain > 1e-9:
                    seq[i + 1 : j + 1] = seq[i + 1 : j + 1][::-1]
                    for m in range(i + 1, j + 1):
                        where[seq[m]] = m
                    improved += 1
                    break
        order = np.array(seq, dtype=np.int64)
        if not improved:
            break
    return order


def or_opt(times: GridTimes, C, order, near, max_len: int = 3, passes: int = 3):
    """Or-opt on an open path: move a run of 1…``max_len`` consecutive poses, possibly reversed,
    between two neighbouring poses elsewhere (or after the last pose) when that shortens the
    total travel time; the insertion places tried are next to the run's end poses' candidates
    in ``near`` (:func:`neighbour_lists`). The first pose stays first. Returns the new order."""
    seq = np.asarray(order).tolist()
    n = len(seq)
    if n < 4:
        return np.array(seq, dtype=np.int64)
    near = np.asarray(near).tolist()
    dist = _pair_time_function(times, C)
    where = [0] * n  # position of each pose on the path
    for k, p in enumerate(seq):
        where[p] = k
    for _ in range(passes):
        improved = 0
        i = 1
        while i < n:
            moved = False
            for L in range(1, max_len + 1):
                e = i + L - 1
                if e >= n:
                    break
                prev, s0, sL = seq[i - 1], seq[i], seq[e]
                nxt = seq[e + 1] if e + 1 < n else None
                removal = dist(prev, s0) + (dist(sL, nxt) - dist(prev, nxt) if nxt is not None else 0.0)
                if removal <= 1e-9:
                    continue
                best, best_k, best_rev = 1e-9, -1, False
                for c in near[s0] + near[sL]:
                    kc = where[c]
                    for k in (kc - 1, kc):  # the edge (seq[k], seq[k + 1]) next to c
                        if k < 0 or (i - 1 <= k <= e):
                            continue
                        u = seq[k]
                        if k + 1 < n:
                            v = seq[k + 1]
                            d_uv = dist(u, v)
                            fwd = dist(u, s0) + dist(sL, v) - d_uv
                            rev = dist(u, sL) + dist(s0, v) - d_uv
                        else:  # after the last pose
                            fwd, rev = dist(u, s0), dist(u, sL)
                        for cost, reverse in ((fwd, False), (rev, True)):
                            if removal - cost > best:
                                best, best_k, best_rev = removal - cost, k, reverse
                if best_k >= 0:
                    run = seq[i : e + 1]
                    if best_rev:
                        run.reverse()
                    rest = seq[:i] + seq[e + 1 :]
                    at = best_k + 1 if best_k < i else best_k + 1 - L  # insert after seq[best_k]
                    seq = rest[:at] + run + rest[at:]
                    for k in range(min(i, at), max(e, at + L - 1) + 1):
                        where[seq[k]] = k
                    improved += 1
                    moved = True
                    break
            if not moved:
                i += 1
        if not improved:
            break
    return np.array(seq, dtype=np.int64)


def segment_samples(qa, qb, max_step_rad):
    """Configurations along the straight joint-space motion qa→qb, ≤ max_step_rad apart (k, N)."""
    qa, qb = np.asarray(qa, dtype=float), np.asarray(qb, dtype=float)
    k = max(1, int(np.ceil(np.max(np.abs(qb - qa)) / max_step_rad)))
    s = np.linspace(0.0, 1.0, k + 1)[:, None]
    return qa + s * (qb - qa)


def segment_sample_counts(Q_from, Q_to, max_step_rad):
    """Number of steps k (m,) of each straight motion Q_from[i]→Q_to[i] (m, N) in
    :func:`segment_samples`: k = ceil(max joint motion / max_step_rad), at least 1."""
    span = np.max(np.abs(np.asarray(Q_to, dtype=float) - np.asarray(Q_from, dtype=float)), axis=1)
    return np.maximum(1, np.ceil(span / max_step_rad)).astype(np.int64)


def interior_samples(Q_from, Q_to, max_step_rad):
    """The inner samples of all segments at once (the end poses excluded): the same
    configurations as ``segment_samples(a, b, max_step_rad)[1:-1]`` for every pair, stacked.

    Returns (q (M, N) rad, segment index (M,))."""
    Q_from, Q_to = np.asarray(Q_from, dtype=float), np.asarray(Q_to, dtype=float)
    k = segment_sample_counts(Q_from, Q_to, max_step_rad)
    inner = k - 1
    seg = np.repeat(np.arange(len(k)), inner)
    # sample number i = 1..k-1 within its segment
    first = np.cumsum(inner) - inner
    i = np.arange(len(seg)) - np.repeat(first, inner) + 1
    s = (i / k[seg])[:, None]
    return Q_from[seg] + s * (Q_to[seg] - Q_from[seg]), seg
