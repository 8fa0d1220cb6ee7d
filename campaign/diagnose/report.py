"""Plots and the HTML report of `campaign diagnose`: RUN/diagnose/report.html."""

from __future__ import annotations

import html
import json
from pathlib import Path

import numpy as np

from campaign.fileio import atomic_write
from campaign.identify.report import _plt, plot_against_joints, plot_history, plot_workspace


def plot_against_context(residuals, series: dict, is_test, out: Path, name: str = "residual_context.png") -> str:
    """‖Δt‖ (mm) of the current model against time, temperature and gravity loads."""
    plt = _plt()
    pos = np.linalg.norm(residuals[:, :3], axis=1) * 1e3
    fig, axes = plt.subplots(1, len(series), figsize=(4.2 * len(series), 3.6), sharey=True)
    axes = np.atleast_1d(axes)
    for ax, (label, x) in zip(axes, series.items()):
        ax.scatter(x[~is_test], pos[~is_test], s=2, alpha=0.3, color="0.6", label="train")
        ax.scatter(x[is_test], pos[is_test], s=3, alpha=0.6, color="C1", label="test")
        ax.set_xlabel(label)
    axes[0].set_ylabel("‖Δt‖ of the current model [mm]")
    axes[0].legend(fontsize=7, markerscale=3)
    fig.suptitle("residual against time, temperature and gravity load")
    fig.tight_layout()
    fig.savefig(out / name, dpi=100)
    plt.close(fig)
    return name


def plot_ranking(diagnosis, out: Path, name: str = "ranking.png") -> str:
    plt = _plt()
    fig, ax = plt.subplots(figsize=(8, 0.5 + 0.45 * max(len(diagnosis.ranking), 1)))
    labels = [c.effect for c in diagnosis.ranking][::-1]
    after = [c.heldout_mean_position_mm_after for c in diagnosis.ranking][::-1]
    colors = ["C2" if c.significant else "0.7" for c in diagnosis.ranking][::-1]
    ax.barh(labels, after, color=colors)
    if diagnosis.ranking:
        ax.axvline(diagnosis.ranking[0].heldout_mean_position_mm_before, color="k", ls="--", label="current model")
        ax.legend(fontsize=8)
    ax.set_xlabel("held-out mean ‖Δt‖ with the candidate added [mm] (green: significant)")
    fig.tight_layout()
    fig.savefig(out / name, dpi=110)
    plt.close(fig)
    return name


def write_diagnosis(diagnosis, *, report: bool = True) -> Path:
    """Write RUN/diagnose/diagnosis.json (what `diagnose --json` prints) and, with ``report``,
    RUN/diagnose/report.html and its PNGs; returns the report's path (or the JSON's)."""
    from campaign.run import RunFolder

    run = RunFolder(diagnosis.run_dir)
    if not report:
        return atomic_write(run.diagnose_dir / "diagnosis.json", json.dumps(diagnosis.as_json(), indent=2))
    with run.store() as store:
        poses = store.load_measured()
    return write_report(diagnosis, poses, run.robot())


def write_report(diagnosis, poses, robot) -> Path:
    """Write RUN/diagnose/report.html, its PNGs and diagnosis.json; return the HTML path."""
    from campaign.effects._gravity import gravity_torques, overturning_moment

    out = Path(diagnosis.run_dir) / "diagnose"
    out.mkdir(parents=True, exist_ok=True)
    res, is_test = diagnosis.residuals, diagnosis.is_test
    title = "current model"
    imgs = [plot_ranking(diagnosis, out),
            plot_against_joints(poses.q, res, is_test, title, out, "residual_joints.png"),
            plot_workspace(poses.xyz, res, title, out, "residual_workspace.png")]
    M = overturning_moment(robot, poses.q)
    tau = gravity_torques(robot, poses.q)
    series = {"time [h]": poses.time_s / 3600.0,
              "overturning moment |M| [N·m]": np.linalg.norm(M, axis=1),
              "gravity torque τ2 [N·m]": tau[:, 1], "gravity torque τ3 [N·m]": tau[:, 2]}
    if "temperature_c" in poses.context:
        series["temperature [°C]"] = poses.context["temperature_c"]
    imgs.append(plot_against_context(res, series, is_test, out))
    hist = plot_history(Path(diagnosis.run_dir) / "calibration" / "history.json", out)
    atomic_write(out / "diagnosis.json", json.dumps(diagnosis.as_json(), indent=2))
    parts = ["<!doctype html><meta charset='utf-8'><title>campaign diagnosis</title>",
             "<style>body{font-family:sans-serif;max-width:1100px;margin:2em auto}pre{background:#f6f6f6;padding:1em}"
             "img{max-width:100%}</style>",
             f"<h1>Diagnosis: {html.escape(Path(diagnosis.run_dir).name)}</h1>",
             f"<pre>{html.escape(diagnosis.text())}</pre>"]
    if hist:
        parts += ["<h2>Watch the error fall (calibrate history)</h2>", f"<img src='{hist}'>"]
    parts += ["<h2>Candidates</h2>", f"<img src='{imgs[0]}'>",
              "<h2>Where the current model fails</h2>"] + [f"<img src='{f}'>" for f in imgs[1:]]
    return atomic_write(out / "report.html", "\n".join(parts))
