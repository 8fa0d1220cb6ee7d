"""Starting the simulated cell as a child process of the driver (`campaign run --sim`)."""

from __future__ import annotations

import json
import os
import subprocess
import sys
from pathlib import Path

from campaign.errors import CampaignError, PeerError


class SimulatedCell:
    """The simulated cell (``python -m campaign.sim.cell``) as a child process of the driver.

    It runs in its own session, so a Ctrl-C at the terminal reaches only the driver (which
    finishes the current pose); it watches its standard input, a pipe from this process,
    and exits when that closes: after :meth:`stop`, or when the driver dies, even by kill -9.
    Its stderr goes to ``RUN/sim/cell.log``. ``start_clock_s``: the simulated campaign clock
    to start from (s), the run's last stored time when a campaign is resumed.
    """

    def __init__(self, config_path, run_dir, *, start_clock_s: float = 0.0):
        log_path = Path(run_dir) / "sim" / "cell.log"
        log_path.parent.mkdir(parents=True, exist_ok=True)
        self.log_path = log_path
        # one BLAS thread: the cell's algebra is tiny, and idle OpenBLAS threads spinning on a
        # loaded machine make its start-up seconds instead of milliseconds
        env = {"OPENBLAS_NUM_THREADS": "1", "OMP_NUM_THREADS": "1", "MKL_NUM_THREADS": "1", **os.environ}
        with open(log_path, "ab") as err:
            self.proc = subprocess.Popen(
                [sys.executable, "-m", "campaign.sim.cell", "--config", str(config_path), "--run", str(run_dir),
                 "--start-clock-s", repr(float(start_clock_s)), "--watch-stdin"],
                stdin=subprocess.PIPE, stdout=subprocess.PIPE, stderr=err, start_new_session=True, env=env)
        line = self.proc.stdout.readline().decode()
        try:
            info = json.loads(line)
        except json.JSONDecodeError:
            self.stop()
            tail = log_path.read_text(errors="replace").strip().splitlines()
            raise PeerError(f"the simulated cell did not start: {tail[-1] if tail else 'no output'} "
                            f"(see {log_path})") from None
        if "error" in info:
            self.stop()
            raise CampaignError(f"simulated cell: {info['error']}")
        self.host = info["host"]
        self.controller = (self.host, int(info["controller"]))
        self.tracker = (self.host, int(info["tracker"]))
        self.truth_path = info["truth"]

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
