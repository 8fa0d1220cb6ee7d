"""The reachable region of the suitable set: which suitable poses one tour can visit.

Suitable poses are joined when the straight joint motion between them keeps the motion
clearance (:func:`campaign.plan.repair.check_segments`). The graph is built like Kruskal's
algorithm in rounds: round r checks, for every pose, the motion to its r-th nearest suitable
pose (largest joint difference in grid cells) when the two lie in different components so far,
all such motions of a round in one batch; then each smaller component is tried against the
largest by the motions between their nearest poses (:data:`JOIN_TRIES` per component, a
lifted-arm or structured via path for the closest pair when those fail). The largest component
is the region the tour visits; the design chooses among its poses only, so the tour rarely has
to drop a chosen pose (campaign.plan.pipeline).

A pose outside the region is there because of a barrier: for each component left outside, the
motions from the nearest region pose that move one joint at a time to the outside pose's value
name the joint(s) whose motion alone collides (a UR10 on its pedestal: joint 2, the upper arm
pointing into the pedestal), else "several joints together".
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from campaign.plan.repair import PathFinder, check_segments

#: nearest suitable poses tried per pose, one round each
NEIGHBOURS = 6
#: motions tried between a smaller component and the largest, nearest first
JOIN_TRIES = 3
#: components (the largest first) whose closest pair to the region is also tried by via paths
VIA_COMPONENTS = 40
#: postures checked per batch (bounds the frames' memory)
EDGE_CHUNK = 4096
#: most suitable poses the region is built on (a random sample, fixed seed, of a larger set; the
#: others are counted with the sampled pose nearest them): the design chooses among these, whose
#: information about the model is that of the whole set within a few per cent
POOL = 2000
POOL_SEED = 20260522


@dataclass(frozen=True)
class Region:
    """inside: (m,) bool over the suitable poses, those of the largest joined component (a pose
    not in the pool: that of the pool pose nearest it); pool: (k,) indices into the suitable
    poses that the region was built on (all of them when m ≤ :data:`POOL`), in_pool: (k,) bool
    which of them are inside; components: number of components among the pool; outside:
    {barrier text: suitable poses outside for it}; motions_checked: straight motions (and via
    paths) checked."""

    inside: np.ndarray
    pool: np.ndarray
    in_pool: np.ndarray
    components: int
    outside: dict = field(default_factory=dict)
    motions_checked: int = 0
    too_few: str | None = None  # why the design chose among every suitable pose instead

    def summary(self) -> dict:
        """summary.json's ``reachable``."""
        m, k = len(self.inside), len(self.pool)
        return {"suitable": int(m), "inside": int(self.inside.sum()), "outside": int(m - self.inside.sum()),
                "outside_by_barrier": dict(self.outside), "pool": int(k), "pool_inside": int(self.in_pool.sum()),
                "components": int(self.components), "motions_checked": int(self.motions_checked),
                "text": ("suitable poses joined to one another by collision-free straight motions (or via paths) "
                         "at plan.motion_clearance_m; the design chooses among the largest set, and its "
                         "prediction (selection.predicted) is averaged over those poses"
                         + ("" if k == m else f" of a random pool of {k:,} (each other suitable pose counted with "
                                              "the pool pose nearest it)"))}


def _labels(m, edges):
    from scipy.sparse import coo_matrix
    from scipy.sparse.csgraph import connected_components

    if len(edges) == 0:
        return np.arange(m)
    e = np.asarray(edges, dtype=np.int64).reshape(-1, 2)
    A = coo_matrix((np.ones(len(e), dtype=np.int8), (e[:, 0], e[:, 1])), shape=(m, m))
    return connected_components(A, directed=False)[1]


