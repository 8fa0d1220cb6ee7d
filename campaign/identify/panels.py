"""Small multiples drawn fast: a grid of panels in one matplotlib Axes.

A figure of 36 subplots spends seconds building and drawing each Axes' ticks (matplotlib
makes every tick an artist of two lines and two texts, per Axes, even where shared axes hide
the labels). The panels here share one Axes: each column one x range, each row one y range
(as ``sharex="col", sharey="row"`` would), the frames, grid lines and curves of all panels a
handful of collections, tick labels only on the outer panels. Drawn in about a tenth of the
time of the subplots (benchmarks/bench_identify.py, the report row).
"""

from __future__ import annotations

import numpy as np

#: ticks per panel axis (matplotlib's MaxNLocator picks round values)
PANEL_TICKS = 4
#: room (inches) left of the first column for the tick labels and the row labels, and below the
#: last row for the tick labels and the column labels
LEFT_ROOM_IN = 0.75
BOTTOM_ROOM_IN = 0.45


def _ticks(lo, hi):
    from matplotlib.ticker import MaxNLocator

    t = MaxNLocator(nbins=PANEL_TICKS, steps=[1, 2, 2.5, 5, 10]).tick_values(lo, hi)
    return t[(t >= lo - 1e-12 * abs(hi - lo)) & (t <= hi + 1e-12 * abs(hi - lo))]


def _decades(lo, hi):
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


