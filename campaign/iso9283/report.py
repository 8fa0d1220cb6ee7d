"""`campaign iso9283 RUN`: the ISO 9283 figures of a measured test run, before and after calibration.

RUN was planned by ``campaign plan --iso9283`` and measured by ``campaign run``. Its own figures
are those of the commands it was planned with: nominal, or corrected by a calibrated model
(``plan --iso9283 --compensate CAL``). ``--calibrated RUN2`` adds the figures of a second run of
the same cube (the compensated commands), so one report shows both. Writes
``RUN/iso9283/report.json`` (``poses``: one entry per test pose, P1..P5, with ``AP_p_mm``,
``RP_l_mm`` and the other figures of RUN, and ``nominal`` / ``calibrated`` blocks) and
``RUN/iso9283/report.html``, both of one evaluation (``iso9283_id``): ``RUN/iso9283`` is a link to
the newest complete one, replaced atomically (campaign/versioned.py).
"""

from __future__ import annotations

import html
import json
from pathlib import Path

import numpy as np

from campaign.errors import DataError
from campaign.fileio import atomic_write, atomic_write_json
from campaign.iso9283.figures import pose_figures

#: targets of two runs are the same test when they agree this well (m, and per matrix entry)
SAME_TARGET_TOL = 1e-9


def read_test(run_dir) -> dict:
    """RUN/plan/iso9283.json, or a one-line DataError saying how to make it."""
    path = Path(run_dir) / "plan" / "iso9283.json"
    if not path.is_file():
        raise DataError(f"{path}: not found; {run_dir} is not an ISO 9283 run (plan one with "
                        f"`campaign plan --iso9283 --run {run_dir}`)")
    try:
        doc = json.loads(path.read_text())
        [np.asarray(p["target_T_IE"], dtype=float).reshape(4, 4) for p in doc["poses"]]
    except (ValueError, KeyError, TypeError) as exc:
        raise DataError(f"{path}: malformed ({exc.__class__.__name__}: {exc})") from None
    return doc


def run_figures(run_dir) -> dict:
    """{"model": "nominal"|"calibrated", "poses": {name: PoseFigures}, "floor": NoiseFloor | None,
    "test": iso9283.json, "measured": n} for one measured ISO 9283 run."""
    from campaign.iso9283.plan import pose_number
    from campaign.measure.floor import floor_from_repeats
    from campaign.run import RunFolder

    test = read_test(run_dir)
    run = RunFolder(run_dir)
    if not run.measurements_path.is_file():
        raise DataError(f"{run.measurements_path}: not found; measure the test first (`campaign run {run_dir} --sim` "
                        "or with the real cell)")
    with run.store() as store:
        poses = store.load_measured()
    if poses.frame != "robot":
        raise DataError(f"{run_dir}: measured in the tracker's frame; ISO 9283 compares attained and commanded "
                        "poses in the robot's base frame")
    robot = run.robot().with_default_reflectors()
    point = None
    if poses.kind == "point":  # one reflector: the commanded point is the target's reflector centre
        point = np.append(robot.reflector_positions_in_E[0], 1.0)
    base = pose_number(poses.pose_id)
    out = {}
    for k, p in enumerate(test["poses"], start=1):
        rows = np.flatnonzero(base == k)
        if len(rows) < 2:
            raise DataError(f"{run_dir}: {p['name']} measured {len(rows)} time(s); ISO 9283 needs at least 2 cycles "
                            f"(`campaign run {run_dir}` measures what is missing)")
        q_cmd = np.asarray(p["q_command"], dtype=float)
        if np.max(np.abs(poses.q[rows] - q_cmd)) > 1e-9:
            raise DataError(f"{run_dir}: the joint commands stored for {p['name']} are not those of "
                            f"plan/iso9283.json; the measurements are of another plan")
        T_c = np.asarray(p["target_T_IE"], dtype=float)
        T_a = poses.T_IE[rows]
        if point is not None:
            T_c = T_c.copy()
            T_c[:3, 3] = (T_c @ point)[:3]
        out[p["name"]] = pose_figures(T_a, T_c, orientation=poses.has_orientation)
    floor = floor_from_repeats(poses.xyz, poses.q, time_s=poses.time_s)
    return {"model": "nominal" if test.get("compensated_with") is None else "calibrated", "poses": out,
            "floor": floor, "test": test, "measured": len(poses), "orientation": poses.has_orientation}


