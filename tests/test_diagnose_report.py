"""diagnose's HTML report: the text box wraps instead of running off the page, the context and
signature figures plot the signed residual components (three rows, units in the labels) at a
size the page shows without shrinking their type, the ranking's bars are the candidates' held-out
errors, and the page renders in headless Chromium with its pictures."""

import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
import yaml

from campaign.cli import main
from campaign.diagnose import diagnose
from campaign.diagnose.report import MAX_WIDTH_PX, write_diagnosis

SCREENSHOT = Path(__file__).resolve().parents[1] / "benchmarks" / "screenshot_reports.py"


@pytest.fixture(scope="module")
def diagnosed(tmp_path_factory):
    """A run hiding the elastic ground (structure the regressor finds), diagnosed with a report."""
    tmp = tmp_path_factory.mktemp("diag_report")
    csv, run = tmp / "m.csv", tmp / "run"
    assert main(["synth", "--csv", str(csv), "--poses", "300", "--seed", "4", "--hidden", "ground_compliance"]) == 0
    assert main(["import", str(csv), "--run", str(run)]) == 0
    cfg = yaml.safe_load((run / "campaign.yaml").read_text())
    (run / "campaign.yaml").write_text(yaml.safe_dump({**cfg, "tracker": {"noise_m": 1e-5}}))
    d = diagnose(run, folds=3, candidates="drift,cyclic")
    return d, write_diagnosis(d, report=True)


def svg_root(path: Path):
    import xml.etree.ElementTree as ET

    return ET.parse(path).getroot()


def svg_texts(root) -> list:
    return ["".join(e.itertext()) for e in root.iter("{http://www.w3.org/2000/svg}text")]


def test_the_text_box_wraps_and_the_figures_show_signed_components_at_a_readable_size(diagnosed):
    d, page = diagnosed
    html = page.read_text()
    assert "white-space:pre-wrap" in html and "overflow-wrap:anywhere" in html
    assert d.text().splitlines()[0] in html
    for name, comps in (("residual_context.svg", ("Δx", "Δy", "Δz")), ("signature.svg", ("Δx₁", "Δy₁", "Δz₁"))):
        assert f"src='{name}'" in html
        root = svg_root(page.parent / name)
        w, h = float(root.get("width")), float(root.get("height"))
        # at most the page's width (no shrinking of the type), three component rows of ~200 px each
        assert w <= MAX_WIDTH_PX and h >= 650, (name, w, h)
        texts = svg_texts(root)
        assert all(f"{c} [µm]" in texts for c in comps), (name, texts)
    context = svg_texts(svg_root(page.parent / "residual_context.svg"))
    assert "time [h]" in context and "overturning moment |M| [N·m]" in context
    assert any(f"bin mean of the {int(d.is_test.sum())} test poses" in t for t in context)


def test_the_ranking_figure_has_a_bar_per_candidate_with_its_held_out_error(diagnosed):
    d, page = diagnosed
    root = svg_root(page.parent / "ranking.svg")
    ns = "{http://www.w3.org/2000/svg}"
    effects = [e.text for e in root.iter(ns + "text") if e.get("class") == "effect"]
    values = [e.text for e in root.iter(ns + "text") if e.get("class") == "value"]
    assert effects == [c.label for c in d.ranking]  # with the joints a search found ("cyclic of joint 2")
    assert values == [f"{c.heldout_mean_position_mm_after:.4g} mm" for c in d.ranking]
    bars = [float(e.get("width")) for e in root.iter(ns + "rect") if e.get("class") == "bar"]
    after = np.array([c.heldout_mean_position_mm_after for c in d.ranking])
    np.testing.assert_allclose(np.array(bars) / bars[0], after / after[0], rtol=1e-3)  # lengths ∝ the values
    fills = [e.get("fill") for e in root.iter(ns + "rect") if e.get("class") == "bar"]
    assert [f == "#2ca02c" for f in fills] == [c.significant for c in d.ranking]
    assert any(c.significant for c in d.ranking) and not all(c.significant for c in d.ranking)


@pytest.mark.skipif(subprocess.run([sys.executable, str(SCREENSHOT), "/nonexistent"], capture_output=True).returncode
                    == 2, reason="no Chromium on this machine (apt-get install chromium)")
def test_the_diagnose_report_renders_in_headless_chromium(diagnosed, tmp_path):
    from PIL import Image

    _, page = diagnosed
    bare = page.with_name("bare.html")
    bare.write_text(page.read_text().replace("<img src=", "<img data-src="))
    try:
        proc = subprocess.run([sys.executable, str(SCREENSHOT), str(page.parent), "--out", str(tmp_path),
                               "--width", "1400", "--height", "5000"], capture_output=True, text=True, timeout=300)
    finally:
        bare.unlink()
    assert proc.returncode == 0, proc.stderr
    ink = [np.mean(np.asarray(Image.open(tmp_path / f"{p}.png").convert("L")) < 245) for p in ("report", "bare")]
    assert ink[0] > 3 * ink[1] and ink[1] > 0.003, ink
    # the text box ends inside the page: no dark pixels in the right margin beside it
    shot = np.asarray(Image.open(tmp_path / "bare.png").convert("L"))
    assert np.mean(shot[:600, 1380:] < 200) < 0.001


@pytest.mark.parametrize("key, label", [("temperature_c", "temperature [°C]"), ("humidity_pct", "humidity [%]"),
                                        ("payload_kg", "payload [kg]"), ("tool_temp_mm", "tool_temp [mm]"),
                                        ("shift", "shift"), ("_c", "_c")])
def test_context_columns_are_labelled_with_the_unit_their_name_carries(key, label):
    from campaign.diagnose.report import context_label

    assert context_label(key) == label


def test_the_report_of_a_run_with_a_reading_fault_left_out_shows_the_poses_diagnose_used(tmp_path, robot, capsys):
    """A fault the calibration left out: diagnose's residuals are of the other poses, and its report
    figures them against those poses (it raised an IndexError: 189 poses against 186 residuals)."""
    from test_edges_late import faulty_run

    run, bad = faulty_run(tmp_path, robot, 0.3)
    assert main(["calibrate", str(run), "--no-ann", "--no-report", "--quiet"]) == 0
    capsys.readouterr()
    assert main(["diagnose", str(run), "--candidates", "drift"]) == 0
    out = capsys.readouterr()
    assert f"poses {bad}: reading faults the last calibration left out" in out.err + out.out
    assert (run / "diagnose" / "report.html").exists() and (run / "diagnose" / "residual_joints.svg").exists()
