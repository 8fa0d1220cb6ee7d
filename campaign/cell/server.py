"""Serving a cell's two adapters over docs/protocol.md (`campaign serve`).

The framework does everything the protocol asks, so an adapter never sees a frame: framing and
validation (campaign.measure.protocol), the reply cache and idempotency (a repeated id gets the
first reply, also while the first is still being served), heartbeats, error replies, the joint
limits, the controller's joint convention, a timeout on every adapter call, authenticated frames
beyond loopback (campaign.measure.auth). Each adapter is called by one thread at a time.

    python -m campaign.cell.server --controller SPEC --tracker SPEC [--run DIR] [--config FILE]
        [--options FILE] [--host H] [--controller-port P] [--tracker-port P] [--token-file F]
        [--move-timeout-s T] [--start-clock-s T] [--watch-stdin]

prints one JSON line ``{"controller": PORT, "tracker": PORT, "host": HOST}`` when ready (or
``{"error": "..."}``); `campaign run --cell` starts it so.
"""

from __future__ import annotations

import json
import math
import os
import socket
import sys
import threading
import time
from collections import OrderedDict

import numpy as np

from campaign.cell import RobotFault, _CONTEXT, _REQUEST, CellContext, close_quietly
from campaign.cell.arguments import add_serve_arguments  # noqa: F401 (python -m campaign.cell.server)
from campaign.errors import AuthError, CampaignError, ConfigError, PeerError, ProtocolError
from campaign.measure import protocol as P
from campaign.measure.auth import NONCE_BYTES, FrameAuth, is_loopback
from campaign.tolerances import JOINT_COMMAND_SLACK

#: replies kept for repeated ids (a retry comes within seconds; a resumed run repeats only the pose in flight)
CACHE_SIZE = 4096
#: a connection silent this long (s) is closed
IDLE_TIMEOUT_S = 300.0
#: pending connections the kernel queues per port
LISTEN_BACKLOG = 128
#: how long an adapter call may take by default (s): the driver's default move timeout
DEFAULT_CALL_TIMEOUT_S = 120.0


def _say(line: str) -> None:
    print(line, file=sys.stderr, flush=True)


class AdapterCall:
    """Runs one adapter's methods one at a time, each within a timeout, in the cell's context."""

    def __init__(self, adapter, role: str, ctx: CellContext):
        self.adapter, self.role, self.ctx = adapter, role, ctx
        self.lock = threading.Lock()

    def __call__(self, method: str, args, request_id, timeout_s: float):
        """(True, value) or (False, exception); TimeoutError when it did not return in time."""
        box = {}
        done = threading.Event()

        def work():
            t1, t2 = _CONTEXT.set(self.ctx), _REQUEST.set(request_id)
            try:
                with self.lock:
                    box["out"] = (True, getattr(self.adapter, method)(*args))
            except Exception as exc:  # the adapter's code: the caller turns it into a reply
                box["out"] = (False, exc)
            finally:
                _REQUEST.reset(t2)
                _CONTEXT.reset(t1)
                done.set()

        threading.Thread(target=work, daemon=True, name=f"{self.role} adapter").start()
        if not done.wait(timeout_s):
            raise TimeoutError(f"the {self.role} adapter's {method} did not return within {timeout_s:g} s")
        return box["out"]

    def optional(self, method: str, *args, locked: bool = True):
        """The adapter's optional hook ``method(*args)`` or None when it has none (called in this
        thread; under the adapter's lock unless ``locked`` is False: a clock is read during a move)."""
        fn = getattr(self.adapter, method, None)
        if not callable(fn):
            return None
        t1 = _CONTEXT.set(self.ctx)
        try:
            if not locked:
                return fn(*args)
            with self.lock:
                return fn(*args)
        finally:
            _CONTEXT.reset(t1)


def require_token(host: str, key) -> None:
    """ConfigError when ``host`` is not loopback and no shared secret is given."""
    if key is None and not is_loopback(host):
        raise ConfigError(f"--host {host}: serving beyond loopback moves a robot for anyone who reaches the "
                          "port; give a shared secret (--token-file FILE, also given to `campaign run`)")


