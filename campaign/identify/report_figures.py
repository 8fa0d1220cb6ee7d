"""The calibration report's figures as SVG files beside report.html, drawn without matplotlib
(campaign.identify.svgplot): one function per section of the page: error distributions per
stage, signed errors against each joint per stage, the error over the workspace, and the history
of held-out errors with the tracker noise floor. The diagnose report draws the last three too.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from campaign.identify.noise_floor import floor_label, tracker_noise_floor
from campaign.identify.report import (SIDE_STAGES, WORKSPACE_CELLS, WORKSPACE_MIN_CELLS, _norms, _which_poses,
                                      _wrap_stage, binned_quantiles, history_rows, history_stages, largest_per_cell,
                                      orientation_measured, signed_components, workspace_colour_scale)
from campaign.identify.svgplot import (LABEL_PX, SUPTITLE_PX, TICK_PX, Svg, SvgPanels, colour, decade_ticks,
                                      nice_ticks, viridis)
from campaign.tolerances import REPORT_LOG_FLOOR_MM

#: colour levels of the workspace figure (one path per level)
WORKSPACE_LEVELS = 64


def svg_distributions(residuals: dict, is_test, out: Path) -> list:
    """Histograms of ‖Δt‖ (mm) and ‖Δφ‖ (mrad, where measured) of every stage on the test set,
    one row per stage on shared log axes; solid line the mean, dashed the 90 % quantile.
    Returns the file names (distributions.svg)."""
    use = np.asarray(is_test, dtype=bool)
    words = f"held-out test set, {int(use.sum())} poses"
    names = list(residuals)
    with_rot = all(orientation_measured(residuals[s]) for s in names)
    blocks = [("position error ‖Δt‖", "mm", 0)] + ([("orientation error ‖Δφ‖", "mrad", 1)] if with_rot else [])
    two_lines = max(len(s) for s in names) > 44
    grid = SvgPanels(len(names), len(blocks), pw=1180 / len(blocks) - 10, ph=90, gx=20, gy=48 if two_lines else 34,
                     left=70, top=70 if two_lines else 56)
    for c, (label, unit, k) in enumerate(blocks):
        vals = [_norms(residuals[s][use])[k] for s in names]
        hi = max(float(np.max(v)) for v in vals)
        hi = max(hi, REPORT_LOG_FLOOR_MM)  # zero errors (exact data) on the floor, not at log10(0)
        lo = min(max(min(max(float(np.min(v)), REPORT_LOG_FLOOR_MM) for v in vals), hi * 1e-5), hi)
        edges = np.linspace(np.log10(lo * 0.95), np.log10(hi * 1.05), 50)  # log10 of the quantity
        for r, (name, v) in enumerate(zip(names, vals)):
            counts, _ = np.histogram(np.log10(np.maximum(v, lo)), bins=edges)
            sx, sy = np.repeat(edges, 2)[1:-1], np.repeat(counts, 2).astype(float)  # the histogram's steps
            grid.band(r, c, sx, np.zeros_like(sy), sy, color=colour(r), alpha=0.45)
            grid.line(r, c, sx, sy, color=colour(r), width=1.2)
            mean, q90 = float(np.mean(v)), float(np.quantile(v, 0.9))
            grid.vline(r, c, np.log10(max(mean, lo)), color="#000", width=1.0)
            grid.vline(r, c, np.log10(max(q90, lo)), color="#000", width=1.0, dash="5 3")
            grid.title(r, c, f"{name}:{chr(10) if two_lines else '  '}mean {mean:.3g} {unit}, q90 {q90:.3g} {unit}")
    svg = Svg(grid.width, grid.height)
    grid.finish(svg, xlabels=[f"{label} [{unit}], log scale" for label, unit, _ in blocks],
                ylabels=["poses"] * len(names), xlog=True, ylow=0.0, zero_line=False)
    svg.text(grid.width / 2, 20, f"error distribution of each model stage ({words}); solid line: mean, "
             "dashed: 90 % quantile", size=SUPTITLE_PX, anchor="middle")
    return [svg.save(Path(out) / "distributions.svg")]


def svg_against_joints(q, dz, is_test, title: str, out: Path, name: str) -> str:
    """Signed error components of one stage against each joint coordinate (deg): per bin of the
    joint, the mean (line) and the 90 % band (5 %–95 % quantiles) of Δx, Δy, Δz (mm) and, where
    measured, Δφx, Δφy, Δφz (mrad) (:func:`campaign.identify.report.binned_quantiles`)."""
    q = np.asarray(q, dtype=float)
    use, words = _which_poses(is_test)
    comps = signed_components(np.asarray(dz)[use])
    n_joints = q.shape[1]
    grid = SvgPanels(len(comps), n_joints, pw=min(200.0, 1180.0 / n_joints - 10), ph=105, gx=10, gy=10,
                     left=80, top=36)
    for j in range(n_joints):
        x = np.rad2deg(q[use, j])
        for r, (label, unit, y) in enumerate(comps):
            b = binned_quantiles(x, y)
            color = colour(0) if unit == "mm" else colour(1)
            grid.band(r, j, b["x"], b["q05"], b["q95"], color=color, alpha=0.25)
            grid.line(r, j, b["x"], b["mean"], color=color, width=1.2, marker=True)
    svg = Svg(grid.width, grid.height)
    grid.finish(svg, xlabels=[f"q{j + 1} [deg]" for j in range(n_joints)],
                ylabels=[f"{label} [{unit}]" for label, unit, _ in comps])
    svg.text(grid.width / 2, 18, f"{title}: signed error against each joint — bin mean (line) and 90 % band "
             f"(5–95 % quantiles); {words}", size=LABEL_PX, anchor="middle")
    return svg.save(Path(out) / name)


def _axis_ticks(svg, x0, y0, w, h, xr, yr, xlabel, ylabel):
    """Frame, ticks and labels of a plain panel at (x0, y0) of w × h px over ranges xr, yr."""
    xt, yt = nice_ticks(*xr, n=5), nice_ticks(*yr, n=5)
    gx = x0 + (xt - xr[0]) / (xr[1] - xr[0]) * w
    gy = y0 + h - (yt - yr[0]) / (yr[1] - yr[0]) * h
    svg.segments(gx, np.full_like(gx, y0 + h), gx, np.full_like(gx, y0 + h + 4), stroke="#333", width=0.8)
    svg.segments(np.full_like(gy, x0 - 4), gy, np.full_like(gy, x0), gy, stroke="#333", width=0.8)
    for t, g in zip(xt, gx):
        svg.text(g, y0 + h + 16, f"{t:.3g}", anchor="middle")
    for t, g in zip(yt, gy):
        svg.text(x0 - 6, g, f"{t:.3g}", anchor="end", baseline="middle")
    svg.path(f"M{x0:.1f} {y0:.1f}h{w:g}v{h:g}h{-w:g}z", stroke="#333", width=0.9)
    svg.text(x0 + w / 2, y0 + h + 36, xlabel, size=LABEL_PX, anchor="middle")
    svg.text(x0 - 46, y0 + h / 2, ylabel, size=LABEL_PX, anchor="middle", baseline="middle", rotate=-90)


def svg_workspace(xyz, dz, title: str, out: Path, name: str) -> str:
    """Tool positions (top view x-z and side view x-y of F_I) coloured by ‖Δt‖ (mm), all poses,
    aggregated: each cell of a square grid (up to WORKSPACE_CELLS along the longer side) shows the
    largest error of its poses (:func:`campaign.identify.report.largest_per_cell`); the colour scale
    runs from 0 to the largest error (square-root spacing); a red circle marks the largest."""
    pos, _ = _norms(np.asarray(dz))
    xyz = np.asarray(xyz, dtype=float)
    vmin, vmax = workspace_colour_scale(pos)
    box_w, box_h, left, top = 470.0, 400.0, 80.0, 60.0
    svg = Svg(1280, top + box_h + 60)
    cells = int(np.clip(3 * np.sqrt(len(pos)), WORKSPACE_MIN_CELLS, WORKSPACE_CELLS))
    levels = viridis(np.linspace(0, 1, WORKSPACE_LEVELS))
    for v, (a, b, la, lb, view) in enumerate(((2, 0, "z_I [m]", "x_I [m]", "top view"),
                                              (2, 1, "z_I [m]", "height −y_I [m]", "side view"))):
        yb = xyz[:, b] if b != 1 else -xyz[:, 1]
        img, (ex0, ex1, ey0, ey1) = largest_per_cell(xyz[:, a], yb, pos, cells)
        scale = min(box_w / max(ex1 - ex0, 1e-12), box_h / max(ey1 - ey0, 1e-12))  # px per m, equal aspect
        w, h = (ex1 - ex0) * scale, (ey1 - ey0) * scale
        x0, y0 = left + v * (box_w + 110), top + (box_h - h) / 2
        cell = (ex1 - ex0) / img.shape[1] * scale
        iy, ix = np.nonzero(np.isfinite(img))
        t = np.sqrt(np.clip((img[iy, ix] - vmin) / (vmax - vmin), 0, 1))  # square-root spacing
        level = np.minimum((t * WORKSPACE_LEVELS).astype(int), WORKSPACE_LEVELS - 1)
        # in cell units (x right, y up, y = j the middle of row j): each cell a stroke of one
        # cell's width along its row, a little longer and wider than the cell (no seams of white
        # between neighbours); one path per colour level
        overlap = 1 + 0.5 / max(cell, 1e-9)
        svg.add(f'<g transform="matrix({cell:.4f} 0 0 {-cell:.4f} {x0:.2f} {y0 + h - cell / 2:.2f})" fill="none" '
                f'stroke-width="{overlap:.3f}" shape-rendering="crispEdges">')
        for k in np.unique(level):
            sel = level == k
            svg.add(f'<path d="{"".join(f"M{i} {j}h{overlap:.2f}" for i, j in zip(ix[sel], iy[sel]))}" '
                    f'stroke="{levels[k]}"/>')
        svg.add("</g>")
        if len(pos):
            k = int(np.argmax(pos))
            cx, cy = x0 + (xyz[k, a] - ex0) * scale, y0 + h - (yb[k] - ey0) * scale
            svg.add(f'<circle cx="{cx:.1f}" cy="{cy:.1f}" r="8" fill="none" stroke="red" stroke-width="1.5" '
                    f'class="largest"/>')
        _axis_ticks(svg, x0, y0, w, h, (ex0, ex1), (ey0, ey1), la, lb)
        svg.text(x0 + w / 2, y0 - 8, view, size=LABEL_PX, anchor="middle")
    # the colour bar: 0 to the largest error, square-root spacing, a red line at the largest
    bx, by, bw, bh = left + 2 * box_w + 110 + 30, top, 16.0, box_h  # right of the side view
    edges = np.linspace(0, 1, WORKSPACE_LEVELS + 1)
    svg.add("".join(f'<rect x="{bx}" y="{by + bh * (1 - edges[k + 1]):.2f}" width="{bw}" '
                    f'height="{bh / WORKSPACE_LEVELS + 0.3:.2f}" fill="{levels[k]}"/>' for k in range(WORKSPACE_LEVELS)))
    svg.path(f"M{bx} {by}h{bw}v{bh}h{-bw}z", stroke="#333", width=0.8)
    ticks = nice_ticks(vmin, vmax, n=5)
    ty = by + bh * (1 - np.sqrt((ticks - vmin) / (vmax - vmin)))
    svg.segments(np.full_like(ty, bx + bw), ty, np.full_like(ty, bx + bw + 4), ty, stroke="#333", width=0.8)
    for t, g in zip(ticks, ty):
        svg.text(bx + bw + 6, g, f"{t:.3g}", baseline="middle")
    svg.path(f"M{bx} {by:.1f}h{bw}", stroke="red", width=2.5)
    svg.text(bx + bw + 62, by + bh / 2, "‖Δt‖ [mm] (0 to the largest, square-root scale)", size=LABEL_PX,
             anchor="middle", baseline="middle", rotate=-90)
    svg.text(640, 22, f"{title}: position error over the workspace, all {len(pos)} poses "
             f"(red circle: the largest, {vmax:.3g} mm)", size=SUPTITLE_PX, anchor="middle")
    return svg.save(Path(out) / name)


def svg_history(history_path: Path, out: Path, name: str = "history.svg", noise_floor="auto"):
    """Test-set mean position error of each model stage as it was added, from the last calibrate run
    that fitted it (:func:`history_stages`: the current model as the verdict states it), and per stage
    (log axis), with the tracker noise floor as a dotted line (``noise_floor``: a NoiseFloor, None
    for none, or "auto": :func:`tracker_noise_floor` of the run that holds ``history_path``)."""
    rows = history_rows(history_path)
    if not rows:
        return None
    if isinstance(noise_floor, str) and noise_floor == "auto":
        noise_floor = tracker_noise_floor(Path(history_path).parent.parent)
    points = history_stages(rows)
    labels = [stage for _, stage, _ in points]
    values = [st["position_mm"]["mean"] for _, _, st in points]
    shown = np.maximum(values, REPORT_LOG_FLOOR_MM)  # on the log axis: exact data on the floor
    lo, hi = float(shown.min()), float(shown.max())
    floor = noise_floor.mean_position_mm if noise_floor is not None and noise_floor.mean_position_mm > 0 else None
    if floor is not None:  # a zero floor has no place on a log axis
        lo = min(lo, floor)
    ylo, yhi = np.log10(lo / 2.5), np.log10(hi * 3.0)
    wrapped = [_wrap_stage(label) for label in labels]
    n_lines = max([s.count("\n") + 1 for s in wrapped] + [1])
    left, top, pw, ph = 90.0, 40.0, 880.0, 340.0
    svg = Svg(left + pw + 20, top + ph + 40 + 16 * n_lines)
    n = len(values)

    def X(x):
        return left + (np.asarray(x, dtype=float) + 0.5) / n * pw

    def Y(v):
        return top + ph - (np.log10(np.asarray(v, dtype=float)) - ylo) / (yhi - ylo) * ph

    # log axis: grid and labels at the decades (2× and 5× too when fewer than two decades)
    dec = decade_ticks(ylo, yhi)
    gy = Y(10.0 ** dec)
    svg.segments(np.full_like(gy, left), gy, np.full_like(gy, left + pw), gy, stroke="#e0e0e0", width=0.6)
    minor = np.log10(np.outer(10.0 ** np.arange(np.floor(ylo), np.ceil(yhi) + 1), np.arange(2, 10)).ravel())
    minor = minor[(minor > ylo) & (minor < yhi)]
    my = Y(10.0 ** minor)
    svg.segments(np.full_like(my, left - 2.5), my, np.full_like(my, left), my, stroke="#333", width=0.6)
    svg.segments(np.full_like(gy, left - 5), gy, np.full_like(gy, left), gy, stroke="#333", width=0.8)
    for t, g in zip(dec, gy):
        svg.text(left - 8, g, f"{10.0 ** t:.3g}", anchor="end", baseline="middle", cls="ytick")
    svg.path(f"M{left} {top}h{pw}v{ph}h{-pw}z", stroke="#333", width=0.9)
    svg.text(left - 62, top + ph / 2, "test-set mean ‖Δt‖ [mm] (log scale)", size=LABEL_PX, anchor="middle",
             baseline="middle", rotate=-90)
    svg.text(left + pw / 2, 22, "watch the error fall: each model stage as it was added", size=SUPTITLE_PX,
             anchor="middle")
    chain = [x for x, label in enumerate(labels) if label not in SIDE_STAGES]
    side = [x for x, label in enumerate(labels) if label in SIDE_STAGES]
    vals = shown
    legend = [("line", colour(0), "model as it was built up")]
    svg.polyline(X(chain), Y(vals[chain]), stroke=colour(0), width=1.6)
    svg.markers(X(chain), Y(vals[chain]), r=4, fill=colour(0))
    if side:
        svg.markers(X(side), Y(vals[side]), r=4, fill="#999", shape="s")
        legend.append(("square", "#999", "ANN on the nominal model (comparison)"))
    if floor is not None:
        fy = float(Y(floor))
        svg.add(f'<path d="M{left} {fy:.1f}h{pw}" stroke="{colour(3)}" stroke-width="1.8" stroke-dasharray="2 3" '
                f'fill="none" class="noise-floor" data-floor-mm="{floor:.6g}"/>')
        legend.append(("dots", colour(3), f"tracker noise floor {floor_label(noise_floor)}"))
    for x, (v, y) in enumerate(zip(values, shown)):
        svg.text(float(X(x)), float(Y(y)) - 9, f"{v:.3g}", anchor="middle")
    for x, s in enumerate(wrapped):
        svg.text(float(X(x)), top + ph + 16, s, anchor="middle")
    # the legend, upper right, on white
    lw = 14 + 8 + max(len(t) for _, _, t in legend) * 6.2
    lx, ly = left + pw - lw - 8, top + 8
    svg.add(f'<rect x="{lx:.1f}" y="{ly:.1f}" width="{lw:.1f}" height="{18 * len(legend) + 8}" fill="#fff" '
            f'fill-opacity="0.85" stroke="#ccc"/>')
    for k, (kind, color, text) in enumerate(legend):
        yy = ly + 13 + 18 * k
        if kind == "square":
            svg.markers([lx + 15], [yy], r=4, fill=color, shape="s")
        else:
            svg.path(f"M{lx + 6:.1f} {yy:.1f}h18", stroke=color, width=1.8, dash="2 3" if kind == "dots" else None)
            if kind == "line":
                svg.markers([lx + 15], [yy], r=3.5, fill=color)
        svg.text(lx + 30, yy, text, size=TICK_PX, baseline="middle", cls="legend")
    return svg.save(Path(out) / name)


def write_figures(run_dir, residuals: dict, order: list, q, xyz, is_test, out: Path, noise_floor):
    """Every figure of the calibration report: (distributions [names], [(stage, joints name)],
    workspace name or None, history name or None)."""
    current = order[-1]
    dist = svg_distributions(residuals, is_test, out)
    joints = [(s, svg_against_joints(q, residuals[s], is_test, s, out, f"joints_{s.replace('+', '_')}.svg"))
              for s in order if s in residuals]
    ws = svg_workspace(xyz, residuals[current], current, out, "workspace.svg") if current in residuals else None
    hist = svg_history(Path(out) / "history.json", out, noise_floor=noise_floor)
    return dist, joints, ws, hist