def _same_test(a: dict, b: dict) -> bool:
    ta = np.array([p["target_T_IE"] for p in a["poses"]], dtype=float)
    tb = np.array([p["target_T_IE"] for p in b["poses"]], dtype=float)
    return ta.shape == tb.shape and bool(np.max(np.abs(ta - tb)) <= SAME_TARGET_TOL)


def iso9283_report(run_dir, calibrated=None) -> dict:
    """Compute and write RUN/iso9283/report.json and report.html; return the report's document.

    calibrated: a second run of the same test with compensated commands (its figures become the
    ``calibrated`` block; RUN's own are ``nominal`` unless RUN itself was compensated)."""
    own = run_figures(run_dir)
    other = None
    if calibrated is not None:
        if own["model"] == "calibrated":
            raise DataError(f"{run_dir}: planned with compensated commands already; give the nominal run first "
                            f"(`campaign iso9283 NOMINAL_RUN --calibrated {run_dir}`)")
        other = run_figures(calibrated)
        if not _same_test(own["test"], other["test"]):
            raise DataError(f"{calibrated}: its ISO 9283 poses are not those of {run_dir} (plan both with the same "
                            "configuration; the compensated one with --compensate)")
        if other["model"] != "calibrated":
            raise DataError(f"{calibrated}: planned with nominal commands; plan it with "
                            f"`campaign plan --iso9283 --compensate CALIBRATED_RUN --run {calibrated}`")
    blocks = {own["model"]: own}
    if other is not None:
        blocks["calibrated"] = other
    poses = []
    # the compensated run's commands against its calibration's domain (recorded by plan --iso9283 --compensate)
    comp = ((other or own)["test"].get("compensated_with") or {}) if (other or own)["model"] == "calibrated" else {}
    in_domain, sigma = comp.get("in_domain"), comp.get("sigma_mm")
    for k, p in enumerate(own["test"]["poses"]):
        name = p["name"]
        entry = {"pose": name, "model": own["model"], **own["poses"][name].as_dict(),
                 "in_domain": None if in_domain is None else bool(in_domain[k]),
                 "sigma_mm": None if sigma is None else float(sigma[k])}
        for label in ("nominal", "calibrated"):
            entry[label] = blocks[label]["poses"][name].as_dict() if label in blocks else None
        poses.append(entry)
    floor = own["floor"]
    doc = {
        "standard": own["test"]["standard"], "run": str(run_dir),
        "calibrated_run": None if calibrated is None else str(calibrated),
        "compensated_with": own["test"].get("compensated_with"),
        "cycles": own["test"]["cycles"], "cube": own["test"]["cube"], "orientation_measured": own["orientation"],
        "noise_floor_mm": None if floor is None else floor.mean_position_mm,
        "noise_floor": None if floor is None else floor.as_json(),
        "poses": poses,
        "summary": {label: {"AP_p_mm_max": max(f.AP_p_mm for f in b["poses"].values()),
                            "AP_p_mm_mean": float(np.mean([f.AP_p_mm for f in b["poses"].values()])),
                            "RP_l_mm_max": max(f.RP_l_mm for f in b["poses"].values())}
                    for label, b in blocks.items()},
    }
    from campaign.run import RunFolder
    from campaign.versioned import VersionedFolder

    # report.json and report.html of one evaluation are published together (campaign/versioned.py)
    folder = VersionedFolder(Path(run_dir), "iso9283", "iso9283_reports", keep=2)
    with RunFolder(run_dir).lock("iso9283"), folder.new_version() as version:
        doc["iso9283_id"] = version.id
        atomic_write_json(version.path / "report.json", doc)
        atomic_write(version.path / "report.html", _html(doc))
    return doc