class ServedCell:
    """A controller adapter and a tracker adapter served on two TCP ports (threads of this process).

    robot: the run's RobotModel (with the reflectors the driver measures); key: the shared secret
    (campaign.measure.auth.read_token) or None, required when ``host`` is not loopback;
    call_timeout_s: how long a move or a measurement may take (s) before it is answered with a
    fault (``move_timeout``, which stops the campaign) or an error. :meth:`start` binds and serves.
    """

    def __init__(self, controller, tracker, robot, *, host="127.0.0.1", controller_port=0, tracker_port=0,
                 key: bytes | None = None, call_timeout_s: float = DEFAULT_CALL_TIMEOUT_S,
                 cell_context: CellContext | None = None):
        require_token(host, key)
        if not call_timeout_s > 0:
            raise ConfigError(f"--move-timeout-s must be > 0, got {call_timeout_s}")
        self.robot, self.key, self.call_timeout_s = robot, key, float(call_timeout_s)
        self.ctx = cell_context if cell_context is not None else CellContext()
        self.adapters = {"controller": controller, "tracker": tracker}
        self.calls = {role: AdapterCall(a, role, self.ctx) for role, a in self.adapters.items()}
        self.targets = set(P.SETUP_TARGETS) | {r.name for r in robot.reflectors}
        self._t0 = time.monotonic()
        self.host = host
        self.ports = {"controller": AdapterPort(self, "controller", host, controller_port),
                      "tracker": AdapterPort(self, "tracker", host, tracker_port)}

    @property
    def controller_port(self) -> int:
        return self.ports["controller"].port

    @property
    def tracker_port(self) -> int:
        return self.ports["tracker"].port

    def start(self) -> "ServedCell":
        for p in self.ports.values():
            threading.Thread(target=p.serve_forever, daemon=True, name=f"{p.role} port").start()
        return self

    def close(self) -> None:
        """Stop listening and call each adapter's close() (what it raises: one line on stderr)."""
        for p in self.ports.values():
            p.close()
        for role, a in self.adapters.items():
            err = close_quietly(a)
            if err:
                _say(f"campaign serve: {role} adapter close(): {err}")

    # -- what the cell answers ------------------------------------------------------------------
    def clock(self) -> float:
        """The cell's clock (s): an adapter's clock() (the controller's first), else the wall clock
        since the start, continuing from the context's start clock."""
        for role in ("controller", "tracker"):
            if callable(getattr(self.adapters[role], "clock", None)):
                return float(self.calls[role].optional("clock", locked=False))
        return self.ctx.start_clock_s + time.monotonic() - self._t0

    def _adapter_failed(self, role, msg, exc):
        text = f"{exc.__class__.__name__}: {exc}"
        _say(f"campaign serve: {role} adapter, request {msg.id}: {text}")
        return P.ErrorReply(msg.id, f"{role} adapter: {text}"[:2000])

    def move(self, msg: P.Move):
        r = self.robot
        q = np.array(msg.q, dtype=float)
        if len(q) != r.n_joints:
            return P.ErrorReply(msg.id, f"move: q has {len(q)} joints, the robot {r.name} has {r.n_joints}")
        limited = np.array([t != "continuous" for t in r.joint_types] or [True] * len(q), dtype=bool)
        outside = limited & ((q < r.q_lower - JOINT_COMMAND_SLACK) | (q > r.q_upper + JOINT_COMMAND_SLACK))
        if outside.any():
            return P.Fault(msg.id, "joint_limit", "target outside the joint limits")
        by_model = getattr(self.adapters["controller"], "joint_convention", "controller") == "model"
        q_adapter = q if by_model else r.to_controller_q(q[None])[0]
        call = self.calls["controller"]
        try:
            ok, out = call("move", (q_adapter.copy(),), msg.id, self.call_timeout_s)
        except TimeoutError as exc:
            _say(f"campaign serve: controller adapter, request {msg.id}: {exc}")
            return P.Fault(msg.id, "move_timeout", str(exc))
        if not ok:
            if isinstance(out, RobotFault):
                return P.Fault(msg.id, out.code[:200], out.reason[:2000])
            return self._adapter_failed("controller", msg, out)
        try:
            readout = call.optional("joints")
        except Exception as exc:  # the adapter's code
            return self._adapter_failed("controller", msg, exc)
        if readout is None:
            q_enc = q
        else:
            q_enc = np.asarray(readout, dtype=float).reshape(-1)
            if q_enc.shape != q.shape or not np.all(np.isfinite(q_enc)):
                return self._adapter_failed("controller", msg, ValueError(
                    f"joints() returned {readout!r}, expected {len(q)} finite numbers"))
            if not by_model:
                q_enc = r.to_model_q(q_enc[None])[0]
        return P.Reached(msg.id, tuple(float(v) for v in q_enc), self.clock())

    def measure(self, msg: P.Measure):
        unknown = [t for t in msg.targets if t not in self.targets]
        if unknown:
            return P.ErrorReply(msg.id, f"unknown target {unknown[0]!r}")
        aims = {t: None if a is None else np.array(a, dtype=float) for t, a in msg.aims_by_target().items()}
        call = self.calls["tracker"]
        t_sample = self.clock()
        try:
            ok, out = call("measure", (aims,), msg.id, self.call_timeout_s)
        except TimeoutError as exc:
            return self._adapter_failed("tracker", msg, exc)
        if not ok:
            return self._adapter_failed("tracker", msg, out)
        try:
            readings = tuple(_reading(t, out) for t in msg.targets)
            temp = call.optional("temperature_c")
            temp = None if temp is None else float(temp)
            if temp is not None and not -50.0 <= temp <= 100.0:
                raise ValueError(f"temperature_c() returned {temp!r}, expected -50..100 °C or None")
        except Exception as exc:  # the adapter's answer breaks the contract
            return self._adapter_failed("tracker", msg, exc)
        return P.Measurement(msg.id, t_sample, readings, temp)


