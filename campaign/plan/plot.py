"""The tour picture ``RUN/plan/tour.png``: where the tool goes, and in which order.

Two views of the cell (top and side; the default cell's frame is the COMAU's F_I) of the tool
positions of the planned poses, the path between
successive poses drawn as a line whose colour runs along the visiting order (colour bar:
visit number), the first and last poses numbered, the switch from one wall group to the
other marked, and the cell's obstacles, the wall (red), the tracker and the robot base.
"""

from __future__ import annotations

import numpy as np



def toward_centre(point, lo, hi, dx: float, dy: float) -> dict:
    """Where a label of a marker at ``point`` goes so that it stays inside the axes [lo, hi]:
    ``xytext`` (points) and the alignment, offset by (dx, dy) towards the axes' centre (left of
    a point in the right half, below one in the upper half)."""
    mid = 0.5 * (np.asarray(lo, dtype=float) + np.asarray(hi, dtype=float))
    right, up = point[0] > mid[0], point[1] > mid[1]
    return {"xytext": (-dx if right else dx, -dy if up else dy), "ha": "right" if right else "left",
            "va": "top" if up else "bottom"}

def tour_positions(robot, Q):
    """Tool positions (n, 3) m in F_I of joint vectors Q (n, N) rad, in visiting order."""
    from campaign.model.kinematics import forward

    return forward(robot, Q)[:, :3, 3] if len(Q) else np.zeros((0, 3))


def _switch_words(switch) -> str:
    """Legend text of the wall-group changes at visit indices ``switch`` (0-based)."""
    if len(switch) <= 1:
        return "next wall group begins"
    shown = ", ".join(f"#{k + 1}" for k in switch[:6]) + (", …" if len(switch) > 6 else "")
    return f"wall group changes ({len(switch)}: {shown})"


def _views(scene, tracker, frame):
    """The two views ((a, b, label a, label b) each: cell axes drawn across and up) and the sign
    that makes the vertical axis point up: across, the horizontal axis that points most towards
    the tracker; up, the other horizontal axis (top view) and the vertical one (side view)."""
    down = np.asarray(getattr(scene, "down", None) if getattr(scene, "down", None) is not None else (0, 1, 0))
    v = int(np.argmax(np.abs(down)))
    horizontal = [k for k in range(3) if k != v]
    a = max(horizontal, key=lambda k: abs(tracker[k]))
    b = [k for k in horizontal if k != a][0]
    up_sign = -1 if down[v] > 0 else 1
    name = "xyz"
    towards = f"{name[a]}_{frame} [m] (towards the tracker)"
    height = f"height {'−' if up_sign < 0 else ''}{name[v]}_{frame} [m]"
    return ((a, b, towards, f"{name[b]}_{frame} [m]"), (a, v, towards, height)), up_sign


def plot_tour(path, robot, scene, Q, front) -> None:
    """Write the tour picture. Q (n, N) rad in visiting order; front (n,) bool: pose in front of the wall."""
    import matplotlib.pyplot as plt

    fig = tour_figure(robot, scene, Q, front)
    fig.savefig(path, dpi=110)
    plt.close(fig)


