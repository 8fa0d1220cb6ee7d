"""Render a run's HTML reports in a real headless browser (Debian's Chromium) and save screenshots.

    python benchmarks/screenshot_reports.py RUN [--out DIR] [--width 1400] [--height 3000]

Every ``*.html`` under RUN (the calibration report, the diagnose report, any other) becomes
``OUT/<folder>_<name>.png`` (default OUT: RUN/screenshots). Look at them: overlapping
labels, cut-off names and empty plots show there, not in the PNGs alone. Prints one line per
screenshot with the page's size and the fraction of non-white pixels. Needs ``chromium``
(``apt-get install chromium``) or ``chromium-browser`` / ``google-chrome`` on PATH, or
``CHROMIUM=/path``. Exits 2 with one line when no browser is found.
"""

from __future__ import annotations

import argparse
import os
import shutil
import subprocess
import sys
import tempfile
from pathlib import Path

BROWSERS = ("chromium", "chromium-browser", "google-chrome", "google-chrome-stable")
FLAGS = ("--headless", "--no-sandbox", "--disable-gpu", "--disable-quic", "--no-first-run",
         "--disable-background-networking", "--disable-component-update", "--disable-sync",
         "--hide-scrollbars")


def find_browser() -> str | None:
    """Path of a Chromium-family browser, or None."""
    if os.environ.get("CHROMIUM"):
        return os.environ["CHROMIUM"]
    for name in BROWSERS:
        path = shutil.which(name)
        if path:
            return path
    return None


def screenshot(html: Path, png: Path, *, width: int = 1400, height: int = 3000, browser: str | None = None,
               timeout_s: float = 120.0) -> Path:
    """Render ``html`` (a local file) headless at width×height CSS px and write ``png``."""
    browser = browser or find_browser()
    if browser is None:
        raise FileNotFoundError("no chromium found (apt-get install chromium, or set CHROMIUM=/path)")
    png = Path(png).resolve()
    png.parent.mkdir(parents=True, exist_ok=True)
    with tempfile.TemporaryDirectory(prefix="campaign-chromium-") as profile:
        cmd = [browser, *FLAGS, f"--user-data-dir={profile}", f"--screenshot={png}",
               f"--window-size={width},{height}", Path(html).resolve().as_uri()]
        proc = subprocess.run(cmd, capture_output=True, text=True, timeout=timeout_s)
    if proc.returncode != 0 or not png.is_file():
        raise RuntimeError(f"chromium failed on {html} (exit {proc.returncode}): {proc.stderr.strip()[-400:]}")
    return png


def ink_fraction(png: Path) -> float:
    """Fraction of pixels that are not (near) white: 0 for a blank page."""
    import numpy as np
    from PIL import Image

    a = np.asarray(Image.open(png).convert("L"))
    return float(np.mean(a < 245))


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("run", type=Path, help="run folder holding the reports")
    ap.add_argument("--out", type=Path, default=None, help="screenshot folder (default: RUN/screenshots)")
    ap.add_argument("--width", type=int, default=1400)
    ap.add_argument("--height", type=int, default=3000)
    args = ap.parse_args(argv)
    browser = find_browser()
    if browser is None:
        print("screenshot_reports: no chromium found (apt-get install chromium, or set CHROMIUM=/path)",
              file=sys.stderr)
        return 2
    pages = sorted(p for p in args.run.rglob("*.html") if "screenshots" not in p.parts)
    if not pages:
        print(f"screenshot_reports: no *.html under {args.run}", file=sys.stderr)
        return 1
    out = args.out or args.run / "screenshots"
    for page in pages:
        rel = page.relative_to(args.run)
        png = out / ("_".join(rel.with_suffix("").parts) + ".png")
        screenshot(page, png, width=args.width, height=args.height, browser=browser)
        print(f"{page} -> {png} ({args.width}x{args.height}, ink {ink_fraction(png):.1%})")
    return 0


if __name__ == "__main__":
    sys.exit(main())
