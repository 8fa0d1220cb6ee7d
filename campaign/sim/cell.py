"""The simulated cell's world, served as the adapters ``sim`` (campaign.sim.adapters) by the
framework of `campaign serve` (campaign.cell.server), like any cell.

Both adapters share one world: a truth robot (nominal + hidden geometric errors + hidden
physical effects), the true pose of the tracker (from the scene), tracker noise, motion that
takes Ruckig's time plus a settle time, tracker time per target, and a simulated clock. The
truth is drawn from a seed and written to the simulator's own file (``RUN/sim/truth.yaml``),
which `plan`, `calibrate` and `diagnose` never read.

Faults are injected with configurable rates; each decision is drawn from a generator seeded
by (seed, request id), so a campaign re-run with the same requests meets the same faults.

    python -m campaign.sim.cell --config RUN/campaign.yaml --run RUN [--watch-stdin]

prints one JSON line ``{"controller": PORT, "tracker": PORT, "host": HOST, "truth": PATH}`` when ready.
With ``--watch-stdin`` it exits when its standard input closes (its parent died or is done).
"""

from __future__ import annotations

import json
import sys
import threading
import time
from pathlib import Path

import numpy as np

from campaign.cell import RobotFault
from campaign.config import FAULT_KINDS, CampaignConfig, parse_faults  # noqa: F401 (re-exported)
from campaign.effects.base import make_effect
from campaign.measure.reflectors import transform_points
from campaign.plan.scene import load_scene
from campaign.plan.timing import rest_to_rest_time
from campaign.run import load_robot
from campaign.sim.truth import hidden_effect_params, make_truth, write_truth

_KIND_CODE = {k: i + 1 for i, k in enumerate(FAULT_KINDS)}
#: distances of the base-frame set-up points from F_I's origin along x and y (m)
SETUP_SPACING_M = 0.3


