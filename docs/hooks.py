"""mkdocs hooks: what the documentation shows is made from the code and the results at build time.

Markers in a page, each on a line of its own:

- ``<!-- help: plan -->`` (or ``<!-- help: model base-params -->``): the command's ``--help``, from
  the same argparse parser the command line uses, so it cannot drift from the code;
- ``<!-- output: NAME -->``: ``docs/generated/NAME.txt``, a command's real output written by
  ``python docs/generate_outputs.py`` from a real run (a missing file fails the build);
- ``<!-- benchmarks -->``: a table of every ``benchmarks/results/*.json``, its headline figures.
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


def _replace(match) -> str:
    kind, arg = match.group(1), (match.group(2) or "").strip()
    if kind == "help":
        return f"```text\n$ campaign {arg} --help\n{command_help(arg).rstrip()}\n```"
    if kind == "output":
        return f"```text\n{generated_output(arg).rstrip()}\n```"
    return benchmark_table()


def on_page_markdown(markdown, page, config, files):
    return MARKER.sub(_replace, markdown)
