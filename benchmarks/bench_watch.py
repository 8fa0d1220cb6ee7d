"""Benchmark of `campaign watch` (issue 33): a simulated run's throughput with the live page served
and two pages polling it, against the same run without, in alternating rounds.

    python benchmarks/bench_watch.py [--poses 2000] [--rounds 4] [--time-factor 0]

Each round measures the same plan of random valid poses in fresh run folders, in turn (the order
alternates between rounds: A B C, C B A, ...):

* ``alone``: `campaign run RUN --sim --quiet`;
* ``--watch``: `campaign run RUN --sim --quiet --watch PORT` (the page served from a thread of
  the driver's own process: the closest a watcher can get to the driver) and two clients;
* ``campaign watch``: the run as ``alone`` with `campaign watch RUN --port PORT` beside it and two
  clients.

A client does what the page does (campaign/watch/assets/watch.js): /api/status every 0.5 s, the
poses stored since its last look (/api/poses?from=K), /api/details every 3 s; the two clients
run as threads of this process (a browser's drawing would be on the operator's machine).
Throughput: stored poses per wall-clock second from the log's ``wall_time_unix_s`` (first to last
pose: start-up excluded); CPU: the run's processes (driver and cell; with `campaign watch`, the
watcher too) from ``resource.getrusage(RUSAGE_CHILDREN)``; the watcher's own CPU as the server
counts it (``/api/details`` ``watcher``: the CPU time of the threads that answered, reads of the
log included), taken against the run's CPU: on a machine with no core to spare (this one, under
the other jobs' load) throughput ratios scatter by tens of per cent between identical runs, and
that share is the slowdown the watcher can cause at most. ``--time-factor 0`` (the default)
runs the simulated cell as fast as it goes, so the watcher competes with the driver for every
cycle: the hardest case; a real cell's poses take seconds each. Writes
benchmarks/results/watch.json.
"""

from __future__ import annotations

import argparse
import json
import os
import re
import resource
import shutil
import socket
import sqlite3
import statistics
import subprocess
import sys
import tempfile
import threading
import time
import urllib.request
from pathlib import Path

import yaml

ROOT = Path(__file__).resolve().parents[1]
ENV = {**os.environ, "PYTHONPATH": str(ROOT)}
CONFIGS = ("alone", "--watch", "campaign watch")


def free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


class Client(threading.Thread):
    """One page's requests (watch.js): status every 0.5 s, new poses, details every 3 s."""

    def __init__(self, port: int):
        super().__init__(daemon=True)
        self.base, self.stop, self.requests, self.errors, self.seen = f"http://127.0.0.1:{port}/", False, 0, 0, 0
        self.cost = None

    def get(self, path):
        with urllib.request.urlopen(self.base + path, timeout=5) as r:
            self.requests += 1
            return json.load(r)

    def run(self):
        details_at = 0.0
        while not self.stop:
            try:
                st = self.get("api/status")
                # details every 3 s, as the page; every time once the run is over, so that the last
                # answer before a --watch run's process exits holds the watcher's whole cost
                if time.monotonic() - details_at > 3.0 or st["state"] != "running":
                    self.cost = self.get("api/details")["watcher"]
                    details_at = time.monotonic()
                if st["measured"] + st["failed"] > self.seen:
                    self.seen += len(self.get(f"api/poses?from={self.seen}"))
            except OSError:
                self.errors += 1
            time.sleep(0.5)


def make_run(folder: Path, poses: int, time_factor: float) -> Path:
    from campaign.model.robot import RobotModel
    from campaign.paths import DEFAULT_SCENE
    from campaign.sim.truth import random_joint_poses

    (folder / "plan").mkdir(parents=True)
    q = random_joint_poses(RobotModel.load(), poses, seed=0)
    (folder / "plan" / "poses.csv").write_text("pose_id,q1,q2,q3,q4,q5,q6\n" + "".join(
        f"{i}," + ",".join(repr(float(v)) for v in q[i]) + "\n" for i in range(poses)))
    cfg = {"robot": "comau_racer5_080", "scene": str(DEFAULT_SCENE),
           "sim": {"seed": 0, "time_factor": time_factor, "hidden_effects": ["ground_compliance"]}}
    (folder / "campaign.yaml").write_text(yaml.safe_dump(cfg))
    return folder


