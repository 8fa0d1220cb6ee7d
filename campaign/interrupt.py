"""A Ctrl-C that a library swallows is not lost.

Python turns SIGINT into a KeyboardInterrupt raised wherever the main thread happens to be. A
library that catches ``BaseException`` there (trimesh has over a hundred such blocks, several in
the mesh code the plan's filters call for every piece) swallows it, and the command runs on to the
end as if nothing happened (`campaign plan` finished normally after Ctrl-C in 3 of 9 trials). The
command line installs :func:`install`: the handler records the interrupt before raising it, and
long computations call :func:`check` at their stage boundaries, which raises it again.
"""

from __future__ import annotations

import signal
import threading

_pending = threading.Event()


def _handler(signum, frame):
    _pending.set()
    raise KeyboardInterrupt


def install() -> None:
    """Record every SIGINT before raising it (only where Python's default handler is in force, on
    the main thread: a SIGINT that is ignored, e.g. under nohup, stays ignored). Clears a recorded one."""
    _pending.clear()
    if threading.current_thread() is not threading.main_thread():
        return
    if signal.getsignal(signal.SIGINT) is signal.default_int_handler:
        signal.signal(signal.SIGINT, _handler)


def uninstall() -> None:
    """Python's default handler again (when ours is in force)."""
    if threading.current_thread() is threading.main_thread() and signal.getsignal(signal.SIGINT) is _handler:
        signal.signal(signal.SIGINT, signal.default_int_handler)


def check() -> None:
    """Raise KeyboardInterrupt when a SIGINT came and was swallowed on its way up (once)."""
    if _pending.is_set():
        _pending.clear()
        raise KeyboardInterrupt
