"""Issue 32 part 2: `campaign import --stream LOG --run RUN`: a tracker's log matched to the program's
stops. The logs are written here by a generator of the test's own (not the simulator): a truth arm
(the nominal COMAU with random geometric errors), motion between the stops, the reflectors measured
in turn at each stop, lost beams, unplanned pauses, spikes, gaps, an unknown clock, the tracker's
frame (a random rigid transform) and millimetres. The truth is read only after the import answered."""

import csv
import re
import sqlite3

import numpy as np
import pytest

from campaign.cli import main
from campaign.model.kinematics import forward
from campaign.program.stops import Stop, stops_path, write_stops_csv

REFLECTORS = ("rrr1", "rrr2", "brr")


def make_stops(robot, n_poses, rng, *, dwell_s=3.5, via_every=9, drift_every=15, repeat_every=20, tail_repeats=3):
    """A program's stops: poses (some validation), a repeat of every ``repeat_every``-th pose after the
    next one, a via before every ``via_every``-th pose, a drift check after every ``drift_every``-th,
    and the last pose measured ``tail_repeats`` more times back to back (at one place: no motion)."""
    lo, hi = robot.q_lower, robot.q_upper
    mid, half = (lo + hi) / 2, (hi - lo) / 2
    Q = mid + 0.55 * half * rng.uniform(-1, 1, (n_poses, robot.n_joints))
    Q[:, 4] = np.where(np.abs(Q[:, 4]) < 0.3, 0.3 * np.sign(Q[:, 4] + 1e-9), Q[:, 4])  # off the wrist singularity
    stops = []

    def add(pid, kind, q, dwell=dwell_s):
        stops.append(Stop(len(stops), int(pid), kind, float(dwell), tuple(map(float, q))))

    pending = None
    for k in range(n_poses):
        pid = 5000 + k
        if via_every and k % via_every == via_every - 1:
            add(pid, "via", (Q[k] + Q[k - 1]) / 2, 0.0)
        add(pid, "validation" if k % 7 == 3 else "pose", Q[k])
        if pending is not None:
            add(pending[0] + 10**9, "repeat", pending[1])
            pending = None
        if repeat_every and k % repeat_every == 1:
            pending = (pid, Q[k])
        if drift_every and (k + 1) % drift_every == 0 and k + 1 < n_poses:
            add(5000, "drift", Q[0])
    for r in range(1, tail_repeats + 1):
        add(5000 + n_poses - 1 + r * 10**9, "repeat", Q[-1])
    return stops


def random_rigid(rng):
    """A tracker's pose: T_LI (4, 4), the robot's frame seen from the tracker 2-4 m away."""
    from campaign.model.rotations import rotvec_to_matrix

    axis = rng.normal(size=3)
    T = np.eye(4)
    T[:3, :3] = rotvec_to_matrix((axis / np.linalg.norm(axis) * rng.uniform(0.3, 3.0))[None])[0]
    T[:3, 3] = rng.uniform(-1, 1, 3) + np.array([0, 0, 3.0])
    return T


