"""SVG figures written directly from numpy: no matplotlib (issue 22: its import and drawing were
most of `campaign calibrate`'s wall time).

:class:`Svg` collects elements (paths, polylines, text) in pixel coordinates (y down) and writes
one standalone ``.svg`` file. :class:`SvgPanels` draws small multiples (rows × cols panels, x
shared per column, y per row, tick labels on the outer panels). Only aggregated data go into a figure
(histogram steps, bin means and bands, per-cell maxima grouped by colour): a figure's size does
not grow with the number of poses.
"""

from __future__ import annotations

import html
from pathlib import Path

import numpy as np

#: matplotlib's default colour cycle ("C0".."C9"), so the figures keep their colours
CYCLE = ("#1f77b4", "#ff7f0e", "#2ca02c", "#d62728", "#9467bd", "#8c564b", "#e377c2", "#7f7f7f", "#bcbd22",
         "#17becf")
#: viridis at 9 evenly spaced points (interpolated linearly in between)
VIRIDIS = np.array([[68, 1, 84], [71, 44, 122], [59, 81, 139], [44, 113, 142], [33, 144, 141],
                    [39, 173, 129], [92, 200, 99], [170, 220, 50], [253, 231, 37]], dtype=float)
FONT = "DejaVu Sans, Arial, sans-serif"
TICK_PX, LABEL_PX, TITLE_PX, SUPTITLE_PX = 11, 13, 12, 14
#: an x tick label this close (px) to a panel's side is written inward from its tick (else it
#: would run into the next panel's first or last label)
EDGE_TICK_PX = 10.0


def colour(k: int) -> str:
    return CYCLE[k % len(CYCLE)]


def viridis(t) -> list:
    """'#rrggbb' for each t in [0, 1]."""
    t = np.clip(np.asarray(t, dtype=float), 0.0, 1.0) * (len(VIRIDIS) - 1)
    k = np.minimum(np.floor(t).astype(int), len(VIRIDIS) - 2)
    f = (t - k)[:, None]
    rgb = np.round(VIRIDIS[k] * (1 - f) + VIRIDIS[k + 1] * f).astype(int)
    return [f"#{r:02x}{g:02x}{b:02x}" for r, g, b in rgb]


def nice_ticks(lo: float, hi: float, n: int = 4) -> np.ndarray:
    """Round tick values inside [lo, hi] (about n intervals, steps 1, 2, 2.5, 5 × 10^k)."""
    if not (np.isfinite(lo) and np.isfinite(hi)) or hi <= lo:
        return np.array([lo])
    raw = (hi - lo) / n
    mag = 10.0 ** np.floor(np.log10(raw))
    step = next(s * mag for s in (1, 2, 2.5, 5, 10) if s * mag >= raw * (1 - 1e-9))
    t = np.arange(np.ceil(lo / step - 1e-9), np.floor(hi / step + 1e-9) + 1) * step
    return np.where(np.abs(t) < step * 1e-9, 0.0, t)


def decade_ticks(lo, hi):
    """Ticks (log10 values) at the decades between lo and hi, with 2× and 5× when fewer than two."""
    d = np.arange(np.ceil(lo), np.floor(hi) + 1)
    if len(d) < 2:
        k = np.arange(np.floor(lo), np.ceil(hi) + 1)
        d = np.sort(np.concatenate([k, k + np.log10(2), k + np.log10(5)]))
        d = d[(d >= lo) & (d <= hi)]
    return d


def _range(values, pad=0.05):
    v = np.concatenate([np.ravel(x) for x in values]) if values else np.zeros(0)
    v = v[np.isfinite(v)]
    if len(v) == 0:
        return -1.0, 1.0
    lo, hi = float(v.min()), float(v.max())
    if hi - lo <= 0:
        w = max(abs(lo), 1e-12) * 0.1
        return lo - w, hi + w
    return lo - pad * (hi - lo), hi + pad * (hi - lo)


def points(x, y) -> str:
    """'x,y x,y …' (px, 0.1 px) of the finite points."""
    x, y = np.asarray(x, dtype=float), np.asarray(y, dtype=float)
    ok = np.isfinite(x) & np.isfinite(y)
    return " ".join(f"{a:.1f},{b:.1f}" for a, b in zip(x[ok], y[ok]))


