"""Plots and the HTML report of `campaign diagnose`: RUN/diagnose/report.html."""

from __future__ import annotations

import html
import json
from pathlib import Path

import numpy as np

from campaign.fileio import atomic_write
from campaign.identify.report import _plt, binned_quantiles, plot_against_joints, plot_history, plot_workspace


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


def _axis(name, x):
    """An input's values for a plot axis and its label: joints in deg, time in h, context as is."""
    if name.startswith("q") and name[1:].isdigit():
        return np.rad2deg(x), f"{name} [deg]"
    if name == "time_s":
        return x / 3600.0, "time [h]"
    return x, name


def plot_signature(diagnosis, out: Path, name: str = "signature.png", max_inputs: int = 6) -> str | None:
    """The signed held-out position residual (Δx₁, Δy₁, Δz₁ in µm, resolved in the frame after
    joint 1) against each input the model-free test found (all inputs when it found none): per
    bin, the mean (line) and the 90 % band (5 %–95 % quantiles)."""
    d = diagnosis
    if d.inputs is None or d.heldout_residual_j1 is None or d.structure is None:
        return None
    names = list(d.depends_on) or list(d.structure.input_names)
    names = names[:max_inputs]
    index = [d.structure.input_names.index(n) for n in names]
    plt = _plt()
    r = d.heldout_residual_j1 * 1e6
    fig, axes = plt.subplots(3, len(names), figsize=(3.0 * len(names) + 0.8, 6.4), sharey="row", squeeze=False)
    for c, (j, label) in enumerate(zip(index, names)):
        x, xlabel = _axis(label, d.inputs[:, j])
        for k, comp in enumerate(("Δx₁", "Δy₁", "Δz₁")):
            ax = axes[k, c]
            b = binned_quantiles(x, r[:, k])
            ax.fill_between(b["x"], b["q05"], b["q95"], color=f"C{k}", alpha=0.25, linewidth=0)
            ax.plot(b["x"], b["mean"], "o-", color=f"C{k}", ms=3, linewidth=1.4)
            ax.axhline(0.0, color="0.5", linewidth=0.6)
            ax.grid(alpha=0.3, linewidth=0.5)
            ax.tick_params(labelsize=9)
            if k == 2:
                ax.set_xlabel(xlabel, fontsize=11)
            if c == 0:
                ax.set_ylabel(f"{comp} [µm]", fontsize=11)
            if k == 0 and d.structure_significant:
                ax.set_title(f"{label}: {100 * d.structure.importance.get(label, 0):.0f} % of the importance",
                             fontsize=10)
    what = "inputs the residual depends on" if d.depends_on else "every input (no structure found)"
    fig.suptitle(f"signed held-out residual of the current model against the {what}\n"
                 "bin mean (line) and 90 % band (5–95 % quantiles); components in the frame after joint 1",
                 fontsize=11)
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
    RUN/diagnose/report.html and its PNGs, holding the run's lock; returns the report's path
    (or the JSON's)."""
    from campaign.run import RunFolder

    run = RunFolder(diagnosis.run_dir)
    with run.lock("diagnose"):
        if not report:
            return atomic_write(run.diagnose_dir / "diagnosis.json", json.dumps(diagnosis.as_json(), indent=2))
        with run.store() as store:
            poses = store.load_measured()
        return write_report(diagnosis, poses, run.robot())


def write_report(diagnosis, poses, robot) -> Path:
    """Write RUN/diagnose/report.html, its PNGs and diagnosis.json; return the HTML path."""
    from campaign.effects.gravity import gravity_torques, overturning_moment

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
    signature = plot_signature(diagnosis, out)
    hist = plot_history(Path(diagnosis.run_dir) / "calibration" / "history.json", out)
    atomic_write(out / "diagnosis.json", json.dumps(diagnosis.as_json(), indent=2))
    parts = ["<!doctype html><meta charset='utf-8'><title>campaign diagnosis</title>",
             "<style>body{font-family:sans-serif;max-width:1100px;margin:2em auto}pre{background:#f6f6f6;padding:1em}"
             "img{max-width:100%}</style>",
             f"<h1>Diagnosis: {html.escape(Path(diagnosis.run_dir).name)}</h1>",
             f"<pre>{html.escape(diagnosis.text())}</pre>"]
    if hist:
        parts += ["<h2>Watch the error fall (calibrate history)</h2>", f"<img src='{hist}'>"]
    if signature:
        parts += ["<h2>What is left, and on what it depends</h2>", f"<img src='{signature}'>"]
    parts += ["<h2>Candidates</h2>", f"<img src='{imgs[0]}'>",
              "<h2>Where the current model fails</h2>"] + [f"<img src='{f}'>" for f in imgs[1:]]
    return atomic_write(out / "report.html", "\n".join(parts))
