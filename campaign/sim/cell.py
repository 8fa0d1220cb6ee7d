"""The simulated cell: one process serving a robot controller and a laser tracker over TCP.

Both ports share one world: a truth robot (nominal + hidden geometric errors + hidden
physical effects), the true pose of the tracker (from the scene), tracker noise, motion that
takes Ruckig's time plus a settle time, tracker time per target, and a simulated clock. The
truth is drawn from a seed and written to the simulator's own file (``RUN/sim/truth.yaml``),
which `plan`, `calibrate` and `diagnose` never read.

Faults are injected with configurable rates; each decision is drawn from a generator seeded
by (seed, request id), so a campaign re-run with the same requests meets the same faults.

    python -m campaign.sim.cell --config RUN/campaign.yaml --run RUN [--watch-stdin]

prints one JSON line ``{"controller": PORT, "tracker": PORT, "truth": PATH}`` when ready.
With ``--watch-stdin`` it exits when its standard input closes (its parent died or is done).
"""

from __future__ import annotations

import argparse
import json
import os
import signal
import socket
import sys
import threading
import time
from collections import OrderedDict
from pathlib import Path

import numpy as np

from campaign.config import FAULT_KINDS, CampaignConfig, load_config, parse_faults  # noqa: F401 (re-exported)
from campaign.effects.base import make_effect
from campaign.errors import CampaignError, PeerError, ProtocolError
from campaign.measure import protocol as P
from campaign.measure.reflectors import transform_points
from campaign.plan.scene import load_scene
from campaign.plan.timing import rest_to_rest_time
from campaign.run import RunFolder, load_robot
from campaign.sim.truth import make_truth, write_truth
from campaign.tolerances import JOINT_COMMAND_SLACK

_KIND_CODE = {k: i + 1 for i, k in enumerate(FAULT_KINDS)}
#: distances of the base-frame set-up points from F_I's origin along x and y (m)
SETUP_SPACING_M = 0.3
#: replies kept for repeated ids (a retry comes within seconds; a resumed run repeats only the pose in flight)
CACHE_SIZE = 4096
#: a connection silent this long (s) is closed
IDLE_TIMEOUT_S = 300.0
#: pending connections the kernel queues per port
LISTEN_BACKLOG = 128


