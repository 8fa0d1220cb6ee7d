"""Authenticated frames: a shared secret between `campaign serve` and `campaign run`.

A peer that serves beyond loopback opens every connection with a ``hello`` frame carrying a
fresh 16-byte nonce. From then on every frame, in both directions, is the 32-byte
HMAC-SHA256 tag followed by the JSON body (the length prefix covers both)::

    tag = HMAC-SHA256(key, "campaign-frame-v1" | direction | nonce | counter | body)

``direction`` is ``b"D"`` for driver -> peer, ``b"P"`` for peer -> driver; ``counter`` is the
frame's index in its direction on this connection (8 bytes, big-endian, from 0); ``key`` is
SHA-256 of the token file's text (stripped). A frame from another connection (another nonce),
replayed within one (another counter), reflected (another direction) or altered fails. See
docs/protocol.md, "Authentication".
"""

from __future__ import annotations

import hashlib
import hmac
import ipaddress
import socket
from pathlib import Path

from campaign.errors import AuthError, ConfigError

SCHEME = "hmac-sha256"
TAG_BYTES = 32
NONCE_BYTES = 16
#: shortest shared secret accepted (characters): a guessable token protects nothing
MIN_TOKEN_CHARS = 16
_DOMAIN = b"campaign-frame-v1"


def read_token(path) -> bytes:
    """The key from a token file (SHA-256 of its stripped text); ConfigError naming the file when
    it is missing, unreadable or shorter than MIN_TOKEN_CHARS."""
    p = Path(path)
    try:
        text = p.read_text(encoding="utf-8").strip()
    except (OSError, UnicodeDecodeError) as exc:
        raise ConfigError(f"--token-file {p}: cannot read it ({getattr(exc, 'strerror', None) or exc})") from None
    if len(text) < MIN_TOKEN_CHARS:
        raise ConfigError(f"--token-file {p}: the token must be at least {MIN_TOKEN_CHARS} characters "
                          f"(e.g. `python -c \"import secrets; print(secrets.token_hex(32))\" > {p}`)")
    return hashlib.sha256(text.encode()).digest()


def is_loopback(host: str) -> bool:
    """True when ``host`` (an address or a name) only reaches this machine."""
    try:
        return ipaddress.ip_address(host).is_loopback
    except ValueError:
        pass
    try:
        infos = socket.getaddrinfo(host, None)
    except OSError:
        return False
    return bool(infos) and all(ipaddress.ip_address(i[4][0]).is_loopback for i in infos)


class FrameAuth:
    """The per-connection state of authenticated frames. ``side``: "driver" or "peer" (this
    end); ``nonce``: the connection's nonce (16 bytes) from the peer's hello."""

    def __init__(self, key: bytes, nonce: bytes, side: str):
        if side not in ("driver", "peer"):
            raise ValueError(f"side must be 'driver' or 'peer', got {side!r}")
        self.key, self.nonce = bytes(key), bytes(nonce)
        self._out, self._in = (b"D", b"P") if side == "driver" else (b"P", b"D")
        self._sent = self._received = 0

    def _tag(self, direction, counter, body) -> bytes:
        msg = _DOMAIN + direction + self.nonce + counter.to_bytes(8, "big") + body
        return hmac.new(self.key, msg, hashlib.sha256).digest()

    def seal(self, body: bytes) -> bytes:
        """tag + body for the next outgoing frame."""
        tag = self._tag(self._out, self._sent, body)
        self._sent += 1
        return tag + body

    def open(self, payload: bytes) -> bytes:
        """The body of the next incoming frame; AuthError when its tag does not match."""
        tag, body = payload[:TAG_BYTES], payload[TAG_BYTES:]
        if len(tag) < TAG_BYTES or not hmac.compare_digest(tag, self._tag(self._in, self._received, body)):
            raise AuthError("frame failed authentication (no token, a wrong token, or a replayed frame)")
        self._received += 1
        return body
