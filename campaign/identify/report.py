"""The calibration report: ``RUN/calibration/report.html`` with PNG plots beside it.

Plots: error distributions per stage (like the paper's Figs. 3, 4, 6, 7), error against
each joint coordinate, error over the workspace, and the history of held-out errors over
successive calibrate runs.
"""

from __future__ import annotations

import html
import json
from pathlib import Path

import numpy as np

from campaign.identify.metrics import format_table6


def _plt():
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    return plt


def _norms(dz):
    return np.linalg.norm(dz[:, :3], axis=1) * 1e3, np.linalg.norm(dz[:, 3:6], axis=1) * 1e3


def plot_distributions(residuals: dict, is_test, out: Path) -> list:
    """Histograms of ‖Δt‖ (mm) and ‖Δφ‖ (mrad) per stage, test set. Returns file names."""
    plt = _plt()
    files = []
    for k, (label, unit) in enumerate((("position error ‖Δt‖", "mm"), ("orientation error ‖Δφ‖", "mrad"))):
        fig, ax = plt.subplots(figsize=(7, 4))
        all_vals = [(_norms(dz[is_test])[k]) for dz in residuals.values()]
        hi = max(np.quantile(v, 0.995) for v in all_vals)
        lo = max(min(max(np.min(v), 1e-6) for v in all_vals), hi * 1e-4)
        bins = np.logspace(np.log10(lo), np.log10(hi * 1.05), 60)
        for name, v in zip(residuals, all_vals):
            ax.hist(v, bins=bins, histtype="step", linewidth=1.5, label=f"{name} (mean {v.mean():.3g} {unit})")
        ax.set_xscale("log")
        ax.set_xlabel(f"{label} [{unit}], test set, log scale")
        ax.set_ylabel("poses")
        ax.legend(fontsize=8)
        ax.set_title(f"{label} per model stage")
        fig.tight_layout()
        name = f"distribution_{'position' if k == 0 else 'orientation'}.png"
        fig.savefig(out / name, dpi=110)
        plt.close(fig)
        files.append(name)
    return files


def plot_against_joints(q, dz, is_test, title: str, out: Path, name: str) -> str:
    """Error of one stage against each joint coordinate (deg), test set."""
    plt = _plt()
    pos, rot = _norms(dz)
    fig, axes = plt.subplots(2, 6, figsize=(16, 5), sharey="row")
    for i in range(6):
        for row, (v, unit) in enumerate(((pos, "‖Δt‖ mm"), (rot, "‖Δφ‖ mrad"))):
            ax = axes[row, i]
            ax.scatter(np.rad2deg(q[~is_test, i]), v[~is_test], s=2, alpha=0.3, color="0.6", label="train")
            ax.scatter(np.rad2deg(q[is_test, i]), v[is_test], s=3, alpha=0.6, color="C0", label="test")
            if row == 1:
                ax.set_xlabel(f"q{i + 1} [deg]")
            if i == 0:
                ax.set_ylabel(unit)
    axes[0, 0].legend(fontsize=7, markerscale=3)
    fig.suptitle(f"{title}: error against each joint coordinate")
    fig.tight_layout()
    fig.savefig(out / name, dpi=100)
    plt.close(fig)
    return name


def plot_workspace(xyz, dz, title: str, out: Path, name: str) -> str:
    """Tool positions (top view x-z and side view x-y of F_I) coloured by ‖Δt‖ (mm)."""
    plt = _plt()
    pos, _ = _norms(dz)
    fig, axes = plt.subplots(1, 2, figsize=(12, 5))
    vmax = np.quantile(pos, 0.98)
    for ax, (a, b, la, lb) in zip(axes, ((0, 2, "x_I [m]", "z_I [m]"), (0, 1, "x_I [m]", "height −y_I [m]"))):
        yb = xyz[:, b] if b != 1 else -xyz[:, 1]
        sc = ax.scatter(xyz[:, a], yb, c=pos, s=4, cmap="viridis", vmin=0, vmax=vmax)
        ax.set_xlabel(la)
        ax.set_ylabel(lb)
        ax.set_aspect("equal")
    fig.colorbar(sc, ax=axes, label="‖Δt‖ [mm]")
    fig.suptitle(f"{title}: position error over the workspace")
    fig.savefig(out / name, dpi=100)
    plt.close(fig)
    return name


#: stages that are a comparison, not a step of the model being built up
SIDE_STAGES = ("ann",)


def history_rows(history_path: Path):
    """[(run index, effects, {stage: mean test position mm})] from history.json."""
    if not history_path.is_file():
        return []
    try:
        runs = json.loads(history_path.read_text()).get("runs", [])
    except (json.JSONDecodeError, AttributeError):
        return []
    return [(i + 1, r.get("effects", []), r.get("order", []), r.get("stages", {})) for i, r in enumerate(runs)]


