"""Figures and the HTML report of `campaign diagnose`: RUN/diagnose/report.html with SVG figures
beside it, written from numpy (campaign.identify.svgplot; no matplotlib, issue 22). Only
aggregated data go into a figure (bin means and quantile bands, per-cell maxima): its size does
not grow with the number of poses."""

from __future__ import annotations

import html
import textwrap
from pathlib import Path

import numpy as np

from campaign.diagnose.engine import without_faults
from campaign.fileio import atomic_write, atomic_write_json
from campaign.identify.noise_floor import tracker_noise_floor
from campaign.identify.report import PAGE_STYLE, binned_quantiles
from campaign.identify.report_figures import svg_against_joints, svg_history, svg_workspace
from campaign.identify.svgplot import LABEL_PX, SUPTITLE_PX, TICK_PX, TITLE_PX, Svg, SvgPanels, colour, nice_ticks

#: px per input column of the signed-residual grids
COLUMN_PX = 260
#: narrowest figure (px): one or two inputs still leave room for the title
MIN_WIDTH_PX = 750
#: widest figure (px): the page's width (report.html's max-width), so that a figure is shown at
#: its own size and its type is never shrunk; many inputs share it
MAX_WIDTH_PX = 1340
#: height (px) of a panel: one row per residual component
ROW_PX = 180
#: average width of a character over its font size (DejaVu Sans), for wrapping text to a width
CHAR_EM = 0.6


def _wrap(text: str, width_px: float, size_px: float) -> str:
    """``text`` broken into lines that fit ``width_px`` at ``size_px`` (its own newlines kept)."""
    chars = max(int(width_px / (CHAR_EM * size_px)), 8)
    return "\n".join(textwrap.fill(line, chars) for line in text.split("\n"))


def svg_signed_against(series: dict, r_um, components, title: str, out: Path, name: str,
                       column_titles=None, is_test=None, unit: str = "µm") -> str:
    """A grid of the signed residual components (rows) against each input (columns): per bin of
    the input, the mean (line with dots) and the 90 % band (5 %–95 % quantiles) of all poses
    given; with ``is_test`` (n,) bool, also the test set's own bin means (dashed line).

    series: column label (with its unit) -> x values (n,); r_um (n, k) residual components in
    µm (or ``unit``); components: their k labels; column_titles: optional title per column."""
    labels = list(series)
    r_um = np.asarray(r_um, dtype=float)
    n_cols = len(labels)
    left, right, gx = 80.0, 12.0, 12.0
    width = float(np.clip(COLUMN_PX * n_cols + left + right, MIN_WIDTH_PX, MAX_WIDTH_PX))
    pw = (width - left - right - (n_cols - 1) * gx) / n_cols
    title = _wrap(title, width - 40, SUPTITLE_PX)
    n_title = title.count("\n") + 1
    col_titles = [_wrap(t, pw, TITLE_PX) for t in column_titles] if column_titles else []
    n_col_title = max([t.count("\n") + 1 for t in col_titles] + [0])
    xlabels = [_wrap(label, pw, LABEL_PX) for label in labels]
    n_xlabel = max([t.count("\n") + 1 for t in xlabels] + [1])
    grid = SvgPanels(len(components), n_cols, pw=pw, ph=ROW_PX, gx=gx, gy=14, left=left, right=right,
                     top=24 + 1.2 * SUPTITLE_PX * n_title + 1.2 * TITLE_PX * n_col_title,
                     bottom=44 + 1.2 * LABEL_PX * n_xlabel)
    test = None if is_test is None else np.asarray(is_test, dtype=bool)
    for c, label in enumerate(labels):
        x = np.asarray(series[label], dtype=float)
        for k in range(len(components)):
            b = binned_quantiles(x, r_um[:, k])
            grid.band(k, c, b["x"], b["q05"], b["q95"], color=colour(k), alpha=0.25)
            grid.line(k, c, b["x"], b["mean"], color=colour(k), width=1.4, marker=True)
            if test is not None and test.any():
                bt = binned_quantiles(x[test], r_um[test, k])
                grid.line(k, c, bt["x"], bt["mean"], color=colour(k), width=1.2, dash="5 3")
        if col_titles:
            grid.title(0, c, col_titles[c])
    svg = Svg(grid.width, grid.height)
    grid.finish(svg, xlabels=xlabels, ylabels=[f"{comp} [{unit}]" for comp in components])
    svg.text(grid.width / 2, 20, title, size=SUPTITLE_PX, anchor="middle")
    return svg.save(Path(out) / name)


