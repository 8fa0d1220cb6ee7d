"""Reports: binned per-joint statistics, the noise floor, full parameter names, colour scales,
and every page rendered in a real headless browser (Chromium), skipped when none is installed."""

import json
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from campaign.identify.metrics import error_stats
from campaign.identify.noise_floor import floor_label, tracker_noise_floor
from campaign.identify.report import binned_quantiles, signed_components, workspace_colour_scale, write_report
from campaign.measure.floor import floor_from_stated
from campaign.model.kinematics import pose_error

ROOT = Path(__file__).resolve().parents[1]
SCREENSHOT = ROOT / "benchmarks" / "screenshot_reports.py"


def test_bins_follow_the_grid_values_and_give_each_bins_own_mean_and_quantiles(rng):
    x = np.repeat([-30.0, -10.0, 10.0, 30.0], [20, 9, 3, 40])  # the third value has too few poses
    y = rng.normal(size=len(x)) + 0.1 * x
    b = binned_quantiles(x, y, min_count=8)
    groups = [x == -30, x == -10, (x == 10) | (x == 30)]  # the short bin joins its neighbour
    np.testing.assert_array_equal(b["n"], [g.sum() for g in groups])
    np.testing.assert_allclose(b["x"], [x[g].mean() for g in groups])
    np.testing.assert_allclose(b["mean"], [y[g].mean() for g in groups])
    np.testing.assert_allclose(b["q05"], [np.quantile(y[g], 0.05) for g in groups])
    np.testing.assert_allclose(b["q95"], [np.quantile(y[g], 0.95) for g in groups])


def test_continuous_coordinates_get_equal_count_bins_that_never_split_a_value(rng):
    x = np.round(rng.uniform(-90, 90, 1000), 0)  # many ties
    y = rng.normal(size=1000)
    b = binned_quantiles(x, y, max_bins=20, min_count=8)
    assert len(b["n"]) <= 20 and b["n"].sum() == 1000 and b["n"].min() >= 8
    # rebuild the bins from their counts: consecutive in sorted x, no value in two bins
    xs = np.sort(x)
    edges = np.cumsum(b["n"]).astype(int)
    for k in edges[:-1]:
        assert xs[k - 1] < xs[k]
    assert np.all(np.diff(b["x"]) > 0)


def test_signed_components_in_mm_and_mrad_and_no_orientation_rows_for_position_only_data():
    dz = np.array([[1e-3, -2e-3, 3e-3, 1e-4, 0.0, -2e-4]])
    comps = signed_components(dz)
    assert [(c[0], c[1]) for c in comps] == [("Δx", "mm"), ("Δy", "mm"), ("Δz", "mm"),
                                            ("Δφx", "mrad"), ("Δφy", "mrad"), ("Δφz", "mrad")]
    np.testing.assert_allclose([c[2][0] for c in comps], [1.0, -2.0, 3.0, 0.1, 0.0, -0.2])
    position_only = dz.copy()
    position_only[:, 3:] = 0.0
    assert [c[0] for c in signed_components(position_only)] == ["Δx", "Δy", "Δz"]


def test_the_workspace_colour_scale_reaches_the_largest_error(rng):
    pos = np.abs(rng.normal(size=500)) * 0.01
    pos[17] = 0.3  # one pose far off: a 98 % quantile scale would leave it beyond the colour bar
    lo, hi = workspace_colour_scale(pos)
    assert lo == 0.0 and hi >= pos.max()


def test_the_noise_floor_of_a_stated_tracker_noise_equals_the_simulated_campaigns_error_of_the_true_robot(robot):
    """Truth in simulation: the tracker measures three reflectors with σ = 10 µm each, Kabsch
    gives the tool pose; the true robot's mean position error is the floor (read after)."""
    from campaign.sim.truth import make_truth, random_joint_poses, synthesize

    floor = floor_from_stated(10e-6, robot.reflector_positions_in_E)
    truth = make_truth(robot, seed=1, noise_m=10e-6, resolution_m=0.0)
    meas = synthesize(truth, random_joint_poses(robot, 3000, seed=2), seed=3)
    dz = pose_error(truth.pose_in_measured_frame(meas.q, meas.T_LI), meas.T_IE)
    observed_mm = np.linalg.norm(dz[:, :3], axis=1).mean() * 1e3
    assert floor.mean_position_mm == pytest.approx(observed_mm, rel=0.03)
    # one point measured with σ would give σ·2√2/√π = 16 µm: the fit of three is well below it
    assert floor.mean_position_mm < 0.7 * 10e-3 * 2 * np.sqrt(2 / np.pi)


