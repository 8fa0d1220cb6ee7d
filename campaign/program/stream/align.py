"""Still windows aligned to a program's stops, in order, on what no frame or clock changes.

The distance between two stops' tool points, predicted by the nominal model, is compared with the
distance between their windows' positions (a rigid motion keeps distances: the tracker's frame
does not matter), and the stops skipped between two windows must have had time for their dwells
(only time differences are used: the clock's offset does not matter). A dynamic programme over the
windows in time order finds the monotone matching of highest score:

* each matched window gains ALIGN_GAIN times the share of the tool's reflectors it holds (a
  fragment at a stop, such as the reflector the tracker followed into it while the robot settled,
  gains less than the stop's whole measurement beside it, which is then the one matched);
* each pair of successive matches pays half the squared distance residual in tolerances
  (STREAM_DISTANCE_TOL_M + STREAM_DISTANCE_TOL_REL · distance), at most ALIGN_PAIR_CAP;
* a stop without a window (a lost beam: skipped, the next window is not shifted onto it) pays
  ALIGN_SKIP_STOP, a window without a stop (an unplanned pause: rejected) ALIGN_REJECT_WINDOW;
* the stops skipped between two windows must fit in the time between them: their dwells (scaled
  to the log's, by the windows' median length over the median dwell), or ALIGN_PERIOD_FACTOR stops
  per typical time between successive windows, whichever allows more.

The chain starts at the first stop not yet imported (skipping stops costs the same there) and may
end anywhere (a log that ends halfway). A beam of ALIGN_BEAM states per window bounds the work.
A second pass adds a time cost (TimeModel: dwells and nominal motion times, scaled to the log by
the first pass's matches), which tells apart stops at one place (a repeat) and refuses windows
whose time is far off (a second log repeating the first's end); a match is kept only when a
neighbouring match in the chain confirms it (its distance residual within ALIGN_CONFIRM tolerances,
its time within ALIGN_CONFIRM standard deviations): no isolated guess is stored.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from campaign.tolerances import (STREAM_DISTANCE_TOL_M, STREAM_DISTANCE_TOL_REL, STREAM_DWELL_FACTOR,
                                 STREAM_DWELL_SLACK_S)

ALIGN_GAIN = 4.0
ALIGN_SKIP_STOP = 1.5
ALIGN_REJECT_WINDOW = 1.0
#: a wrong pair costs far more than a match gains: a chain never buys a match with a bad distance
ALIGN_PAIR_CAP = 60.0
#: a pair of windows one of which holds no reflector of the model says nothing: this cost
ALIGN_PAIR_UNKNOWN = 1.0
ALIGN_BEAM = 24
#: predecessors looked at directly (older ones through the best of them)
ALIGN_LOOKBACK = 6
#: stops skipped between two successive matches at most (the dwell bound is usually tighter)
ALIGN_MAX_JUMP = 2000
#: windows at the start that may begin the chain (before them: a set-up, a warm-up)
ALIGN_START_WINDOWS = 400
ALIGN_CONFIRM = 3.0
#: stops that may be skipped per typical stop-to-stop time of the log (twice the typical rate, and
#: a margin: motions differ in length)
ALIGN_PERIOD_FACTOR = 2.5
#: the second pass's time cost: half the squared log of observed over expected time, in units of
#: ALIGN_TIME_LOG_SIGMA (a stop's time varies by tens of per cent: pauses, a motion's profile), at
#: most ALIGN_TIME_CAP / 2: twice a match's gain, so a window whose time is off by more than about
#: 2.3x is not worth matching on a chance distance (every chain across a long pause pays it alike)
ALIGN_TIME_LOG_SIGMA = 0.3
ALIGN_TIME_CAP = 16.0
#: successive matches needed to fit the time model, and the windows of the first pass that fits it
ALIGN_TIME_MIN_PAIRS = 5
ALIGN_TIME_FIT_WINDOWS = 400
#: the time fit's outliers are beyond 3 robust deviations of its residuals, a deviation of at least
#: this (s): a log's stamps are no finer than its samples (0.1 s at 10 Hz)
ALIGN_TIME_MIN_MAD_S = 0.05


@dataclass(frozen=True)
class Match:
    """Window ``window`` matched to stop ``stop``; ``residual``: its distance residual to the
    previous and the next match in tolerances (NaN where none), ``confirmed`` when one is small."""

    window: int
    stop: int
    residual_prev: float
    residual_next: float
    confirmed: bool


def _common(a: dict, b: dict):
    for c in sorted(a):
        if c in b:
            return c
    return None


def pair_residual(wa, wb, P, ja, jb) -> np.ndarray:
    """Distance residuals in tolerances between windows wa, wb matched to stops ja, jb (arrays), on
    the first reflector both hold, else between the first reflector of each (the tool's layout
    predicts that distance as well: two windows without a reflector in common still say where they
    are). NaN when a window holds none (P has fewer reflectors)."""
    c = _common(wa.position, wb.position)
    ca, cb = (c, c) if c is not None else (min(wa.position, default=None), min(wb.position, default=None))
    if ca is None or cb is None or ca >= P.shape[1] or cb >= P.shape[1]:
        return np.full(np.broadcast(ja, jb).shape, np.nan)
    d_obs = float(np.linalg.norm(wb.position[cb] - wa.position[ca]))
    d_pred = np.linalg.norm(P[jb, cb] - P[ja, ca], axis=-1)
    return (d_obs - d_pred) / (STREAM_DISTANCE_TOL_M + STREAM_DISTANCE_TOL_REL * d_pred)


def _pair_cost(r):
    cost = 0.5 * np.minimum(r * r, ALIGN_PAIR_CAP)
    return np.where(np.isnan(r), ALIGN_PAIR_UNKNOWN, cost)


@dataclass(frozen=True)
class TimeModel:
    """The log's time between two stops: ``dwell_scale`` · (their dwells) + ``motion_scale`` ·
    (the nominal motion times between them), both cumulative over the stops (n + 1,) s, fitted to
    the first pass's matches of successive stops."""

    dwell_scale: float
    motion_scale: float
    cum_dwell: np.ndarray
    cum_motion: np.ndarray

    def expected_s(self, ja, jb) -> np.ndarray:
        """Expected start-to-start time (s) from stop ja to stop jb (arrays): the dwells of ja..jb-1
        and the motions into ja+1..jb."""
        return self.dwell_scale * (self.cum_dwell[jb] - self.cum_dwell[ja]) \
            + self.motion_scale * (self.cum_motion[jb + 1] - self.cum_motion[ja + 1])

    def cost(self, dt_s, ja, jb) -> np.ndarray:
        """The time cost of observing dt_s (s, scalar or array) from stop ja to stop jb."""
        expected = np.maximum(self.expected_s(ja, jb), 1e-3)
        z = np.log(np.maximum(dt_s, 1e-3) / expected) / ALIGN_TIME_LOG_SIGMA
        return 0.5 * np.minimum(z * z, ALIGN_TIME_CAP)