def svg_against_context(residuals, series: dict, is_test, out: Path, name: str = "residual_context.svg") -> str:
    """The signed position residual (Δx, Δy, Δz of the tool point in F_I, µm) of the current model
    against time, temperature and the gravity load: all poses, bin means and 90 % bands, and the
    test set's bin means apart (dashed)."""
    n_test = int(np.sum(is_test))
    return svg_signed_against(series, np.asarray(residuals)[:, :3] * 1e6, ("Δx", "Δy", "Δz"),
                              "signed position residual of the current model (in F_I) against time, context and "
                              f"gravity load\nall {len(residuals)} poses: bin mean (line with dots) and 90 % band (5–95 % "
                              f"quantiles); dashed: the bin mean of the {n_test} test poses",
                              out, name, is_test=is_test)


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


def svg_signature(diagnosis, out: Path, name: str = "signature.svg", max_inputs: int = 8) -> str | None:
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
    return svg_signed_against(series, d.heldout_residual_j1 * 1e6, ("Δx₁", "Δy₁", "Δz₁"),
                              f"signed held-out residual of the current model against {what}\n"
                              "bin mean (line with dots) and 90 % band (5–95 % quantiles); components in the frame "
                              "after joint 1", out, name, column_titles=titles)


def svg_rotation(diagnosis, out: Path, name: str = "rotation.svg", max_inputs: int = 4) -> str | None:
    """The signed held-out rotation residual (µrad), resolved in the frame after the joint where the
    rotation test found most (campaign.diagnose.chain), against each input it depends on: per bin,
    the mean and the 90 % band; None when that test is not significant."""
    c = getattr(diagnosis, "chain", None)
    if c is None or not c.significant or c.residual is None:
        return None
    names = c.depends_on(0.05)[:max_inputs] or list(c.result.input_names)[:max_inputs]
    series, titles = {}, []
    for label in names:
        x, xlabel = _axis(label, c.inputs[:, c.result.input_names.index(label)])
        series[xlabel] = x
        titles.append(f"{label}: {100 * c.result.importance.get(label, 0):.0f} % of the importance")
    j = c.joint
    return svg_signed_against(series, c.residual * 1e6, (f"δφx{j}", f"δφy{j}", f"δφz{j}"),
                              f"signed held-out rotation residual of the current model in the frame after joint {j} "
                              "against the inputs it depends on\nbin mean (line with dots) and 90 % band (5–95 % "
                              "quantiles)", out, name, column_titles=titles, unit="µrad")


def svg_ranking(diagnosis, out: Path, name: str = "ranking.svg") -> str:
    """The held-out mean ‖Δt‖ (mm) with each candidate added, one bar a candidate in the
    ranking's order (green: significant, grey: not), each labelled with its value; a dashed line
    at the current model's."""
    ranking = list(diagnosis.ranking)
    labels = [c.label for c in ranking]
    after = np.array([c.heldout_mean_position_mm_after for c in ranking], dtype=float)
    before = ranking[0].heldout_mean_position_mm_before if ranking else None
    bar, gap, top = 26.0, 10.0, 40.0  # the legend above the bars (they reach the current model's line)
    left = 24 + CHAR_EM * TICK_PX * max([len(label) for label in labels] + [4])
    pw = 880.0 - left - 24
    ph = max(len(ranking), 1) * (bar + gap) + gap
    svg = Svg(880, top + ph + 56)
    finite = [v for v in [*after, before] if v is not None and np.isfinite(v)]
    hi = max(finite + [1e-9]) * 1.2  # room right of the longest bar for its value
    ticks = nice_ticks(0.0, hi, n=5)

    def X(v):
        return left + np.asarray(v, dtype=float) / hi * pw

    gx = X(ticks)
    svg.segments(gx, np.full_like(gx, top), gx, np.full_like(gx, top + ph), stroke="#e0e0e0", width=0.6)
    svg.segments(gx, np.full_like(gx, top + ph), gx, np.full_like(gx, top + ph + 4), stroke="#333", width=0.8)
    for t, g in zip(ticks, gx):
        svg.text(g, top + ph + 16, f"{t:.4g}", anchor="middle")
    for k, (label, value, cand) in enumerate(zip(labels, after, ranking)):
        y = top + gap + k * (bar + gap)
        fill = colour(2) if cand.significant else "#b3b3b3"
        if np.isfinite(value):
            svg.add(f'<rect x="{left:.1f}" y="{y:.1f}" width="{float(X(value)) - left:.1f}" height="{bar:g}" '
                    f'fill="{fill}" class="bar"/>')
            svg.text(float(X(value)) + 6, y + bar / 2, f"{value:.4g} mm", baseline="middle", cls="value")
        svg.text(left - 6, y + bar / 2, label, anchor="end", baseline="middle", cls="effect")
    if not ranking:
        svg.text(left + pw / 2, top + ph / 2, "no candidate scored", anchor="middle", baseline="middle")
    svg.path(f"M{left:.1f} {top}h{pw:.1f}v{ph:.1f}h{-pw:.1f}z", stroke="#333", width=0.9)
    if before is not None and np.isfinite(before):
        bx = float(X(before))
        svg.path(f"M{bx:.1f} {top}v{ph:.1f}", stroke="#000", width=1.5, dash="6 4", cls="current-model")
        svg.path(f"M{bx:.1f} {top - 26:.1f}v14", stroke="#000", width=1.5, dash="6 4")
        svg.text(bx - 6, top - 19, f"current model: {before:.4g} mm", anchor="end", baseline="middle")
    svg.text(left + pw / 2, top + ph + 40, "held-out mean ‖Δt‖ with the candidate added [mm] (green: significant)",
             size=LABEL_PX, anchor="middle")
    return svg.save(Path(out) / name)