def plot_history(history_path: Path, out: Path, name: str = "history.png"):
    """Held-out mean position error of the current model after each calibrate run, and per stage."""
    rows = history_rows(history_path)
    if not rows:
        return None
    plt = _plt()
    fig, ax = plt.subplots(figsize=(8, 4))
    labels, values = [], []
    seen = set()
    for idx, effects, order, stages in rows:
        for stage in order:
            key = stage if stage not in seen else None
            if key is None:
                continue
            seen.add(stage)
            labels.append(stage)
            values.append(stages[stage]["position_mm"]["mean"])
    # the sequence of models a user builds up is one line; the network trained on the nominal
    # model alone (stage "ann", the paper's comparison) is a side branch, drawn apart
    chain = [x for x, label in enumerate(labels) if label not in SIDE_STAGES]
    side = [x for x, label in enumerate(labels) if label in SIDE_STAGES]
    ax.plot(chain, [values[x] for x in chain], "o-", label="model as it was built up")
    if side:
        ax.plot(side, [values[x] for x in side], "s", color="0.6", label="ANN on the nominal model (comparison)")
    ax.legend(fontsize=8)
    ax.set_xticks(range(len(values)), labels, rotation=20, ha="right", fontsize=8)
    ax.set_yscale("log")
    ax.set_ylabel("held-out mean ‖Δt‖ [mm]")
    ax.set_title("watch the error fall: each model stage as it was added")
    for x, v in enumerate(values):
        ax.annotate(f"{v:.3g}", (x, v), textcoords="offset points", xytext=(0, 6), ha="center", fontsize=8)
    fig.tight_layout()
    fig.savefig(out / name, dpi=110)
    plt.close(fig)
    return name


def write_report(run_dir, stages: dict, order: list, residuals: dict, q, xyz, is_test,
                 param_text: str = "", extra_html: str = "") -> Path:
    """Write ``RUN/calibration/report.html`` and its PNGs; return the HTML path.

    residuals: stage name -> Δz (n, 6) for every pose; q (n, 6) rad; xyz (n, 3) m measured
    tool positions; is_test (n,) bool.
    """
    out = Path(run_dir) / "calibration"
    out.mkdir(parents=True, exist_ok=True)
    is_test = np.asarray(is_test, dtype=bool)
    imgs = plot_distributions(residuals, is_test, out)
    current = order[-1]
    first = order[0]
    joint_imgs = [plot_against_joints(q, residuals[s], is_test, s, out, f"joints_{s.replace('+', '_')}.png")
                  for s in dict.fromkeys([first, current]) if s in residuals]
    ws_img = plot_workspace(xyz, residuals[current], current, out, "workspace.png") if current in residuals else None
    hist_img = plot_history(out / "history.json", out)
    table_test = format_table6(stages, order, "test")
    table_train = format_table6(stages, order, "train")
    parts = [
        "<!doctype html><meta charset='utf-8'><title>campaign calibration report</title>",
        "<style>body{font-family:sans-serif;max-width:1100px;margin:2em auto}pre{background:#f6f6f6;padding:1em}"
        "img{max-width:100%}</style>",
        f"<h1>Calibration report: {html.escape(str(Path(run_dir).name))}</h1>",
        f"<p>Current model: <b>{html.escape(current)}</b>. Statistics in the shape of the paper's Table 6.</p>",
        "<h2>Test set</h2>", f"<pre>{html.escape(table_test)}</pre>",
        "<h2>Training set</h2>", f"<pre>{html.escape(table_train)}</pre>",
    ]
    if hist_img:
        parts += ["<h2>Watch the error fall</h2>", f"<img src='{hist_img}'>"]
    parts += ["<h2>Error distributions (test set)</h2>"] + [f"<img src='{f}'>" for f in imgs]
    parts += ["<h2>Error against each joint coordinate</h2>"] + [f"<img src='{f}'>" for f in joint_imgs]
    if ws_img:
        parts += ["<h2>Error over the workspace</h2>", f"<img src='{ws_img}'>"]
    if extra_html:
        parts.append(extra_html)
    if param_text:
        parts += ["<h2>Parameters</h2>", f"<pre>{html.escape(param_text)}</pre>"]
    path = out / "report.html"
    tmp = path.with_name("report.html.partial")
    tmp.write_text("\n".join(parts))
    tmp.replace(path)
    return path


def history_table(run_dir) -> str:
    """The held-out (test-set) mean errors of every calibrate run, one row per model stage as added."""
    rows = history_rows(Path(run_dir) / "calibration" / "history.json")
    if not rows:
        return "no calibrate runs yet"
    lines = [f"{'calibrate run':<14}{'model stage':<44}{'mean ‖Δt‖ mm':>13}{'mean ‖Δφ‖ mrad':>15}"]
    seen = set()
    for idx, effects, order, stages in rows:
        for stage in order:
            if stage in seen:
                continue
            seen.add(stage)
            st = stages[stage]
            lines.append(f"{idx:<14}{stage:<44}{st['position_mm']['mean']:>13.4f}{st['orientation_mrad']['mean']:>15.4f}")
    return "\n".join(lines)