def table_text(doc: dict) -> str:
    """The printed table: AP_P, its components and RP_l per pose, each model side by side."""
    labels = [m for m in ("nominal", "calibrated") if doc["poses"][0][m] is not None]
    cube = doc["cube"]
    lines = [f"ISO 9283 pose accuracy (AP) and repeatability (RP), {doc['cycles']} cycles, cube edge "
             f"{1e3 * cube['edge_m']:.0f} mm centred at ({', '.join(f'{1e3 * c:.0f}' for c in cube['centre_m'])}) mm"]
    head = f"{'pose':<5}" + "".join(f" | {m:^43}" for m in labels)
    sub = f"{'':<5}" + "".join(f" | {'AP_P mm':>8} {'AP_x':>8} {'AP_y':>8} {'AP_z':>8} {'RP_l mm':>7}" for _ in labels)
    lines += [head, sub]
    for p in doc["poses"]:
        row = f"{p['pose']:<5}"
        for m in labels:
            f = p[m]
            row += f" | {f['AP_p_mm']:8.4f} {f['AP_x_mm']:8.4f} {f['AP_y_mm']:8.4f} {f['AP_z_mm']:8.4f} {f['RP_l_mm']:7.4f}"
        lines.append(row)
    if doc["orientation_measured"]:
        lines.append("orientation (mrad): " + "; ".join(
            f"{m} AP_a,b,c max {max(max(abs(p[m][f'AP_{c}_mrad']) for c in 'abc') for p in doc['poses']):.3f}, "
            f"RP_a,b,c max {max(max(p[m][f'RP_{c}_mrad'] for c in 'abc') for p in doc['poses']):.3f}" for m in labels))
    outside = [p["pose"] for p in doc["poses"] if p.get("in_domain") is False]
    if outside:
        lines.append(f"outside the calibrated domain: {', '.join(outside)} (the calibrated figures there are "
                     "extrapolated; sigma_mm " + ", ".join(f"{p['pose']} {p['sigma_mm']:.4f}" for p in doc["poses"]
                                                           if p.get("sigma_mm") is not None) + ")")
    if doc["noise_floor_mm"] is not None:
        lines.append(f"noise floor {doc['noise_floor_mm']:.4f} mm (mean position error of one measurement, from the "
                     "cycles measured back to back)")
    return "\n".join(lines)


def _bars_svg(doc: dict, key: str, title: str) -> str:
    """An inline SVG bar chart of ``key`` per pose, nominal and calibrated side by side."""
    labels = [m for m in ("nominal", "calibrated") if doc["poses"][0][m] is not None]
    colours = {"nominal": "#c0504d", "calibrated": "#4f81bd"}
    vals = [[p[m][key] for m in labels] for p in doc["poses"]]
    top = max(max(v) for v in vals) or 1.0
    floor = doc["noise_floor_mm"]
    w, h, left, bottom = 460, 220, 50, 30
    bw = (w - left - 20) / len(vals) / (len(labels) + 1)
    parts = [f'<svg xmlns="http://www.w3.org/2000/svg" width="{w}" height="{h + 20}" role="img">',
             f'<text x="{left}" y="14" font-size="13">{html.escape(title)}</text>']
    scale = (h - bottom - 20) / (1.1 * max(top, floor or 0))
    for i, (p, v) in enumerate(zip(doc["poses"], vals)):
        x0 = left + i * bw * (len(labels) + 1)
        for j, m in enumerate(labels):
            bh = v[j] * scale
            parts.append(f'<rect x="{x0 + j * bw:.1f}" y="{h - bottom - bh:.1f}" width="{bw * 0.9:.1f}" '
                         f'height="{bh:.1f}" fill="{colours[m]}"><title>{p["pose"]} {m}: {v[j]:.4f} mm</title></rect>')
        parts.append(f'<text x="{x0 + bw * len(labels) / 2:.1f}" y="{h - bottom + 14}" font-size="11" '
                     f'text-anchor="middle">{p["pose"]}</text>')
    if floor is not None:
        y = h - bottom - floor * scale
        parts.append(f'<line x1="{left}" x2="{w - 10}" y1="{y:.1f}" y2="{y:.1f}" stroke="#333" stroke-dasharray="4 3"/>'
                     f'<text x="{w - 10}" y="{y - 3:.1f}" font-size="10" text-anchor="end">noise floor '
                     f'{floor:.4f} mm</text>')
    parts.append(f'<text x="4" y="{(h - bottom) / 2:.0f}" font-size="11">mm</text>')
    for j, m in enumerate(labels):
        parts.append(f'<rect x="{left + j * 110}" y="{h + 4}" width="10" height="10" fill="{colours[m]}"/>'
                     f'<text x="{left + 14 + j * 110}" y="{h + 13}" font-size="11">{m}</text>')
    parts.append("</svg>")
    return "".join(parts)


