"""`campaign watch RUN [--host H] [--port P] [--token-file F]`, and ``--watch [PORT]`` of
`campaign run` and `campaign auto` (docs/watch.md)."""

from __future__ import annotations

import contextlib
import sys

DEFAULT_PORT = 8765  # campaign.watch.server.DEFAULT_PORT, here so that --help imports nothing


def register(sub):
    p = sub.add_parser(
        "watch", help="the live page of a run: progress, failures, drift, residuals, auto's rounds, in a browser",
        description="Serve a page that follows RUN while it is measured (or after): measured / failed / planned, "
                    "campaign clock, rate and ETA, failures and where they happen, drift checks, each pose's "
                    "residual against the nominal and the calibrated model over time and in 3-D, auto's rounds, "
                    "links to the reports; JSON at /api/status and /api/poses. The log is only read; the run is "
                    "never locked. Beyond loopback --token-file is required: open http://HOST:PORT/?token=<its text> "
                    "once, the browser keeps a cookie (docs/watch.md). Ctrl-C stops.")
    p.add_argument("run", metavar="RUN", help="run folder (planned, running or done)")
    p.add_argument("--host", default="127.0.0.1", help="address to bind (default: %(default)s; any other needs "
                                                       "--token-file)")
    p.add_argument("--port", type=int, default=DEFAULT_PORT, help="port (default: %(default)s; 0: any free port)")
    p.add_argument("--token-file", metavar="FILE", default=None,
                   help="shared secret (at least 16 characters): required beyond loopback; the page asks for it "
                        "once as ?token=<its text>")
    p.set_defaults(func=_watch)


def add_watch_argument(p) -> None:
    """``--watch [PORT]`` for `campaign run` and `campaign auto`."""
    p.add_argument("--watch", nargs="?", type=int, const=DEFAULT_PORT, default=None, metavar="PORT",
                   help=f"serve the live page on 127.0.0.1:PORT (default {DEFAULT_PORT}) while this command runs "
                        "(`campaign watch RUN --host ... --token-file F` for another machine)")


def _watch(args):
    from campaign.errors import ConfigError, DataError
    from campaign.measure.auth import read_token
    from campaign.watch.server import WatchServer, require_token
    from campaign.watch.view import run_folder_error

    if not 0 <= args.port < 65536:
        raise ConfigError(f"--port {args.port}: expected 0..65535")
    key = read_token(args.token_file) if args.token_file else None
    require_token(args.host, key)  # before anything else is looked at
    problem = run_folder_error(args.run)
    if problem:
        raise DataError(problem)
    server = WatchServer(args.run, host=args.host, port=args.port, key=key)
    auth = "open it once with ?token=<the token file's text>" if key else "loopback, no token"
    url = server.url
    if args.host in ("0.0.0.0", "::", ""):  # an address to bind, not one a browser can open
        url = f"http://<this machine's name or address>:{server.port}/ (every interface)"
    print(f"watching {args.run}: {url} ({auth}); Ctrl-C stops", flush=True)
    server.view.refresh(force=True)
    if server.view.log_error:  # the page says it too, as its state
        print(f"warning: {server.view.log_error}", file=sys.stderr, flush=True)
    return server.serve_until_interrupted()


@contextlib.contextmanager
def watching(run_dir, port):
    """Serve the live page of ``run_dir`` on 127.0.0.1:``port`` for the block (``port`` None:
    nothing); at the end it keeps serving a few seconds while a page polls, so the page shows
    how the command ended."""
    if port is None:
        yield None
        return
    from campaign.errors import ConfigError
    from campaign.watch.server import WatchServer

    if not 0 <= port < 65536:
        raise ConfigError(f"--watch {port}: expected a port in 0..65535")
    server = WatchServer(run_dir, port=port, option="--watch").start()
    print(f"watching {run_dir}: {server.url}", file=sys.stderr, flush=True)
    try:
        yield server
    finally:
        server.stop(linger=True)