def fit_time_model(matches, windows, dwell_s, motion_s):
    """A :class:`TimeModel` from confirmed matches of successive stops (robust least squares:
    one refit without the pairs beyond three median deviations); None with fewer than
    ALIGN_TIME_MIN_PAIRS or a degenerate fit."""
    cum_dwell = np.concatenate([[0.0], np.cumsum(dwell_s)])
    cum_motion = np.concatenate([[0.0], np.cumsum(motion_s)])
    rows, obs = [], []
    for a, b in zip(matches[:-1], matches[1:]):
        if a.confirmed and b.confirmed and b.stop == a.stop + 1 and b.window == a.window + 1:
            rows.append((cum_dwell[b.stop] - cum_dwell[a.stop], cum_motion[b.stop + 1] - cum_motion[a.stop + 1]))
            obs.append(windows[b.window].t0 - windows[a.window].t0)
    if len(rows) < ALIGN_TIME_MIN_PAIRS:
        return None
    A, y = np.array(rows), np.array(obs)
    keep = np.ones(len(y), bool)
    for _ in range(2):
        coef = np.linalg.lstsq(A[keep], y[keep], rcond=None)[0]
        res = y - A @ coef
        # about the residuals' median, at least a sample's worth of scale: many pairs alike (stops
        # one joint apart, each the same time) leave a median deviation of zero about a median off zero
        centre = np.median(res[keep])
        mad = max(float(np.median(np.abs(res[keep] - centre))), ALIGN_TIME_MIN_MAD_S)
        keep = np.abs(res - centre) <= 3 * 1.4826 * mad
        if keep.sum() < ALIGN_TIME_MIN_PAIRS:
            return None
    if not np.all(np.isfinite(coef)) or coef[0] < 0 or coef[1] <= 0:
        return None
    return TimeModel(float(coef[0]), float(coef[1]), cum_dwell, cum_motion)


