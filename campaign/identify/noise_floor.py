"""The tracker noise floor on the reports' history chart: the mean position error ‖Δt‖ (mm)
that measurement noise alone leaves to a perfect model.

The floor is campaign.measure.floor's (docs/effects.md, "The noise floor"): from repeated
measurements of the same joints and the drift checks' re-measurements, else from the tracker
noise the user states (``tracker: {noise_m: σ}``), carried through the rigid fit of the tool's
reflectors. A run measured on the simulated cell (it has RUN/sim/) that gives neither falls
back to the simulated tracker's configured noise ``sim.noise_m`` through the same fit (the
configuration, never the simulator's truth). For the COMAU's three reflectors and σ = 10 µm
per reflector coordinate that is 9.8 µm, not the 16 µm (σ·2√2/√π) of one measured point.
A held-out error can only approach the floor from above: the model's estimation error adds.
"""

from __future__ import annotations

from pathlib import Path

from campaign.measure.floor import NoiseFloor, floor_from_stated, noise_floor
from campaign.run import RunFolder


def tracker_noise_floor(run_dir, poses=None, robot=None):
    """The run's noise floor (campaign.measure.floor.NoiseFloor with a known
    ``mean_position_mm``) or None. poses: the run's MeasuredPoses, robot: its RobotModel
    (both loaded from the run folder when not given)."""
    run = RunFolder(run_dir)
    try:
        if robot is None:
            robot = run.robot()
        if poses is None:
            with run.store() as store:
                poses = store.load_measured()
        floor = noise_floor(run.path, poses, robot)
        if floor.known:
            return floor
        if Path(run.sim_dir).is_dir() and run.config.sim.noise_m:
            stated = floor_from_stated(float(run.config.sim.noise_m), robot.reflector_positions_in_E)
            return NoiseFloor("simulated", stated.sigma_position_m, stated.mean_position_mm, 0, 0.0,
                              f"the simulated tracker's configured noise sim.noise_m, "
                              f"σ {run.config.sim.noise_m * 1e6:.3g} µm per reflector coordinate")
    except Exception:  # a chart's reference line is never worth failing a report for
        return None
    return None


def floor_label(floor) -> str:
    """The floor in words for a legend: value, uncertainty and where it came from."""
    unc = f" ± {100 * floor.relative_uncertainty:.0f} %" if floor.relative_uncertainty else ""
    return f"{floor.mean_position_mm:.3g} mm{unc} ({floor.detail})"
