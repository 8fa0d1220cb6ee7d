"""Stage 3's repair: a straight joint motion between two poses of the tour that does not keep
the motion clearance is replaced by a path through two via postures that lift the arm; when
that path collides too, the pose is dropped, and the motions that then start elsewhere are
checked again."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from campaign.model.kinematics import frames
from campaign.plan.geometry import nominal_frames_entry_first
from campaign.plan.tour import interior_samples

#: joints 2 and 3 of the via posture that lifts the arm clear of the wall (rad)
VIA_Q2, VIA_Q3 = 0.0, -np.pi / 2
#: motion samples checked together (bounds memory at about 2 kB a sample)
MOTION_CHUNK = 32_768
#: rounds of re-checking the motions that start elsewhere after poses were dropped
RECHECK_ROUNDS = 5


def check_segments(robot, checker, Q_from, Q_to, max_step, clearance, chunk=MOTION_CHUNK):
    """(m,) bool: each straight joint-space motion Q_from[i]→Q_to[i] (m, 6) clear by
    ``clearance`` (m) at every sample ≤ ``max_step`` (rad) of joint motion apart.

    The end poses themselves are not re-checked here (they passed the pose filter at the
    stricter pose clearance); all inner samples of all segments are generated at once and
    checked ``chunk`` at a time (FK, sphere bounds, FCL for what the bounds leave)."""
    ok = np.ones(len(Q_from), dtype=bool)
    if len(Q_from) == 0:
        return ok
    q, seg = interior_samples(Q_from, Q_to, max_step)
    for s in range(0, len(q), chunk):
        R, t = nominal_frames_entry_first(robot, q[s : s + chunk])
        good = checker.clear_entry_first(R, t, clearance)
        ok[seg[s : s + chunk][~good]] = False
    return ok


@dataclass(frozen=True)
class Repair:
    """keep: (n,) bool, which tour poses stay; vias: {pose_id: [q (6,) rad, ...]} postures passed
    before reaching that pose; dropped: [(pose_id, reason), ...] in the order they were dropped."""

    keep: np.ndarray
    vias: dict
    dropped: list


def _via_path(a, b):
    """[a, lifted a, lifted b, b]: joints 1 and 4..6 kept, the arm raised by joints 2 and 3."""
    v1 = np.array([a[0], VIA_Q2, VIA_Q3, *a[3:]])
    v2 = np.array([b[0], VIA_Q2, VIA_Q3, *b[3:]])
    return np.array([a, v1, v2, b])


def repair_tour(robot, checker, order, Q, ok, max_step, clearance) -> Repair:
    """Repair the tour ``order`` (n,) pose ids with joint vectors Q (n, 6) rad, whose motions
    ``ok`` (n - 1,) bool say which straight motions keep ``clearance`` (m) at samples
    ``max_step`` (rad) apart (:func:`check_segments`)."""
    vias, dropped = {}, []
    via_from = {}  # tour index of a pose reached through vias → tour index its via path starts from
    keep = np.ones(len(order), dtype=bool)

    def prev_of(k):
        return max(i for i in range(k + 1) if keep[i])

    for m in np.flatnonzero(~ok):
        k = m + 1  # pose that the colliding motion reaches
        path = _via_path(Q[prev_of(m)], Q[k])
        if checker.clear(*frames(robot, path[1:3]), clearance).all() and \
                check_segments(robot, checker, path[:-1], path[1:], max_step, clearance).all():
            vias[int(order[k])] = [path[1], path[2]]
            via_from[k] = prev_of(m)
        else:
            keep[k] = False
            dropped.append((int(order[k]), "no collision-free motion from the previous pose, even via a lifted arm"))
    # motions after a dropped pose start elsewhere: re-check those (only those: every other
    # motion is unchanged and already checked) and repeat until clean
    known_ok = {(m, m + 1) for m in np.flatnonzero(ok)} | {(via_from[k], k) for k in via_from}
    for _ in range(RECHECK_ROUNDS):
        kept = np.flatnonzero(keep)
        starts = [i for i in range(1, len(kept)) if (kept[i - 1], kept[i]) not in known_ok]
        if not starts:
            break
        starts = np.array(starts)
        # a pose reached through vias: its first via posture is the motion's target
        targets = np.array([vias[int(order[kept[i]])][0] if int(order[kept[i]]) in vias else Q[kept[i]]
                            for i in starts])
        seg_ok = check_segments(robot, checker, Q[kept[starts - 1]], targets, max_step, clearance)
        known_ok |= {(kept[i - 1], kept[i]) for i in starts[seg_ok]}
        if seg_ok.all():
            break
        for i in starts[~seg_ok]:
            keep[kept[i]] = False
            dropped.append((int(order[kept[i]]), "no collision-free motion after re-ordering"))
    return Repair(keep, vias, dropped)


def tour_path(order, Q, vias) -> np.ndarray:
    """(m, 6) rad: the tour's joint vectors with each pose's via postures before it."""
    path = [Q[0]] if len(Q) else []
    for i in range(1, len(order)):
        path.extend(vias.get(int(order[i]), []))
        path.append(Q[i])
    return np.array(path).reshape(-1, Q.shape[1] if Q.ndim == 2 else 6)