def align(windows, P, dwell_s, *, first_stop: int = 0, t_start: float | None = None, motion_s=None) -> list:
    """The matches of ``windows`` (campaign.program.stream.windows.Window, time order) to stops
    ``first_stop``.. whose nominal points per reflector code are P (n, k, 3) m and dwells
    ``dwell_s`` (n,) s; a list of :class:`Match` in order. ``t_start``: the log's first time (s).
    ``motion_s`` (n,) s: the nominal motion time into each stop from the one before; given, a second
    pass weighs how well the time between two windows fits the stops between them (a time model
    fitted to the first pass's matches): stops at one place (a repeat) are told apart by time."""
    m, n = len(windows), len(P)
    if m == 0 or first_stop >= n:
        return []
    dwell_s = np.asarray(dwell_s, dtype=float)
    if motion_s is None:
        return _confirm(_dp(windows, P, dwell_s, first_stop, t_start, None), windows, P)
    # the time model from a first pass over the log's beginning (the program's speed is one), else
    # over all of it
    model = None
    for part in ([windows[:ALIGN_TIME_FIT_WINDOWS]] if m > ALIGN_TIME_FIT_WINDOWS else []) + [windows]:
        matches = _confirm(_dp(part, P, dwell_s, first_stop, t_start, None), part, P)
        model = fit_time_model(matches, part, dwell_s, np.asarray(motion_s, dtype=float))
        if model is not None:
            break
    if model is None:
        return matches
    return _confirm(_dp(windows, P, dwell_s, first_stop, t_start, model), windows, P, model)


def _dp(windows, P, dwell_s, first_stop, t_start, time_model) -> list:
    """The best chain [(window, stop), ...] (module docstring); ``time_model`` adds its cost. Each
    window's candidates from all its predecessors' states are scored at once (arrays)."""
    m, n, k = len(windows), len(P), P.shape[1]
    # the windows' positions per reflector code (NaN where a window has none)
    W = np.full((m, k, 3), np.nan)
    for i, w in enumerate(windows):
        for c, pos in w.position.items():
            W[i, c] = pos
    has = np.isfinite(W[:, :, 0])
    gain = ALIGN_GAIN * has.sum(axis=1) / k
    t0 = np.array([w.t0 for w in windows])
    t1 = np.array([w.t1 for w in windows])
    # the dwells as the log keeps them (the clock's rate, a program run slower or faster): scaled by
    # the windows' median length over the stops' median dwell, never up
    scale = float(np.clip(np.median(t1 - t0) / np.median(dwell_s), 0.0, 1.0)) if np.median(dwell_s) > 0 else 0.0
    C = np.concatenate([[0.0], np.cumsum(dwell_s * scale)])  # dwell of the stops before k
    # a stop takes the log's typical stop-to-stop time or more (a count bound that holds whatever
    # the dwells: a log of stable points has windows without length)
    period = float(np.median(np.diff(t0))) if m > 1 else 0.0
    t_start = t0[0] if t_start is None else t_start
    tol = STREAM_DISTANCE_TOL_M
    states = []  # per window: (J, S, back window, back state)
    old = None  # the best state of windows beyond the lookback: (S + reject · i, i, k)

    def reach(j_prev_next, dt):
        """The last stop reachable: stops j_prev_next..j-1 skipped need their dwell in dt, or at most
        ALIGN_PERIOD_FACTOR stops per typical period of the log fit in dt."""
        dt = np.maximum(dt, 0.0)
        budget = C[j_prev_next] + dt * STREAM_DWELL_FACTOR + STREAM_DWELL_SLACK_S
        hi = np.searchsorted(C, budget, side="right") - 1  # C[hi] <= budget: stops < hi fit
        if period > 0:
            hi = np.maximum(hi, j_prev_next + (ALIGN_PERIOD_FACTOR * dt / period).astype(np.int64) + 1)
        return np.minimum(np.minimum(hi, j_prev_next + ALIGN_MAX_JUMP), n - 1)

    empty = (np.zeros(0, np.int64), np.zeros(0), np.zeros(0, np.int64), np.zeros(0, np.int64))
    for i in range(m):
        cJ, cS, cB, cK = [], [], [], []
        if i < ALIGN_START_WINDOWS:
            hi = int(reach(np.int64(first_stop), np.float64(t0[i] - t_start)))
            J = np.arange(first_stop, hi + 1)
            cJ.append(J)
            cS.append(gain[i] - ALIGN_REJECT_WINDOW * i - ALIGN_SKIP_STOP * (J - first_stop))
            cB.append(np.full(len(J), -1))
            cK.append(np.full(len(J), -1))
        # every predecessor's states at once: the last ALIGN_LOOKBACK windows', and the best older one
        parts = [(ip, states[ip][0], states[ip][1], np.arange(len(states[ip][0])))
                 for ip in range(max(0, i - ALIGN_LOOKBACK), i) if len(states[ip][0])]
        if old is not None:
            Jo, So = states[old[1]][0], states[old[1]][1]
            parts.append((old[1], Jo[old[2]:old[2] + 1], So[old[2]:old[2] + 1], np.array([old[2]])))
        if parts:
            Jp = np.concatenate([p[1] for p in parts])
            Sp = np.concatenate([p[2] for p in parts])
            Bp = np.concatenate([np.full(len(p[1]), p[0]) for p in parts])
            Kp = np.concatenate([p[3] for p in parts])
            hi = reach(Jp + 1, t0[i] - t1[Bp])
            cnt = np.maximum(hi - Jp, 0)
            total = int(cnt.sum())
            if total:
                rep = np.repeat(np.arange(len(Jp)), cnt)
                Ja, Ba = Jp[rep], Bp[rep]
                J = Ja + 1 + (np.arange(total) - np.repeat(np.cumsum(cnt) - cnt, cnt))
                # the distance residual on the first reflector both windows hold, else between the
                # first of each (the tool's layout predicts it too; NaN: a window holds none)
                common = has[Ba] & has[i][None, :]
                shared = common.any(axis=1)
                cb = np.where(shared, np.argmax(common, axis=1), np.argmax(has[i]))
                ca = np.where(shared, cb, np.argmax(has[Ba], axis=1))
                d_obs = np.linalg.norm(W[i, cb] - W[Ba, ca], axis=1)
                d_pred = np.linalg.norm(P[J, cb] - P[Ja, ca], axis=1)
                r = (d_obs - d_pred) / (tol + STREAM_DISTANCE_TOL_REL * d_pred)
                r[~(has[Ba].any(axis=1) & has[i].any())] = np.nan
                S = Sp[rep] + gain[i] - ALIGN_SKIP_STOP * (J - Ja - 1) \
                    - ALIGN_REJECT_WINDOW * (i - Ba - 1) - _pair_cost(r)
                if time_model is not None:
                    S = S - time_model.cost(t0[i] - t0[Ba], Ja, J)
                cJ.append(J)
                cS.append(S)
                cB.append(Ba)
                cK.append(Kp[rep])
        if not cJ:
            states.append(empty)
        else:
            J, S, Bk, K = (np.concatenate(a) for a in (cJ, cS, cB, cK))
            order = np.lexsort((-S, J))
            first = np.ones(len(order), bool)
            first[1:] = J[order][1:] != J[order][:-1]
            keep = order[first]
            keep = keep[np.argsort(-S[keep], kind="stable")[:ALIGN_BEAM]]
            states.append((J[keep], S[keep], Bk[keep], K[keep]))
        leaving = i - ALIGN_LOOKBACK
        if leaving >= 0 and len(states[leaving][0]):
            kk = int(np.argmax(states[leaving][1]))
            v = states[leaving][1][kk] + ALIGN_REJECT_WINDOW * leaving
            if old is None or v > old[0]:
                old = (v, leaving, kk)
    best, at = -np.inf, None
    for i, (J, S, _, _) in enumerate(states):
        if len(J):
            kk = int(np.argmax(S))
            v = S[kk] - ALIGN_REJECT_WINDOW * (m - 1 - i)
            if v > best:
                best, at = v, (i, kk)
    chain = []
    while at is not None and at[0] >= 0:
        i, kk = at
        J, _, Bk, K = states[i]
        chain.append((i, int(J[kk])))
        at = (int(Bk[kk]), int(K[kk])) if Bk[kk] >= 0 else None
    chain.reverse()
    return chain