def test_the_chart_floor_is_the_texts_floor_the_stated_noise_else_none_never_the_simulators(tmp_path, robot, capsys):
    from campaign.cli import main
    from campaign.measure.csvio import write_measured_csv
    from campaign.sim.truth import make_truth, random_joint_poses, synthesize

    meas = synthesize(make_truth(robot, seed=3), random_joint_poses(robot, 40, seed=4), seed=5)
    write_measured_csv(tmp_path / "m.csv", meas)
    run = tmp_path / "run"
    assert main(["import", str(tmp_path / "m.csv"), "--run", str(run)]) == 0
    assert tracker_noise_floor(run) is None  # no repeats, no drift checks, no stated noise
    cfg = (run / "campaign.yaml").read_text() if (run / "campaign.yaml").is_file() else "robot: comau_racer5_080\n"
    (run / "campaign.yaml").write_text(cfg + "sim:\n  noise_m: 2.0e-05\n")
    (run / "sim").mkdir()
    assert tracker_noise_floor(run) is None  # the simulator's configured noise is no floor, sim/ or not
    capsys.readouterr()
    assert main(["calibrate", str(run), "--no-ann"]) == 0
    assert "no noise floor" in capsys.readouterr().out
    page = (run / "calibration" / "report.html").read_text()
    assert "no noise floor" in page and "The dotted line is the tracker noise floor" not in page
    assert "noise-floor" not in (run / "calibration" / "history.svg").read_text()  # no line in the chart either
    (run / "campaign.yaml").write_text(cfg + "sim:\n  noise_m: 2.0e-05\ntracker:\n  noise_m: 5.0e-06\n")
    stated = tracker_noise_floor(run)
    assert stated.source == "stated"
    assert stated.mean_position_mm == pytest.approx(
        floor_from_stated(5e-6, robot.reflector_positions_in_E).mean_position_mm, rel=1e-12)
    assert main(["calibrate", str(run), "--no-ann"]) == 0
    text = capsys.readouterr().out
    page = (run / "calibration" / "report.html").read_text()
    shown = f"{stated.mean_position_mm:.4f} mm"
    assert shown in text and shown in page and "The dotted line is the tracker noise floor" in page
    value_mm, y, y_expected, legend = chart_floor(run / "calibration" / "history.svg")
    assert value_mm == pytest.approx(stated.mean_position_mm, rel=1e-5) and y == pytest.approx(y_expected, abs=0.6)
    assert f"tracker noise floor {floor_label(stated)}" in legend


def chart_floor(svg_path: Path):
    """The noise floor line of a history chart: (its value in mm, its y in px, the y where that
    value lies on the chart's log axis (from the decade tick labels' positions), the legend's text)."""
    import xml.etree.ElementTree as ET

    root = ET.parse(svg_path).getroot()
    ns = "{http://www.w3.org/2000/svg}"
    line = [e for e in root.iter(ns + "path") if e.get("class") == "noise-floor"]
    assert len(line) == 1
    ticks = [(float(e.text), float(e.get("y"))) for e in root.iter(ns + "text") if e.get("class") == "ytick"]
    assert len(ticks) >= 2
    slope, offset = np.polyfit(np.log10([v for v, _ in ticks]), [y for _, y in ticks], 1)
    value = float(line[0].get("data-floor-mm"))
    y = float(line[0].get("d").split()[1].split("h")[0])
    legend = " ".join(e.text for e in root.iter(ns + "text") if e.get("class") == "legend")
    return value, y, slope * np.log10(value) + offset, legend


def test_parameter_table_keeps_every_name_whole(robot):
    from campaign.identify.calibrate import parameter_text
    from campaign.identify.solver import CalibrationModel
    from campaign.sim.truth import make_truth, random_joint_poses, synthesize

    meas = synthesize(make_truth(robot, seed=3), random_joint_poses(robot, 120, seed=4), seed=5)
    model = CalibrationModel(robot=robot).fit(meas.q, meas.T_IE)
    text = parameter_text(model).splitlines()
    names = [model.base_.expression(i) for i in range(model.base_.n_base)]
    assert max(len(n) for n in names) > 34  # the old table cut names at 34 characters
    for line, name in zip(text[1:], names):
        assert f" {name} " in line


def synthetic_report(folder: Path, rng, reflectors_in_E, n: int = 300) -> Path:
    """A calibration report from made-up residuals (a trend in q2 left in 'geometric', two
    identical stages), with a two-run history: no calibration needed, fast."""
    q = np.deg2rad(rng.choice(np.linspace(-120, 120, 9), size=(n, 6)))
    noise = rng.normal(0, 8e-6, size=(n, 6))
    trend = np.zeros((n, 6))
    trend[:, 1] = 60e-6 * np.sin(q[:, 1])
    residuals = {"nominal": noise * 300 + 2e-3, "geometric": noise + trend, "geometric+ground_compliance": noise,
                 "geometric+ground_compliance+ann": noise.copy()}
    is_test = rng.uniform(size=n) < 0.2
    stages = {s: {"train": error_stats(dz[~is_test]), "test": error_stats(dz[is_test])} for s, dz in residuals.items()}
    order = list(residuals)
    out = folder / "calibration"
    out.mkdir(parents=True)
    runs = [{"effects": [], "order": order[:2], "stages": {s: stages[s]["test"] for s in order[:2]}},
            {"effects": ["ground_compliance"], "order": order, "stages": {s: stages[s]["test"] for s in order}}]
    (out / "history.json").write_text(json.dumps({"runs": runs}))
    xyz = rng.uniform(-0.5, 0.5, size=(n, 3))
    long_name = "pL_I0_x - pL_01_y - 0.189 pR_01_x + pL_12_y - 0.050 pR_12_x"
    return write_report(folder, stages, order, residuals, q, xyz, is_test,
                        param_text=f"  # parameter\n  1 {long_name}  0.00052  2.1e-06  m",
                        noise_floor=floor_from_stated(10e-6, reflectors_in_E))


