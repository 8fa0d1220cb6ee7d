"""The wire protocol between the campaign driver and the robot controller / laser tracker.

Framing: a 4-byte big-endian length, then that many bytes of UTF-8 JSON holding one object.
Frames above :data:`MAX_FRAME` bytes are refused. Every request carries an integer ``id``;
a peer that sees an id again answers with its first reply and does not act twice, so a
retry after a lost reply is idempotent. docs/protocol.md describes every message.

Parsing is pure: :func:`decode` turns bytes into a typed, validated message or raises
:class:`campaign.errors.ProtocolError` naming what is wrong. No pickle, no eval.
"""

from __future__ import annotations

import json
import math
import socket
import struct
import time
from dataclasses import asdict, dataclass, field

from campaign.errors import AuthError, PeerError, ProtocolError, TrackerTimeout
from campaign.measure.auth import SCHEME, TAG_BYTES, FrameAuth

MAX_FRAME = 64 * 1024
_HEADER = struct.Struct(">I")

#: target names the tracker knows: the tool's reflectors and the base-frame set-up points
SETUP_TARGETS = ("setup_origin", "setup_x", "setup_y")
#: most joints a ``move``/``reached`` carries (field ``joints``; 6 when absent)
MAX_JOINTS = 32
TARGET_STATUS = ("ok", "beam_lost", "out_of_range")


# -- messages ---------------------------------------------------------------------------------

@dataclass(frozen=True)
class Move:
    """Controller request: move to joint coordinates ``q`` (rad)."""
    id: int
    q: tuple
    type: str = "move"


@dataclass(frozen=True)
class Reached:
    """Controller reply: the pose is reached; ``q_encoder`` rad, ``time_s`` campaign clock."""
    id: int
    q_encoder: tuple
    time_s: float
    type: str = "reached"


@dataclass(frozen=True)
class Fault:
    """Controller reply: the robot stopped with a fault."""
    id: int
    code: str
    message: str
    type: str = "fault"


@dataclass(frozen=True)
class Measure:
    """Tracker request: measure the named targets. ``aims``: optional ((name, (x, y, z) m or
    None), ...), the driver's prediction of each target's centre in F_L (None: not predictable
    yet); a tracker may point its beam there."""
    id: int
    targets: tuple
    aims: tuple | None = None
    type: str = "measure"

    def aims_by_target(self) -> dict:
        """{target: (3,) tuple m or None} for every target (None where no aim was sent)."""
        given = dict(self.aims or ())
        return {t: given.get(t) for t in self.targets}


@dataclass(frozen=True)
class Reading:
    """One target of a measurement: ``status`` in TARGET_STATUS; ``xyz_m`` in F_L (m) when ok."""
    target: str
    status: str
    xyz_m: tuple | None = None


@dataclass(frozen=True)
class Measurement:
    """Tracker reply: one reading per target, coordinates in F_L (m); the tracker's air
    temperature sensor (°C) when it has one."""
    id: int
    time_s: float
    readings: tuple = field(default_factory=tuple)
    temperature_c: float | None = None
    type: str = "measurement"


@dataclass(frozen=True)
class Heartbeat:
    """Either peer: are you there, and who are you?"""
    id: int
    type: str = "heartbeat"


@dataclass(frozen=True)
class HeartbeatAck:
    """Reply to a heartbeat: the peer's clock (s) and its role, "controller" or "tracker"."""
    id: int
    time_s: float
    peer: str
    type: str = "heartbeat_ack"


@dataclass(frozen=True)
class Hello:
    """Peer -> driver, first frame of a connection to a peer that authenticates frames
    (campaign.measure.auth): the connection's nonce (32 hex digits) and the scheme."""
    nonce: str
    auth: str = "hmac-sha256"
    type: str = "hello"


@dataclass(frozen=True)
class ErrorReply:
    """Either peer: the request could not be understood."""
    id: int
    message: str
    type: str = "error"


def _num(obj, key, what):
    v = obj.get(key)
    if isinstance(v, bool) or not isinstance(v, (int, float)) or not math.isfinite(v):
        raise ProtocolError(f"{what}: field '{key}' must be a finite number, got {v!r}")
    return float(v)


def _id(obj, what):
    v = obj.get("id")
    if isinstance(v, bool) or not isinstance(v, int) or v < 0 or v >= 2**63:
        raise ProtocolError(f"{what}: field 'id' must be a non-negative integer, got {v!r}")
    return v


def _vec(obj, key, n, what):
    v = obj.get(key)
    if not isinstance(v, list) or len(v) != n:
        raise ProtocolError(f"{what}: field '{key}' must be a list of {n} numbers")
    out = []
    for x in v:
        if isinstance(x, bool) or not isinstance(x, (int, float)) or not math.isfinite(x):
            raise ProtocolError(f"{what}: field '{key}' must hold finite numbers, got {x!r}")
        out.append(float(x))
    return tuple(out)


