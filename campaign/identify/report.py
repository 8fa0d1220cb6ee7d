"""The calibration report: ``RUN/calibration/report.html`` with SVG figures beside it
(campaign.identify.report_figures, drawn without matplotlib); here the page and the figures'
aggregation of the data (bins, cells, history rows), which the diagnose report shares.

Plots: error distributions of every stage as small multiples (like the paper's Figs. 3, 4,
6, 7), the signed error components of every stage against each joint coordinate (bin means
and 90 % bands), the error over the workspace, and the history of held-out errors over
successive calibrate runs with the tracker noise floor (campaign.identify.noise_floor).
"""

from __future__ import annotations

import html
import json
from pathlib import Path

import numpy as np

from campaign.identify.metrics import format_table6
from campaign.identify.noise_floor import floor_label, tracker_noise_floor


def _norms(dz):
    return np.linalg.norm(dz[:, :3], axis=1) * 1e3, np.linalg.norm(dz[:, 3:6], axis=1) * 1e3


def orientation_measured(dz) -> bool:
    """Whether Δz (n, 6) carries an orientation error (position-only data leave it 0 or NaN)."""
    dz = np.asarray(dz, dtype=float)
    return dz.shape[1] >= 6 and bool(np.all(np.isfinite(dz[:, 3:6]))) and bool(np.any(dz[:, 3:6] != 0.0))


def signed_components(dz) -> list:
    """[(label, unit, values (n,))]: Δx, Δy, Δz of F_I in mm, then Δφx, Δφy, Δφz (rotation
    vector in F_I) in mrad when the orientation was measured."""
    dz = np.asarray(dz, dtype=float)
    comps = [(f"Δ{c}", "mm", dz[:, k] * 1e3) for k, c in enumerate("xyz")]
    if orientation_measured(dz):
        comps += [(f"Δφ{c}", "mrad", dz[:, 3 + k] * 1e3) for k, c in enumerate("xyz")]
    return comps


#: at most this many bins along a joint coordinate, and at least this many poses in each
#: (a 90 % band from fewer values would be its minimum and maximum)
MAX_BINS = 24
MIN_BIN_POSES = 8


def binned_quantiles(x, y, *, max_bins: int = MAX_BINS, min_count: int = MIN_BIN_POSES) -> dict:
    """Mean and 5 %/95 % quantiles (a 90 % band) of y in bins of x.

    Bins: one per distinct value of x when x takes at most ``max_bins`` values (poses on a
    grid), else ``max_bins`` bins of about equal count (equal x values never split); then
    neighbouring bins are merged until each holds ``min_count`` poses (the last short bin
    joins its neighbour). Returns {"x": mean x per bin, "n", "mean", "q05", "q95"}, each (b,).
    """
    x, y = np.asarray(x, dtype=float), np.asarray(y, dtype=float)
    order = np.argsort(x, kind="stable")
    xs, ys = x[order], y[order]
    n = len(xs)
    empty = {k: np.zeros(0) for k in ("x", "n", "mean", "q05", "q95")}
    if n == 0:
        return empty
    values = np.unique(xs)
    if len(values) <= max_bins:
        starts = np.searchsorted(xs, values, side="left")
    else:
        cut = np.round(np.linspace(0, n, max_bins + 1)[:-1]).astype(int)
        starts = np.unique(np.searchsorted(xs, xs[cut], side="left"))
    bounds = list(starts) + [n]
    merged = [0]
    for k in range(1, len(bounds)):
        if bounds[k] - merged[-1] >= min_count or k == len(bounds) - 1:
            merged.append(bounds[k])
    if len(merged) > 2 and merged[-1] - merged[-2] < min_count:
        del merged[-2]
    lo, hi = np.asarray(merged[:-1]), np.asarray(merged[1:])
    count = hi - lo
    out = {"x": np.add.reduceat(xs, lo) / count, "n": count.astype(float), "mean": np.add.reduceat(ys, lo) / count}
    # quantiles per bin at once: y sorted within each bin, then np.quantile's linear rule
    # (position q·(m − 1) between the order statistics) on each bin's slice
    bin_of = np.repeat(np.arange(len(lo)), count)
    y_sorted = ys[np.lexsort((ys, bin_of))]
    for key, qq in (("q05", 0.05), ("q95", 0.95)):
        pos = qq * (count - 1)
        below = np.floor(pos).astype(int)
        frac = pos - below
        a = y_sorted[lo + below]
        b = y_sorted[lo + np.minimum(below + 1, count - 1)]
        out[key] = a + (b - a) * frac
    return out