def _reading(target, out) -> P.Reading:
    """One target of a tracker adapter's answer: (3,) m, None (lost beam), or a status string."""
    if not hasattr(out, "get"):
        raise TypeError(f"measure() returned {type(out).__name__}, expected a mapping name -> (3,) or None")
    v = out.get(target)
    if v is None:
        return P.Reading(target, "beam_lost")
    if isinstance(v, str):
        if v not in P.TARGET_STATUS or v == "ok":
            raise ValueError(f"measure() returned status {v!r} for {target!r}, expected one of beam_lost, "
                             "out_of_range")
        return P.Reading(target, v)
    xyz = np.asarray(v, dtype=float).reshape(-1)
    if xyz.shape != (3,) or not all(math.isfinite(x) for x in xyz):
        raise ValueError(f"measure() returned {v!r} for {target!r}, expected 3 finite numbers (m) or None")
    return P.Reading(target, "ok", tuple(float(x) for x in xyz))


class AdapterPort:
    """One listening port (controller or tracker) with a reply cache for idempotent retries."""

    def __init__(self, cell: ServedCell, role: str, host: str, port: int):
        self.cell, self.role = cell, role
        family = socket.AF_INET6 if ":" in host else socket.AF_INET
        self.sock = socket.socket(family, socket.SOCK_STREAM)
        self.sock.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
        try:
            self.sock.bind((host, port))
        except OSError as exc:
            self.sock.close()
            raise ConfigError(f"--{role}-port {port} on {host}: cannot bind ({exc.strerror or exc})") from None
        # a deep backlog: a burst of (re)connections must not wait for the kernel's SYN retry (1 s)
        self.sock.listen(LISTEN_BACKLOG)
        self.port = self.sock.getsockname()[1]
        self.cache: OrderedDict = OrderedDict()
        self.inflight: dict = {}
        self.cache_lock = threading.Lock()
        #: how often each request id was seen: an adapter's transport faults are drawn per (id, attempt)
        self.seen: dict = {}

    def close(self):
        try:
            self.sock.close()
        except OSError:
            pass

    def serve_forever(self):
        while True:
            try:
                conn, addr = self.sock.accept()
            except OSError:
                return
            threading.Thread(target=self._handle, args=(conn, addr), daemon=True).start()

    def _reply_for(self, msg):
        if isinstance(msg, P.Heartbeat):
            return P.HeartbeatAck(msg.id, self.cell.clock(), self.role)
        if not ((self.role == "controller" and isinstance(msg, P.Move))
                or (self.role == "tracker" and isinstance(msg, P.Measure))):
            return P.ErrorReply(getattr(msg, "id", 0), f"the {self.role} does not accept '{msg.type}'")
        with self.cache_lock:
            if msg.id in self.cache:
                return self.cache[msg.id]
            pending = self.inflight.get(msg.id)
            if pending is None:
                self.inflight[msg.id] = threading.Event()
        if pending is not None:  # a retry while the first request is served: its reply, not a second action
            pending.wait()
            with self.cache_lock:
                return self.cache.get(msg.id) or P.ErrorReply(msg.id, "reply no longer cached")
        try:
            reply = self.cell.move(msg) if self.role == "controller" else self.cell.measure(msg)
        except Exception as exc:  # a bug must cost one request, never the cell
            reply = self.cell._adapter_failed(self.role, msg, exc)
        with self.cache_lock:
            self.cache[msg.id] = reply
            while len(self.cache) > CACHE_SIZE:
                self.cache.popitem(last=False)
            self.inflight.pop(msg.id).set()
        return reply

    def _transport_fault(self, msg):
        """The adapter's transport_fault(request_id, attempt) hook: None, "drop" or "garble"."""
        adapter = self.cell.adapters[self.role]
        if not callable(getattr(adapter, "transport_fault", None)):
            return None
        with self.cache_lock:
            attempt = self.seen.get(msg.id, 0)
            self.seen[msg.id] = attempt + 1
            while len(self.seen) > 4 * CACHE_SIZE:
                self.seen.pop(next(iter(self.seen)))
        return adapter.transport_fault(msg.id, attempt)

    def _handle(self, sock, addr):
        sock.setsockopt(socket.IPPROTO_TCP, socket.TCP_NODELAY, 1)
        who = f"{addr[0]}:{addr[1]}"
        c = P.Connection(sock, f"driver {who} at the {self.role}")
        try:
            if self.cell.key is not None:
                nonce = os.urandom(NONCE_BYTES)
                c.send(P.Hello(nonce.hex()))
                c.auth = FrameAuth(self.cell.key, nonce, "peer")
            while True:
                try:
                    msg = c.receive(timeout_s=IDLE_TIMEOUT_S)
                except AuthError:
                    _say(f"campaign serve: {self.role}: refused a frame from {who}: it failed authentication "
                         "(no token, a wrong token, or a replayed frame); connection closed, nothing done")
                    return
                except ProtocolError as exc:
                    # the stream cannot be trusted after a bad frame: say why, then hang up
                    try:
                        c.send(P.ErrorReply(0, str(exc)))
                    except CampaignError:
                        pass
                    return
                reply = self._reply_for(msg)
                fault = self._transport_fault(msg)
                if fault == "drop":
                    return  # the reply is cached: a retry with the same id gets it
                if fault == "garble":
                    c.send_raw(b"\x00\x00\x00\x10{not json at all")
                    return
                c.send(reply)
        except (PeerError, OSError):
            return
        except Exception as exc:  # a bug must cost one connection, never the cell
            _say(f"campaign serve: {self.role}: {exc.__class__.__name__}: {exc}")
            return
        finally:
            c.close()