def one(template: Path, work: Path, config: str) -> dict:
    """One run of ``config``: its throughput (poses/s), wall and CPU seconds."""
    run = work / "run"
    shutil.rmtree(run, ignore_errors=True)
    shutil.copytree(template, run)
    cmd = [sys.executable, "-m", "campaign.cli", "run", str(run), "--sim", "--quiet"]
    watcher, port = None, free_port()
    if config == "--watch":
        cmd += ["--watch", str(port)]
    cpu0 = resource.getrusage(resource.RUSAGE_CHILDREN)
    if config == "campaign watch":
        watcher = subprocess.Popen([sys.executable, "-m", "campaign.cli", "watch", str(run), "--port", str(port)],
                                   stdout=subprocess.PIPE, stderr=subprocess.DEVNULL, text=True, env=ENV)
        watcher.stdout.readline()  # "watching ...": it serves
    t0 = time.perf_counter()
    driver = subprocess.Popen(cmd, stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, text=True, env=ENV)
    clients = []
    if config != "alone":
        if config == "--watch":  # the driver says where once it serves
            line = driver.stderr.readline()
            assert re.search(rf":{port}/", line), line
        clients = [Client(port) for _ in range(2)]
        for c in clients:
            c.start()
    driver.wait()
    wall = time.perf_counter() - t0
    for c in clients:
        c.stop = True
    for c in clients:
        c.join()
    # what serving cost, as the server counts it: its last answer (`campaign watch` still serves)
    costs = [c.cost for c in clients if c.cost]
    if watcher is not None and clients:
        try:
            costs.append(clients[0].get("api/details")["watcher"])
        except OSError:
            pass
    watcher_cost = max(costs, key=lambda c: c["requests"]) if costs else None
    if watcher is not None:
        watcher.terminate()
        watcher.wait()
    cpu1 = resource.getrusage(resource.RUSAGE_CHILDREN)
    assert driver.returncode == 0, driver.stderr.read()
    with sqlite3.connect(f"file:{run / 'measurements.sqlite'}?mode=ro", uri=True) as db:
        n, first, last = db.execute("SELECT COUNT(*), MIN(wall_time_unix_s), MAX(wall_time_unix_s) FROM poses "
                                    "WHERE status = 'measured'").fetchone()
    return {"config": config, "poses": n, "poses_per_s": (n - 1) / (last - first), "wall_s": wall,
            "cpu_s": (cpu1.ru_utime + cpu1.ru_stime) - (cpu0.ru_utime + cpu0.ru_stime),
            "watcher_requests": watcher_cost and watcher_cost["requests"],
            "watcher_cpu_s": watcher_cost and watcher_cost["cpu_s"],
            "client_requests": sum(c.requests for c in clients), "client_errors": sum(c.errors for c in clients),
            "client_poses_seen": [c.seen for c in clients]}


def main():
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--poses", type=int, default=2000)
    ap.add_argument("--rounds", type=int, default=4)
    ap.add_argument("--time-factor", type=float, default=0.0, help="the simulated cell's (0: as fast as it goes)")
    args = ap.parse_args()
    runs = []
    load_before = os.getloadavg()
    with tempfile.TemporaryDirectory(prefix="bench-watch-") as tmp:
        template = make_run(Path(tmp) / "template", args.poses, args.time_factor)
        for k in range(args.rounds):
            order = CONFIGS if k % 2 == 0 else CONFIGS[::-1]
            for config in order:
                res = one(template, Path(tmp), config)
                res.update(round=k + 1, load_average=os.getloadavg()[0])
                runs.append(res)
                served = "" if res["watcher_cpu_s"] is None else \
                    f", watcher CPU {res['watcher_cpu_s']:.2f} s for {res['watcher_requests']} requests"
                print(f"round {k + 1} {config:>14}: {res['poses_per_s']:7.1f} poses/s, wall {res['wall_s']:5.1f} s, "
                      f"CPU {res['cpu_s']:5.1f} s{served}, {res['client_requests']} requests, clients saw "
                      f"{res['client_poses_seen']} of {res['poses']}; load {res['load_average']:.2f}", flush=True)
    summary = {}
    for config in CONFIGS:
        mine = [r for r in runs if r["config"] == config]
        summary[config] = {"poses_per_s_median": statistics.median(r["poses_per_s"] for r in mine),
                           "cpu_s_median": statistics.median(r["cpu_s"] for r in mine)}
    base = summary["alone"]["poses_per_s_median"]
    # each watched run against the unwatched run of its own round (the load drifts between rounds)
    for config in CONFIGS[1:]:
        ratios = [w["poses_per_s"] / a["poses_per_s"] for a in runs if a["config"] == "alone"
                  for w in runs if w["config"] == config and w["round"] == a["round"]]
        summary[config]["throughput_vs_alone_per_round"] = ratios
        summary[config]["throughput_vs_alone_median"] = statistics.median(ratios)
        summary[config]["throughput_vs_alone_of_medians"] = summary[config]["poses_per_s_median"] / base
        # the watcher's CPU against the run's own (driver and cell, the same round's run alone): the
        # share of the machine it takes, the slowdown it could cause on a machine with no core to spare
        shares = [w["watcher_cpu_s"] / a["cpu_s"] for a in runs if a["config"] == "alone"
                  for w in runs if w["config"] == config and w["round"] == a["round"] and w["watcher_cpu_s"]]
        summary[config]["watcher_cpu_vs_run_cpu_per_round"] = shares
        summary[config]["watcher_cpu_vs_run_cpu_median"] = statistics.median(shares) if shares else None
    doc = {"poses": args.poses, "rounds": args.rounds, "time_factor": args.time_factor, "summary": summary,
           "runs": runs, "load_average_before": load_before, "load_average_after": os.getloadavg(),
           "cpus": os.cpu_count()}
    for config in CONFIGS[1:]:
        s = summary[config]
        print(f"{config}: throughput {s['throughput_vs_alone_median']:.3f}x of the run alone (median of the rounds' "
              f"ratios; {', '.join(f'{r:.3f}' for r in s['throughput_vs_alone_per_round'])}); the watcher's CPU "
              f"{100 * (s['watcher_cpu_vs_run_cpu_median'] or 0):.2f} % of the run's")
    print(f"load average before {load_before[0]:.2f}, after {os.getloadavg()[0]:.2f} on {os.cpu_count()} CPUs")
    out = Path(__file__).parent / "results" / f"watch{'' if args.time_factor == 0 else '_realtime'}.json"
    out.write_text(json.dumps(doc, indent=2))
    print(f"written: {out}")


if __name__ == "__main__":
    main()
