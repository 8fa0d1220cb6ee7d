"""Plots and the HTML report of `campaign diagnose`: RUN/diagnose/report.html."""

from __future__ import annotations

import html
from pathlib import Path

import numpy as np

from campaign.fileio import atomic_write, atomic_write_json
from campaign.identify.noise_floor import tracker_noise_floor
from campaign.identify.report import (PAGE_STYLE, PNG_FAST, _plt, binned_quantiles, plot_against_joints,
                                     plot_history, plot_workspace)

#: font sizes of the diagnose figures (pt at 100 dpi), readable at the page's width
LABEL_PT, TICK_PT, TITLE_PT = 12, 10, 12
#: inches per input column of the signed-residual grids (the page shows about 13 in at 100 dpi)
COLUMN_IN = 2.6
#: narrowest figure (in): one or two inputs still leave room for the title
MIN_WIDTH_IN = 7.5
#: widest figure (in): many inputs share it rather than shrink the type on the page
MAX_WIDTH_IN = 14.0


def plot_signed_against(series: dict, r_um, components, title: str, out: Path, name: str,
                        column_titles=None) -> str:
    """A grid of the signed residual components (rows) against each input (columns): per bin of
    the input, the mean (line) and the 90 % band (5 %–95 % quantiles).

    series: column label -> x values (n,); r_um (n, 3) residual components in µm; components:
    their labels; column_titles: optional title per column."""
    import textwrap

    from campaign.identify.panels import PanelGrid

    plt = _plt()
    labels = list(series)
    width_in = min(max(COLUMN_IN * len(labels) + 1.1, MIN_WIDTH_IN), MAX_WIDTH_IN)
    # the title wrapped to the figure's width (about 10 characters per inch at TITLE_PT)
    title = "\n".join(textwrap.fill(line, int(10 * width_in)) for line in title.split("\n"))
    n_title = title.count("\n") + 1
    fig = plt.figure(figsize=(width_in, 2.1 * len(components) + 0.9 + 0.25 * n_title))
    w, h = fig.get_size_inches()
    top_in = 0.25 + 0.22 * n_title + (0.3 if column_titles else 0.0)
    ax = fig.add_axes((0.1 / w, 0.1 / h, 1 - 0.25 / w, 1 - (0.1 + top_in) / h))  # margins in inches
    grid = PanelGrid(ax, len(components), len(labels), gap_x=0.08, gap_y=0.1)  # rows share y, columns x
    for c, label in enumerate(labels):
        x = np.asarray(series[label], dtype=float)
        for k, comp in enumerate(components):
            b = binned_quantiles(x, r_um[:, k])
            grid.band(k, c, b["x"], b["q05"], b["q95"], color=f"C{k}", alpha=0.25)
            grid.line(k, c, b["x"], b["mean"], color=f"C{k}", marker="o", ms=3, linewidth=1.4)
        if column_titles:
            grid.title(0, c, column_titles[c], fontsize=TICK_PT + 1)
    grid.finish(xlabels=labels, ylabels=[f"{comp} [µm]" for comp in components], label_size=TICK_PT - 1)
    fig.suptitle(title, fontsize=TITLE_PT)
    fig.savefig(out / name, dpi=100, pil_kwargs=PNG_FAST)
    plt.close(fig)
    return name


def plot_against_context(residuals, series: dict, is_test, out: Path, name: str = "residual_context.png") -> str:
    """The signed position residual (Δx, Δy, Δz of the tool point in F_I, µm) of the current model
    against time, temperature and the gravity load: all poses, bin means and 90 % bands."""
    n_test = int(np.sum(is_test))
    return plot_signed_against(series, np.asarray(residuals)[:, :3] * 1e6, ("Δx", "Δy", "Δz"),
                               "signed position residual of the current model (in F_I) against time, context and "
                               f"gravity load\nall {len(residuals)} poses ({n_test} of them the test set): bin mean "
                               "(line) and 90 % band (5–95 % quantiles)", out, name)


#: a context column's unit from its name's suffix (``temperature_c``, ``humidity_pct``, ...)
UNIT_SUFFIXES = {"_c": "°C", "_k": "K", "_s": "s", "_h": "h", "_m": "m", "_mm": "mm", "_um": "µm", "_deg": "deg",
                 "_rad": "rad", "_pct": "%", "_pa": "Pa", "_hpa": "hPa", "_kg": "kg", "_nm": "N·m"}


def context_label(key: str) -> str:
    """A context column's axis label with its unit: ``temperature_c`` -> ``temperature [°C]``;
    a name without a known unit suffix as it is."""
    for suffix in sorted(UNIT_SUFFIXES, key=len, reverse=True):
        if key.lower().endswith(suffix) and len(key) > len(suffix):
            return f"{key[:-len(suffix)]} [{UNIT_SUFFIXES[suffix]}]"
    return key


def _axis(name, x):
    """An input's values for a plot axis and its label: joints in deg, time in h, context with
    the unit its name carries."""
    if name.startswith("q") and name[1:].isdigit():
        return np.rad2deg(x), f"{name} [deg]"
    if name == "time_s":
        return x / 3600.0, "time [h]"
    return x, context_label(name)