class Svg:
    """An SVG image of width × height px; elements in px, y down."""

    def __init__(self, width: float, height: float):
        self.width, self.height = float(width), float(height)
        self.parts: list = []

    def add(self, element: str):
        self.parts.append(element)

    def path(self, d: str, *, stroke="none", fill="none", width=1.0, dash=None, opacity=None, cls=None, extra=""):
        attrs = f' stroke="{stroke}" fill="{fill}" stroke-width="{width:g}"'
        if dash:
            attrs += f' stroke-dasharray="{dash}"'
        if opacity is not None:
            attrs += f' fill-opacity="{opacity:g}"'
        if cls:
            attrs += f' class="{cls}"'
        self.add(f'<path d="{d}"{attrs}{extra}/>')

    def polyline(self, x, y, *, stroke, width=1.2, dash=None, cls=None):
        dash_attr = f' stroke-dasharray="{dash}"' if dash else ""
        cls_attr = f' class="{cls}"' if cls else ""
        self.add(f'<polyline points="{points(x, y)}" fill="none" stroke="{stroke}" stroke-width="{width:g}"'
                 f'{dash_attr}{cls_attr}/>')

    def segments(self, x0, y0, x1, y1, **style):
        """Straight segments (x0, y0)–(x1, y1) (arrays of the same length) as one path."""
        d = "".join(f"M{a:.1f} {b:.1f}L{c:.1f} {e:.1f}" for a, b, c, e in zip(x0, y0, x1, y1))
        if d:
            self.path(d, **style)

    def markers(self, x, y, *, r=2.5, fill, shape="o"):
        """Markers at (x, y): circles ("o") or squares ("s"), as one path."""
        if shape == "s":
            d = "".join(f"M{a - r:.1f} {b - r:.1f}h{2 * r:g}v{2 * r:g}h{-2 * r:g}z" for a, b in zip(x, y))
        else:
            d = "".join(f"M{a - r:.1f} {b:.1f}a{r:g} {r:g} 0 1 0 {2 * r:g} 0a{r:g} {r:g} 0 1 0 {-2 * r:g} 0z"
                        for a, b in zip(x, y))
        if d:
            self.path(d, fill=fill)

    def text(self, x, y, s: str, *, size=TICK_PX, anchor="start", baseline="auto", rotate=None, fill="#000",
             weight=None, cls=None):
        """Text at (x, y); several lines when s holds newlines (each 1.2 em below the last)."""
        rot = f' transform="rotate({rotate:g} {x:.1f} {y:.1f})"' if rotate is not None else ""
        wt = f' font-weight="{weight}"' if weight else ""
        cl = f' class="{cls}"' if cls else ""
        lines = str(s).split("\n")
        if len(lines) == 1:
            body = html.escape(lines[0])
        else:
            body = "".join(f'<tspan x="{x:.1f}" dy="{0 if k == 0 else 1.2:g}em">{html.escape(line)}</tspan>'
                           for k, line in enumerate(lines))
        self.add(f'<text x="{x:.1f}" y="{y:.1f}" font-size="{size:g}" text-anchor="{anchor}" '
                 f'dominant-baseline="{baseline}" fill="{fill}"{wt}{rot}{cl}>{body}</text>')

    def text_svg(self) -> str:
        return (f'<svg xmlns="http://www.w3.org/2000/svg" width="{self.width:.0f}" height="{self.height:.0f}" '
                f'viewBox="0 0 {self.width:.0f} {self.height:.0f}" font-family="{FONT}">'
                f'<rect width="100%" height="100%" fill="#fff"/>' + "".join(self.parts) + "</svg>\n")

    def save(self, path: Path) -> str:
        """Write the file; return its name."""
        path = Path(path)
        path.write_text(self.text_svg(), encoding="utf-8")
        return path.name


