"""Benchmark of `campaign import --stream` on a 3.5-day campaign's continuous log (issue 32 part 5).

    flock /tmp/campaign-bench.lock python benchmarks/bench_stream.py            # 3.5 days at 100 Hz
    python benchmarks/bench_stream.py --days 0.2 --rate 100 --keep             # a quick look
    ... --rounds 2 --reference     # alternating with the reader alone (the parse's floor)

Writes a run folder with RUN/program/stops.csv (the paper's campaign: about 13,900 stops of 17 s
dwell, a settle and three reflectors measured in turn, and about 4.7 s of motion between them, drift
checks, repeats) and the tracker's log of it at --rate Hz, generated in chunks of stops (nominal
kinematics with random geometric errors, a random rigid tracker frame, millimetres, 1 % lost beams,
1 % unplanned pauses, spikes, 20 µm noise). Then imports the log in a child process and quotes its
wall time, CPU time and peak RSS (the child's resource.getrusage), the load average beside them, and
how many of the stops the log holds whole were found, and how many were put at another pose's place.
Figures merged into benchmarks/results/stream.json.
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import shutil
import sqlite3
import subprocess
import sys
import time
from pathlib import Path

import numpy as np

from campaign.model.kinematics import forward
from campaign.model.robot import RobotModel
from campaign.program.stops import Stop, stops_path, write_stops_csv
from campaign.program.stream.logwrite import format_rows, log_header

RESULTS = Path(__file__).parent / "results" / "stream.json"
NAMES = ("rrr1", "rrr2", "brr")
SETTLE_S, PER_REFLECTOR_S, SWITCH_S = 2.0, 5.0, 0.2


def make_stops(robot, n, rng):
    from campaign.sim.truth import random_joint_poses

    Q = random_joint_poses(robot, n, seed=int(rng.integers(1 << 30)))
    dwell = SETTLE_S + len(NAMES) * PER_REFLECTOR_S
    stops = []
    for k in range(n):
        stops.append(Stop(len(stops), 100_000 + k, "pose", dwell, tuple(Q[k])))
        if k % 500 == 499:
            stops.append(Stop(len(stops), 100_000, "drift", dwell, tuple(Q[0])))
        if k % 1000 == 1:
            stops.append(Stop(len(stops), 100_000 + k + 10**9, "repeat", dwell, tuple(Q[k])))
    return stops


def write_log(path, stops, points, rate, rng, *, lost_rate=0.01, pause_rate=0.01, spike_rate=1e-4,
              noise_m=20e-6, chunk=400):
    """The log of ``stops`` whose reflectors stand at ``points`` (n, 3, 3) m in the tracker's frame;
    returns ({stop: samples of its least-measured reflector}, samples written)."""
    dt = 1.0 / rate
    lost = rng.random(len(stops)) < lost_rate
    pause = rng.random(len(stops)) < pause_rate
    got, total = {}, 0
    t = 1.0e6 * rng.random()
    prev = points[0, 0]
    with open(path, "wb") as fh:
        fh.write(log_header(True).encode())
        for c0 in range(0, len(stops), chunk):
            T, P, G = [], [], []
            for k in range(c0, min(c0 + chunk, len(stops))):
                here = points[k]
                dist = float(np.linalg.norm(here[0] - prev))
                move_s = 1.5 + dist / 0.25
                n_move = int(move_s * rate)
                tau = np.arange(n_move) / n_move
                s = 3 * tau ** 2 - 2 * tau ** 3
                if pause[k]:
                    s = np.concatenate([s[:n_move // 2], np.full(int(2.5 * rate), s[n_move // 2]), s[n_move // 2:]])
                pts = prev + s[:, None] * (here[0] - prev)
                ts = t + dt * np.arange(len(pts))
                t = ts[-1] + dt if len(ts) else t
                keep = np.ones(len(ts), bool)
                if lost[k]:
                    keep[len(ts) // 2:] = False
                T.append(ts[keep])
                P.append(pts[keep])
                G.append(np.zeros(keep.sum(), np.int64))
                pieces = [(0, SETTLE_S)] + [(c, PER_REFLECTOR_S - SWITCH_S) for c in range(len(NAMES))]
                counts = []
                for j, (code, length) in enumerate(pieces):
                    if j > 1:
                        t += SWITCH_S
                    m = int(length * rate)
                    ts = t + dt * np.arange(m)
                    t = ts[-1] + dt
                    if lost[k]:
                        counts.append(0)
                        continue
                    T.append(ts)
                    P.append(np.repeat(here[code][None], m, axis=0))
                    G.append(np.full(m, code, np.int64))
                    counts.append(m)
                got[k] = min(counts[1:])
                prev = here[0]
            T, P, G = np.concatenate(T), np.concatenate(P), np.concatenate(G)
            P = P + rng.normal(0, noise_m, P.shape)
            spikes = np.flatnonzero(rng.random(len(T)) < spike_rate)
            P[spikes] += rng.normal(0, 0.05, (len(spikes), 3))
            fh.write(format_rows(T, P, G, NAMES, scale=1e3, length_decimals=4))
            total += len(T)
    return got, total


#: the child's own peak: VmHWM of /proc/self/status (Linux keeps ru_maxrss across exec, so a child
#: forked from this process would start at this process's size), else ru_maxrss
PEAK = """
def peak_rss_mb():
    try:
        for line in open("/proc/self/status"):
            if line.startswith("VmHWM:"):
                return int(line.split()[1]) / 1024
    except OSError:
        pass
    return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024
