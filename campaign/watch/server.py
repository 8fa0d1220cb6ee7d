"""The live page's web server: the standard library's ThreadingHTTPServer over a :class:`RunView`.

Routes (GET only):

* ``/``: the page (``assets/index.html`` with its script and style, all in the package: no CDN);
* ``/api/status``: ``{measured, failed, planned, eta_s, state, campaign_h, last_pose, drift}``;
* ``/api/poses[?from=K]``: the stored poses from position K in visiting order (a list);
* ``/api/details``: drift checks, warnings, stops, auto's rounds, the reports present;
* ``/run/<folder>/<file>``: the reports' files (calibration, diagnose, iso9283, auto, plan only).

Beyond loopback a shared secret is required (``--token-file``, as for `campaign serve`): the
browser gives it once as ``?token=...`` and is answered with a cookie (HttpOnly, SameSite=Strict,
a keyed hash of the token, not the token); the page then takes the token out of its address
(``history.replaceState``). Every request with neither is refused (401). Every answer is strict JSON or a file of the package or the run: nothing from a
request is evaluated.
"""

from __future__ import annotations

import hashlib
import hmac
import mimetypes
import socket
import threading
import time
from http.cookies import CookieError, SimpleCookie
from http.server import BaseHTTPRequestHandler, ThreadingHTTPServer
from importlib import resources
from urllib.parse import parse_qs, unquote, urlsplit

from campaign.errors import ConfigError
from campaign.measure.auth import is_loopback
from campaign.watch.view import RunView, strict_json

DEFAULT_PORT = 8765
#: the cookie's name, followed by the port: a browser keeps one cookie per host whatever the port,
#: so two watchers on one machine (two runs, two tokens) would otherwise overwrite each other's
COOKIE = "campaign_watch"
#: how long a browser keeps the cookie (s): a campaign's days and then some, across browser
#: restarts (a session cookie asked for the token again after each)
COOKIE_MAX_AGE_S = 30 * 86400
#: the page's own files (campaign/watch/assets), by URL path
ASSETS = {"/": "index.html", "/watch.js": "watch.js", "/watch.css": "watch.css"}
#: how long `--watch` keeps serving after the run ended when a page was open (s): the pages poll
#: every POLL_S and so see the final state
LINGER_S = 3.0
POLL_S = 0.5  # assets/watch.js POLL_MS
_CSP = "default-src 'self'; img-src 'self' data:; style-src 'self'; script-src 'self'; frame-ancestors 'none'"


def require_token(host: str, key) -> None:
    """ConfigError (one line) when ``host`` is beyond loopback and no shared secret is given."""
    if key is None and not is_loopback(host):
        raise ConfigError(f"--host {host}: the page would show the campaign to anyone who reaches the port; give a "
                          "shared secret (--token-file FILE) and open http://HOST:PORT/?token=<its text> once")


def _asset(name: str) -> bytes:
    return resources.files("campaign.watch").joinpath("assets", name).read_bytes()


class WatchServer:
    """The live page of run ``run_dir`` on ``host:port`` (port 0: any free port). ``key``: the
    shared secret (campaign.measure.auth.read_token) or None; required beyond loopback.
    ``option``: the command-line option the port came from, for the error when it is taken."""

    def __init__(self, run_dir, *, host: str = "127.0.0.1", port: int = DEFAULT_PORT, key: bytes | None = None,
                 option: str = "--port"):
        require_token(host, key)
        self.view = RunView(run_dir)
        self.view.prepare()
        self.key = key
        self.cookie_value = hmac.new(key, b"campaign-watch-cookie-v1", hashlib.sha256).hexdigest() if key else None
        self.last_request = -float("inf")
        #: what serving has cost: requests answered and the CPU seconds their threads used
        self.cost = {"requests": 0, "cpu_s": 0.0}
        self._cost_guard = threading.Lock()
        handler = type("Handler", (_Handler,), {"watch": self})
        server_class = type("Server", (ThreadingHTTPServer,), {
            "address_family": socket.AF_INET6 if ":" in host else socket.AF_INET, "daemon_threads": True,
            "allow_reuse_address": True})
        try:
            self.httpd = server_class((host, int(port)), handler)
        except OSError as exc:
            raise ConfigError(f"{option} {port} on {host}: cannot bind ({exc.strerror or exc}); is another watcher "
                              "serving there? give another port") from None
        self.host, self.port = host, self.httpd.server_address[1]
        self.cookie_name = f"{COOKIE}_{self.port}"
        self._thread = None

    @property
    def url(self) -> str:
        host = f"[{self.host}]" if ":" in self.host else self.host
        return f"http://{host}:{self.port}/"

    def start(self) -> "WatchServer":
        """Serve in a background (daemon) thread."""
        self._thread = threading.Thread(target=self.httpd.serve_forever, kwargs={"poll_interval": 0.25},
                                        name="campaign-watch", daemon=True)
        self._thread.start()
        return self

    def stop(self, *, linger: bool = False) -> None:
        """Stop serving; ``linger``: first keep serving up to LINGER_S while a page is polling."""
        if linger:
            end = time.monotonic() + LINGER_S
            while time.monotonic() < end and time.monotonic() - self.last_request < 2 * POLL_S + LINGER_S:
                time.sleep(0.1)
        if self._thread is not None:
            self.httpd.shutdown()
            self._thread.join()
        self.httpd.server_close()

    def serve_until_interrupted(self) -> int:
        """Serve in this thread until Ctrl-C; 0."""
        try:
            self.httpd.serve_forever(poll_interval=0.25)
        except KeyboardInterrupt:
            pass
        finally:
            self.httpd.server_close()
        return 0


