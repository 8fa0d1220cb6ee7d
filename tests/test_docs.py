"""The documentation against the code: every command and option shown in the README and the docs
exists, the README fits on a screen with the two commands first, and the site builds with
`mkdocs build --strict` (a broken link, a missing page or a missing generated output fails it)."""

import argparse
import re
import shlex
import subprocess
import sys
from pathlib import Path

import pytest

from campaign.cli import build_parser

ROOT = Path(__file__).resolve().parent.parent
PAGES = [ROOT / "README.md", *sorted((ROOT / "docs").rglob("*.md"))]
FENCE = re.compile(r"```[a-z]*\n(.*?)```", re.DOTALL)
INLINE = re.compile(r"`(campaign [^`]+)`")


def _subparsers(parser):
    return next((a for a in parser._actions if isinstance(a, argparse._SubParsersAction)), None)


def _shown_commands(text: str) -> list:
    """Every `campaign ...` command line in code blocks and inline code of a page."""
    lines = []
    for block in FENCE.findall(text):
        joined = block.replace("\\\n", " ")
        for line in joined.splitlines():
            for part in line.split("#")[0].split("&&"):  # `a && b`: two commands
                part = part.strip().removeprefix("$ ")
                if part.startswith("campaign "):
                    lines.append(part)
    lines += [m.strip() for m in INLINE.findall(text)]
    # "campaign calibrate: ..." is an error message shown, not a command
    return [line for line in lines if not line.split()[1].endswith(":")]


def _check(line: str, parser) -> list:
    """Problems of one shown command line: an unknown command or an option its parser lacks."""
    try:
        words = shlex.split(line.replace("|", " "))
    except ValueError:
        words = line.split()
    words = words[1:]
    p, path = parser, ["campaign"]
    while words and _subparsers(p) is not None and not words[0].startswith("-"):
        sub = _subparsers(p)
        if words[0] in ("...", "…") or words[0].isupper() or words[0].startswith("["):
            break
        if words[0] not in sub.choices:
            return [f"{line!r}: `{' '.join(path)} {words[0]}` is not a command"]
        p, path = sub.choices[words[0]], path + [words.pop(0)]
    known = set(p._option_string_actions)
    problems = []
    for w in words:
        w = w.strip("[]()`,;")
        if w.startswith("--") and len(w) > 2:
            for opt in w.split("=")[0].split("/"):  # --ann/--no-ann: both
                if opt not in known:
                    problems.append(f"{line!r}: `{' '.join(path)}` has no option {opt}")
    return problems


def test_every_command_and_option_shown_in_the_readme_and_docs_exists():
    parser = build_parser()
    problems, shown = [], 0
    for page in PAGES:
        for line in _shown_commands(page.read_text()):
            shown += 1
            problems += [f"{page.relative_to(ROOT)}: {p}" for p in _check(line, parser)]
    assert shown > 50
    assert not problems, "\n".join(problems)


def test_the_checker_catches_a_removed_command_and_option():
    parser = build_parser()
    assert _check("campaign plan --select 5", parser) == []
    assert _check("campaign model base-params --position-only", parser) == []
    assert _check("campaign calibrate runs/x --no-such-flag", parser)
    assert _check("campaign frobnicate runs/x", parser)


def test_readme_fits_on_a_screen_with_the_two_commands_first():
    lines = (ROOT / "README.md").read_text().splitlines()
    assert len(lines) <= 300, len(lines)
    head = "\n".join(lines[:20])
    assert "campaign demo" in head and "python -m pytest" in head


def test_the_site_builds_strict(tmp_path):
    pytest.importorskip("mkdocs", reason="the docs extra (pip install -e '.[test]') brings mkdocs")
    done = subprocess.run([sys.executable, "-m", "mkdocs", "build", "--strict", "--site-dir", str(tmp_path / "site")],
                          cwd=ROOT, capture_output=True, text=True)
    assert done.returncode == 0, done.stderr[-3000:]
    assert (tmp_path / "site" / "commands" / "iso9283" / "index.html").is_file()
    api = (tmp_path / "site" / "api" / "index.html").read_text()
    assert "RunFolder" in api and "solve_pose" in api