def _which_poses(is_test):
    """The poses the per-joint plots bin: the held-out test set, unless it
    is too small to fill MAX_BINS bins of MIN_BIN_POSES poses (then every pose, training poses
    included: their residuals show the same systematic errors, slightly smaller). (mask, words)."""
    is_test = np.asarray(is_test, dtype=bool)
    if is_test.sum() >= MAX_BINS * MIN_BIN_POSES:
        return is_test, f"held-out test set, {int(is_test.sum())} poses"
    return np.ones_like(is_test), f"all {len(is_test)} poses, train and test (the test set alone is too small to bin)"


def workspace_colour_scale(pos_mm):
    """(vmin, vmax) mm of the workspace plot's colour scale: from 0 to the largest error."""
    pos_mm = np.asarray(pos_mm, dtype=float)
    top = float(np.max(pos_mm)) if len(pos_mm) else 0.0
    return 0.0, top if top > 0 else 1.0


#: cells of the workspace figure's grid along the longer side of a view, at most (~12 mm on a
#: 2 m view, ~3 px at the figure's 100 dpi: about a marker's size) and at least (a few poses
#: stay visible: 3·√n cells for n poses in between)
WORKSPACE_CELLS = 150
WORKSPACE_MIN_CELLS = 40


def largest_per_cell(x, y, v, cells: int = WORKSPACE_CELLS):
    """The largest ``v`` per cell of a square grid over the points (x, y) (all (n,)): (image
    (rows, cols) with NaN where no point lies, extent (x0, x1, y0, y1) for imshow)."""
    x, y, v = (np.asarray(a, dtype=float) for a in (x, y, v))
    if len(x) == 0:
        return np.full((1, 1), np.nan), (0.0, 1.0, 0.0, 1.0)
    x0, y0 = x.min(), y.min()
    size = max(x.max() - x0, y.max() - y0, 1e-9) / cells * (1 + 1e-9)  # the largest point inside
    ix, iy = ((x - x0) / size).astype(int), ((y - y0) / size).astype(int)
    img = np.full((iy.max() + 1, ix.max() + 1), np.nan)
    np.fmax.at(img, (iy, ix), v)
    return img, (x0, x0 + img.shape[1] * size, y0, y0 + img.shape[0] * size)


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


def history_stages(rows) -> list:
    """[(run index, stage, test statistics)] of :func:`history_rows`: each model stage once, in the
    order the stages were first added, with its figures from the last calibrate run that fitted it
    (so the last row is the current model as the verdict states it, not an earlier run's)."""
    first, latest = [], {}
    for idx, _effects, order, stages in rows:
        for stage in order:
            if stage not in latest:
                first.append(stage)
            latest[stage] = (idx, stages[stage])
    return [(latest[s][0], s, latest[s][1]) for s in first]


def _wrap_stage(name: str, width: int = 22) -> str:
    """A stage name broken before its '+' parts so that a tick label stays narrow, never cut."""
    lines = [""]
    for k, part in enumerate(name.split("+")):
        piece = part if k == 0 else "+" + part
        if lines[-1] and len(lines[-1]) + len(piece) > width:
            lines.append(piece)
        else:
            lines[-1] += piece
    return "\n".join(lines)


PAGE_STYLE = ("<style>body{font-family:sans-serif;max-width:1340px;margin:2em auto;padding:0 1em}"
              "pre{background:#f6f6f6;padding:1em;overflow-x:auto}img{max-width:100%;display:block;margin:0.5em 0}"
              "h3{margin-bottom:0.2em}</style>")