class SvgPanels:
    """rows × cols panels of pw × ph px, the top-left one at (left, top), gaps gx, gy px between.
    Add curves (data coordinates of a panel) with :meth:`band`, :meth:`line`, :meth:`vline` and
    :meth:`title`, then :meth:`finish` maps them and draws frames, grid lines, zero lines and the
    outer panels' tick labels."""

    def __init__(self, rows, cols, *, pw, ph, gx=12.0, gy=14.0, left=80.0, top=40.0, bottom=56.0, right=12.0):
        self.rows, self.cols, self.pw, self.ph, self.gx, self.gy = rows, cols, pw, ph, gx, gy
        self.left, self.top = left, top
        self.width = left + cols * pw + (cols - 1) * gx + right
        self.height = top + rows * ph + (rows - 1) * gy + bottom
        self._items, self._titles = [], []

    def origin(self, r, c):
        """Top-left px of panel (r, c)."""
        return self.left + c * (self.pw + self.gx), self.top + r * (self.ph + self.gy)

    def band(self, r, c, x, lo, hi, *, color, alpha=0.25):
        self._items.append(("band", r, c, np.asarray(x, float), np.asarray(lo, float), np.asarray(hi, float),
                            (color, alpha)))

    def line(self, r, c, x, y, *, color, width=1.2, marker=False, dash=None):
        self._items.append(("line", r, c, np.asarray(x, float), np.asarray(y, float), None,
                            (color, width, marker, dash)))

    def vline(self, r, c, x, *, color="#000", width=1.0, dash=None):
        self._items.append(("vline", r, c, np.asarray([x], float), None, None, (color, width, dash)))

    def title(self, r, c, text):
        self._titles.append((r, c, text))

    def finish(self, svg: Svg, *, xlabels=(), ylabels=(), zero_line=True, xlog=False, ylow=None):
        """Draw into ``svg``; xlog: the x values given are log10 of the quantity (ticks at decades,
        labelled with the quantity); ylow: the lower end of every row's y range (0 for counts)."""
        xr = [_range([it[3] for it in self._items if it[2] == c], pad=0.03) for c in range(self.cols)]
        yr = [_range([v for it in self._items if it[1] == r for v in (it[4], it[5]) if v is not None] + [np.zeros(1)])
              for r in range(self.rows)]
        if ylow is not None:
            yr = [(float(ylow), hi) for _, hi in yr]
        xticks = [(decade_ticks(*xr[c]) if xlog else nice_ticks(*xr[c])) for c in range(self.cols)]
        yticks = [nice_ticks(*yr[r]) for r in range(self.rows)]

        def px(r, c, x, y):
            x0, y0 = self.origin(r, c)
            (xl, xh), (yl, yh) = xr[c], yr[r]
            return x0 + (np.asarray(x) - xl) / (xh - xl) * self.pw, y0 + self.ph - (np.asarray(y) - yl) / (yh - yl) * self.ph

        grid, zeros, frames = [], [], []
        for r in range(self.rows):
            for c in range(self.cols):
                x0, y0 = self.origin(r, c)
                frames.append(f"M{x0:.1f} {y0:.1f}h{self.pw:g}v{self.ph:g}h{-self.pw:g}z")
                gxs, _ = px(r, c, xticks[c], 0.0)
                grid += [f"M{g:.1f} {y0:.1f}v{self.ph:g}" for g in np.atleast_1d(gxs)]
                _, gys = px(r, c, 0.0, yticks[r])
                grid += [f"M{x0:.1f} {g:.1f}h{self.pw:g}" for g in np.atleast_1d(gys)]
                if zero_line and yr[r][0] < 0 < yr[r][1]:
                    _, zy = px(r, c, 0.0, 0.0)
                    zeros.append(f"M{x0:.1f} {float(zy):.1f}h{self.pw:g}")
        svg.path("".join(grid), stroke="#d9d9d9", width=0.6)
        if zeros:
            svg.path("".join(zeros), stroke="#808080", width=0.8)
        # curves grouped by style: one path per style
        bands, lines, vlines = {}, {}, {}
        for kind, r, c, x, a, b, style in self._items:
            if kind == "band":
                X, A = px(r, c, x, a)
                _, B = px(r, c, x, b)
                bands.setdefault(style, []).append("M" + points(np.r_[X, X[::-1]], np.r_[A, B[::-1]]).replace(" ", "L") + "z")
            elif kind == "line":
                X, Y = px(r, c, x, a)
                lines.setdefault(style, []).append((X, Y))
            else:
                X, _ = px(r, c, x, 0.0)
                y0 = self.origin(r, c)[1]
                vlines.setdefault(style, []).append(f"M{float(X[0]):.1f} {y0:.1f}v{self.ph:g}")
        for (color, alpha), ds in bands.items():
            svg.path("".join(ds), fill=color, opacity=alpha)
        for (color, width, marker, dash), segs in lines.items():
            svg.path("".join("M" + points(X, Y).replace(" ", "L") for X, Y in segs if len(X)),
                     stroke=color, width=width, dash=dash, extra=' stroke-linejoin="round"')
            if marker:
                svg.markers(np.concatenate([X for X, _ in segs]), np.concatenate([Y for _, Y in segs]), r=2.2,
                            fill=color)
        for (color, width, dash), ds in vlines.items():
            svg.path("".join(ds), stroke=color, width=width, dash=dash)
        svg.path("".join(frames), stroke="#333", width=0.9)
        for r, c, text in self._titles:
            x0, y0 = self.origin(r, c)
            svg.text(x0, y0 - 5 - 1.2 * TITLE_PX * text.count("\n"), text, size=TITLE_PX)  # the last line 5 px above
        fmt_x = (lambda t: f"{10.0 ** t:.3g}") if xlog else (lambda t: f"{t:.4g}")  # noqa: E731
        r = self.rows - 1
        for c in range(self.cols):
            x0, y0 = self.origin(r, c)
            gxs, _ = px(r, c, xticks[c], 0.0)
            for t, g in zip(xticks[c], np.atleast_1d(gxs)):
                # a label at a panel's side stands inside the panel's width, clear of the neighbour's
                anchor = "start" if g - x0 < EDGE_TICK_PX else "end" if x0 + self.pw - g < EDGE_TICK_PX else "middle"
                svg.text(g + {"start": -2, "end": 2, "middle": 0}[anchor], y0 + self.ph + 14, fmt_x(t), anchor=anchor)
            if c < len(xlabels):
                svg.text(x0 + self.pw / 2, y0 + self.ph + 36, xlabels[c], size=LABEL_PX, anchor="middle")
        for r in range(self.rows):
            x0, y0 = self.origin(r, 0)
            _, gys = px(r, 0, 0.0, yticks[r])
            for t, g in zip(yticks[r], np.atleast_1d(gys)):
                svg.text(x0 - 4, g, f"{t:.4g}", anchor="end", baseline="middle")
            if r < len(ylabels):
                svg.text(x0 - self.left + 16, y0 + self.ph / 2, ylabels[r], size=LABEL_PX, anchor="middle",
                         baseline="middle", rotate=-90)
        return xr, yr
