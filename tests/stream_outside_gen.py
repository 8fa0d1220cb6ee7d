"""An outside checker's tracker-log generator for `campaign import --stream` (issue 32's Done-means).

Independent of the project's simulator and of tests/test_stream_import.py: the truth arm is the
robot's URDF with its chain joints' origins perturbed (hidden geometric errors) evaluated by
Pinocchio; the motion between stops is a cosine profile of its own timing; the tracker is a vendor's
software: it measures its reflectors in turn at each stop (named as the vendor names them), follows
one reflector while the robot moves, loses the beam, spikes, drops samples, and writes its log with
its own clock (ISO 8601 with a time zone, a clock running fast), its own frame, millimetres and its
own columns. Only RUN/program/stops.csv (read here by the csv module) and the URDF are shared with
campaign. The truth (when each stop was dwelt at, where each reflector was) is kept for the checks.
"""

from __future__ import annotations

import csv
import datetime as dt
import re
from pathlib import Path

import numpy as np

URDF = Path(__file__).resolve().parent.parent / "campaign" / "data" / "robot_models" / "comau_racer5_080" / "robot.urdf"
CHAIN = ("I0", "joint1", "joint2", "joint3", "joint4", "joint5", "joint6", "6E")
LINKS = ("rrr1", "rrr2", "brr")  # the URDF's reflector links, in the order the vendor names them
VMAX = np.array([7.330, 6.109, 7.330, 9.599, 9.599, 13.963])


def read_stops(path):
    """[(stop, pose_id, kind, dwell_s, q (6,))] from a stops.csv, by its header."""
    with open(path) as f:
        return [(int(r["stop"]), int(r["pose_id"]), r["kind"], float(r["dwell_s"]),
                 np.array([float(r[f"q{i}"]) for i in range(1, 7)])) for r in csv.DictReader(f)]


def perturbed_urdf(rng, xyz_m=3e-4, rpy_rad=5e-4) -> str:
    """The URDF's text with each chain joint's origin moved by N(0, xyz_m) and turned by N(0, rpy_rad)."""
    text = URDF.read_text()
    for name in CHAIN:
        m = re.search(rf'<joint name="{re.escape(name)}".*?<origin xyz="([^"]*)" rpy="([^"]*)"/>', text, re.S)
        xyz = np.array(m.group(1).split(), float) + rng.normal(0, xyz_m, 3)
        rpy = np.array(m.group(2).split(), float) + rng.normal(0, rpy_rad, 3)
        new = m.group(0).replace(f'xyz="{m.group(1)}" rpy="{m.group(2)}"',
                                 f'xyz="{" ".join(f"{v:.12g}" for v in xyz)}" rpy="{" ".join(f"{v:.12g}" for v in rpy)}"')
        text = text[:m.start()] + new + text[m.end():]
    return text


class TruthArm:
    """Pinocchio on a (perturbed) URDF: the reflectors' positions in the root frame."""

    def __init__(self, urdf_text: str):
        import pinocchio as pin

        self.pin = pin
        self.model = pin.buildModelFromXML(urdf_text)
        self.data = self.model.createData()
        self.frames = [self.model.getFrameId(n) for n in LINKS]

    def points(self, Q) -> np.ndarray:
        """(n, 3 reflectors, 3) m."""
        pin = self.pin
        Q = np.atleast_2d(Q)
        out = np.empty((len(Q), len(self.frames), 3))
        for i, q in enumerate(Q):
            pin.framesForwardKinematics(self.model, self.data, np.asarray(q, float))
            for k, f in enumerate(self.frames):
                out[i, k] = self.data.oMf[f].translation
        return out


def random_rigid(rng):
    """The robot's root frame seen from the tracker: (R, t), 2.5-4 m away, any orientation."""
    a = rng.normal(size=4)
    w, x, y, z = a / np.linalg.norm(a)
    R = np.array([[1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y)],
                  [2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x)],
                  [2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)]])
    d = rng.normal(size=3)
    return R, d / np.linalg.norm(d) * rng.uniform(2.5, 4.0)


