"""The data flow of DESIGN.md, read from the source: nothing below `diagnose` imports it, and the
package's module-level imports form no circle (a circle is what makes an import order matter).

The graph is built from each module's top-level ``import`` / ``from ... import`` statements
(function-level imports are deferred and cannot form a load-time circle, but they still count
for the layering rule).
"""

import ast
from pathlib import Path

import campaign

ROOT = Path(campaign.__file__).parent


def _modules() -> dict:
    """module name -> path, for every .py file of the package."""
    out = {}
    for path in ROOT.rglob("*.py"):
        parts = path.relative_to(ROOT.parent).with_suffix("").parts
        name = ".".join(parts[:-1] if parts[-1] == "__init__" else parts)
        out[name] = path
    return out


def _imports(path: Path, name: str, top_level_only: bool) -> set:
    """campaign.* modules imported by the module at ``path`` (named ``name``)."""
    tree = ast.parse(path.read_text(), filename=str(path))
    nodes = tree.body if top_level_only else list(ast.walk(tree))
    package = name if path.name == "__init__.py" else name.rpartition(".")[0]
    found = set()
    for node in nodes:
        if isinstance(node, ast.Import):
            found |= {a.name for a in node.names if a.name.startswith("campaign")}
        elif isinstance(node, ast.ImportFrom):
            if node.level:
                base = package.rsplit(".", node.level - 1)[0] if node.level > 1 else package
                mod = f"{base}.{node.module}" if node.module else base
            else:
                mod = node.module or ""
            if mod.startswith("campaign"):
                found.add(mod)
                found |= {f"{mod}.{a.name}" for a in node.names}
    return found


def _resolve(imported: set, modules: dict) -> set:
    """The package modules an import set loads (a module and every package above it)."""
    out = set()
    for mod in imported:
        parts = mod.split(".")
        for i in range(1, len(parts) + 1):
            if ".".join(parts[:i]) in modules:
                out.add(".".join(parts[:i]))
    return out


#: modules above diagnose in DESIGN.md's list: the command line and the loop that calls every stage
#: (packages: every module under them)
ABOVE_DIAGNOSE = ("campaign.cli", "campaign.auto")


def test_nothing_below_diagnose_imports_it():
    modules = _modules()
    offenders = []
    for name, path in modules.items():
        if name.startswith("campaign.diagnose") or name.startswith(ABOVE_DIAGNOSE):
            continue
        hits = [m for m in _resolve(_imports(path, name, top_level_only=False), modules)
                if m.startswith("campaign.diagnose")]
        if hits:
            offenders.append(f"{name} imports {', '.join(sorted(hits))}")
    assert not offenders, offenders


def test_the_noise_floor_lives_below_identify_and_diagnose():
    from campaign.measure import floor

    assert floor.__name__ == "campaign.measure.floor"
    modules = _modules()
    for user in ("campaign.identify.noise_floor", "campaign.identify.calibrate", "campaign.diagnose.engine"):
        assert "campaign.measure.floor" in _resolve(_imports(modules[user], user, top_level_only=True), modules)
    assert "campaign.diagnose.floor" not in modules


def test_module_level_imports_form_no_circle():
    modules = _modules()
    graph = {name: _resolve(_imports(path, name, top_level_only=True), modules) - {name}
             for name, path in modules.items()}
    # a package's __init__ runs before its submodules: an edge from a submodule to its own
    # package is not a circle unless the __init__ imports back
    state, cycles = {}, []

    def visit(node, stack):
        state[node] = "open"
        stack.append(node)
        for nxt in sorted(graph.get(node, ())):
            if nxt.startswith(node + "."):
                continue
            if state.get(nxt) == "open":
                cycle = stack[stack.index(nxt):] + [nxt]
                if not all(b.startswith(a + ".") or a.startswith(b + ".") for a, b in zip(cycle, cycle[1:])):
                    cycles.append(" -> ".join(cycle))
            elif nxt not in state:
                visit(nxt, stack)
        stack.pop()
        state[node] = "done"

    for name in sorted(graph):
        if name not in state:
            visit(name, [])
    assert not cycles, cycles
