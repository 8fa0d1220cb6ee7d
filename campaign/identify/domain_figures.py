"""The calibrated domain drawn (campaign.identify.svgplot): per joint, the training range with its
margin (shaded), the measured poses' sigma_mm (binned along the joint: mean and 5-95 % band) and
sigma_mm along a sweep of that joint
over its whole limit range, the other joints at the training poses' median (line): the model's
uncertainty rising where the data end. And the page section of the report that shows it."""

from __future__ import annotations

import html
from pathlib import Path

import numpy as np

from campaign.identify.report import binned_quantiles
from campaign.identify.svgplot import LABEL_PX, Svg, SvgPanels, colour

#: points of each joint's sweep
SWEEP_POINTS = 61


def joint_sweeps(robot, domain, sigma_fn, q_train) -> list:
    """[(x (SWEEP_POINTS,) in the joint's unit, sigma_mm (SWEEP_POINTS,))] per joint: joint j over its
    limits (±π where unbounded), the others at the training median; sigma_fn(q (n, N)) -> mm."""
    q0 = np.median(np.asarray(q_train, dtype=float), axis=0)
    out = []
    for j in range(robot.n_joints):
        lo, hi = robot.q_lower[j], robot.q_upper[j]
        if not (np.isfinite(lo) and np.isfinite(hi)):
            lo, hi = -np.pi, np.pi
        x = np.linspace(lo, hi, SWEEP_POINTS)
        Q = np.repeat(q0[None], SWEEP_POINTS, axis=0)
        Q[:, j] = x
        out.append((x, np.asarray(sigma_fn(Q), dtype=float)))
    return out


def svg_domain(robot, domain, sweeps, q_measured, sigma_measured, out: Path, name: str = "domain.svg",
               title: str = "") -> str:
    """One panel per joint: sigma_mm (log10) against the joint (deg, mm for prismatic); the shaded
    band is the calibrated domain's range of that joint (training range and margin)."""
    N = robot.n_joints
    f = np.where(robot.prismatic, 1e3, 180.0 / np.pi)
    q = np.asarray(q_measured, dtype=float)
    s_meas = np.log10(np.maximum(np.asarray(sigma_measured, dtype=float), 1e-6))
    s_all = np.concatenate([s_meas] + [np.log10(np.maximum(s, 1e-6)) for _, s in sweeps])
    lo_y, hi_y = float(np.min(s_all)), float(np.max(s_all))
    grid = SvgPanels(1, N, pw=min(200.0, 1180.0 / N - 10), ph=200, gx=10, gy=10, left=80, top=58)
    for j, (x, s) in enumerate(sweeps):
        a, b = (domain.lower[j] - domain.margin[j]) * f[j], (domain.upper[j] + domain.margin[j]) * f[j]
        grid.band(0, j, [a, b], [lo_y, lo_y], [hi_y, hi_y], color="#2ca02c", alpha=0.15)
        grid.line(0, j, x * f[j], np.log10(np.maximum(s, 1e-6)), color=colour(0), width=1.6)
        b = binned_quantiles(q[:, j] * f[j], s_meas)  # the measured poses, aggregated along the joint
        grid.band(0, j, b["x"], b["q05"], b["q95"], color=colour(1), alpha=0.35)
        grid.line(0, j, b["x"], b["mean"], color=colour(1), width=1.0, marker=True)
    svg = Svg(grid.width, grid.height)
    unit = ["mm" if p else "deg" for p in robot.prismatic]
    grid.finish(svg, xlabels=[f"q{j + 1} [{unit[j]}]" for j in range(N)], ylabels=["log10 sigma_mm"], zero_line=False)
    svg.text(grid.width / 2, 16, title or "sigma_mm, the model's 1-σ position uncertainty at the tool point: along "
             "each joint's range (line; the other joints at the training median)\nand at the measured poses (dots: "
             "bin mean, band 5-95 %); green: the calibrated domain", size=LABEL_PX, anchor="middle")
    return svg.save(Path(out) / name)


def domain_html(robot, record: dict, figure: str | None, heldout_mm: float | None) -> str:
    """The report's section: the identifiability, the per-joint ranges and coverage, the uncertainty
    over the domain beside the held-out error, and the figure."""
    from campaign.identify.domain import Domain

    dom = Domain.from_json(record["domain"], "domain")
    rows = "".join(f"<tr><td>{n}</td><td>{lo:.1f}</td><td>{hi:.1f}</td><td>{100 * cov:.0f} %</td></tr>"
                   for n, lo, hi, cov in dom.summary(robot))
    parts = ["<h2>Calibrated domain and uncertainty</h2>",
             "<p>Where the model was measured (training poses) and how well it is known there. Rows of "
             "<code>predict</code>, <code>compensate</code> and <code>export --csv</code> carry "
             "<code>in_domain</code> and <code>sigma_mm</code> (docs/domain.md).</p>",
             "<table><tr><th>joint</th><th>lowest (deg / mm)</th><th>highest</th><th>coverage of its range</th></tr>"
             f"{rows}</table>"]
    ident = record.get("identifiability") or {}
    if ident.get("words"):
        parts.append("<p>Not or barely identified by these poses: " + html.escape("; ".join(ident["words"])) + "</p>")
    for stage, o in record.get("over_domain", {}).items():
        held = "" if heldout_mm is None else f" (test-set mean error {heldout_mm:.4f} mm)"
        parts.append(f"<p>{html.escape(stage)}: sigma_mm over the measured poses mean {o['sigma_mm_mean']:.4f} mm, "
                     f"95th percentile {o['sigma_mm_q95']:.4f} mm{held if stage == list(record['over_domain'])[-1] else ''}; "
                     f"{html.escape(o['basis'])}.</p>")
    if figure:
        parts.append(f"<img src='{figure}'>")
    return "\n".join(parts)