def _joints(obj, what) -> int:
    """The joint count of a ``move``/``reached``: field ``joints`` (1..MAX_JOINTS), 6 when absent."""
    n = obj.get("joints", 6)
    if isinstance(n, bool) or not isinstance(n, int) or not 1 <= n <= MAX_JOINTS:
        raise ProtocolError(f"{what}: field 'joints' must be an integer in 1..{MAX_JOINTS}, got {n!r}")
    return n


def _str(obj, key, what, max_len=200):
    v = obj.get(key)
    if not isinstance(v, str) or len(v) > max_len:
        raise ProtocolError(f"{what}: field '{key}' must be a string of at most {max_len} characters")
    return v


def _aims(obj, what):
    """A measure's optional ``aims``: {name: [x, y, z] or null} -> ((name, xyz or None), ...)."""
    a = obj.get("aims")
    if a is None:
        return None
    if not isinstance(a, dict) or len(a) > 16:
        raise ProtocolError(f"{what}: field 'aims' must be an object of at most 16 targets")
    out = []
    for name, v in a.items():
        if len(name) > 64:
            raise ProtocolError(f"{what}: field 'aims' holds a target name over 64 characters")
        out.append((name, None if v is None else _vec(a, name, 3, f"{what} aims")))
    return tuple(out)


def from_dict(obj) -> object:
    """Validate a decoded JSON object into a message dataclass."""
    if not isinstance(obj, dict):
        raise ProtocolError("message must be a JSON object")
    kind = obj.get("type")
    what = f"message '{kind}'"
    if kind == "move":
        return Move(_id(obj, what), _vec(obj, "q", _joints(obj, what), what))
    if kind == "reached":
        return Reached(_id(obj, what), _vec(obj, "q_encoder", _joints(obj, what), what), _num(obj, "time_s", what))
    if kind == "fault":
        return Fault(_id(obj, what), _str(obj, "code", what), _str(obj, "message", what, 2000))
    if kind == "measure":
        t = obj.get("targets")
        if not isinstance(t, list) or not 1 <= len(t) <= 16 or not all(isinstance(x, str) and len(x) <= 64 for x in t):
            raise ProtocolError(f"{what}: field 'targets' must be a list of 1-16 target names")
        return Measure(_id(obj, what), tuple(t), _aims(obj, what))
    if kind == "measurement":
        rs = obj.get("readings")
        if not isinstance(rs, list) or len(rs) > 16:
            raise ProtocolError(f"{what}: field 'readings' must be a list")
        readings = []
        for r in rs:
            if not isinstance(r, dict):
                raise ProtocolError(f"{what}: each reading must be an object")
            status = _str(r, "status", what)
            if status not in TARGET_STATUS:
                raise ProtocolError(f"{what}: reading status must be one of {', '.join(TARGET_STATUS)}, got {status!r}")
            xyz = _vec(r, "xyz_m", 3, what) if status == "ok" else None
            readings.append(Reading(_str(r, "target", what, 64), status, xyz))
        temp = _num(obj, "temperature_c", what) if obj.get("temperature_c") is not None else None
        if temp is not None and not -50.0 <= temp <= 100.0:
            raise ProtocolError(f"{what}: field 'temperature_c' must lie in -50..100, got {temp!r}")
        return Measurement(_id(obj, what), _num(obj, "time_s", what), tuple(readings), temp)
    if kind == "heartbeat":
        return Heartbeat(_id(obj, what))
    if kind == "heartbeat_ack":
        return HeartbeatAck(_id(obj, what), _num(obj, "time_s", what), _str(obj, "peer", what))
    if kind == "hello":
        nonce = _str(obj, "nonce", what, 64)
        if len(nonce) != 32 or any(c not in "0123456789abcdef" for c in nonce):
            raise ProtocolError(f"{what}: field 'nonce' must be 32 lower-case hex digits")
        return Hello(nonce, _str(obj, "auth", what, 64))
    if kind == "error":
        return ErrorReply(_id(obj, what) if "id" in obj else 0, _str(obj, "message", what, 2000))
    raise ProtocolError(f"unknown message type {kind!r}")


def to_dict(msg) -> dict:
    d = asdict(msg)
    if isinstance(msg, Measurement):
        d["readings"] = [{k: v for k, v in asdict(r).items() if v is not None} for r in msg.readings]
        if msg.temperature_c is None:
            del d["temperature_c"]
    if isinstance(msg, Measure):
        if msg.aims is None:
            del d["aims"]
        else:
            d["aims"] = {name: None if v is None else list(v) for name, v in msg.aims}
    for key in ("q", "q_encoder", "targets"):
        if key in d:
            d[key] = list(d[key])
    for key in ("q", "q_encoder"):  # a chain of other than six joints says how many
        if key in d and len(d[key]) != 6:
            d["joints"] = len(d[key])
    return d