# -- a served cell, from specs -----------------------------------------------------------------

def open_cell(controller_spec, tracker_spec, cfg, *, run_dir=None, options=None, host="127.0.0.1",
              controller_port=0, tracker_port=0, key=None, call_timeout_s=None, start_clock_s=0.0) -> ServedCell:
    """Load the two adapters for the robot of ``cfg`` (a validated CampaignConfig) and serve them
    (started). options: the mapping of campaign.cell.load_options; key: the shared secret or None;
    call_timeout_s: default ``cfg.run.move_timeout_s``; start_clock_s: the run's last stored time (s).
    Relative adapter files are looked up in the current directory, then beside ``cfg``'s file."""
    from pathlib import Path

    from campaign.cell import load_adapters
    from campaign.run import load_robot

    robot = load_robot(cfg.robot_spec, tool_frame=cfg.tool_frame, base_frame=cfg.base_frame).with_default_reflectors()
    ctx = CellContext(Path(run_dir) if run_dir is not None else None, cfg, float(start_clock_s))
    base_dir = Path(cfg.path).parent if getattr(cfg, "path", None) else None
    controller, tracker = load_adapters(controller_spec, tracker_spec, robot, options, base_dir, cell_context=ctx)
    try:
        cell = ServedCell(controller, tracker, robot, host=host, controller_port=controller_port,
                          tracker_port=tracker_port, key=key, cell_context=ctx,
                          call_timeout_s=cfg.run.move_timeout_s if call_timeout_s is None else call_timeout_s)
    except CampaignError:
        for a in (controller, tracker):
            close_quietly(a)
        raise
    return cell.start()