class World:
    """The physical state shared by both adapters. All methods hold the lock."""

    def __init__(self, cfg: CampaignConfig, run_dir, start_clock_s: float = 0.0):
        sc = cfg.sim
        # the reflectors `campaign run` measures: robot.yaml's, or the default triad
        self.robot = load_robot(cfg.robot_spec, tool_frame=cfg.tool_frame,
                                base_frame=cfg.base_frame).with_default_reflectors()
        self.scene = load_scene(cfg.scene_path).placed(self.robot)
        self.seed = sc.seed
        hidden = {spec: hidden_effect_params(make_effect(spec, self.robot), self.seed, params)
                  for spec, params in cfg.hidden_effects()}
        self.truth = make_truth(self.robot, seed=self.seed, noise_m=sc.noise_m, effects=hidden,
                                T_LI=self.scene.T_LI)
        self.settle_s = cfg.plan.settle_time_s
        self.tracker_s = cfg.plan.tracker_time_per_reflector_s
        self.time_factor = sc.time_factor
        self.faults, self.late_delay_s = dict(sc.faults), sc.late_delay_s
        #: the simulated campaign clock (s); a resumed campaign continues from its last stored time
        self.clock_s = float(start_clock_s)
        self.q = np.array(self.robot.q_mid)
        self.last_temperature_c = None
        self.lock = threading.Lock()
        self.truth_path = Path(run_dir) / "sim" / "truth.yaml"
        self.truth_path.parent.mkdir(parents=True, exist_ok=True)
        write_truth(self.truth, self.truth_path)
        # an emergency stop happens once: the operator resets it, and the re-run passes that move
        self.estops_path = self.truth_path.parent / "estops.json"
        self.estops = set(json.loads(self.estops_path.read_text())) if self.estops_path.is_file() else set()
        self.setup_I = {"setup_origin": np.zeros(3), "setup_x": np.array([SETUP_SPACING_M, 0, 0]),
                        "setup_y": np.array([0, SETUP_SPACING_M, 0])}
        self.reflectors = {r.name: np.array(r.position_in_E) for r in self.robot.reflectors}

    def fault(self, kind, request_id) -> bool:
        rate = self.faults.get(kind, 0.0)
        if rate <= 0:
            return False
        return np.random.default_rng([self.seed, _KIND_CODE[kind], int(request_id)]).random() < rate

    def _advance(self, dt):
        self.clock_s += dt
        if self.time_factor > 0:
            time.sleep(dt * self.time_factor)

    def context(self):
        ctx = {"time_s": np.array([self.clock_s])}
        ctx["temperature_c"] = np.array([20.0 + 5.0 * np.sin(2 * np.pi * self.clock_s / 86400.0)])
        return ctx

    def move(self, q, request_id):
        """Move to q (N,) rad (model convention) for request ``request_id``; the simulated clock
        advances by Ruckig's time plus the settle time. RobotFault for an injected fault."""
        q = np.array(q, dtype=float)
        if request_id not in self.estops and self.fault("estop", request_id):
            with self.lock:
                self.estops.add(request_id)
                self.estops_path.write_text(json.dumps(sorted(self.estops)))
            raise RobotFault("emergency stop pressed", code="emergency_stop")
        if self.fault("robot_fault", request_id):
            raise RobotFault("drive reported a following error; move not executed")
        with self.lock:
            dt = float(rest_to_rest_time(self.robot, self.q[None], q[None])[0]) + self.settle_s
            self._advance(dt)
            self.q = q

    def measure(self, targets, request_id) -> dict:
        """{target: (3,) m in F_L, or "beam_lost" / "out_of_range"} for request ``request_id``;
        the pose is sampled when the measurement starts, its temperature kept in
        ``last_temperature_c``; the clock advances by the tracker time per target."""
        with self.lock:
            rng = np.random.default_rng([self.seed, 99, int(request_id)])
            ctx = self.context()
            self.last_temperature_c = float(ctx["temperature_c"][0])
            T_LE = self.truth.T_LI @ self.truth.pose(self.q[None], ctx)[0]
            out = {}
            for k, target in enumerate(targets):
                self._advance(self.tracker_s)
                if target in self.reflectors:
                    p = transform_points(T_LE, self.reflectors[target][None])[0]
                else:
                    p = transform_points(self.truth.T_LI, self.setup_I[target][None])[0]
                if self.fault("beam_lost", request_id * 16 + k):
                    out[target] = "beam_lost"
                    continue
                dist = np.linalg.norm(p - 0.0)
                if not self.scene.min_range_m <= dist <= self.scene.max_range_m:
                    out[target] = "out_of_range"
                    continue
                if self.truth.noise_m > 0:
                    p = p + rng.normal(0.0, self.truth.noise_m, 3)
                if self.truth.resolution_m > 0 and self.truth.noise_m > 0:
                    p = np.round(p / self.truth.resolution_m) * self.truth.resolution_m
                out[target] = p
            return out

    def transport_fault(self, request_id, attempt):
        """"drop", "garble" or None for the reply to (request_id, attempt); a "late" reply is
        held back here (late_delay_s)."""
        key = (request_id * 8 + attempt) * 4
        if self.fault("drop", key + 1):
            return "drop"
        if self.fault("late", key + 2):
            time.sleep(self.late_delay_s)
        if self.fault("garble", key + 3):
            return "garble"
        return None


def start_cell(cfg, run_dir, host="127.0.0.1", controller_port=0, tracker_port=0, start_clock_s=0.0):
    """Serve the simulated cell in this process (threads): ``campaign serve --controller sim
    --tracker sim``. Returns (world, the started campaign.cell.server.ServedCell).

    cfg: a validated CampaignConfig; start_clock_s: the simulated clock to start from (s)."""
    from campaign.cell.server import open_cell

    cell = open_cell("sim", "sim", cfg, run_dir=run_dir, host=host, controller_port=controller_port,
                     tracker_port=tracker_port, start_clock_s=start_clock_s)
    return cell.ctx.shared["world"], cell


def main(argv=None):
    """``python -m campaign.sim.cell [--config F] [--run DIR] [--host H] [--controller-port P]
    [--tracker-port P] [--start-clock-s T] [--watch-stdin]``: ``python -m campaign.cell.server
    --controller sim --tracker sim`` with the run defaulting to runs/sim."""
    from campaign.cell.server import main as serve_main

    argv = list(sys.argv[1:] if argv is None else argv)
    if not any(a == "--run" or a.startswith("--run=") for a in argv):
        argv += ["--run", "runs/sim"]
    return serve_main(["--controller", "sim", "--tracker", "sim", *argv], prog="python -m campaign.sim.cell")


if __name__ == "__main__":
    sys.exit(main())
