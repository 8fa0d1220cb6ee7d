"""mkdocs hooks: what the documentation shows is made from the code and the results at build time.

Markers in a page, each on a line of its own:

- ``<!-- help: plan -->`` (or ``<!-- help: model base-params -->``): the command's ``--help``, from
  the same argparse parser the command line uses, so it cannot drift from the code;
- ``<!-- output: NAME -->``: ``docs/generated/NAME.txt``, a command's real output written by
  ``python docs/generate_outputs.py`` from a real run (a missing file fails the build);
- ``<!-- benchmarks -->``: a table of every ``benchmarks/results/*.json``, its headline figures;

and inline, anywhere in a sentence:

- ``<!-- value: NAME -->``: one number of a generated output (:data:`VALUES`: the output and the
  pattern that finds it), so prose that quotes the demo cannot drift from what the demo printed
  (a pattern that no longer matches fails the build, and tests/test_docs_values.py);
- ``<!-- timing: NAME -->``: how long ``generate_outputs.py`` took for that output, and at what load
  (``docs/generated/timings.json``; empty when it was not recorded).
"""

from __future__ import annotations

import json
import os
import re
from pathlib import Path

ROOT = Path(__file__).resolve().parent.parent
MARKER = re.compile(r"^<!-- (help|output|benchmarks)(?::\s*([^>]*?))?\s*-->\s*$", re.MULTILINE)


def command_help(words: str) -> str:
    """``campaign WORDS --help`` as the command line prints it (100 columns)."""
    import argparse

    os.environ["COLUMNS"] = "100"
    from campaign.cli import build_parser

    parser = build_parser()
    for word in words.split():
        sub = next(a for a in parser._actions if isinstance(a, argparse._SubParsersAction))
        if word not in sub.choices:
            raise KeyError(f"campaign {words}: no such command")
        parser = sub.choices[word]
    return parser.format_help()


def generated_output(name: str) -> str:
    path = ROOT / "docs" / "generated" / f"{name}.txt"
    if not path.is_file():
        raise FileNotFoundError(f"{path}: run `python docs/generate_outputs.py` to make it")
    return path.read_text()


#: top-level keys shown for a benchmark (those present), in this order
HEADLINE = ("command", "robot", "poses", "wall_s", "identification_time_s", "peak_rss_mb", "ratio_to_floor",
            "measured", "failed", "simulated_days", "suitable", "verdict")


def _cell(v) -> str:
    if isinstance(v, float):
        return f"{v:.4g}"
    if isinstance(v, (dict, list)):
        return ""
    return str(v).replace("|", "\\|")


def benchmark_table() -> str:
    rows = ["| result file | figures |", "| --- | --- |"]
    for path in sorted((ROOT / "benchmarks" / "results").glob("*.json")):
        try:
            doc = json.loads(path.read_text())
        except ValueError:
            continue
        if not isinstance(doc, dict):
            continue
        shown = [f"`{k}` {_cell(doc[k])}" for k in HEADLINE if k in doc and _cell(doc[k])]
        if not shown:
            shown = [f"`{k}` {_cell(v)}" for k, v in doc.items() if _cell(v)][:6]
        rows.append(f"| `{path.name}` | {'; '.join(shown) or '(nested; see the file)'} |")
    return "\n".join(rows)


#: NAME -> (generated output, pattern whose group 1 is the number): the figures prose quotes. The
#: patterns accept the wordings of earlier outputs where a later one renamed a figure.
VALUES = {
    "plan.suitable": ("plan", r"suitable poses ([\d,]+)"),
    "plan.chosen": ("plan", r"D-optimal for (\d+) poses"),
    "plan.validation": ("plan", r"(\d+) random validation poses added"),
    "plan.repeats": ("plan", r"(\d+) poses measured \d+ times back to back"),
    "plan.predicted_um": ("plan", r"held-out ([\d.]+) µm"),
    "demo.plan_poses": ("demo", r"plan: ([\d,]+) poses, estimated"),
    "demo.plan_hours": ("demo", r"plan: [\d,]+ poses, estimated ([\d.]+) h"),
    "demo.training_poses": ("demo", r"calibrate: geometric on (\d+) training poses"),
    "demo.geometric_mm": ("demo", r"round 1: .*?geometric: (?:held-out|test set) ([\d.]+) mm"),
    "demo.folds_before_mm": ("demo", r"on the folds ([\d.]+) → [\d.]+ mm"),
    "demo.folds_after_mm": ("demo", r"on the folds [\d.]+ → ([\d.]+) mm"),
    "demo.final_poses": ("demo", r"verdict: .*? on (\d+) poses \("),
    "demo.final_hours": ("demo", r"verdict: .*? on \d+ poses \(([\d.]+) h\)"),
    "demo.final_mm": ("demo", r"verdict: .*? mean ([\d.]+) mm = [\d.]+×"),
    "demo.final_ratio": ("demo", r"verdict: .*? mean [\d.]+ mm = ([\d.]+)×"),
    "diagnose.r2": ("diagnose", r"the held-out residual follows it: R² ([\d.]+)"),
}
VALUE = re.compile(r"<!-- (value|timing): *([\w.-]+) *-->")


def doc_value(name: str) -> str:
    """The number :data:`VALUES` names, as the generated output prints it; KeyError/ValueError
    naming the marker when it has no entry or its pattern no longer matches."""
    if name not in VALUES:
        raise KeyError(f"<!-- value: {name} -->: not in docs/hooks.py VALUES")
    output, pattern = VALUES[name]
    m = re.search(pattern, generated_output(output))
    if m is None:
        raise ValueError(f"<!-- value: {name} -->: docs/generated/{output}.txt no longer matches {pattern!r}")
    return m.group(1)


def timing_text(name: str) -> str:
    """`` (13 s wall at load 2.0 when generated)`` from docs/generated/timings.json, with its leading
    space (the marker follows a word), or "" when not recorded."""
    path = ROOT / "docs" / "generated" / "timings.json"
    try:
        t = json.loads(path.read_text())[name]
    except (OSError, ValueError, KeyError, TypeError):
        return ""
    peak = f", {t['peak_rss_mb']:.0f} MB peak" if t.get("peak_rss_mb") else ""
    return f" ({t['wall_s']:.0f} s wall{peak} at load {t['load']:.1f} when generated)"


def _value(match) -> str:
    return doc_value(match.group(2)) if match.group(1) == "value" else timing_text(match.group(2))


def _replace(match) -> str:
    kind, arg = match.group(1), (match.group(2) or "").strip()
    if kind == "help":
        return f"```text\n$ campaign {arg} --help\n{command_help(arg).rstrip()}\n```"
    if kind == "output":
        return f"```text\n{generated_output(arg).rstrip()}\n```"
    return benchmark_table()


def on_page_markdown(markdown, page, config, files):
    return VALUE.sub(_value, MARKER.sub(_replace, markdown))