class _Handler(BaseHTTPRequestHandler):
    watch: WatchServer
    server_version = "campaign-watch"
    sys_version = ""

    def log_message(self, format, *args):  # noqa: A002 (the base class's name): no line per request
        pass

    def do_GET(self):  # noqa: N802 (the base class's name)
        w = self.watch
        w.last_request = time.monotonic()
        cpu0 = time.thread_time()
        try:
            self._get()
        finally:
            with w._cost_guard:
                w.cost["requests"] += 1
                w.cost["cpu_s"] += time.thread_time() - cpu0

    def _get(self):
        w = self.watch
        url = urlsplit(self.path)
        query = parse_qs(url.query)
        if w.key is not None and not self._authorised(url, query):
            return
        path = url.path
        try:
            if path == "/favicon.ico":  # asked by the browser for every page (the reports' too): none
                return self._send(204, b"", "image/x-icon")
            if path in ASSETS:
                return self._send(200, _asset(ASSETS[path]), _type(ASSETS[path]), csp=True)
            if path == "/api/status":
                return self._json(w.view.status())
            if path == "/api/poses":
                start = query.get("from", ["0"])[0]
                if not start.isdigit():
                    return self._send(400, b"from: expected a non-negative integer\n", "text/plain; charset=utf-8")
                return self._json(w.view.poses(int(start)))
            if path == "/api/details":
                with w._cost_guard:
                    cost = dict(w.cost)
                return self._json({**w.view.details(), "watcher": cost})
            if path.startswith("/run/"):
                file = w.view.served_file(path[len("/run/"):])
                if file is not None:
                    return self._send(200, file.read_bytes(), _type(file.name))
            return self._send(404, b"not found\n", "text/plain; charset=utf-8")
        except (BrokenPipeError, ConnectionResetError):
            pass

    def _authorised(self, url, query) -> bool:
        """True with the cookie, or with the right ?token= (the answer then sets the cookie)."""
        w = self.watch
        self._set_cookie = False
        try:
            jar = SimpleCookie(self.headers.get("Cookie") or "")
        except CookieError:
            jar = SimpleCookie()
        name = w.cookie_name
        if name in jar and hmac.compare_digest(jar[name].value.encode(), w.cookie_value.encode()):
            return True
        # the token as a form decodes it, and as typed: a base64 token's '+' pasted into the
        # address bar is a '+', not the space a form's encoding makes of it
        typed = [unquote(v) for k, _, v in (p.partition("=") for p in url.query.split("&")) if k == "token"]
        for token in query.get("token", []) + typed:
            if token.strip() and hmac.compare_digest(hashlib.sha256(token.strip().encode()).digest(), w.key):
                self._set_cookie = True
                return True
        self._send(401, b"campaign watch: open this page once as http://HOST:PORT/?token=<the text of the token "
                        b"file>; the browser then keeps a cookie\n", "text/plain; charset=utf-8")
        return False

    def _json(self, doc):
        self._send(200, strict_json(doc), "application/json")

    def _send(self, code, body: bytes, ctype: str, *, csp: bool = False):
        self.send_response(code)
        self.send_header("Content-Type", ctype)
        self.send_header("Content-Length", str(len(body)))
        self.send_header("Cache-Control", "no-store")
        self.send_header("X-Content-Type-Options", "nosniff")
        self.send_header("Referrer-Policy", "no-referrer")
        if csp:
            self.send_header("Content-Security-Policy", _CSP)
        if getattr(self, "_set_cookie", False) and code == 200:
            self.send_header("Set-Cookie", f"{self.watch.cookie_name}={self.watch.cookie_value}; HttpOnly; "
                                           f"SameSite=Strict; Path=/; Max-Age={COOKIE_MAX_AGE_S}")
        self.end_headers()
        self.wfile.write(body)


def _type(name: str) -> str:
    ctype = {".js": "text/javascript", ".css": "text/css", ".html": "text/html", ".svg": "image/svg+xml",
             ".json": "application/json"}.get("." + name.rpartition(".")[2]) or mimetypes.guess_type(name)[0]
    ctype = ctype or "application/octet-stream"
    return ctype + "; charset=utf-8" if ctype.startswith("text/") else ctype


__all__ = ["WatchServer", "DEFAULT_PORT", "require_token"]
