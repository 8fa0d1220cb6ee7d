"""The plausibility of a calibration (campaign.measure.plausibility), gathered for `calibrate`.

The data are checked again as the model sees them (registered, at the measured point), the
import's own warnings (those only the CSV could show, e.g. a rotation reading) are repeated,
and the fit is checked: corrections against the robot's size, the fitted noise against the
measured one, the held-out error against what a calibrated robot reaches.
"""

from __future__ import annotations

import numpy as np

from campaign.measure.importer import recorded_source
from campaign.measure.plausibility import Finding, check_data, check_fit, merge


def calibration_warnings(run_dir, robot, poses, model, heldout_mean_mm, noise_floor: dict | None) -> list:
    """Warnings (list of Finding) for a calibration of ``poses`` (as the model sees them) by
    ``model`` (the fitted geometric CalibrationModel of ``robot``); heldout_mean_mm: the current
    physical model's held-out mean position error; noise_floor: NoiseFloor.as_json() or None."""
    floor_mm = sigma_m = None
    if noise_floor and noise_floor.get("mean_position_mm") is not None:
        floor_mm = noise_floor["mean_position_mm"]
        sigma_m = float(np.mean(noise_floor["sigma_position_mm"])) * 1e-3
    data = check_data(robot, poses, noise_mm=floor_mm or None)
    recorded = [Finding.from_json(w) for w in recorded_source(run_dir).get("warnings") or []]
    fit = check_fit(robot, model.params_min_norm_, noise_sigma_m=model.noise_sigma_["position_m"],
                    heldout_mean_m=None if heldout_mean_mm is None else heldout_mean_mm * 1e-3, floor_sigma_m=sigma_m,
                    floor_source=(noise_floor or {}).get("source") or "stated")
    return merge(data, recorded, fit)


def with_checks(result, robot, poses, geo, stage: str):
    """``result`` (a CalibrationResult) with its plausibility ``warnings`` and its ``test_pose_ids``
    (the held-out poses' ids, in the order of ``poses``). geo: the fitted geometric model; stage:
    the current physical model's stage name (its held-out mean is checked)."""
    from dataclasses import replace

    test = result.stages.get(stage, {}).get("test", {})
    mean = test.get("position_mm", {}).get("mean")
    warnings = calibration_warnings(result.run_dir, robot, poses, geo, mean, result.noise_floor)
    return replace(result, warnings=tuple(warnings),
                   test_pose_ids=tuple(int(i) for i in poses.pose_id[np.asarray(result.is_test, dtype=bool)]))