def tour_figure(robot, scene, Q, front):
    """The tour picture as a matplotlib Figure (:func:`plot_tour` writes it)."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    from matplotlib.collections import LineCollection
    from matplotlib.colors import Normalize
    from matplotlib.lines import Line2D
    from matplotlib.patches import Patch

    T_cell_I = np.eye(4) if getattr(scene, "T_cell_I", None) is None else np.asarray(scene.T_cell_I)
    t = tour_positions(robot, Q) @ T_cell_I[:3, :3].T + T_cell_I[:3, 3]  # in the cell's frame
    n = len(t)
    base = T_cell_I[:3, 3]
    front = np.asarray(front, dtype=bool)
    # the visit index where the tour crosses from one wall group to the other (None: one group)
    switch = np.flatnonzero(front[1:] != front[:-1]) + 1 if n > 1 else np.zeros(0, int)
    cmap = plt.get_cmap("viridis")
    norm = Normalize(1, max(n, 2))
    o = T_cell_I[:3, :3] @ scene.tracker_position + T_cell_I[:3, 3]
    views, up_sign = _views(scene, o, "I" if np.array_equal(T_cell_I, np.eye(4)) else "cell")
    # each view: the tool positions and the robot base, with a margin; the rest of the cell
    # (the tracker, far away) is pointed at from the edge. Panel widths follow the views' extents
    # (equal scales on both axes) so that no space is wasted beside them.
    limits = []
    for a, b, _, _ in views:
        sign = up_sign if b == views[1][1] else 1
        box = np.vstack([np.column_stack([t[:, a], sign * t[:, b]]), [[base[a], sign * base[b]]]])
        limits.append((box.min(axis=0) - 0.15, box.max(axis=0) + 0.15))
    panel_h = 4.0
    widths = [panel_h * (hi[0] - lo[0]) / (hi[1] - lo[1]) for lo, hi in limits]
    fig_w = sum(widths) + 3.2
    fig = plt.figure(figsize=(fig_w, panel_h + 2.1))
    gs = fig.add_gridspec(1, 3, width_ratios=(*widths, 0.15), left=0.8 / fig_w, right=1 - 1.0 / fig_w,
                          bottom=1.3 / (panel_h + 2.1), top=1 - 0.75 / (panel_h + 2.1), wspace=0.25)
    axes = [fig.add_subplot(gs[0, 0]), fig.add_subplot(gs[0, 1])]
    cax = fig.add_subplot(gs[0, 2])
    for ax, (a, b, la, lb), (lo, hi) in zip(axes, views, limits):
        sign = up_sign if b == views[1][1] else 1
        xy = np.column_stack([t[:, a], sign * t[:, b]])
        for obs in scene.obstacles:
            if obs.name == "floor":
                continue
            ext = np.asarray(obs.size if obs.kind == "box" else (2 * obs.size[0], 2 * obs.size[0], obs.size[1]))
            corners = np.array([[sx, sy, sz] for sx in (-.5, .5) for sy in (-.5, .5) for sz in (-.5, .5)]) * ext
            T_obs = obs.T_I if np.array_equal(T_cell_I, np.eye(4)) else T_cell_I @ obs.T_I
            w = corners @ T_obs[:3, :3].T + T_obs[:3, 3]
            color = "r" if obs.name == scene.wall_name else "0.6"
            ax.add_patch(plt.Rectangle((w[:, a].min(), (sign * w[:, b]).min()), np.ptp(w[:, a]), np.ptp(w[:, b]),
                                       fill=obs.name == scene.wall_name, alpha=0.35, color=color, zorder=0))
            cx, cy = w[:, a].mean(), (sign * w[:, b]).max()
            if lo[0] <= cx <= hi[0] and lo[1] <= cy <= hi[1]:  # name the obstacles in view
                ax.annotate(obs.name, (cx, cy), fontsize=8, ha="center", va="bottom", zorder=5)
        if n > 1:
            segs = np.stack([xy[:-1], xy[1:]], axis=1)
            lc = LineCollection(segs, cmap=cmap, norm=norm, linewidths=0.5, alpha=0.55, zorder=1)
            lc.set_array(np.arange(1, n))
            ax.add_collection(lc)
        ax.scatter(xy[:, 0], xy[:, 1], c=np.arange(1, n + 1), cmap=cmap, norm=norm, s=3, zorder=2)
        ax.plot([base[a]], [sign * base[b]], "ks", ms=6, zorder=4)
        trk = np.array([o[a], sign * o[b]])
        if np.all((trk >= lo) & (trk <= hi)):
            ax.plot(*trk, "k^", ms=10, zorder=4)
        else:
            edge = np.clip(trk, lo, hi)
            ax.plot(*edge, "k>", ms=9, zorder=8, clip_on=False)
        if n:
            ends = [(0, "start", "C2")] + ([(n - 1, "end", "C3")] if n > 1 else [])
            for k, word, color in ends:
                ax.plot(*xy[k], "o", ms=13, mfc=color, mec="k", zorder=6)
                ax.annotate(f"{word} #{k + 1}", xy[k], **toward_centre(xy[k], lo, hi, 9, 9), textcoords="offset points",
                            fontsize=9, weight="bold", zorder=7,
                            bbox=dict(boxstyle="round,pad=0.2", fc="w", ec=color, alpha=0.9))
            for k in switch:
                ax.plot(*xy[k], "D", ms=9, mfc="w", mec="k", zorder=6)
                if len(switch) == 1:  # several changes (a selected tour) are listed in the legend instead
                    ax.annotate(f"#{k + 1}: {'front' if front[k] else 'behind'} group begins", xy[k],
                                **toward_centre(xy[k], lo, hi, 9, 12), textcoords="offset points", fontsize=8,
                                zorder=7, bbox=dict(boxstyle="round,pad=0.2", fc="w", ec="0.3", alpha=0.9))
        ax.set_xlim(lo[0], hi[0])
        ax.set_ylim(lo[1], hi[1])
        ax.set_xlabel(la)
        ax.set_ylabel(lb)
        ax.set_aspect("equal", adjustable="box")
    axes[0].set_title("tool positions in visiting order, top view")
    axes[1].set_title("side view")
    sm = plt.cm.ScalarMappable(norm=norm, cmap=cmap)
    fig.colorbar(sm, cax=cax, label=f"visit number (1 … {n})")
    handles = [Line2D([], [], ls="", marker="o", ms=9, mfc="C2", mec="k", label="first pose"),
               Line2D([], [], ls="", marker="o", ms=9, mfc="C3", mec="k", label="last pose"),
               Line2D([], [], ls="", marker="D", ms=7, mfc="w", mec="k", label=_switch_words(switch)),
               Line2D([], [], ls="", marker="s", ms=6, color="k", label="robot base"),
               Patch(color="r", alpha=0.35, label="wall"),
               Line2D([], [], ls="", marker=">", ms=8, color="k", label=f"towards the tracker (at {np.round(o, 2).tolist()} m, out of view)")]
    n_front = int(front.sum())
    fig.suptitle(f"tour of {n} poses: {n_front} in front of the wall, {n - n_front} behind it "
                 f"(colour: order of visits)", fontsize=11)
    fig.legend(handles=handles, loc="lower center", ncol=3, fontsize=9, frameon=False, bbox_to_anchor=(0.5, 0.0))
    return fig