def write_report(run_dir, stages: dict, order: list, residuals: dict, q, xyz, is_test,
                 param_text: str = "", extra_html: str = "", noise_floor="auto", out_dir=None,
                 calibration_id: str | None = None) -> Path:
    """Write ``RUN/calibration/report.html`` and its SVG figures; return the HTML path.

    residuals: stage name -> Δz (n, 6) for every pose; q (n, N) rad; xyz (n, 3) m measured
    tool positions; is_test (n,) bool. noise_floor: a campaign.measure.floor.NoiseFloor, None,
    or "auto" (:func:`tracker_noise_floor` of the run: repeats, drift checks, stated noise).
    out_dir: the folder to write into (default RUN/calibration; `calibrate` gives the new
    calibration's folder); calibration_id: shown on the page (the id of metrics.json and params.yaml).
    """
    out = Path(out_dir) if out_dir is not None else Path(run_dir) / "calibration"
    out.mkdir(parents=True, exist_ok=True)
    is_test = np.asarray(is_test, dtype=bool)
    if isinstance(noise_floor, str) and noise_floor == "auto":
        noise_floor = tracker_noise_floor(run_dir)
    from campaign.identify.report_figures import write_figures  # SVG, no matplotlib (issue 22)

    current = order[-1]
    imgs, joint_imgs, ws_img, hist_img = write_figures(run_dir, residuals, order, q, xyz, is_test, out, noise_floor)
    table_test = format_table6(stages, order, "test")
    table_train = format_table6(stages, order, "train")
    parts = [
        "<!doctype html><meta charset='utf-8'><title>campaign calibration report</title>", PAGE_STYLE,
        f"<h1>Calibration report: {html.escape(str(Path(run_dir).name))}</h1>",
        f"<p>Current model: <b>{html.escape(current)}</b>. Statistics in the shape of the paper's Table 6.</p>",
        *([f"<p class='calibration-id'>Calibration <code>{html.escape(calibration_id)}</code> (the "
           "<code>calibration_id</code> of metrics.json, params.yaml and the history)</p>"] if calibration_id else []),
        "<h2>Test set</h2>", f"<pre>{html.escape(table_test)}</pre>",
        "<h2>Training set</h2>", f"<pre>{html.escape(table_train)}</pre>",
    ]
    if hist_img:
        floor_words = (f" The dotted line is the tracker noise floor: the mean ‖Δt‖ that measurement noise alone "
                       f"leaves to a perfect model, {html.escape(floor_label(noise_floor))}."
                       if noise_floor is not None else " No tracker noise floor: no repeated measurements, no "
                       "drift checks and no stated tracker noise (tracker: {noise_m: σ} in campaign.yaml).")
        parts += ["<h2>Watch the error fall</h2>", f"<p>Held-out mean position error of each model stage.{floor_words}</p>",
                  f"<img src='{hist_img}'>"]
    parts += ["<h2>Error distributions</h2>", "<p>One row per model stage, on shared axes.</p>"]
    parts += [f"<img src='{f}'>" for f in imgs]
    parts += ["<h2>Error against each joint coordinate</h2>",
              "<p>Every model stage, signed components: where a stage's band leaves zero along a joint, the model "
              "misses something that depends on that joint.</p>"]
    for stage, f in joint_imgs:
        parts += [f"<h3>{html.escape(stage)}</h3>", f"<img src='{f}'>"]
    if ws_img:
        parts += ["<h2>Error over the workspace</h2>", f"<img src='{ws_img}'>"]
    if extra_html:
        parts.append(extra_html)
    if param_text:
        parts += ["<h2>Parameters</h2>", f"<pre>{html.escape(param_text)}</pre>"]
    from campaign.fileio import atomic_write

    return atomic_write(out / "report.html", "\n".join(parts))


def history_table(run_dir) -> str:
    """The test-set mean errors of the calibrate runs, one row per model stage as added, each from
    the last run that fitted it (:func:`history_stages`)."""
    rows = history_rows(Path(run_dir) / "calibration" / "history.json")
    if not rows:
        return "no calibrate runs yet"
    lines = [f"{'calibrate run':<14}{'model stage':<44}{'mean ‖Δt‖ mm':>13}{'mean ‖Δφ‖ mrad':>15}"]
    for idx, stage, st in history_stages(rows):
        rot = f"{st['orientation_mrad']['mean']:>15.4f}" if "orientation_mrad" in st else f"{'-':>15}"
        lines.append(f"{idx:<14}{stage:<44}{st['position_mm']['mean']:>13.4f}{rot}")
    return "\n".join(lines)


def model_choice_html(choice: dict | None) -> str:
    """The report's "Model choice" section (campaign.identify.model_choice): the chosen model and
    why, the cross-validation curve as a table (every candidate's leave-one-out held-out mean),
    the parameters held by --fix, and the expected held-out error next to the measured one."""
    if not choice:
        return ""
    from campaign.identify.model_choice import choice_text

    def strength(c):
        return "" if c["strength"] is None else f"{c['strength']:g}"

    rows = "".join(
        f"<tr><td>{html.escape(c['model'])}</td><td>{strength(c)}</td>"
        f"<td>{len(c['dropped']) or ''}</td><td>{c['cv_mean_position_mm']:.4f}</td><td>{c['n_effective']:.1f}</td>"
        f"<td>{'chosen' if c['model'] == choice['choice'] and c['strength'] == choice['strength'] else ''}</td></tr>"
        for c in choice.get("candidates", []))
    table = ("<table><tr><th>candidate</th><th>prior strength</th><th>dropped</th>"
             "<th>leave-one-out mean on the training poses (mm)</th><th>effective unknowns</th><th></th></tr>" + rows + "</table>") if rows else ""
    return f"<h2>Model choice</h2><pre>{html.escape(choice_text(choice))}</pre>{table}"