class World:
    """The physical state shared by both ports. All methods hold the lock."""

    def __init__(self, cfg: CampaignConfig, run_dir, start_clock_s: float = 0.0):
        sc = cfg.sim
        # the reflectors `campaign run` measures: robot.yaml's, or the default triad
        self.robot = load_robot(cfg.robot_spec, tool_frame=cfg.tool_frame,
                                base_frame=cfg.base_frame).with_default_reflectors()
        self.scene = load_scene(cfg.scene_path).placed(self.robot)
        self.seed = sc.seed
        hidden = {}
        for name in sc.hidden_effects:
            e = make_effect(name, self.robot)
            hidden[name] = e.typical_params(self.seed)
        self.truth = make_truth(self.robot, seed=self.seed, noise_m=sc.noise_m, effects=hidden,
                                T_LI=self.scene.T_LI)
        self.settle_s = cfg.plan.settle_time_s
        self.tracker_s = cfg.plan.tracker_time_per_reflector_s
        self.time_factor = sc.time_factor
        self.faults, self.late_delay_s = dict(sc.faults), sc.late_delay_s
        #: the simulated campaign clock (s); a resumed campaign continues from its last stored time
        self.clock_s = float(start_clock_s)
        self.q = np.array(self.robot.q_mid)
        self.lock = threading.Lock()
        self.truth_path = Path(run_dir) / "sim" / "truth.yaml"
        self.truth_path.parent.mkdir(parents=True, exist_ok=True)
        write_truth(self.truth, self.truth_path)
        # an emergency stop happens once: the operator resets it, and the re-run passes that move
        self.estops_path = self.truth_path.parent / "estops.json"
        self.estops = set(json.loads(self.estops_path.read_text())) if self.estops_path.is_file() else set()
        self.setup_I = {"setup_origin": np.zeros(3), "setup_x": np.array([SETUP_SPACING_M, 0, 0]),
                        "setup_y": np.array([0, SETUP_SPACING_M, 0])}
        self.reflectors = {r.name: np.array(r.position_in_E) for r in self.robot.reflectors}

    def fault(self, kind, request_id) -> bool:
        rate = self.faults.get(kind, 0.0)
        if rate <= 0:
            return False
        return np.random.default_rng([self.seed, _KIND_CODE[kind], int(request_id)]).random() < rate

    def _advance(self, dt):
        self.clock_s += dt
        if self.time_factor > 0:
            time.sleep(dt * self.time_factor)

    def context(self):
        ctx = {"time_s": np.array([self.clock_s])}
        ctx["temperature_c"] = np.array([20.0 + 5.0 * np.sin(2 * np.pi * self.clock_s / 86400.0)])
        return ctx

    def move(self, msg: P.Move):
        q = np.array(msg.q)
        if np.any(q < self.robot.q_lower - JOINT_COMMAND_SLACK) or np.any(q > self.robot.q_upper + JOINT_COMMAND_SLACK):
            return P.Fault(msg.id, "joint_limit", "target outside the joint limits")
        if msg.id not in self.estops and self.fault("estop", msg.id):
            with self.lock:
                self.estops.add(msg.id)
                self.estops_path.write_text(json.dumps(sorted(self.estops)))
            return P.Fault(msg.id, "emergency_stop", "emergency stop pressed")
        if self.fault("robot_fault", msg.id):
            return P.Fault(msg.id, "move_rejected", "drive reported a following error; move not executed")
        with self.lock:
            dt = float(rest_to_rest_time(self.robot, self.q[None], q[None])[0]) + self.settle_s
            self._advance(dt)
            self.q = q
            return P.Reached(msg.id, tuple(float(v) for v in q), self.clock_s)

    def measure(self, msg: P.Measure):
        unknown = [t for t in msg.targets if t not in self.reflectors and t not in self.setup_I]
        if unknown:
            return P.ErrorReply(msg.id, f"unknown target {unknown[0]!r}")
        with self.lock:
            rng = np.random.default_rng([self.seed, 99, int(msg.id)])
            # the pose is sampled when the measurement starts; its time and temperature are reported
            ctx = self.context()
            t_sample = self.clock_s
            T_LE = self.truth.T_LI @ self.truth.pose(self.q[None], ctx)[0]
            readings = []
            for k, target in enumerate(msg.targets):
                self._advance(self.tracker_s)
                if target in self.reflectors:
                    p = transform_points(T_LE, self.reflectors[target][None])[0]
                else:
                    p = transform_points(self.truth.T_LI, self.setup_I[target][None])[0]
                if self.fault("beam_lost", msg.id * 16 + k):
                    readings.append(P.Reading(target, "beam_lost"))
                    continue
                dist = np.linalg.norm(p - 0.0)
                if not self.scene.min_range_m <= dist <= self.scene.max_range_m:
                    readings.append(P.Reading(target, "out_of_range"))
                    continue
                if self.truth.noise_m > 0:
                    p = p + rng.normal(0.0, self.truth.noise_m, 3)
                if self.truth.resolution_m > 0 and self.truth.noise_m > 0:
                    p = np.round(p / self.truth.resolution_m) * self.truth.resolution_m
                readings.append(P.Reading(target, "ok", tuple(float(v) for v in p)))
            return P.Measurement(msg.id, t_sample, tuple(readings), float(ctx["temperature_c"][0]))