def diagnosis_doc(diagnosis, diagnosis_id: str | None) -> dict:
    """diagnosis.json: ``{"diagnosis_id", ...}`` and what :meth:`Diagnosis.as_json` holds."""
    return {"diagnosis_id": diagnosis_id, **diagnosis.as_json()}


def write_diagnosis(diagnosis, *, report: bool = True) -> Path:
    """Write a new diagnosis, holding the run's lock: RUN/diagnoses/<diagnosis_id>/ with
    diagnosis.json (what `diagnose --json` prints, with its ``diagnosis_id``) and, with
    ``report``, report.html and its SVG figures, all of it made the current RUN/diagnose at once
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
                poses = without_faults(run, store.load_measured())[0]  # the poses as the diagnosis saw them
            if diagnosis.cells is not None:  # several cells: the poses as the diagnosis saw them
                poses = diagnosis.cells.apply(poses)[0]
            if diagnosis.pose_ids is not None:  # those diagnosed (a reading fault calibrate left out is not)
                poses = poses.subset(np.flatnonzero(np.isin(poses.pose_id, diagnosis.pose_ids)))
            name = write_report(diagnosis, poses, run.robot(), out=version.path, diagnosis_id=version.id).name
    return versions.store_dir / version.id / name


def write_report(diagnosis, poses, robot, *, out=None, diagnosis_id: str | None = None) -> Path:
    """Write report.html, its SVG figures and diagnosis.json into ``out`` (default RUN/diagnose); return
    the HTML path. diagnosis_id: in diagnosis.json and shown on the page."""
    from campaign.effects.gravity import gravity_torques, overturning_moment

    out = Path(out) if out is not None else Path(diagnosis.run_dir) / "diagnose"
    out.mkdir(parents=True, exist_ok=True)
    res, is_test = diagnosis.residuals, diagnosis.is_test
    title = "current model"
    imgs = [svg_ranking(diagnosis, out),
            svg_against_joints(poses.q, res, is_test, title, out, "residual_joints.svg"),
            svg_workspace(poses.xyz, res, title, out, "residual_workspace.svg")]
    series = {"time [h]": poses.time_s / 3600.0}
    for key in sorted(poses.context):
        v = np.asarray(poses.context[key], dtype=float)
        if v.shape == (len(poses.q),) and np.all(np.isfinite(v)) and np.ptp(v) > 0:
            series[context_label(key)] = v
    series["overturning moment |M| [N·m]"] = np.linalg.norm(overturning_moment(robot, poses.q), axis=1)
    tau = gravity_torques(robot, poses.q)
    for j in sorted(np.argsort(np.ptp(tau, axis=0))[::-1][:2]):  # the two joints the load varies most
        series[f"gravity torque τ{j + 1} [N·m]"] = tau[:, j]
    imgs.append(svg_against_context(res, series, is_test, out))
    signature = svg_signature(diagnosis, out)
    rotation = svg_rotation(diagnosis, out)
    hist = svg_history(Path(diagnosis.run_dir) / "calibration" / "history.json", out,
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
    if rotation:
        parts += [f"<h2>Where in the chain it arises: the rotation error after joint {diagnosis.chain.joint}</h2>",
                  f"<img src='{rotation}'>"]
    parts += ["<h2>Candidates</h2>", f"<img src='{imgs[0]}'>",
              "<h2>Where the current model fails</h2>"] + [f"<img src='{f}'>" for f in imgs[1:]]
    return atomic_write(out / "report.html", "\n".join(parts))