def _html(doc: dict) -> str:
    labels = [m for m in ("nominal", "calibrated") if doc["poses"][0][m] is not None]
    keys = ["AP_p_mm", "AP_x_mm", "AP_y_mm", "AP_z_mm", "RP_l_mm"]
    if doc["orientation_measured"]:
        keys += ["AP_a_mrad", "AP_b_mrad", "AP_c_mrad", "RP_a_mrad", "RP_b_mrad", "RP_c_mrad"]
    rows = []
    for m in labels:
        for p in doc["poses"]:
            rows.append("<tr><td>" + html.escape(m) + "</td><td>" + p["pose"] + "</td>"
                        + "".join(f"<td>{p[m][k]:.4f}</td>" for k in keys) + "</tr>")
    cube = doc["cube"]
    floor = ("" if doc["noise_floor_mm"] is None else
             f"<p>Noise floor: {doc['noise_floor_mm']:.4f} mm, the mean position error of one measurement, from the "
             f"{doc['cycles']} cycles of each pose ({html.escape(doc['noise_floor']['detail'])}).</p>")
    return f"""<!doctype html><html><head><meta charset="utf-8"><title>ISO 9283 pose test</title>
<style>body{{font-family:sans-serif;margin:2em;max-width:70em}} table{{border-collapse:collapse}}
td,th{{border:1px solid #bbb;padding:2px 6px;text-align:right}} .charts svg{{margin-right:2em}}</style></head><body>
<h1>ISO 9283 pose accuracy and repeatability</h1>
<p>Evaluation {html.escape(doc.get("iso9283_id") or "")}</p>
<p>{html.escape(doc['standard'])}. Run <code>{html.escape(doc['run'])}</code>{'' if not doc['calibrated_run'] else
 ', calibrated: <code>' + html.escape(doc['calibrated_run']) + '</code>'}. {doc['cycles']} cycles of P1, P5, P4, P3, P2;
cube edge {1e3 * cube['edge_m']:.1f} mm, centre ({', '.join(f'{1e3 * c:.1f}' for c in cube['centre_m'])}) mm in F_I,
P2..P5 on the diagonals of the plane C1-C2-C7-C8 at {100 * cube['corner_fraction']:.0f} % of the diagonal
({1e3 * cube['diagonal_m']:.1f} mm) from the corners.</p>
{floor}
<div class="charts">{_bars_svg(doc, 'AP_p_mm', 'pose accuracy AP_P (mm)')}{_bars_svg(doc, 'RP_l_mm', 'pose repeatability RP_l (mm)')}</div>
<p>AP_P = ‖x̄ − x_c‖ (barycentre of the attained positions vs the command); RP_l = l̄ + 3 S_l, l the distance of
each attained position from the barycentre. Orientation: deviations about the x, y, z axes of F_I (the rotation
vector of R·R_cᵀ); AP_a,b,c their means, RP_a,b,c three sample standard deviations.</p>
<table><tr><th>model</th><th>pose</th>{''.join(f'<th>{k}</th>' for k in keys)}</tr>{''.join(rows)}</table>
</body></html>
"""
