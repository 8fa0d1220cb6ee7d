"""The neural residual stages of `campaign calibrate` (the paper's section 5).

Two variants, as in the paper's Tables 5 and 6: the network learns the residual of the
nominal model (stage ``ann``) or of the identified model (stage ``<model>+ann``, e.g.
``geometric+ann``). For each, hidden sizes are chosen by K-fold cross-validation on the
training set only, the best size is retrained on the whole training set, and the test set
is evaluated once, at the end.
"""

from __future__ import annotations

import dataclasses
import html
import json
from pathlib import Path

import numpy as np

from campaign.errors import ConfigError
from campaign.model.kinematics import pose_error

#: hidden sizes tried by default: the paper's four and one beyond
DEFAULT_SIZES = ((16, 16), (32, 16), (32, 32), (64, 32), (128, 64))


def parse_sizes(text: str) -> tuple:
    """``"16x16,32x16"`` -> ((16, 16), (32, 16))."""
    sizes = []
    for item in str(text).split(","):
        item = item.strip().lower()
        if not item:
            continue
        try:
            n1, n2 = (int(v) for v in item.split("x"))
        except ValueError:
            raise ConfigError(f"--sizes: '{item}' is not of the form N1xN2 (e.g. 64x32)") from None
        if n1 < 1 or n2 < 1:
            raise ConfigError(f"--sizes: '{item}' must have positive sizes")
        sizes.append((n1, n2))
    if not sizes:
        raise ConfigError("--sizes: no hidden sizes given")
    return tuple(sizes)


def format_table5(cv: dict) -> str:
    """Cross-validation results like the paper's Table 5, one block per variant."""
    lines = [f"{'hidden neurons':<16}{'RMSE Δz_tot':>14}{'max ‖Δr‖ mm':>14}{'max ‖Δφ‖ mrad':>15}  {'prior model':<20}"]
    for variant, block in cv.items():
        for row in block["sizes"]:
            mark = " *" if tuple(row["hidden"]) == tuple(block["best"]) else ""
            lines.append(f"{str(tuple(row['hidden'])):<16}{row['rmse_normalised']:>14.3f}"
                         f"{row['max_position_mm']:>14.3f}{row['max_orientation_mrad']:>15.3f}  {variant:<20}{mark}")
    lines.append("* best by cross-validation (lowest RMSE of the normalised Δz_tot), retrained on the whole training set")
    return "\n".join(lines)


def run_ann_stages(run_dir, robot, poses, is_test, T_prior: dict, options: dict, progress=None):
    """Train the residual networks; return ({stage: Δz (n, 6)}, extra).

    T_prior: stage name of the prior model -> its poses (n, 4, 4) for every measured pose,
    e.g. {"nominal": ..., "geometric": ...}. The ANN stage after "nominal" is called
    ``ann``; after any other model ``<model>+ann``.
    """
    try:
        from campaign.ann import compensate_pose, fit_ann_stage
    except ImportError as exc:
        raise ConfigError(f"the neural compensator is unavailable ({exc}); run with --no-ann") from None

    out = Path(run_dir) / "calibration"
    out.mkdir(parents=True, exist_ok=True)
    tr = ~np.asarray(is_test, dtype=bool)
    sizes = tuple(options.get("sizes", DEFAULT_SIZES))
    folds = int(options.get("folds", 5))
    fit_kwargs = {k: v for k, v in options.items() if k not in ("sizes", "folds")}
    residuals, cv_all, files = {}, {}, {}
    for prior, T_model in T_prior.items():
        stage = "ann" if prior == "nominal" else f"{prior}+ann"
        dz = pose_error(T_model, poses.T_IE)
        say = (lambda msg, _s=stage: progress(f"[{_s}] {msg}" if isinstance(msg, str)
                                              else dataclasses.replace(msg, stage=_s))) if progress else None
        net, cv = fit_ann_stage(poses.q[tr], dz[tr], sizes=sizes, folds=folds, progress=say,
                                q_lower=robot.q_lower, q_upper=robot.q_upper, **fit_kwargs)
        dz_hat = net.predict(poses.q)
        residuals[stage] = pose_error(compensate_pose(T_model, dz_hat), poses.T_IE)
        cv_all[prior] = cv
        fname = "ann_nominal.pt" if prior == "nominal" else "ann_geometric.pt"
        net.save(out / fname)
        files[stage] = fname
    (out / "ann_cv.json").write_text(json.dumps(cv_all, indent=2))
    table5 = format_table5(cv_all)
    extra = {"ann_cv": cv_all, "ann_files": files, "table5": table5,
             "report_html": "<h2>Cross-validation of the residual network (Table 5)</h2>"
                            f"<pre>{html.escape(table5)}</pre>"}
    return residuals, extra