def served_cell_from_args(args, start_clock_s=None):
    """(RunFolder or None, ServedCell) for parsed serve arguments; the caller holds the run's
    cell lock. The clock starts at ``start_clock_s``, else at the run's last stored time."""
    from campaign.cell import load_options
    from campaign.config import load_config
    from campaign.measure.auth import read_token
    from campaign.run import RunFolder

    key = read_token(args.token_file) if args.token_file else None
    require_token(args.host, key)  # before any adapter is loaded
    options = load_options(args.options)
    run = None
    if args.run is not None:
        run = RunFolder(args.run, config=args.config)
        run.check_recorded_robot()
        cfg = run.config
        clock = run.clock_s() if start_clock_s is None else start_clock_s
    else:
        cfg, clock = load_config(args.config), start_clock_s or 0.0
    cell = open_cell(args.controller, args.tracker, cfg, run_dir=None if run is None else run.path, options=options,
                     host=args.host, controller_port=args.controller_port, tracker_port=args.tracker_port, key=key,
                     call_timeout_s=args.move_timeout_s, start_clock_s=clock)
    return run, cell


def serve_until_interrupted(cell: ServedCell, *, watch_stdin: bool = False) -> int:
    """Serve until Ctrl-C or SIGTERM (or, with ``watch_stdin``, until stdin closes: a child of the
    driver, which ignores SIGINT, as Ctrl-C is the driver's to handle); then close the adapters. 0."""
    import signal

    def stop(signum, frame):
        raise KeyboardInterrupt

    signal.signal(signal.SIGTERM, stop)
    if watch_stdin:
        signal.signal(signal.SIGINT, signal.SIG_IGN)
        try:
            while sys.stdin.buffer.read(1024):
                pass
        except KeyboardInterrupt:
            pass
        finally:
            cell.close()
            os._exit(0)
    # SIGINT stops the cell even when it was started ignoring it (a job started in the background
    # by a non-interactive shell inherits SIGINT ignored, and Python then leaves it so)
    signal.signal(signal.SIGINT, signal.default_int_handler)
    try:
        while True:
            time.sleep(3600)
    except KeyboardInterrupt:
        cell.close()
    return 0


def main(argv=None, prog="python -m campaign.cell.server") -> int:
    """A cell as a child process (`campaign run --cell`): one JSON line when ready, then serve
    until stdin closes (``--watch-stdin``) or SIGINT."""
    import argparse
    import contextlib

    ap = argparse.ArgumentParser(prog=prog, description="serve a cell's adapters (docs/cell.md)")
    add_serve_arguments(ap)
    ap.add_argument("--start-clock-s", type=float, default=None, help="the cell's clock at start (s)")
    ap.add_argument("--watch-stdin", action="store_true", help="exit when stdin closes")
    args = ap.parse_args(argv)
    try:
        if args.start_clock_s is not None and not 0 <= args.start_clock_s < float("inf"):
            raise CampaignError(f"--start-clock-s must be a finite time >= 0, got {args.start_clock_s}")
        from campaign.run import RunFolder

        # one cell per run, for this process's lifetime (RUN/sim/.lock; the driver holds RUN/.lock)
        what = "sim (a driver's simulated cell)" if (args.controller, args.tracker) == ("sim", "sim") else \
            f"serve --controller {args.controller} --tracker {args.tracker} (a driver's cell)"
        lock = RunFolder(args.run).sim_lock(what) if args.run else contextlib.nullcontext()
        with lock:
            _, cell = served_cell_from_args(args, args.start_clock_s)
            info = {"controller": cell.controller_port, "tracker": cell.tracker_port, "host": args.host,
                    **cell.ctx.shared.get("announce", {})}
            print(json.dumps(info), flush=True)
            return serve_until_interrupted(cell, watch_stdin=args.watch_stdin)
    except CampaignError as exc:
        print(json.dumps({"error": str(exc)}), flush=True)
        return 1


if __name__ == "__main__":
    sys.exit(main())