"""

IMPORT = """
import json, resource, sys, time
""" + PEAK + """
t0, c0 = time.perf_counter(), time.process_time()
from campaign.program.stream import import_stream
res = import_stream(sys.argv[1], sys.argv[2], length_unit="mm", frame="tracker")
print(json.dumps({"wall_s": time.perf_counter() - t0, "cpu_s": time.process_time() - c0,
                  "peak_rss_mb": peak_rss_mb(), "ru_maxrss_mb": resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024,
                  "summary": res.summary(sys.argv[1], sys.argv[2])}))
"""

#: the reference: the same blocks read by the same reader, nothing else (the parse's floor)
PARSE = """
import json, resource, sys, time
""" + PEAK + """
t0, c0 = time.perf_counter(), time.process_time()
from campaign.program.stream.logread import iter_log, read_layout
n = sum(len(c.t) for c in iter_log(read_layout(sys.argv[1], length_unit="mm", targets=("rrr1", "rrr2", "brr"))))
print(json.dumps({"wall_s": time.perf_counter() - t0, "cpu_s": time.process_time() - c0,
                  "peak_rss_mb": peak_rss_mb(), "ru_maxrss_mb": resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024,
                  "rows": n}))
"""


def child(script, *argv) -> dict:
    """Run ``script`` in a fresh interpreter: its figures, and the load average after it."""
    r = subprocess.run([sys.executable, "-c", script, *map(str, argv)], capture_output=True, text=True,
                       env={**os.environ, "OPENBLAS_NUM_THREADS": "1"})
    if r.returncode:
        sys.exit(r.stderr)
    return {**json.loads(r.stdout.strip().splitlines()[-1]), "load_after": os.getloadavg()[0]}


def make_log(args, rng, out):
    """The run folder's stops and the log: (stops, reflector points (n, 3, 3) m, samples per stop, samples,
    generation figures)."""
    from campaign.model.rotations import rotvec_to_matrix

    robot = RobotModel.load()
    per_stop = SETTLE_S + len(NAMES) * PER_REFLECTOR_S + 4.7
    stops = make_stops(robot, int(args.days * 86400 / per_stop), rng)
    write_stops_csv(stops_path(out / "run"), stops)
    p_e = rng.normal(0, 4e-4, robot.n_params)
    T_LI = np.eye(4)
    T_LI[:3, :3] = rotvec_to_matrix(rng.normal(size=(1, 3)))[0]
    T_LI[:3, 3] = (0.5, -0.8, 3.0)
    T = T_LI @ forward(robot, np.array([s.q for s in stops]), p_e)
    P_E = robot.with_default_reflectors().reflector_positions_in_E
    points = np.einsum("nij,kj->nki", T[:, :3, :3], P_E) + T[:, None, :3, 3]
    t0, c0 = time.perf_counter(), time.process_time()
    got, samples = write_log(out / "tracker.csv", stops, points, args.rate, rng)
    return stops, points, got, samples, {"wall_s": time.perf_counter() - t0, "cpu_s": time.process_time() - c0}


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--days", type=float, default=3.5)
    ap.add_argument("--rate", type=float, default=100.0)
    ap.add_argument("--out", default="/tmp/campaign-bench-stream")
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--keep", action="store_true", help="keep the run folder and the log")
    ap.add_argument("--rounds", type=int, default=1, help="imports timed (alternating with the reference)")
    ap.add_argument("--reference", action="store_true",
                    help="after each import, time the reader alone (the same blocks, nothing else)")
    args = ap.parse_args(argv)
    rng = np.random.default_rng(args.seed)
    out = Path(args.out)
    shutil.rmtree(out, ignore_errors=True)
    run, log = out / "run", out / "tracker.csv"
    load_before = os.getloadavg()
    stops, points, got, samples, gen = make_log(args, rng, out)
    size_mb = log.stat().st_size / 1e6
    print(f"log: {samples:,} samples, {len(stops):,} stops, {size_mb:,.0f} MB written in {gen['wall_s']:.1f} s "
          f"(cpu {gen['cpu_s']:.1f} s)", flush=True)
    imports, parses = [], []
    for r in range(args.rounds):  # alternating: the import, then the reference
        (run / "measurements.sqlite").unlink(missing_ok=True)
        shutil.rmtree(run / "import", ignore_errors=True)
        imports.append(child(IMPORT, log, run))
        print(f"round {r + 1}: import {imports[-1]['wall_s']:.1f} s wall, {imports[-1]['cpu_s']:.1f} s cpu, "
              f"{imports[-1]['peak_rss_mb']:.0f} MB (load after {imports[-1]['load_after']:.1f})", flush=True)
        if args.reference:
            parses.append(child(PARSE, log))
            print(f"round {r + 1}: reader alone {parses[-1]['wall_s']:.1f} s wall, {parses[-1]['cpu_s']:.1f} s cpu, "
                  f"{parses[-1]['peak_rss_mb']:.0f} MB (load after {parses[-1]['load_after']:.1f})", flush=True)
    # after the import: found, and at the right place
    with sqlite3.connect(run / "measurements.sqlite") as db:
        readings = db.execute("SELECT pose_id, name, x_L_m, y_L_m, z_L_m FROM reflector_readings").fetchall()
    index = {s.pose_id: s.stop for s in stops if s.kind != "drift"}
    wrong = sum(np.abs(np.array(p) - points[index[pid], NAMES.index(n)]).max() > 3e-4 for pid, n, *p in readings)
    whole = [k for k, n in got.items() if n >= 40]  # two blocks (0.4 s at 100 Hz) a reflector
    with open(run / "import" / "stream_match.csv") as f:
        matched = {int(line.split(",")[0]) for line in f.read().splitlines()[1:] if ",matched," in line}
    found = sum(k in matched for k in whole) / len(whole)
    best = {k: min(i[k] for i in imports) for k in ("wall_s", "cpu_s")}
    doc = {"days": args.days, "rate_hz": args.rate, "samples": samples, "stops": len(stops), "log_mb": size_mb,
           "generate": gen, "import": {**best, "peak_rss_mb": max(i["peak_rss_mb"] for i in imports)},
           "import_rounds": imports, "reader_alone_rounds": parses,
           "found": found, "wrong": int(wrong), "summary": imports[-1]["summary"],
           "load": {"before": load_before, "after": os.getloadavg()},
           "machine": {"cpus": os.cpu_count(), "python": platform.python_version(), "numpy": np.__version__},
           "date": time.strftime("%Y-%m-%dT%H:%M:%SZ", time.gmtime())}
    print(f"import: {best['wall_s']:.1f} s wall, {best['cpu_s']:.1f} s cpu (best of {args.rounds}), peak RSS "
          f"{doc['import']['peak_rss_mb']:.0f} MB; found {found:.2%} of the {len(whole):,} stops the log holds whole, "
          f"{wrong} readings at another pose's place")
    print(imports[-1]["summary"])
    results = json.loads(RESULTS.read_text()) if RESULTS.is_file() else {}
    results[f"{args.days:g}d_{args.rate:g}hz"] = doc
    RESULTS.parent.mkdir(exist_ok=True)
    RESULTS.write_text(json.dumps(results, indent=2) + "\n")
    if not args.keep:
        shutil.rmtree(out, ignore_errors=True)


if __name__ == "__main__":
    main()
