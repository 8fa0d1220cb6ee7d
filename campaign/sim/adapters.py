"""The simulated cell as the adapters ``sim`` (docs/cell.md): a controller and a tracker sharing
one :class:`campaign.sim.cell.World`, built from the served run's configuration on first use.

They use the hooks a simulator needs beyond the contract: the world's simulated clock, the
request id (faults and noise are drawn from the seed and the id, so a re-run meets the same),
the air temperature at the sample, and injected transport faults (``sim.faults``).
"""

from __future__ import annotations

from campaign.cell import context, request_id
from campaign.errors import ConfigError


def world():
    """The cell's one World (``context().shared["world"]``), built on first use."""
    from campaign.sim.cell import World

    ctx = context()
    w = ctx.shared.get("world")
    if w is None:
        if ctx.config is None or ctx.run_dir is None:
            raise ConfigError("the simulated cell serves a run: give --run DIR (its campaign.yaml configures the "
                              "cell: robot, scene, hidden errors)")
        w = ctx.shared["world"] = World(ctx.config, ctx.run_dir, ctx.start_clock_s)
        ctx.shared.setdefault("announce", {})["truth"] = str(w.truth_path)
    return w


class _Simulated:
    joint_convention = "model"

    def __init__(self, robot, options):
        if options:
            raise ConfigError(f"the simulated cell takes no options (got {', '.join(map(str, options))}); "
                              "it is configured by the run's campaign.yaml (sim:)")
        self.world = world()

    def clock(self):
        """The simulated campaign clock (s)."""
        return self.world.clock_s

    def transport_fault(self, rid, attempt):
        return self.world.transport_fault(rid, attempt)


class Controller(_Simulated):
    """The simulated robot: Ruckig's motion time plus the settle time on the simulated clock."""

    def move(self, q):
        self.world.move(q, request_id())


class Tracker(_Simulated):
    """The simulated tracker: the truth robot's reflectors with noise, beam losses, range."""

    def measure(self, aims):
        return self.world.measure(list(aims), request_id())

    def temperature_c(self):
        return self.world.last_temperature_c