class Port:
    """One listening port (controller or tracker) with a reply cache for idempotent retries."""

    def __init__(self, world: World, name: str, host: str, port: int):
        self.world, self.name = world, name
        self.sock = socket.socket(socket.AF_INET, socket.SOCK_STREAM)
        self.sock.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
        self.sock.bind((host, port))
        # a deep backlog: a burst of (re)connections must not wait for the kernel's SYN retry (1 s)
        self.sock.listen(LISTEN_BACKLOG)
        self.port = self.sock.getsockname()[1]
        self.cache: OrderedDict = OrderedDict()
        self.cache_lock = threading.Lock()
        #: how often each request id was seen: transport faults are drawn per (id, attempt)
        self.seen: dict = {}

    def serve_forever(self):
        while True:
            try:
                conn, addr = self.sock.accept()
            except OSError:
                return
            threading.Thread(target=self._handle, args=(conn,), daemon=True).start()

    def _reply_for(self, msg):
        if isinstance(msg, P.Heartbeat):
            return P.HeartbeatAck(msg.id, self.world.clock_s, self.name)
        with self.cache_lock:
            if msg.id in self.cache:
                return self.cache[msg.id]
        if self.name == "controller" and isinstance(msg, P.Move):
            reply = self.world.move(msg)
        elif self.name == "tracker" and isinstance(msg, P.Measure):
            reply = self.world.measure(msg)
        else:
            return P.ErrorReply(msg.id, f"the {self.name} does not accept '{msg.type}'")
        with self.cache_lock:
            self.cache[msg.id] = reply
            while len(self.cache) > CACHE_SIZE:
                self.cache.popitem(last=False)
        return reply

    def _handle(self, conn):
        conn.setsockopt(socket.IPPROTO_TCP, socket.TCP_NODELAY, 1)
        c = P.Connection(conn, f"driver at {self.name}")
        try:
            while True:
                try:
                    msg = c.receive(timeout_s=IDLE_TIMEOUT_S)
                except ProtocolError as exc:
                    # the stream cannot be trusted after a bad frame: say why, then hang up
                    try:
                        c.send(P.ErrorReply(0, str(exc)))
                    except CampaignError:
                        pass
                    return
                reply = self._reply_for(msg)
                w = self.world
                with self.cache_lock:
                    attempt = self.seen.get(msg.id, 0)
                    self.seen[msg.id] = attempt + 1
                    while len(self.seen) > 4 * CACHE_SIZE:
                        self.seen.pop(next(iter(self.seen)))
                key = (msg.id * 8 + attempt) * 4
                if w.fault("drop", key + 1):
                    return  # the reply is cached: a retry with the same id gets it
                if w.fault("late", key + 2):
                    time.sleep(w.late_delay_s)
                if w.fault("garble", key + 3):
                    c.send_raw(b"\x00\x00\x00\x10{not json at all")
                    return
                c.send(reply)
        except (PeerError, OSError):
            return
        except Exception as exc:  # a bug must cost one connection, never the cell
            print(f"cell {self.name}: {exc.__class__.__name__}: {exc}", file=sys.stderr, flush=True)
            return
        finally:
            c.close()


def start_cell(cfg, run_dir, host="127.0.0.1", controller_port=0, tracker_port=0, start_clock_s=0.0):
    """Start both ports in this process (threads); returns (world, controller Port, tracker Port).

    cfg: a validated CampaignConfig; start_clock_s: the simulated clock to start from (s)."""
    world = World(cfg, run_dir, start_clock_s)
    ports = (Port(world, "controller", host, controller_port), Port(world, "tracker", host, tracker_port))
    for p in ports:
        threading.Thread(target=p.serve_forever, daemon=True).start()
    return (world,) + ports


def _watch_stdin():
    try:
        while sys.stdin.buffer.read(1024):
            pass
    finally:
        os._exit(0)


def main(argv=None):
    ap = argparse.ArgumentParser(prog="python -m campaign.sim.cell", description="the simulated robot cell")
    ap.add_argument("--config", default=None)
    ap.add_argument("--run", default="runs/sim")
    ap.add_argument("--host", default="127.0.0.1")
    ap.add_argument("--controller-port", type=int, default=0)
    ap.add_argument("--tracker-port", type=int, default=0)
    ap.add_argument("--start-clock-s", type=float, default=0.0, help="simulated clock at start (s)")
    ap.add_argument("--watch-stdin", action="store_true")
    args = ap.parse_args(argv)
    try:
        if not 0 <= args.start_clock_s < float("inf"):
            raise CampaignError(f"--start-clock-s must be a finite time >= 0, got {args.start_clock_s}")
        cfg = load_config(args.config)
        # one cell per run, for this process's lifetime (RUN/sim/.lock; the driver holds RUN/.lock)
        with RunFolder(args.run).sim_lock("sim (a driver's simulated cell)"):
            world, ctrl, trk = start_cell(cfg, args.run, args.host, args.controller_port, args.tracker_port,
                                          args.start_clock_s)
            return _serve(args, world, ctrl, trk)
    except CampaignError as exc:
        print(json.dumps({"error": str(exc)}), flush=True)
        return 1


def _serve(args, world, ctrl, trk) -> int:
    print(json.dumps({"controller": ctrl.port, "tracker": trk.port, "host": args.host,
                      "truth": str(world.truth_path)}), flush=True)
    if args.watch_stdin:
        # a child of the driver: Ctrl-C is the driver's to handle (it finishes the current pose)
        signal.signal(signal.SIGINT, signal.SIG_IGN)
        _watch_stdin()
    try:
        while True:
            time.sleep(3600)
    except KeyboardInterrupt:
        return 0


if __name__ == "__main__":
    sys.exit(main())
