"""Starting the simulated cell as a child process of the driver (`campaign run --sim`)."""

from __future__ import annotations

from pathlib import Path

from campaign.cell.launcher import CellProcess


class SimulatedCell(CellProcess):
    """The simulated cell (``python -m campaign.sim.cell``, i.e. `campaign serve --controller sim
    --tracker sim`) as a child process of the driver (see CellProcess). Its stderr goes to
    ``RUN/sim/cell.log``. ``start_clock_s``: the simulated campaign clock to start from (s), the
    run's last stored time when a campaign is resumed."""

    def __init__(self, config_path, run_dir, *, start_clock_s: float = 0.0):
        super().__init__("campaign.sim.cell", ["--config", config_path, "--run", run_dir,
                                               "--start-clock-s", repr(float(start_clock_s))],
                         Path(run_dir) / "sim" / "cell.log", "the simulated cell")
        self.truth_path = self.info["truth"]