class LogWriter:
    """A tracker's continuous log of a program run by a truth arm: rows (t, x, y, z, target), the
    faults chosen, and for every measured stop whether each reflector had clean samples."""

    def __init__(self, robot, stops, rng, *, rate_hz=50.0, noise_m=20e-6, p_e_scale=4e-4, lost_rate=0.04,
                 pause_rate=0.05, spike_rate=0.002, short_gaps=4, long_gap_stops=3, switch_s=0.3,
                 settle_s=0.5, clock0_s=None, T_LI=None, targets=True, dwell_scale=1.0, bursts=0, pause_s=2.5):
        self.robot, self.stops, self.rng = robot, stops, rng
        self.rate, self.noise = rate_hz, noise_m
        self.p_e = rng.normal(0, p_e_scale, robot.n_params)
        self.T_LI = random_rigid(rng) if T_LI is None else T_LI
        self.P_E = robot.with_default_reflectors().reflector_positions_in_E
        self.names = tuple(r.name for r in robot.with_default_reflectors().reflectors)
        self.clock0 = rng.uniform(1e5, 1e7) if clock0_s is None else clock0_s
        self.targets = targets
        n = len(stops)
        measured = [s.stop for s in stops if s.kind != "via"]
        self.lost = set(rng.choice(measured, int(round(lost_rate * len(measured))), replace=False).tolist())
        start = int(rng.integers(n // 3, 2 * n // 3))
        self.long_gap = set(measured[measured.index(next(m for m in measured if m >= start)):][:long_gap_stops])
        self.pauses = set(rng.choice(n, int(round(pause_rate * n)), replace=False).tolist())
        self.spike_rate, self.short_gaps, self.switch_s, self.settle_s = spike_rate, short_gaps, switch_s, settle_s
        self.dwell_scale = dwell_scale
        self.bursts, self.pause_s = bursts, pause_s

    def truth_points(self, q):
        """The reflectors' true positions in the tracker's frame, (n, 3, 3) m."""
        T = self.T_LI @ forward(self.robot, np.atleast_2d(q), self.p_e)
        return np.einsum("nij,kj->nki", T[:, :3, :3], self.P_E) + T[:, None, :3, 3]

    def rows(self):
        """(t (n,), P (n, 3) m, target (n,) codes) and, per measured stop, the samples each reflector got."""
        dt = 1.0 / self.rate
        t_list, q_list, g_list, stop_of = [], [], [], []
        t = 0.0
        q_prev = np.array(self.stops[0].q)
        for s in self.stops:
            q = np.array(s.q)
            move_s = 0.0 if np.array_equal(q, q_prev) else 0.8 + float(np.max(np.abs(q - q_prev))) / 0.8
            n_move = int(move_s * self.rate)
            tau = np.arange(n_move) / max(n_move, 1)
            prof = 3 * tau ** 2 - 2 * tau ** 3
            qs = q_prev + prof[:, None] * (q - q_prev)
            if s.stop in self.pauses:  # an unplanned pause halfway
                half = n_move // 2
                hold = np.repeat(qs[half:half + 1], int(self.pause_s * self.rate), axis=0)
                qs = np.concatenate([qs[:half], hold, qs[half:]])
            ts = t + dt * np.arange(len(qs))
            t = ts[-1] + dt if len(ts) else t
            t_list.append(ts)
            q_list.append(qs)
            g_list.append(np.zeros(len(qs), int))
            stop_of.append(np.full(len(qs), -1))
            if s.dwell_s > 0:
                slot = (s.dwell_s * self.dwell_scale - self.settle_s) / len(self.P_E)
                segs = [(0, self.settle_s)] + [(k, slot - self.switch_s) for k in range(len(self.P_E))]
                for k, (code, length) in enumerate(segs):
                    if k > 1:
                        t += self.switch_s  # the beam moves to the next reflector: no samples
                    m = int(length * self.rate)
                    ts = t + dt * np.arange(m)
                    t = ts[-1] + dt if m else t
                    t_list.append(ts)
                    q_list.append(np.repeat(q[None], m, axis=0))
                    g_list.append(np.full(m, code if self.targets else 0))
                    stop_of.append(np.full(m, s.stop if k > 0 else -1))
            q_prev = q
        t, Q, g, stop_of = (np.concatenate(a) for a in (t_list, q_list, g_list, stop_of))
        P = self.truth_points(Q)[np.arange(len(Q)), g]
        keep = np.ones(len(t), bool)
        # a lost beam: nothing from the motion into the stop to its end
        for s in self.stops:
            if s.stop in self.lost or s.stop in self.long_gap:
                at = np.flatnonzero(stop_of == s.stop)
                keep[max(at[0] - int(1.5 * self.rate), 0):at[-1] + 1] = False
        for _ in range(self.short_gaps):
            a = int(self.rng.integers(0, len(t) - 200))
            keep[a:a + int(1.5 * self.rate)] = False
        P = P + self.rng.normal(0, self.noise, P.shape)
        spikes = self.rng.random(len(t)) < self.spike_rate
        d = self.rng.normal(size=(spikes.sum(), 3))
        P[spikes] += d / np.linalg.norm(d, axis=1)[:, None] * self.rng.uniform(1e-3, 0.3, (spikes.sum(), 1))
        for _ in range(self.bursts):  # 0.2-1 s of garbage: every sample within 5 cm of the truth
            a = int(self.rng.integers(0, len(t) - 100))
            n = int(self.rng.uniform(0.2, 1.0) * self.rate)
            P[a:a + n] += self.rng.uniform(-0.05, 0.05, (n, 3))
        got = {}
        for s in self.stops:
            if s.kind != "via":
                got[s.stop] = [int(np.sum(keep & (stop_of == s.stop) & (g == c))) for c in range(len(self.P_E))]
        self.moving = (stop_of < 0)[keep]  # in motion or settling: what a tracker may leave unnamed
        return t[keep] + self.clock0, P[keep], g[keep], got

    def write(self, path, *, mm=True, part=None, preamble="", unnamed_in_motion=False):
        """The log as the tracker's software exports it; ``part`` (a, b): only rows a..b; ``preamble``:
        lines before the header; ``unnamed_in_motion``: no target named while moving or settling."""
        t, P, g, got = self.rows()
        names = np.array(self.names + ("",), dtype=object)[np.where(self.moving & unnamed_in_motion, -1, g)]
        if part is not None:
            t, P, names = t[part[0]:part[1]], P[part[0]:part[1]], names[part[0]:part[1]]
        scale = 1e3 if mm else 1.0
        with open(path, "w") as f:
            f.write(preamble + ("time_s,x,y,z,target\n" if self.targets else "time_s,x,y,z\n"))
            for k in range(len(t)):
                row = f"{t[k]:.4f},{P[k, 0] * scale:.5f},{P[k, 1] * scale:.5f},{P[k, 2] * scale:.5f}"
                f.write(row + (f",{names[k]}\n" if self.targets else "\n"))
        return got


def make_run(tmp_path, robot, n_poses=150, seed=0, name="run", dwell_s=3.5, **kw):
    rng = np.random.default_rng(seed)
    stops = make_stops(robot, n_poses, rng, dwell_s=dwell_s)
    run = tmp_path / name
    stops_path(run).parent.mkdir(parents=True)
    write_stops_csv(stops_path(run), stops)
    return run, stops, LogWriter(robot, stops, rng, **kw)


def match_rows(run):
    with open(run / "import" / "stream_match.csv") as f:
        return list(csv.DictReader(f))


def stored(run):
    """{pose_id: (status, {reflector: (3,) in the log's frame, m})}"""
    with sqlite3.connect(run / "measurements.sqlite") as db:
        status = dict(db.execute("SELECT pose_id, status FROM poses"))
        refl = {}
        for pid, name, x, y, z in db.execute("SELECT pose_id, name, x_L_m, y_L_m, z_L_m FROM reflector_readings"):
            refl.setdefault(pid, {})[name] = np.array([x, y, z])
    return {p: (s, refl.get(p, {})) for p, s in status.items()}


def check_found_and_right(run, stops, writer, got, *, min_found=0.98):
    """≥ min_found of the stops with every reflector measured are matched, and every stored pose
    lies where the truth put that stop (within 0.3 mm)."""
    rows = [r for r in match_rows(run) if r["stop"]]
    status = {int(r["stop"]): r["status"] for r in rows}
    complete = [k for k, n in got.items() if min(n) >= 20]  # two blocks (0.4 s at 50 Hz) a reflector
    found = [k for k in complete if status.get(k) == "matched"]
    assert len(found) >= min_found * len(complete), (len(found), len(complete),
                                                     [(k, status.get(k)) for k in complete if k not in found])
    by_id = {s.pose_id: s for s in stops if s.kind not in ("via", "drift")}
    log = stored(run)
    n_measured = 0
    for pid, (st, refl) in log.items():
        if st != "measured":
            continue
        n_measured += 1
        truth = writer.truth_points(np.array(by_id[pid].q))[0]
        P = np.array([refl[n] for n in writer.names])
        assert np.abs(P - truth).max() < 3e-4, (pid, np.abs(P - truth).max())
    return found, complete, n_measured


def test_a_continuous_log_in_mm_in_the_tracker_frame_is_matched_with_every_fault(tmp_path, robot):
    run, stops, writer = make_run(tmp_path, robot)
    log = tmp_path / "tracker.csv"
    got = writer.write(log)
    assert main(["import", "--stream", str(log), "--run", str(run), "--length-unit", "mm", "--frame", "tracker",
                 "--quiet"]) == 0
    found, complete, n = check_found_and_right(run, stops, writer, got)
    rows = match_rows(run)
    # every stop with a lost beam (and the long gap's) is skipped, never filled by another window
    for r in rows:
        if r["stop"] and int(r["stop"]) in writer.lost | writer.long_gap:
            assert r["status"] == "skipped", r
    # the unplanned pauses are windows matched to no stop
    assert sum(r["status"] == "rejected" for r in rows) >= len(writer.pauses) - 2
    # the drift stops are drift checks as `campaign run` stores them: the reference re-read, its distance
    # from the first reading (the generator's cell does not drift: noise only)
    import json

    with sqlite3.connect(run / "measurements.sqlite") as db:
        checks = [json.loads(d) for (d,) in db.execute("SELECT detail FROM events WHERE kind = 'drift_check'")]
    drift_rows = [r for r in rows if r["kind"] == "drift"]
    reference_measured = next(r for r in rows if r["pose_id"] == "5000")["status"] == "matched"
    assert reference_measured  # else the first drift reading is the reference's first, not a check
    assert len(checks) == len(drift_rows)
    read = [c for c in checks if c["drift_mm"] is not None]
    assert len(read) == sum(r["status"] == "matched" for r in drift_rows) and len(read) >= 5
    assert all(c["reference_pose_id"] == 5000 and c["drift_mm"] < 0.02 and "xyz_m" in c for c in read)
    assert n >= 0.9 * len([s for s in stops if s.kind not in ("via", "drift")]) - len(writer.lost)


def test_an_imported_log_calibrates_to_the_noise_floor(tmp_path, robot):
    import json


    run, stops, writer = make_run(tmp_path, robot, n_poses=200, seed=3)
    log = tmp_path / "tracker.csv"
    writer.write(log)
    assert main(["import", "--stream", str(log), "--run", str(run), "--length-unit", "mm", "--frame", "tracker",
                 "--quiet"]) == 0
    assert main(["calibrate", str(run), "--no-ann"]) == 0
    metrics = json.loads((run / "calibration" / "metrics.json").read_text())
    test_mean = metrics["stages"]["geometric"]["test"]["position_mm"]["mean"]
    floor = metrics["noise_floor"]["mean_position_mm"]
    assert test_mean <= 1.2 * floor, (test_mean, floor)


def test_a_log_that_ends_halfway_imports_what_it_has_and_a_second_log_continues(tmp_path, robot):
    run, stops, writer = make_run(tmp_path, robot, seed=5, lost_rate=0.03, pause_rate=0.03)
    full = tmp_path / "full.csv"
    got = writer.write(full)
    lines = full.read_text().splitlines(keepends=True)
    cut = len(lines) // 2
    (tmp_path / "a.csv").write_text("".join(lines[:cut]))
    (tmp_path / "b.csv").write_text(lines[0] + "".join(lines[cut:]))
    args = ["--run", str(run), "--length-unit", "mm", "--frame", "tracker", "--quiet"]
    assert main(["import", "--stream", str(tmp_path / "a.csv"), *args]) == 0
    first = {int(r["stop"]) for r in match_rows(run) if r["stop"]}
    assert 0.3 * len(stops) < max(first) < 0.7 * len(stops)  # what the first half holds, no more
    assert main(["import", "--stream", str(tmp_path / "b.csv"), *args]) == 0
    rows = [r for r in match_rows(run) if r["stop"]]
    stop_ids = [int(r["stop"]) for r in rows]
    assert stop_ids == sorted(set(stop_ids)), "the second log continues after the first; no stop twice"
    assert {r["log"] for r in rows} == {"a.csv", "b.csv"}
    # the stop the cut went through may be lost: one stop more than the faults
    found, complete, _ = check_found_and_right(run, stops, writer, got, min_found=0.95)
    assert len(complete) - len(found) <= 2


def test_iso_time_stamps_and_a_log_in_the_robot_frame_in_metres(tmp_path, robot):
    run, stops, writer = make_run(tmp_path, robot, n_poses=40, seed=7, T_LI=np.eye(4), lost_rate=0.0,
                                  pause_rate=0.0, short_gaps=0, long_gap_stops=0, clock0_s=0.0)
    got = writer.write(tmp_path / "m.csv", mm=False)
    start = np.datetime64("2026-03-29T00:59:58.5")
    out = ["timestamp;X;Y;Z;target"]
    for ln in (tmp_path / "m.csv").read_text().splitlines()[1:]:
        t, x, y, z, g = ln.split(",")
        stamp = start + np.timedelta64(int(round(float(t) * 1e6)), "us")
        out.append(f"{stamp}+01:00;{x};{y};{z};{g}")
    (tmp_path / "iso.csv").write_text("\n".join(out) + "\n")
    assert main(["import", "--stream", str(tmp_path / "iso.csv"), "--run", str(run), "--columns", "x=X,y=Y,z=Z",
                 "--quiet"]) == 0
    found, complete, n = check_found_and_right(run, stops, writer, got, min_found=1.0)
    with sqlite3.connect(run / "measurements.sqlite") as db:
        frame = db.execute("SELECT value FROM meta WHERE key = 'frame'").fetchone()[0]
        x0 = db.execute("SELECT x, y, z FROM poses WHERE status = 'measured' ORDER BY seq LIMIT 1").fetchone()
    assert frame == '"robot"'
    first = next(s for s in stops if s.kind != "via")
    assert np.allclose(x0, forward(robot, np.array([first.q]), writer.p_e)[0, :3, 3], atol=1e-4)


def test_a_log_of_one_record_per_stable_point_is_matched(tmp_path, robot):
    run, stops, writer = make_run(tmp_path, robot, n_poses=60, seed=9, pause_rate=0.0, short_gaps=0, spike_rate=0.0)
    t, P, g, got = writer.rows()
    # the tracker's software keeps one averaged point per reflector and stop
    rows = []
    k = 0
    while k < len(t):
        e = k
        while e + 1 < len(t) and g[e + 1] == g[k] and t[e + 1] - t[e] < 0.1 and np.linalg.norm(P[e + 1] - P[e]) < 2e-4:
            e += 1
        if e - k >= 20:
            rows.append((t[e], *(P[k:e + 1].mean(axis=0) * 1e3), REFLECTORS[g[k]]))
        k = e + 1
    (tmp_path / "points.csv").write_text("time_s,x,y,z,target\n" + "".join(
        f"{r[0]:.3f},{r[1]:.4f},{r[2]:.4f},{r[3]:.4f},{r[4]}\n" for r in rows))
    assert main(["import", "--stream", str(tmp_path / "points.csv"), "--run", str(run), "--length-unit", "mm",
                 "--frame", "tracker", "--quiet"]) == 0
    check_found_and_right(run, stops, writer, got)


def test_a_log_without_target_is_one_point_per_stop(tmp_path, robot):
    """No target column: the tool frame's origin of a robot with several reflectors (like a one-reflector
    CSV import); here the log tracks the reflector the generator puts at the tool frame's origin."""
    run, stops, writer = make_run(tmp_path, robot, n_poses=60, seed=11, targets=False)
    writer.P_E = np.zeros((1, 3))
    got = writer.write(tmp_path / "one.csv")
    assert main(["import", "--stream", str(tmp_path / "one.csv"), "--run", str(run), "--length-unit", "mm",
                 "--frame", "tracker", "--quiet"]) == 0
    status = {int(r["stop"]): r["status"] for r in match_rows(run) if r["stop"]}
    complete = [k for k, n in got.items() if min(n) >= 20]  # two blocks (0.4 s at 50 Hz) a reflector
    assert sum(status.get(k) == "matched" for k in complete) >= 0.98 * len(complete)
    with sqlite3.connect(run / "measurements.sqlite") as db:
        kind = db.execute("SELECT value FROM meta WHERE key = 'kind'").fetchone()[0]
        xyz = dict((p, np.array(v)) for p, *v in db.execute("SELECT pose_id, x, y, z FROM poses WHERE status = 'measured'"))
    assert kind == '"point"'
    by_id = {s.pose_id: s for s in stops}
    for pid, p in xyz.items():
        assert np.abs(p - writer.truth_points(np.array(by_id[pid].q))[0, 0]).max() < 3e-4


@pytest.mark.parametrize("text, message", [
    ("time_s,x,y,z\n0,1,2,3\n1,1,2,oops\n", r"bad\.csv: row 3, column z: not a number \('oops'\)"),
    ("time_s,x,y,z,target\n0,1,2,3,rrr1\n1,1,2,3,prism9\n",
     r"bad\.csv: row 3, column target: 'prism9' is not one of the robot's reflectors \(rrr1, rrr2, brr\)"),
    ("time_s,x,y,z\n0,1,2,3\n1,1,2\n", r"bad\.csv: row 3 has 3 fields, expected 4"),
    ("t,x,y,z\n0,1,2,3\n", r"bad\.csv: no time column \(time_s in s, or time/timestamp in ISO 8601\)"),
    ("time_s,x,y\n0,1,2\n", r"bad\.csv: no column z in the header"),
    ("timestamp,x,y,z\n2026-13-45T00:00:00,1,2,3\n", r"bad\.csv: row 2, column timestamp: not an ISO 8601 time"),
    ("", r"bad\.csv: empty"),
])
def test_a_bad_log_is_one_line_naming_the_file_row_and_column(tmp_path, robot, capsys, text, message):
    import re

    run, _, _ = make_run(tmp_path, robot, n_poses=5)
    (tmp_path / "bad.csv").write_text(text)
    assert main(["import", "--stream", str(tmp_path / "bad.csv"), "--run", str(run)]) == 1
    err = capsys.readouterr().err.strip()
    assert len(err.splitlines()) == 1 and re.search(message, err), err
    assert not (run / "measurements.sqlite").exists() and not (run / "import").exists()


def test_import_stream_refuses_what_it_cannot_do_in_one_line(tmp_path, robot, capsys):
    run, _, writer = make_run(tmp_path, robot, n_poses=20)
    writer.write(tmp_path / "log.csv")
    cases = [(["import", "--stream", str(tmp_path / "log.csv"), "--run", str(tmp_path / "nowhere")], "no such"),
             (["import", "x.csv", "--stream", str(tmp_path / "log.csv"), "--run", str(run)], "not both"),
             (["import", "--stream", str(tmp_path / "log.csv"), "--run", str(run), "--angle-unit", "deg"],
              "--angle-unit: not with --stream")]
    for argv, msg in cases:
        assert main(argv) == 1
        err = capsys.readouterr().err.strip()
        assert len(err.splitlines()) == 1 and msg in err, err
    (run / "program" / "stops.csv").unlink()
    assert main(["import", "--stream", str(tmp_path / "log.csv"), "--run", str(run)]) == 1
    assert "campaign program RUN --format csv" in capsys.readouterr().err


def test_dwells_shorter_than_the_program_says_and_a_gap_of_eight_stops(tmp_path, robot):
    """The cell ran the program faster (dwells at 70 %) and the tracker was off for eight stops: the
    skip bound scales with the log's own windows and stop-to-stop time, so nothing after the gap is
    shifted."""
    run, stops, writer = make_run(tmp_path, robot, seed=21, dwell_scale=0.7, switch_s=0.1, long_gap_stops=8)
    got = writer.write(tmp_path / "log.csv")
    assert main(["import", "--stream", str(tmp_path / "log.csv"), "--run", str(run), "--length-unit", "mm",
                 "--frame", "tracker", "--quiet"]) == 0
    check_found_and_right(run, stops, writer, got)
    status = {int(r["stop"]): r["status"] for r in match_rows(run) if r["stop"]}
    assert all(status[k] == "skipped" for k in writer.long_gap)


def test_without_a_program_the_plan_gives_the_stops(tmp_path, robot):
    """No RUN/program/stops.csv yet: the stops are the plan's, as `campaign program` would write them."""
    import yaml

    from campaign.program.stops import plan_stops

    run, stops, writer = make_run(tmp_path, robot, n_poses=40, seed=23, lost_rate=0.0)
    poses = [s for s in stops if s.kind in ("pose", "validation")]
    (run / "plan").mkdir()
    (run / "plan" / "poses.csv").write_text("pose_id,q1,q2,q3,q4,q5,q6\n" + "".join(
        f"{s.pose_id}," + ",".join(repr(v) for v in s.q) + "\n" for s in poses))
    (run / "campaign.yaml").write_text(yaml.safe_dump({"robot": "comau_racer5_080", "run": {"drift_check_every": 0},
                                                       "plan": {"settle_time_s": 0.5,
                                                                "tracker_time_per_reflector_s": 1.0}}))
    stops_path(run).unlink()
    planned = plan_stops(run)
    writer.stops = planned
    writer.lost, writer.long_gap, writer.pauses = set(), set(), set()
    got = writer.write(tmp_path / "log.csv")
    assert main(["import", "--stream", str(tmp_path / "log.csv"), "--run", str(run), "--length-unit", "mm",
                 "--frame", "tracker", "--quiet"]) == 0
    check_found_and_right(run, planned, writer, got)


def test_bursts_of_garbage_inside_dwells_do_not_split_a_stop(tmp_path, robot):
    """Bursts of 0.2-1 s of garbage (every sample up to 5 cm off), forty of them, some inside a
    reflector's samples: the reflector back at its place continues the window."""
    run, stops, writer = make_run(tmp_path, robot, seed=31, bursts=40, lost_rate=0.02, pause_rate=0.02)
    got = writer.write(tmp_path / "log.csv")
    assert main(["import", "--stream", str(tmp_path / "log.csv"), "--run", str(run), "--length-unit", "mm",
                 "--frame", "tracker", "--quiet"]) == 0
    check_found_and_right(run, stops, writer, got)


def test_a_burst_inside_a_reflectors_samples_does_not_split_its_window():
    """One stop, three reflectors 1.2 s each at 50 Hz, a 0.8 s burst of garbage (4 blocks) in the
    middle reflector's samples: one window with all three, each at its place."""
    from campaign.program.stream.logread import LogChunk
    from campaign.program.stream.windows import WindowFinder

    rng = np.random.default_rng(5)
    places = np.array([[1.0, 2.0, 0.5], [1.05, 2.0, 0.5], [1.0, 2.05, 0.5]])
    t = np.arange(180) * 0.02
    g = np.repeat([0, 1, 2], 60)
    P = places[g] + rng.normal(0, 10e-6, (180, 3))
    P[70:110] += rng.uniform(-0.05, 0.05, (40, 3))  # inside reflector 1's samples
    D = np.linalg.norm(places[:, None] - places[None], axis=-1)
    finder = WindowFinder(D)
    finder.feed(LogChunk(t[:90], P[:90], g[:90].astype(np.int16), 91))
    finder.feed(LogChunk(t[90:], P[90:], g[90:].astype(np.int16), 181))
    windows = finder.finish()
    assert len(windows) == 1 and sorted(windows[0].position) == [0, 1, 2], [w.counts for w in windows]
    for c in range(3):
        assert np.abs(windows[0].position[c] - places[c]).max() < 2e-5


def test_any_serial_arm_a_ur10_log_is_matched(tmp_path, erd):
    """The matching knows nothing of the COMAU: a UR10 (±360° joints) with the default reflectors."""
    import yaml

    from campaign.run import load_robot

    ur10 = load_robot(erd("ur_description/urdf/ur10_robot.urdf"), tool_frame="tool0")
    run, stops, writer = make_run(tmp_path, ur10, n_poses=80, seed=41)
    (run / "campaign.yaml").write_text(yaml.safe_dump({"robot": erd("ur_description/urdf/ur10_robot.urdf"),
                                                       "tool_frame": "tool0"}))
    got = writer.write(tmp_path / "log.csv")
    assert main(["import", "--stream", str(tmp_path / "log.csv"), "--run", str(run), "--length-unit", "mm",
                 "--frame", "tracker", "--quiet"]) == 0
    check_found_and_right(run, stops, writer, got)


def test_notes_before_the_header_and_no_target_named_in_motion(tmp_path, robot):
    """The tracker's software writes notes (``#``) before the header and names no reflector while the
    robot moves or settles: those rows are no reflector's measurement."""
    run, stops, writer = make_run(tmp_path, robot, n_poses=60, seed=43)
    got = writer.write(tmp_path / "log.csv", preamble="# exported by the tracker's software\n# units: mm\n\n",
                       unnamed_in_motion=True)
    text = (tmp_path / "log.csv").read_text()
    assert ",\n" in text and text.startswith("# exported")
    assert main(["import", "--stream", str(tmp_path / "log.csv"), "--run", str(run), "--length-unit", "mm",
                 "--frame", "tracker", "--quiet"]) == 0
    check_found_and_right(run, stops, writer, got)


@pytest.mark.parametrize("rate_hz, noise_um, dwell_s", [(10.0, 60.0, 8.0), (1000.0, 3.0, 3.5)])
def test_the_noise_level_and_rate_come_from_the_log(tmp_path, robot, capsys, rate_hz, noise_um, dwell_s):
    """10 Hz with 60 µm noise, 1,000 Hz with 3 µm: the still threshold follows the log's own noise."""
    run, stops, writer = make_run(tmp_path, robot, n_poses=40, seed=47, rate_hz=rate_hz, noise_m=noise_um * 1e-6,
                                  dwell_s=dwell_s)
    got = writer.write(tmp_path / "log.csv")
    assert main(["import", "--stream", str(tmp_path / "log.csv"), "--run", str(run), "--length-unit", "mm",
                 "--frame", "tracker"]) == 0
    out = capsys.readouterr().out
    rate, noise = re.search(r"\((\d+) Hz, noise ([\d.]+) µm\)", out).groups()
    assert float(rate) == rate_hz and 0.5 * noise_um < float(noise) < 1.5 * noise_um, out
    check_found_and_right(run, stops, writer, got)


def test_a_log_without_target_that_follows_one_reflector_finds_which(tmp_path, robot):
    """No target column, the tracker following one reflector of the three (not at the tool frame's
    origin): the reflector whose distances fit is found, its positions stored, and calibrate finds the
    point on the tool from the data."""
    run, stops, writer = make_run(tmp_path, robot, n_poses=60, seed=53, targets=False)
    writer.P_E = writer.P_E[[2]]  # brr
    got = writer.write(tmp_path / "one.csv")
    assert main(["import", "--stream", str(tmp_path / "one.csv"), "--run", str(run), "--length-unit", "mm",
                 "--frame", "tracker", "--quiet"]) == 0
    status = {int(r["stop"]): r["status"] for r in match_rows(run) if r["stop"]}
    complete = [k for k, n in got.items() if min(n) >= 20]
    assert sum(status.get(k) == "matched" for k in complete) >= 0.98 * len(complete)
    with sqlite3.connect(run / "measurements.sqlite") as db:
        names = {n for (n,) in db.execute("SELECT DISTINCT name FROM reflector_readings")}
        xyz = dict((p, np.array(v)) for p, *v in db.execute("SELECT pose_id, x, y, z FROM poses WHERE status = 'measured'"))
    assert names == {writer.names[2]}
    by_id = {s.pose_id: s for s in stops}
    for pid, p in xyz.items():
        assert np.abs(p - writer.truth_points(np.array(by_id[pid].q))[0, 0]).max() < 3e-4


def test_a_second_log_that_repeats_the_end_of_the_first_and_long_pauses(tmp_path, robot):
    """The second log starts 200 s before the first ended (about 30 stops already imported: a window
    of one of those, whose distance to the next stop fits by chance, must not become the next stop),
    and the robot paused for 5 minutes in three motions."""
    run, stops, writer = make_run(tmp_path, robot, seed=5, lost_rate=0.03, pause_rate=0.02, pause_s=300.0)
    got = writer.write(tmp_path / "full.csv")
    lines = (tmp_path / "full.csv").read_text().splitlines(keepends=True)
    cut = len(lines) // 2
    (tmp_path / "a.csv").write_text("".join(lines[:cut]))
    (tmp_path / "b.csv").write_text(lines[0] + "".join(lines[cut - 10000:]))
    args = ["--run", str(run), "--length-unit", "mm", "--frame", "tracker", "--quiet"]
    assert main(["import", "--stream", str(tmp_path / "a.csv"), *args]) == 0
    assert main(["import", "--stream", str(tmp_path / "b.csv"), *args]) == 0
    check_found_and_right(run, stops, writer, got)


def test_a_log_naming_the_reflectors_its_own_way_is_assigned_by_geometry(tmp_path, robot):
    """The tracker's software calls the reflectors SMR_A, SMR_B, SMR_C (not robot.yaml's names): which
    is which comes from the distances, and the robot's names are stored."""
    run, stops, writer = make_run(tmp_path, robot, n_poses=60, seed=59)
    got = writer.write(tmp_path / "log.csv")
    text = (tmp_path / "log.csv").read_text()
    for own, theirs in zip(writer.names, ("SMR_B", "SMR_C", "SMR_A")):
        text = text.replace(f",{own}\n", f",{theirs}\n")
    (tmp_path / "log.csv").write_text(text)
    assert main(["import", "--stream", str(tmp_path / "log.csv"), "--run", str(run), "--length-unit", "mm",
                 "--frame", "tracker", "--quiet"]) == 0
    check_found_and_right(run, stops, writer, got)
