"""A served cell as a child process of the driver (`campaign run --cell SPEC`, `--sim`)."""

from __future__ import annotations

import json
import os
import subprocess
import sys
from pathlib import Path

from campaign.errors import CampaignError, ConfigError, PeerError


class CellProcess:
    """``python -m MODULE ARGS --watch-stdin`` (a cell server) as a child process of the driver.

    It runs in its own session, so a Ctrl-C at the terminal reaches only the driver (which
    finishes the current pose); it watches its standard input, a pipe from this process, and
    exits when that closes: after :meth:`stop`, or when the driver dies, even by kill -9. Its
    stderr goes to ``log_path``. Its ready line (JSON) is ``info``; ``controller`` and
    ``tracker`` are (host, port).
    """

    def __init__(self, module: str, args, log_path, what: str):
        log_path = Path(log_path)
        log_path.parent.mkdir(parents=True, exist_ok=True)
        self.log_path = log_path
        # one BLAS thread: the cell's algebra is tiny, and idle OpenBLAS threads spinning on a
        # loaded machine make its start-up seconds instead of milliseconds
        env = {"OPENBLAS_NUM_THREADS": "1", "OMP_NUM_THREADS": "1", "MKL_NUM_THREADS": "1", **os.environ}
        with open(log_path, "ab") as err:
            self.proc = subprocess.Popen(
                [sys.executable, "-m", module, *map(str, args), "--watch-stdin"],
                stdin=subprocess.PIPE, stdout=subprocess.PIPE, stderr=err, start_new_session=True, env=env)
        line = self.proc.stdout.readline().decode()
        try:
            info = json.loads(line)
        except json.JSONDecodeError:
            self.stop()
            tail = log_path.read_text(errors="replace").strip().splitlines()
            raise PeerError(f"{what} did not start: {tail[-1] if tail else 'no output'} (see {log_path})") from None
        if "error" in info:
            self.stop()
            raise CampaignError(f"{what}: {info['error']}")
        self.info = info
        self.host = info["host"]
        self.controller = (self.host, int(info["controller"]))
        self.tracker = (self.host, int(info["tracker"]))

    def stop(self):
        """Close the cell's stdin and wait for it to exit (killed after 10 s)."""
        try:
            if self.proc.stdin and not self.proc.stdin.closed:
                self.proc.stdin.close()
            self.proc.wait(timeout=10)
        except Exception:
            self.proc.kill()
            self.proc.wait()
        if self.proc.stdout:
            self.proc.stdout.close()

    def __enter__(self):
        return self

    def __exit__(self, *exc):
        self.stop()


def cell_specs(spec: str) -> tuple:
    """(controller spec, tracker spec) of ``campaign run --cell SPEC``: ``sim``, ``mujoco``, a
    FILE.py or module holding classes ``Controller`` and ``Tracker``, or an entry point."""
    spec = str(spec).strip()
    if not spec:
        raise ConfigError("--cell: empty spec (sim, mujoco, FILE.py with classes Controller and Tracker, ...)")
    src, sep, cls = spec.rpartition(":")
    if sep and cls.isidentifier() and src:
        raise ConfigError(f"--cell {spec}: --cell names a file or module holding classes Controller and Tracker; "
                          f"for other class names serve it yourself (`campaign serve --controller {src}:... "
                          f"--tracker {src}:...`) and drive it with --controller/--tracker")
    return spec, spec


class ServeProcess(CellProcess):
    """`campaign serve --controller C --tracker T --run RUN` as a child of the driver; its log
    is RUN/cell/serve.log. ``options``: the adapters' options file or None."""

    def __init__(self, spec, config_path, run_dir, *, start_clock_s: float = 0.0, options=None):
        controller, tracker = cell_specs(spec)
        args = ["--controller", controller, "--tracker", tracker, "--config", config_path, "--run", run_dir,
                "--start-clock-s", repr(float(start_clock_s))]
        if options is not None:
            args += ["--options", Path(options).resolve()]
        super().__init__("campaign.cell.server", args, Path(run_dir) / "cell" / "serve.log", f"cell {spec}")