class VendorLog:
    """The samples a tracker's software records while a controller runs the program of ``stops``.

    Faults (all optional): ``lost_runs`` runs of three consecutive measured stops with the beam lost
    (nothing from the motion into the first to the end of the third); ``lost_one`` stops where one
    reflector is never measured; ``pause_motion`` / ``pause_stop`` / ``hold`` (s): an unplanned pause
    halfway through a motion, a stop held twice as long, an operator hold after a stop's dwell;
    ``spike_rate``, ``gaps`` (dropouts of 0.3-3 s) and ``empty_rows`` (rows without coordinates).
    """

    def __init__(self, stops, rng, *, rate_hz=1000.0, noise_m=15e-6, repeat_rad=1.2e-5, speed=0.5,
                 settle_s=0.6, switch_s=0.25, lost_runs=2, lost_one=3, pause_motion=300.0, pause_stop=True,
                 hold=90.0, spike_rate=1e-3, gaps=12, empty_rows=3, clock_rate=1.001, urdf_errors=True):
        self.stops, self.rng = stops, rng
        self.rate, self.noise = rate_hz, noise_m
        self.arm = TruthArm(perturbed_urdf(rng) if urdf_errors else URDF.read_text())
        self.R, self.t = random_rigid(rng)
        self.clock_rate = clock_rate
        self.epoch = dt.datetime(2031, 1, 1, tzinfo=dt.timezone.utc) + dt.timedelta(
            seconds=float(rng.uniform(0, 3e8)))
        measured = [k for k, s in enumerate(stops) if s[2] != "via"]
        n = len(stops)
        # faults at stops well inside the program
        self.lost = set()
        for _ in range(lost_runs):
            a = int(rng.integers(3, len(measured) - 6))
            self.lost |= set(measured[a:a + 3])
        free = [k for k in measured if k not in self.lost]
        self.lost_one = {int(k): int(rng.integers(0, 3)) for k in rng.choice(free, lost_one, replace=False)}
        self.pause_motion_at = int(rng.integers(n // 4, n // 2)) if pause_motion else None
        self.pause_motion_s = pause_motion
        self.pause_stop_at = int(rng.choice([k for k in free if k > n // 2])) if pause_stop else None
        self.hold_at = int(rng.choice([k for k in free if k < n // 3])) if hold else None
        self.hold_s = hold
        self.q_actual = {k: s[4] + rng.normal(0, repeat_rad, 6) for k, s in enumerate(stops)}
        self.speed, self.settle, self.switch = speed, settle_s, switch_s
        self.spike_rate, self.gaps, self.empty_rows = spike_rate, gaps, empty_rows
        self._build()

    # -- the truth -----------------------------------------------------------------------------
    def to_tracker(self, P):
        return P @ self.R.T + self.t

    def stop_points(self, k) -> np.ndarray:
        """(3, 3) m: the reflectors at stop k as the arm stood there, in the tracker's frame."""
        return self.to_tracker(self.arm.points(self.q_actual[k])[0])

    def motion_s(self, qa, qb) -> float:
        """This controller's own timing: a cosine profile whose peak speed is at most ``speed`` of the
        limits, plus 0.15 s of blending at each end."""
        d = np.abs(qb - qa)
        if d.max() == 0:
            return 0.0
        return float(np.max(d * np.pi / 2 / (self.speed * VMAX))) + 0.3

    def _build(self):
        """The timeline: arrays t (true s from the start), P (m, tracker frame), g (reflector code),
        stop (the stop whose dwell a sample belongs to, -1 in motion/settling), and per measured
        stop its dwell interval and the samples each reflector got."""
        rate, dt_s = self.rate, 1.0 / self.rate
        T, Pl, G, S = [], [], [], []
        self.interval, self.got = {}, {}
        t = 0.0
        g_track = 0
        q_prev = self.q_actual[0]

        def emit(ts, P, g, stop):
            T.append(ts)
            Pl.append(P)
            G.append(np.full(len(ts), g, np.int16))
            S.append(np.full(len(ts), stop, np.int32))

        for k, (stop, pid, kind, dwell, _q) in enumerate(self.stops):
            q = self.q_actual[k]
            dur = self.motion_s(q_prev, q)
            if dur > 0:
                # the motion, the tracker following reflector g_track; the arm's points on a 50 Hz grid
                n = max(int(dur * rate), 2)
                tau = np.arange(n) / n
                prof = (1 - np.cos(np.pi * tau)) / 2
                coarse = np.linspace(0, 1, max(int(dur * 50), 2))
                Qc = q_prev + ((1 - np.cos(np.pi * coarse)) / 2)[:, None] * (q - q_prev)
                Pc = self.to_tracker(self.arm.points(Qc)[:, g_track])
                P = np.stack([np.interp(tau, coarse, Pc[:, i]) for i in range(3)], axis=1)
                ts = t + dt_s * np.arange(n)
                if k == self.pause_motion_at:  # the robot stopped halfway (an unplanned pause)
                    h = n // 2
                    m = int(self.pause_motion_s * rate)
                    ts = np.concatenate([ts[:h], ts[h] + dt_s * np.arange(m), ts[h:] + m * dt_s])
                    P = np.concatenate([P[:h], np.repeat(P[h:h + 1], m, axis=0), P[h:]])
                emit(ts, P, g_track, -1)
                t = ts[-1] + dt_s
            q_prev = q
            if kind == "via":
                if dwell > 0:
                    m = int(dwell * rate)
                    P = self.to_tracker(self.arm.points(q)[0, g_track])
                    emit(t + dt_s * np.arange(m), np.repeat(P[None], m, axis=0), g_track, -1)
                    t += m * dt_s
                continue
            pts = self.stop_points(k)
            # settling: a decaying 60 um vibration on the reflector followed
            m = int(self.settle * rate)
            ts = t + dt_s * np.arange(m)
            vib = 6e-5 * np.exp(-(ts - t) / 0.12)[:, None] * np.sin(2 * np.pi * 7 * (ts - t))[:, None] * np.array([1, .6, -.4])
            emit(ts, pts[g_track] + vib, g_track, -1)
            t += m * dt_s
            slot = (dwell - self.settle) / 3 * (2 if k == self.pause_stop_at else 1)
            start = t
            self.got[k] = [0, 0, 0]
            for g in range(3):
                t += self.switch
                m = int((slot - self.switch) * rate)
                if self.lost_one.get(k) == g:  # the software could not lock on this reflector
                    t += m * dt_s
                    continue
                ts = t + dt_s * np.arange(m)
                emit(ts, np.repeat(pts[g][None], m, axis=0), g, k)
                self.got[k][g] = m
                t += m * dt_s
                g_track = g
            if k == self.hold_at:  # the operator held the controller after the dwell
                m = int(self.hold_s * rate)
                emit(t + dt_s * np.arange(m), np.repeat(pts[g_track][None], m, axis=0), g_track, -1)
                t += m * dt_s
            self.interval[k] = (start, t)
        t_all = np.concatenate(T)
        P = np.concatenate(Pl)
        g = np.concatenate(G)
        s = np.concatenate(S)
        keep = np.ones(len(t_all), bool)
        for k in self.lost:  # the beam lost from the motion into the stop to its end
            a, b = self.interval[k]
            keep &= ~((t_all >= a - 1.0) & (t_all <= b))
            self.got[k] = [0, 0, 0]
        n = len(t_all)
        for _ in range(self.gaps):
            a = int(self.rng.integers(0, n))
            keep[a:a + int(self.rng.uniform(0.3, 3.0) * self.rate)] = False
        for k in self.got:  # what each reflector kept
            sel = keep & (s == k)
            self.got[k] = [int(np.sum(sel & (g == c))) for c in range(3)]
        P = P + self.rng.normal(0, self.noise, P.shape)
        spikes = self.rng.random(n) < self.spike_rate
        d = self.rng.normal(size=(int(spikes.sum()), 3))
        P[spikes] += d / np.linalg.norm(d, axis=1)[:, None] * self.rng.uniform(5e-4, 0.1, (len(d), 1))
        self.t_true, self.P, self.g, self.s, self.keep, self.spikes = t_all, P, g, s, keep, spikes
        self.recorded = None
        self.empty = set(self.rng.choice(np.flatnonzero(keep), self.empty_rows, replace=False).tolist()) \
            if self.empty_rows else set()

    # -- what the truth says ---------------------------------------------------------------------
    def log_time(self, t_true):
        """The tracker's clock: s since 1970 (running ``clock_rate`` fast from its epoch)."""
        return self.epoch.timestamp() + np.asarray(t_true) * self.clock_rate

    def measured(self, min_s=0.3) -> list:
        """The stops every reflector of which has at least ``min_s`` of samples (a log of stable
        points: a record)."""
        if self.recorded is not None:
            return sorted(k for k, g in self.recorded.items() if len(g) == 3)
        return sorted(k for k, n in self.got.items() if min(n) >= min_s * self.rate)

    # -- the log as the vendor's software writes it ------------------------------------------------
    def records(self, mode="continuous", every=1):
        """(t_true, P (m), g, keep-mask already applied): every ``every``-th kept sample, or
        (mode "points") one averaged record per reflector per still stretch of at least 0.3 s."""
        idx = np.flatnonzero(self.keep)
        self.recorded = None
        if mode == "continuous":
            idx = idx[::every]
            return self.t_true[idx], self.P[idx], self.g[idx], idx
        # stable points: the software averages each stretch of one reflector at rest (its own test:
        # successive samples within 0.1 mm, no time gap), spikes dropped by a median
        out_t, out_P, out_g, out_i = [], [], [], []
        idx = idx[~self.spikes[idx]]  # the software's own filter drops a spike
        self.recorded = {}
        t, P, g, s = self.t_true[idx], self.P[idx], self.g[idx], self.s[idx]
        brk = np.flatnonzero((np.diff(t) > 2.5 / self.rate) | (g[1:] != g[:-1]) | (s[1:] != s[:-1])
                             | (np.linalg.norm(np.diff(P, axis=0), axis=1) > 1e-3)) + 1
        for a, b in zip(np.r_[0, brk], np.r_[brk, len(t)]):
            if t[b - 1] - t[a] < 0.3:
                continue
            med = np.median(P[a:b], axis=0)
            ok = np.linalg.norm(P[a:b] - med, axis=1) < 2e-4
            if ok.mean() < 0.8:
                continue  # moving
            out_t.append(t[b - 1])
            out_P.append(P[a:b][ok].mean(axis=0))
            out_g.append(g[a])
            out_i.append(idx[b - 1])
            if s[a] >= 0:
                self.recorded.setdefault(int(s[a]), set()).add(int(g[a]))
        return np.array(out_t), np.array(out_P), np.array(out_g), np.array(out_i)

    def write(self, path, *, mode="continuous", every=1, names=("SMR1", "SMR2", "SMR3"), unit="mm",
              iso=True, tz_hours=2, extra=True, header=("Time", "X", "Y", "Z", "Target"), delim=",",
              part=None):
        """Write the log; returns the list of paths (``part``: a fraction: the log cut there and
        continued in a second file with its own header)."""
        t, P, g, idx = self.records(mode, every)
        scale = {"m": 1.0, "mm": 1e3, "in": 1 / 0.0254}[unit]
        tz = dt.timezone(dt.timedelta(hours=tz_hours))
        tl = self.log_time(t)
        self.written_offset = 0.0 if iso else self.epoch.timestamp()
        cols = list(header[:4]) + ([header[4]] if names else [])
        if extra:
            cols = cols[:1] + ["Quality"] + cols[1:] + ["Distance_mm", "Temp_C"]
        lines = []
        base = dt.datetime.fromtimestamp(0, tz)
        empty = self.empty
        for k in range(len(t)):
            stamp = (base + dt.timedelta(seconds=float(tl[k]))).isoformat(timespec="microseconds") if iso \
                else f"{tl[k] - self.written_offset:.6f}"
            xyz = [f"{v * scale:.5f}" for v in P[k]]
            if idx[k] in empty:
                xyz = ["", "", ""]
            row = [stamp] + xyz + ([names[g[k]]] if names else [])
            if extra:
                d = float(np.linalg.norm(P[k]) * 1e3)
                row = row[:1] + [f"{0.9 + 0.1 * self.rng.random():.3f}"] + row[1:] + [f"{d:.3f}",
                                                                                         f"{20.3 + t[k] * 1e-4:.2f}"]
            lines.append(delim.join(row) + "\n")
        head = delim.join(cols) + "\n"
        path = Path(path)
        if part is None:
            path.write_text(head + "".join(lines))
            return [path]
        cut = int(part * len(lines))
        second = path.with_name(path.stem + "_2" + path.suffix)
        path.write_text(head + "".join(lines[:cut]))
        second.write_text(head + "".join(lines[cut:]))
        return [path, second]


def check(run, gen: VendorLog, *, tol_m=3e-4):
    """(found, measured, wrong, details): of the stops the log measured whole, how many stream_match.csv
    says matched; a match is wrong when its window is not inside the stop's dwell in the log's clock,
    or when a stored reading is farther than ``tol_m`` from where the reflector was."""
    import sqlite3

    with open(Path(run) / "import" / "stream_match.csv") as f:
        rows = [r for r in csv.DictReader(f) if r["stop"]]
    measured = gen.measured()
    status = {int(r["stop"]): r for r in rows}
    found = [k for k in measured if status.get(k, {}).get("status") == "matched"]
    wrong = []
    spans = {k: gen.log_time(np.array(v)) - gen.written_offset for k, v in gen.interval.items()}
    for r in rows:
        if r["status"] != "matched":
            continue
        k = int(r["stop"])
        a, b = spans.get(k, (np.nan, np.nan))
        w0, w1 = float(r["window_start_s"]), float(r["window_end_s"])
        # the window must overlap the stop's dwell and reach into no other stop's
        other = [j for j, (c, d) in spans.items() if j != k and (c <= w0 <= d or c <= w1 <= d)]
        if not (w0 <= b and w1 >= a) or other:
            wrong.append((k, "time", w0 - a, w1 - b, other))
    # the stored readings against the truth (the log's frame; pose ids of the poses and repeats)
    by_pid = {}
    for k, s in enumerate(gen.stops):
        if s[2] in ("pose", "validation", "repeat"):
            by_pid.setdefault(s[1], []).append(k)
    with sqlite3.connect(Path(run) / "measurements.sqlite") as db:
        got = {}
        for pid, name, x, y, z in db.execute("SELECT pose_id, name, x_L_m, y_L_m, z_L_m FROM reflector_readings"):
            got.setdefault(pid, {})[name] = np.array([x, y, z])
    names = ("rrr1", "rrr2", "brr")
    for pid, refl in got.items():
        ks = by_pid.get(pid, [])
        err = min((max(np.linalg.norm(refl[n] - gen.stop_points(k)[c]) for c, n in enumerate(names) if n in refl)
                   for k in ks), default=np.inf)
        if err > tol_m:
            wrong.append((pid, "place", err))
    return len(found), len(measured), wrong, [k for k in measured if k not in found]