@pytest.fixture(scope="module")
def report_page(tmp_path_factory, robot):
    return synthetic_report(tmp_path_factory.mktemp("report") / "run", np.random.default_rng(7),
                            robot.reflector_positions_in_E)


def test_the_report_shows_every_stage_against_the_joints_the_floor_and_whole_names(report_page, robot):
    page = report_page
    html = page.read_text()
    stages = ("nominal", "geometric", "geometric+ground_compliance", "geometric+ground_compliance+ann")
    for stage in stages:
        img = f"joints_{stage.replace('+', '_')}.svg"
        assert f"<img src='{img}'>" in html and (page.parent / img).stat().st_size > 20_000
        svg = (page.parent / img).read_text()
        assert f"{stage}: signed error against each joint" in svg
        for label in [f"q{j} [deg]" for j in range(1, 7)] + ["Δx [mm]", "Δz [mm]", "Δφx [mrad]", "Δφz [mrad]"]:
            assert label in svg
    assert "tracker noise floor" in html and "<img src='history.svg'>" in html
    floor = floor_from_stated(10e-6, robot.reflector_positions_in_E)
    value_mm, y, y_expected, legend = chart_floor(page.parent / "history.svg")
    assert value_mm == pytest.approx(floor.mean_position_mm, rel=1e-5) and y == pytest.approx(y_expected, abs=0.6)
    assert f"tracker noise floor {floor_label(floor)}" in legend
    assert "pL_I0_x - pL_01_y - 0.189 pR_01_x + pL_12_y - 0.050 pR_12_x" in html
    dist = (page.parent / "distributions.svg").read_text()
    assert "<img src='distributions.svg'>" in html and all(f"{s}:  mean " in dist for s in stages)
    assert "[mm], log scale" in dist and "[mrad], log scale" in dist
    ws = (page.parent / "workspace.svg").read_text()
    assert "<img src='workspace.svg'>" in html and "top view" in ws and "side view" in ws and 'class="largest"' in ws


def _browser():
    sys.path.insert(0, str(SCREENSHOT.parent))
    try:
        from screenshot_reports import find_browser
    finally:
        sys.path.pop(0)
    return find_browser()


@pytest.mark.skipif(_browser() is None, reason="no Chromium on this machine (apt-get install chromium): "
                                              "the reports are not rendered in a browser here")
def test_the_report_renders_in_headless_chromium_with_its_pictures(report_page, tmp_path):
    from PIL import Image

    # the same page without its pictures: the rendered report must carry much more ink than that
    bare = report_page.with_name("bare.html")
    bare.write_text(report_page.read_text().replace("<img src=", "<img data-src="))
    shots = tmp_path / "shots"
    proc = subprocess.run([sys.executable, str(SCREENSHOT), str(report_page.parent.parent), "--out", str(shots),
                           "--width", "1400", "--height", "6000"], capture_output=True, text=True, timeout=300)
    assert proc.returncode == 0, proc.stderr
    full, text_only = shots / "calibration_report.png", shots / "calibration_bare.png"
    assert Image.open(full).size == (1400, 6000)
    ink = [np.mean(np.asarray(Image.open(p).convert("L")) < 245) for p in (full, text_only)]
    assert ink[0] > 3 * ink[1] and ink[1] > 0.003


def test_a_panel_title_of_several_lines_ends_above_its_panel():
    import xml.etree.ElementTree as ET

    from campaign.identify.svgplot import TITLE_PX, Svg, SvgPanels

    grid = SvgPanels(2, 1, pw=300, ph=80, gy=48, top=70)
    grid.line(1, 0, [0.0, 1.0], [0.0, 1.0], color="#000")
    grid.title(1, 0, "a long stage name:\nmean 0.1 mm, q90 0.2 mm")
    svg = Svg(grid.width, grid.height)
    grid.finish(svg)
    title = next(e for e in ET.fromstring(svg.text_svg()).iter("{http://www.w3.org/2000/svg}text")
                 if "".join(e.itertext()).startswith("a long stage name"))
    last_baseline = float(title.get("y")) + 1.2 * TITLE_PX  # the second line, 1.2 em below the first
    assert last_baseline <= grid.origin(1, 0)[1] - 4
