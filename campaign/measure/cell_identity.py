"""Which cell a run is measured on, and the refusal to measure one run on two cells.

A run's measurements belong to one cell: the same robot and tracker, or the same simulated
world. The cell's identity is recorded in the run's log (meta ``cell``: ``{"kind", "spec",
"fingerprint", "detail"}``, and each session's ``session_start`` event): for the simulated cell
its world (``sim:`` seed, noise, hidden effects and their parameters and files); for adapters
(``--cell SPEC``) the content of its file (a FILE.py, a module's source; not where it lies), and
for the built-in MuJoCo twin the ``sim:`` world it takes its defaults from and its options file
(a user's adapters' options, addresses and timeouts, are recorded but do not make another cell);
for a controller and a tracker given by address, the addresses. The fingerprint is a SHA-256
of that description.

Resuming on a cell whose fingerprint differs is refused in one line, before anything is started
or written, unless the caller allows it (``--allow-other-cell``): the change is then recorded
(event ``cell_changed``, meta ``cells`` lists every cell the run was measured on).
"""

from __future__ import annotations

import hashlib
import json
from pathlib import Path

from campaign.errors import ConfigError


def _file_digest(path) -> str | None:
    try:
        return hashlib.sha256(Path(path).read_bytes()).hexdigest()
    except OSError:
        return None


def _sim_world(cfg) -> dict:
    """What makes the simulated world of ``cfg`` (a CampaignConfig): not its speed or its faults."""
    effects = []
    here = Path(cfg.path).parent if getattr(cfg, "path", None) else Path.cwd()
    for spec, params in cfg.hidden_effects():
        spec = str(spec)
        file = spec.rpartition(":")[0] if ":" in spec else None
        if file and file.endswith(".py"):  # a user's effect, relative to the campaign.yaml that names it
            file = Path(file) if Path(file).is_absolute() else here / file
        else:
            file = None  # a built-in effect, or a module's (named as it is)
        # a file's effect by its class and content, not where the file lies (a run folder moved)
        effects.append({"effect": spec.rpartition(":")[2] if file else spec,
                        "params": None if params is None else [float(v) for v in params],
                        "file_sha256": _file_digest(file) if file else None})
    return {"seed": int(cfg.sim.seed), "noise_m": float(cfg.sim.noise_m), "hidden_effects": effects}


def cell_identity(cfg, *, sim: bool = False, cell: str | None = None, options=None, controller=None,
                  tracker=None) -> dict:
    """The identity of the cell a session measures on (module docstring): ``{"kind": "sim" |
    "cell" | "peers", "spec": the command line's words, "fingerprint": 16 hex digits, "detail",
    "resolved"}``; ``resolved`` False when an adapter's source cannot be found (the cell then
    fails to start with its own error)."""
    resolved = True
    if sim:
        kind, spec, detail = "sim", "--sim", {"world": _sim_world(cfg)}
    elif cell is not None:
        from campaign.cell import adapter_source

        kind, spec = "cell", f"--cell {cell}" + (f" --options {options}" if options is not None else "")
        source = adapter_source(str(cell), Path(cfg.path).parent if getattr(cfg, "path", None) else None)
        resolved = source is not None
        detail = {"spec": str(cell), "source": None if source is None else str(source),
                  "source_sha256": None if source is None else _file_digest(source)}
        if str(cell) == "mujoco":  # the twin's world: the sim section's and its options' (seed, stiffness, ...)
            detail["world"] = _sim_world(cfg)
            detail["options_sha256"] = None if options is None else _file_digest(options)
    else:
        kind = "peers"
        spec = f"--controller {controller[0]}:{controller[1]} --tracker {tracker[0]}:{tracker[1]}"
        detail = {"controller": f"{controller[0]}:{controller[1]}", "tracker": f"{tracker[0]}:{tracker[1]}"}
    what = {k: v for k, v in detail.items() if k not in ("spec", "source")}  # the content, not where it lies
    text = json.dumps({"kind": kind, **what}, sort_keys=True)
    return {"kind": kind, "spec": spec, "fingerprint": hashlib.sha256(text.encode()).hexdigest()[:16],
            "detail": detail, "resolved": resolved}


def recorded_cell(store) -> dict | None:
    """The cell the run's log was last measured on (meta ``cell``), or None."""
    return store.get_meta("cell")


def check_cell(run_dir, identity: dict, allow_other_cell: bool = False) -> dict | None:
    """ConfigError (one line) when the run holds measurements of another cell than ``identity``
    and ``allow_other_cell`` is not given; the recorded cell (or None) otherwise. Reads only."""
    from campaign.measure.store import open_run

    if not (Path(run_dir) / "measurements.sqlite").is_file():
        return None
    with open_run(run_dir) as store:
        return refuse_other_cell(run_dir, recorded_cell(store), identity, allow_other_cell)


def refuse_other_cell(run_dir, before: dict | None, identity: dict, allow_other_cell: bool = False) -> dict | None:
    """:func:`check_cell` on the recorded cell ``before`` (None: none recorded)."""
    if (before is None or before.get("fingerprint") == identity["fingerprint"] or allow_other_cell
            or not identity.get("resolved", True)):
        return before
    changed = _changes(before.get("detail"), identity.get("detail")) if before.get("spec") == identity["spec"] else []
    raise ConfigError(f"{run_dir}: measured so far on another cell ({before.get('spec')}, fingerprint "
                      f"{before.get('fingerprint')}) than {identity['spec']} (fingerprint {identity['fingerprint']}"
                      + (f"; {', '.join(changed)}" if changed else "") + "): "
                      "one run's measurements come from one cell; resume on that cell, or give --allow-other-cell "
                      "to measure the rest here (recorded in the run)")


def _changes(before, now, prefix: str = "") -> list:
    """What differs between two cells' ``detail`` of one spec, in campaign.yaml's words where
    it has them (``sim.seed 0 -> 3``): the same words on the command line can be another world."""
    if isinstance(before, dict) and isinstance(now, dict):
        out = []
        for key in sorted(set(before) | set(now), key=str):
            if key in ("spec", "source"):  # where it lies, not what it is
                continue
            name = "sim" if key == "world" and not prefix else f"{prefix}.{key}" if prefix else str(key)
            out += _changes(before.get(key), now.get(key), name)
        return out
    if before == now:
        return []
    if prefix.endswith("_sha256"):
        return [f"{prefix[:-len('_sha256')]} changed (another file content)"]
    if isinstance(before, list) or isinstance(now, list):
        return [f"{prefix} changed"]
    return [f"{prefix} {before} -> {now}"]


def record_cell(store, identity: dict, *, allowed: bool = False) -> None:
    """Record ``identity`` as the run's cell in its log (meta ``cell`` and ``cells``); a change
    from the recorded cell (allowed by the caller) as a ``cell_changed`` event."""
    before = recorded_cell(store)
    cells = list(store.get_meta("cells") or ([before] if before else []))
    if before is not None and before.get("fingerprint") != identity["fingerprint"]:
        store.add_event("cell_changed", {"from": before, "to": identity,
                                         "allowed_by": "--allow-other-cell" if allowed else None})
    if not cells or cells[-1].get("fingerprint") != identity["fingerprint"]:
        cells.append(identity)
    store.set_meta("cells", cells)
    store.set_meta("cell", identity)