def _confirm(chain, windows, P, time_model=None) -> list:
    """The chain's matches, each confirmed when the distance to its previous or next match fits
    (ALIGN_CONFIRM tolerances) and, with a time model, so does the time between them (its log
    ratio within ALIGN_CONFIRM standard deviations): a window chosen among many for one distance
    that fits by chance is not confirmed."""
    out = []
    res, fits = [], []
    for a, b in zip(chain[:-1], chain[1:]):
        res.append(float(pair_residual(windows[a[0]], windows[b[0]], P, np.int64(a[1]), np.int64(b[1]))))
        if time_model is None:
            fits.append(True)
        else:
            z2 = 2 * float(time_model.cost(windows[b[0]].t0 - windows[a[0]].t0, np.int64(a[1]), np.int64(b[1])))
            fits.append(z2 <= ALIGN_CONFIRM ** 2)
    for k, (i, j) in enumerate(chain):
        rp = res[k - 1] if k > 0 else np.nan
        rn = res[k] if k < len(res) else np.nan
        ok = any(np.isfinite(r) and abs(r) <= ALIGN_CONFIRM and fit
                 for r, fit in ((rp, k > 0 and fits[k - 1]), (rn, k < len(res) and fits[k])))
        out.append(Match(i, j, rp, rn, bool(ok)))
    return out