class PanelGrid:
    """rows × cols panels in one Axes ``ax`` (its own axis hidden), with shared x per column
    and shared y per row. Add curves with :meth:`band` and :meth:`line` (data coordinates of
    the panel), then :meth:`finish` computes the ranges, maps everything into the Axes and
    draws frames, grid lines, zero lines and the outer panels' tick labels.

    Panel (r, c) fills [c·(1 + gap_x), c·(1 + gap_x) + 1] × [−r·(1 + gap_y) − 1, −r·(1 + gap_y)]
    of the Axes' data coordinates (row 0 on top).
    """

    def __init__(self, ax, rows: int, cols: int, *, gap_x: float = 0.06, gap_y: float = 0.08):
        self.ax, self.rows, self.cols, self.gap_x, self.gap_y = ax, rows, cols, gap_x, gap_y
        self._items = []  # (kind, r, c, x, y..., style)
        self._titles = []
        ax.set_axis_off()

    def band(self, r, c, x, lo, hi, **style):
        """A filled band between lo and hi along x (all (k,))."""
        self._items.append(("band", r, c, np.asarray(x, float), np.asarray(lo, float), np.asarray(hi, float), style))

    def line(self, r, c, x, y, **style):
        """A line (with markers when ``marker`` is given) through (x, y) (both (k,))."""
        self._items.append(("line", r, c, np.asarray(x, float), np.asarray(y, float), None, style))

    def vline(self, r, c, x, **style):
        """A vertical line at x across the panel's height (``linestyle`` "-" or "--")."""
        self._items.append(("vline", r, c, np.asarray([x], float), None, None, style))

    def title(self, r, c, text, *, fontsize: float = 9.0):
        """A line of text above the panel, at its left edge."""
        self._titles.append((r, c, text, fontsize))

    def _origin(self, r, c):
        return c * (1.0 + self.gap_x), -r * (1.0 + self.gap_y) - 1.0

    def finish(self, *, xlabels=(), ylabels=(), label_size: float = 7.0, zero_line: bool = True,
               xlog: bool = False, ylow=None):
        """Map the curves into the panels and draw; xlabels: one per column (under the bottom
        row), ylabels: one per row (left of the first column). xlog: the x values given are
        log10 of the quantity (ticks at decades, labelled with the quantity); ylow: the lower
        end of every row's y range (e.g. 0 for counts) instead of the data's."""
        from matplotlib.collections import LineCollection, PolyCollection

        ax = self.ax
        xr = [_range([it[3] for it in self._items if it[2] == c], pad=0.03) for c in range(self.cols)]
        yr = [_range([v for it in self._items if it[1] == r for v in (it[4], it[5]) if v is not None] + [np.zeros(1)])
              for r in range(self.rows)]
        if ylow is not None:
            yr = [(float(ylow), hi) for _, hi in yr]
        xticks = [(_decades if xlog else _ticks)(*xr[c]) for c in range(self.cols)]
        fmt_x = (lambda t: f"{10.0 ** t:.3g}") if xlog else (lambda t: f"{t:.4g}")  # noqa: E731

        def to_ax(r, c, x, y):
            x0, y0 = self._origin(r, c)
            (xl, xh), (yl, yh) = xr[c], yr[r]
            return x0 + (x - xl) / (xh - xl), y0 + (y - yl) / (yh - yl)

        frames, grid, zeros = [], [], []
        for r in range(self.rows):
            yt = _ticks(*yr[r])
            for c in range(self.cols):
                x0, y0 = self._origin(r, c)
                frames.append([(x0, y0), (x0 + 1, y0), (x0 + 1, y0 + 1), (x0, y0 + 1), (x0, y0)])
                for t in xticks[c]:
                    gx, _ = to_ax(r, c, t, 0.0)
                    grid.append([(gx, y0), (gx, y0 + 1)])
                for t in yt:
                    _, gy = to_ax(r, c, 0.0, t)
                    grid.append([(x0, gy), (x0 + 1, gy)])
                if zero_line and yr[r][0] < 0 < yr[r][1]:
                    _, zy = to_ax(r, c, 0.0, 0.0)
                    zeros.append([(x0, zy), (x0 + 1, zy)])
        ax.add_collection(LineCollection(grid, colors="0.85", linewidths=0.5, zorder=0))
        ax.add_collection(LineCollection(zeros, colors="0.5", linewidths=0.6, zorder=1))
        # the curves, grouped by style: one collection (or one Line2D) per style
        bands, lines, vlines = {}, {}, {}
        for kind, r, c, x, a, b, style in self._items:
            key = tuple(sorted(style.items()))
            if kind == "vline":
                px, _ = to_ax(r, c, x, 0.0)
                y0 = self._origin(r, c)[1]
                vlines.setdefault(key, []).append([(px[0], y0), (px[0], y0 + 1)])
            elif kind == "band":
                px, pa = to_ax(r, c, x, a)
                _, pb = to_ax(r, c, x, b)
                bands.setdefault(key, []).append(np.column_stack([np.r_[px, px[::-1]], np.r_[pa, pb[::-1]]]))
            else:
                px, py = to_ax(r, c, x, a)
                lines.setdefault(key, []).append((px, py))
        for key, polys in bands.items():
            st = dict(key)
            ax.add_collection(PolyCollection(polys, facecolors=st.get("color", "C0"), alpha=st.get("alpha", 0.25),
                                             linewidths=0, zorder=2))
        for key, segs in lines.items():
            st = dict(key)
            # one Line2D per style: the segments joined by NaN breaks
            xs = np.concatenate([np.r_[px, np.nan] for px, _ in segs])
            ys = np.concatenate([np.r_[py, np.nan] for _, py in segs])
            ax.plot(xs, ys, color=st.get("color", "C0"), linewidth=st.get("linewidth", 1.2),
                    marker=st.get("marker"), ms=st.get("ms", 2.5), zorder=3)
        for key, segs in vlines.items():
            st = dict(key)
            ax.add_collection(LineCollection(segs, colors=st.get("color", "k"), linewidths=st.get("linewidth", 1.0),
                                             linestyles=st.get("linestyle", "-"), zorder=3))
        ax.add_collection(LineCollection(frames, colors="0.2", linewidths=0.8, zorder=4))
        # room for the labels, in inches of the figure: the Axes' limits leave it left and below
        fig_w, fig_h = ax.figure.get_size_inches()
        pos = ax.get_position()
        ax_w, ax_h = pos.width * fig_w, pos.height * fig_h
        x_end, y_end = self._origin(self.rows - 1, self.cols - 1)
        inner_w, inner_h = x_end + 1.0, -y_end
        scale = max(1.0, label_size / 7.0)  # the room grows with the type
        left_in, bottom_in = LEFT_ROOM_IN * scale, BOTTOM_ROOM_IN * scale
        room_l, room_b = left_in / ax_w, bottom_in / ax_h  # fractions of the Axes
        ux = inner_w / (1.0 - room_l) / ax_w  # data units per inch
        uy = inner_h / (1.0 - room_b) / ax_h
        ax.set_xlim(-left_in * ux, inner_w + 0.02 * ux)  # the frames' lines whole at the edges
        ax.set_ylim(y_end - bottom_in * uy, 0.02 * uy)
        for r, c, text, size in self._titles:
            x0, y0 = self._origin(r, c)
            ax.text(x0, y0 + 1.0 + 0.03 * uy, text, ha="left", va="bottom", fontsize=size)
        # tick labels on the outer panels only
        fmt = lambda t: f"{t:.4g}"  # noqa: E731
        for c in range(self.cols):
            r = self.rows - 1
            x0, y0 = self._origin(r, c)
            for t in xticks[c]:
                gx, _ = to_ax(r, c, t, 0.0)
                ax.text(gx, y0 - 0.04 * uy, fmt_x(t), ha="center", va="top", fontsize=label_size)
            if c < len(xlabels):
                ax.text(x0 + 0.5, y0 - 0.22 * scale * uy, xlabels[c], ha="center", va="top", fontsize=label_size + 2)
        for r in range(self.rows):
            x0, y0 = self._origin(r, 0)
            for t in _ticks(*yr[r]):
                _, gy = to_ax(r, 0, 0.0, t)
                ax.text(x0 - 0.04 * ux, gy, fmt(t), ha="right", va="center", fontsize=label_size)
            if r < len(ylabels):
                ax.text(x0 - (left_in - 0.12 * scale) * ux, y0 + 0.5, ylabels[r], ha="center", va="center", rotation=90,
                        fontsize=label_size + 2)
        return xr, yr