def plot_signature(diagnosis, out: Path, name: str = "signature.png", max_inputs: int = 8) -> str | None:
    """The signed held-out position residual (Δx₁, Δy₁, Δz₁ in µm, resolved in the frame after
    joint 1) against each input the model-free test found (all inputs when it found none): per
    bin, the mean (line) and the 90 % band (5 %–95 % quantiles)."""
    d = diagnosis
    if d.inputs is None or d.heldout_residual_j1 is None or d.structure is None:
        return None
    names = (list(d.depends_on) or list(d.structure.input_names))[:max_inputs]
    series, titles = {}, []
    for label in names:
        x, xlabel = _axis(label, d.inputs[:, d.structure.input_names.index(label)])
        series[xlabel] = x
        titles.append(f"{label}: {100 * d.structure.importance.get(label, 0):.0f} % of the importance"
                      if d.structure_significant else label)
    what = "each input it depends on" if d.depends_on else "every input (no structure found)"
    return plot_signed_against(series, d.heldout_residual_j1 * 1e6, ("Δx₁", "Δy₁", "Δz₁"),
                               f"signed held-out residual of the current model against {what}\n"
                               "bin mean (line) and 90 % band (5–95 % quantiles); components in the frame after joint 1",
                               out, name, column_titles=titles)


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
    # a fixed layout (tight_layout draws the figure once more): room for the longest effect name
    w, h = fig.get_size_inches()
    left_in = 0.3 + 0.085 * max([len(label) for label in labels] + [4])
    fig.subplots_adjust(left=min(left_in / w, 0.6), right=0.97, bottom=0.5 / h + 0.02, top=1 - 0.15 / h)
    fig.savefig(out / name, dpi=110, pil_kwargs=PNG_FAST)
    plt.close(fig)
    return name


def diagnosis_doc(diagnosis, diagnosis_id: str | None) -> dict:
    """diagnosis.json: ``{"diagnosis_id", ...}`` and what :meth:`Diagnosis.as_json` holds."""
    return {"diagnosis_id": diagnosis_id, **diagnosis.as_json()}


def write_diagnosis(diagnosis, *, report: bool = True) -> Path:
    """Write a new diagnosis, holding the run's lock: RUN/diagnoses/<diagnosis_id>/ with
    diagnosis.json (what `diagnose --json` prints, with its ``diagnosis_id``) and, with
    ``report``, report.html and its PNGs, all of it made the current RUN/diagnose at once
    (campaign.versioned); earlier diagnoses stay in RUN/diagnoses/. Returns the report's path
    (or the JSON's) in the diagnosis's own folder, which later diagnoses leave as it is."""
    from campaign.run import RunFolder
    from campaign.versioned import diagnosis_folder

    run = RunFolder(diagnosis.run_dir)
    versions = diagnosis_folder(run.path)
    with run.lock("diagnose"), versions.new_version() as version:
        if not report:
            atomic_write_json(version.path / "diagnosis.json", diagnosis_doc(diagnosis, version.id))
            name = "diagnosis.json"
        else:
            with run.store() as store:
                poses = store.load_measured()
            name = write_report(diagnosis, poses, run.robot(), out=version.path, diagnosis_id=version.id).name
    return versions.store_dir / version.id / name


def write_report(diagnosis, poses, robot, *, out=None, diagnosis_id: str | None = None) -> Path:
    """Write report.html, its PNGs and diagnosis.json into ``out`` (default RUN/diagnose); return
    the HTML path. diagnosis_id: in diagnosis.json and shown on the page."""
    from campaign.effects.gravity import gravity_torques, overturning_moment

    out = Path(out) if out is not None else Path(diagnosis.run_dir) / "diagnose"
    out.mkdir(parents=True, exist_ok=True)
    res, is_test = diagnosis.residuals, diagnosis.is_test
    title = "current model"
    imgs = [plot_ranking(diagnosis, out),
            plot_against_joints(poses.q, res, is_test, title, out, "residual_joints.png"),
            plot_workspace(poses.xyz, res, title, out, "residual_workspace.png")]
    series = {"time [h]": poses.time_s / 3600.0}
    for key in sorted(poses.context):
        v = np.asarray(poses.context[key], dtype=float)
        if v.shape == (len(poses.q),) and np.all(np.isfinite(v)) and np.ptp(v) > 0:
            series[context_label(key)] = v
    series["overturning moment |M| [N·m]"] = np.linalg.norm(overturning_moment(robot, poses.q), axis=1)
    tau = gravity_torques(robot, poses.q)
    for j in sorted(np.argsort(np.ptp(tau, axis=0))[::-1][:2]):  # the two joints the load varies most
        series[f"gravity torque τ{j + 1} [N·m]"] = tau[:, j]
    imgs.append(plot_against_context(res, series, is_test, out))
    signature = plot_signature(diagnosis, out)
    hist = plot_history(Path(diagnosis.run_dir) / "calibration" / "history.json", out,
                        noise_floor=tracker_noise_floor(diagnosis.run_dir, poses, robot))  # the poses read once
    atomic_write_json(out / "diagnosis.json", diagnosis_doc(diagnosis, diagnosis_id))
    parts = ["<!doctype html><meta charset='utf-8'><title>campaign diagnosis</title>",
             PAGE_STYLE.replace("pre{", "pre{white-space:pre-wrap;overflow-wrap:anywhere;"),
             f"<h1>Diagnosis: {html.escape(Path(diagnosis.run_dir).name)}</h1>",
             *([f"<p class='diagnosis-id'>Diagnosis <code>{html.escape(diagnosis_id)}</code> (the "
                "<code>diagnosis_id</code> of diagnosis.json)</p>"] if diagnosis_id else []),
             f"<pre>{html.escape(diagnosis.text())}</pre>"]
    if hist:
        parts += ["<h2>Watch the error fall (calibrate history)</h2>", f"<img src='{hist}'>"]
    if signature:
        parts += ["<h2>What is left, and on what it depends</h2>", f"<img src='{signature}'>"]
    parts += ["<h2>Candidates</h2>", f"<img src='{imgs[0]}'>",
              "<h2>Where the current model fails</h2>"] + [f"<img src='{f}'>" for f in imgs[1:]]
    return atomic_write(out / "report.html", "\n".join(parts))