def reachable_region(robot, checker, grid, suitable, max_step, clearance, *, neighbours: int = NEIGHBOURS,
                     progress=None, pose_clearance=None) -> Region:
    """The :class:`Region` of the ``suitable`` grid indices (m,): motions keep ``clearance`` (m)
    at samples ``max_step`` (rad) apart; the checker as the filters'. ``progress``: a
    :class:`campaign.progress.Progress` or None. ``pose_clearance``: the clearance (m) the
    suitable poses keep (the filters'), which bounds the motions near them
    (:func:`campaign.plan.repair.check_segments`' ``ends_clearance``)."""
    from scipy.spatial import cKDTree

    suitable = np.asarray(suitable, dtype=np.int64)
    everything = len(suitable)
    pool = np.arange(everything) if everything <= POOL else \
        np.sort(np.random.default_rng(POOL_SEED).choice(everything, POOL, replace=False))
    m = len(pool)
    if m <= 1:
        return Region(np.ones(everything, dtype=bool), pool, np.ones(m, dtype=bool), m)
    Q = grid.q(suitable[pool])
    X = grid.cell_indices(suitable[pool]).astype(float)
    k = min(neighbours, m - 1)
    _, near = cKDTree(X).query(X, k=k + 1, p=np.inf)
    edges, checked = [], 0
    labels = np.arange(m)
    for r in range(1, k + 1):
        a, b = np.arange(m), near[:, r]
        pairs = np.unique(np.sort(np.stack([a, b], axis=1)[labels[a] != labels[b]], axis=1), axis=0)
        if len(pairs) == 0:
            continue
        ok = check_segments(robot, checker, Q[pairs[:, 0]], Q[pairs[:, 1]], max_step, clearance,
                            ends_clearance=pose_clearance)
        checked += len(pairs)
        edges.extend(pairs[ok].tolist())
        labels = _labels(m, edges)
        if progress is not None:
            progress.update(1, f"{len(np.unique(labels))} sets")
    finder = PathFinder(robot, checker, max_step, clearance)
    failed = np.zeros(m, dtype=bool)  # poses of sets that no motion joined to the largest
    for _ in range(3):  # the largest set grows as others join it: try again against it
        main = np.bincount(labels).argmax()
        a, b, comp = _nearest_pairs(X, labels, main, JOIN_TRIES, exclude=failed)
        if len(a) == 0:
            break
        sizes = np.bincount(labels)
        by_size = sorted(set(comp.tolist()), key=lambda c: (-int(sizes[c]), c))
        ok = check_segments(robot, checker, Q[a], Q[b], max_step, clearance, ends_clearance=pose_clearance)
        checked += len(a)
        joined = set(comp[ok].tolist())
        edges.extend(np.stack([a[ok], b[ok]], axis=1).tolist())
        for c in by_size[:VIA_COMPONENTS]:
            if c in joined:
                continue
            i = int(np.flatnonzero(comp == c)[0])
            checked += 1
            if finder.vias(Q[a[i]], Q[b[i]], None, search=False) is not None:
                edges.append([int(a[i]), int(b[i])])
                joined.add(c)
        failed |= np.isin(labels, list(set(comp.tolist()) - joined))
        labels = _labels(m, edges)
    main = np.bincount(labels).argmax()
    in_pool = labels == main
    # every suitable pose with the pool pose nearest it (itself when in the pool)
    nearest = np.arange(m) if m == everything else \
        cKDTree(X).query(grid.cell_indices(suitable).astype(float), k=1, p=np.inf)[1]
    outside = {}
    if not in_pool.all():
        why = _barriers(robot, checker, Q, X, labels, main, max_step, clearance)
        for c, n in zip(*np.unique(labels[nearest], return_counts=True)):
            if c != main:
                outside[why[c]] = outside.get(why[c], 0) + int(n)
    outside = dict(sorted(outside.items(), key=lambda kv: -kv[1]))
    return Region(in_pool[nearest], pool, in_pool, int(len(np.unique(labels))), outside, checked)


def _nearest_pairs(X, labels, main, per, exclude=None):
    """For each component but ``main`` (and those of the poses ``exclude``, (m,) bool), its ``per`` poses nearest the
    main component (largest cell difference) and the main pose nearest each: (a, b, component)
    index arrays, components ascending, the nearest pair first."""
    from scipy.spatial import cKDTree

    inside = np.flatnonzero(labels == main)
    rest = np.flatnonzero((labels != main) if exclude is None else (labels != main) & ~exclude)
    if len(rest) == 0:
        return np.zeros(0, np.int64), np.zeros(0, np.int64), np.zeros(0, np.int64)
    d, j = cKDTree(X[inside]).query(X[rest], k=1, p=np.inf)
    order = np.lexsort((d, labels[rest]))
    lab = labels[rest][order]
    rank = np.arange(len(order)) - np.searchsorted(lab, lab)  # place within its component
    keep = order[rank < per]
    return rest[keep], inside[j[keep]], labels[rest][keep]


def _barriers(robot, checker, Q, X, labels, main, max_step, clearance) -> dict:
    """{component: barrier text} for the components outside the region: the motions from the
    region pose nearest each that move one joint alone to its nearest pose's value."""
    N = Q.shape[1]
    xs, ys, comps = _nearest_pairs(X, labels, main, 1)
    pairs = list(zip(xs, ys))
    src, dst = [], []
    for x, y in pairs:
        for joint in range(N):
            q = Q[y].copy()
            q[joint] = Q[x][joint]
            src.append(Q[y])
            dst.append(q)
    src, dst = np.array(src), np.array(dst)
    from campaign.plan.geometry import nominal_frames_entry_first

    ok = np.zeros(len(src), dtype=bool)
    for s in range(0, len(src), EDGE_CHUNK):
        end = checker.clear_entry_first(*nominal_frames_entry_first(robot, dst[s:s + EDGE_CHUNK]), clearance)
        ok[s:s + EDGE_CHUNK] = end & check_segments(robot, checker, src[s:s + EDGE_CHUNK], dst[s:s + EDGE_CHUNK],
                                                    max_step, clearance)
    out = {}
    for n, c in enumerate(comps):
        blocked = [j + 1 for j in range(N) if not ok[n * N + j]]
        out[c] = (f"joint {blocked[0]}" if len(blocked) == 1 else
                  f"joints {', '.join(map(str, blocked))}" if blocked else "several joints together")
    return out
