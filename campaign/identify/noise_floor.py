"""The tracker noise floor on the reports' history chart: the mean position error ‖Δt‖ (mm)
that measurement noise alone leaves to a perfect model.

The floor is campaign.measure.floor's (docs/effects.md, "The noise floor"), the one every text
states: from back-to-back repeated measurements of the same joints (and, as an upper bound, the
drift checks' re-measurements), else from the tracker noise the user states
(``tracker: {noise_m: σ}``), carried through the rigid fit of the tool's reflectors; else none.
The simulator's configured noise (``sim.noise_m``) is never a floor: a chart and a text that
disagree on the floor were a report contradicting itself. For the COMAU's three reflectors and
σ = 10 µm per reflector coordinate the stated floor is 9.8 µm, not the 16 µm (σ·2√2/√π) of one
measured point. A held-out error can only approach the floor from above: the model's
estimation error adds.
"""

from __future__ import annotations

from campaign.measure.floor import noise_floor
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
    except Exception:  # a chart's reference line is never worth failing a report for
        return None
    return None


def floor_label(floor) -> str:
    """The floor in words for a legend: value, uncertainty and where it came from."""
    unc = f" ± {100 * floor.relative_uncertainty:.0f} %" if floor.relative_uncertainty else ""
    return f"{floor.mean_position_mm:.3g} mm{unc} ({floor.detail})"