def encode(msg) -> bytes:
    body = json.dumps(to_dict(msg), separators=(",", ":")).encode()
    if len(body) > MAX_FRAME:
        raise ProtocolError(f"message of {len(body)} bytes exceeds the {MAX_FRAME}-byte limit")
    return _HEADER.pack(len(body)) + body


def decode(body: bytes):
    try:
        obj = json.loads(body.decode("utf-8"))
    except (UnicodeDecodeError, json.JSONDecodeError) as exc:
        raise ProtocolError(f"frame is not UTF-8 JSON ({exc.__class__.__name__})") from None
    except RecursionError:
        raise ProtocolError("frame nests JSON too deeply (a message is one flat object)") from None
    return from_dict(obj)


# -- a framed connection ----------------------------------------------------------------------

class Connection:
    """A TCP connection that sends and receives whole frames, with a per-call timeout.
    ``auth``: a :class:`campaign.measure.auth.FrameAuth` when frames are authenticated."""

    def __init__(self, sock: socket.socket, peer: str, auth: FrameAuth | None = None):
        self.sock, self.peer, self.auth = sock, peer, auth
        self._buf = b""

    @classmethod
    def connect(cls, host: str, port: int, timeout_s: float, name: str, key: bytes | None = None) -> "Connection":
        """Connect to a peer; with ``key`` (campaign.measure.auth.read_token) read its hello and
        authenticate every frame from then on (AuthError when it sends none)."""
        conn = cls._open(host, port, timeout_s, name)
        if key is not None:
            try:
                hello = conn.receive(timeout_s)
            except (TrackerTimeout, PeerError, ProtocolError):
                conn.close()
                raise AuthError(f"{conn.peer}: sent no hello within {timeout_s:g} s (is it served with "
                                "--token-file?)") from None
            if not isinstance(hello, Hello) or hello.auth != SCHEME:
                conn.close()
                raise AuthError(f"{conn.peer}: answered '{getattr(hello, 'type', '?')}' instead of a {SCHEME} hello")
            conn.auth = FrameAuth(key, bytes.fromhex(hello.nonce), "driver")
        return conn

    @classmethod
    def _open(cls, host, port, timeout_s, name) -> "Connection":
        peer = f"{name} {host}:{port}"
        try:
            sock = socket.create_connection((host, port), timeout=timeout_s)
        except ConnectionRefusedError:
            raise PeerError(f"{peer}: connection refused") from None
        except socket.timeout:
            raise PeerError(f"{peer}: no answer to connect within {timeout_s:g} s") from None
        except OSError as exc:
            raise PeerError(f"{peer}: cannot connect ({exc.strerror or exc})") from None
        sock.setsockopt(socket.IPPROTO_TCP, socket.TCP_NODELAY, 1)
        return cls(sock, peer)

    def send(self, msg) -> None:
        data = encode(msg)
        if self.auth is not None:
            body = self.auth.seal(data[_HEADER.size:])
            data = _HEADER.pack(len(body)) + body
        self.send_raw(data)

    def send_raw(self, data: bytes) -> None:
        try:
            self.sock.sendall(data)
        except OSError as exc:
            raise PeerError(f"{self.peer}: connection lost while sending ({exc.strerror or exc})") from None

    def _read_exact(self, n, deadline, timeout_s):
        while len(self._buf) < n:
            left = deadline - time.monotonic()
            if left <= 0:
                raise TrackerTimeout(f"{self.peer}: no complete reply within {timeout_s:g} s")
            self.sock.settimeout(left)
            try:
                chunk = self.sock.recv(max(65536, n - len(self._buf)))
            except socket.timeout:
                raise TrackerTimeout(f"{self.peer}: no reply within {timeout_s:g} s") from None
            except OSError as exc:
                raise PeerError(f"{self.peer}: connection lost ({exc.strerror or exc})") from None
            if not chunk:
                raise PeerError(f"{self.peer}: connection closed by the peer")
            self._buf += chunk
        out, self._buf = self._buf[:n], self._buf[n:]
        return out

    def receive(self, timeout_s: float):
        """The next message, whole within ``timeout_s`` (a peer trickling bytes times out too).

        ProtocolError for a bad frame (the connection is then unusable), TrackerTimeout when
        no complete frame arrived in time, PeerError when the connection is lost.
        """
        deadline = time.monotonic() + timeout_s
        (length,) = _HEADER.unpack(self._read_exact(4, deadline, timeout_s))
        limit = MAX_FRAME + (TAG_BYTES if self.auth is not None else 0)
        if length > limit:
            raise ProtocolError(f"{self.peer}: frame of {length} bytes exceeds the {limit}-byte limit")
        body = self._read_exact(length, deadline, timeout_s)
        if self.auth is not None:
            body = self.auth.open(body)
        return decode(body)

    def close(self) -> None:
        try:
            self.sock.close()
        except OSError:
            pass
