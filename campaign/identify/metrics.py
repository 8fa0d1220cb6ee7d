"""Error statistics in the shape of the paper's Table 6."""

from __future__ import annotations

import numpy as np


def error_stats(dz, *, orientation: bool = True) -> dict:
    """Table 6 statistics of pose errors Δz (n, 6) (m, rad).

    Returns ``{"position_mm": {"max", "mean", "q90"}, "orientation_mrad": {...}, "n_poses"}``;
    without ``orientation`` (positions only were measured) no ``orientation_mrad``.
    """
    dz = np.asarray(dz, dtype=float)
    pos = np.linalg.norm(dz[:, :3], axis=1) * 1e3
    rot = np.linalg.norm(dz[:, 3:6], axis=1) * 1e3

    def s(v):
        return {"max": float(np.max(v)), "mean": float(np.mean(v)), "q90": float(np.quantile(v, 0.9))}

    if not orientation:
        return {"position_mm": s(pos), "n_poses": int(len(dz))}
    return {"position_mm": s(pos), "orientation_mrad": s(rot), "n_poses": int(len(dz))}


def reflector_stats(dp, *, key: str = "reflector_position_mm") -> dict:
    """Statistics of reflector position errors dp (n, k, 3) m over every seen reflector (NaN rows:
    missed): ``{key: {"max", "mean", "q90"} mm, "n_reflectors"}`` (raw reflector data)."""
    e = np.linalg.norm(np.asarray(dp, dtype=float), axis=-1).reshape(-1) * 1e3
    e = e[np.isfinite(e)]
    if not len(e):
        return {key: {"max": None, "mean": None, "q90": None, "n_reflectors": 0}}
    return {key: {"max": float(np.max(e)), "mean": float(np.mean(e)), "q90": float(np.quantile(e, 0.9)),
                  "n_reflectors": int(len(e))}}


def format_table6(stages: dict, order, split: str = "test") -> str:
    """Stages side by side, like the paper's Table 6, with the ratio to the first stage."""
    cols = [name for name in order if name in stages]
    widths = [max(11, len(c) + 2) for c in cols]
    head = f"{'error (' + split + ' set)':<28}" + "".join(f"{c:>{w}}" for c, w in zip(cols, widths))
    lines = [head, "-" * len(head)]
    first = stages[cols[0]][split]
    blocks = [b for b in (("position_mm", "‖Δt‖ mm"), ("orientation_mrad", "‖Δφ‖ mrad")) if b[0] in first]
    for block, unit in blocks:
        for stat, label in (("max", "max"), ("mean", "mean"), ("q90", "Q0.9")):
            row = f"{label + ' ' + unit:<28}"
            for c, w in zip(cols, widths):
                row += f"{stages[c][split][block][stat]:>{w}.3f}"
            lines.append(row)
    for block, unit in (("position_mm", "‖Δt‖"), ("orientation_mrad", "‖Δφ‖")):
        if block not in first:
            continue
        lines.append(f"{'mean ' + unit + ' / ' + cols[0]:<28}" + "".join(
            f"{100 * stages[c][split][block]['mean'] / max(first[block]['mean'], 1e-300):>{w - 1}.2f}%"
            for c, w in zip(cols, widths)))
    lines.append(f"{'n poses':<28}" + "".join(f"{stages[c][split]['n_poses']:>{w}d}" for c, w in zip(cols, widths)))
    return "\n".join(lines)
