"""campaign/tolerances.py holds each tolerance once: a name assigned twice (a merge that brought a
removed block back) silently replaces the value the code was tested with."""

import ast
import collections
from pathlib import Path

import campaign.tolerances


def test_every_tolerance_is_defined_once():
    tree = ast.parse(Path(campaign.tolerances.__file__).read_text())
    names = collections.Counter(t.id for node in tree.body if isinstance(node, (ast.Assign, ast.AnnAssign))
                                for t in (node.targets if isinstance(node, ast.Assign) else [node.target])
                                if isinstance(t, ast.Name))
    assert [n for n, k in names.items() if k > 1] == []
