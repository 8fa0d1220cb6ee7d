"""Which cell a run is measured on, and the refusal to measure one run on two cells.

A run's measurements belong to one cell: the same robot and tracker, or the same simulated
world. The cell's identity is recorded in the run's log (meta ``cell``: ``{"kind", "spec",
"fingerprint", "detail"}``, and each session's ``session_start`` event): for the simulated cell
its world (``sim:`` seed, noise, hidden effects and their parameters and files); for adapters
(``--cell SPEC``) the content of its file (a FILE.py, a module's source; not where it lies), and
for the built-in MuJoCo twin the ``sim:`` world it takes its defaults from and its options file
(a user's adapters' options, addresses and timeouts, are recorded but do not make another cell);
for a controller and a tracker given by address, the addresses. The simulated world includes
the scene's placement of the tracker and of the robot (``placement``): a tracker moved is
another cell. The fingerprint is a SHA-256 of that description; a cell recorded before the
world held its placement is the same cell as one that differs from it by that key alone
(:func:`same_cell`).

A run resumed on another cell (allowed) is then measured in *cell segments*: the poses of each
recorded cell (:func:`cell_segments`, ``RunFolder.cell_segments``), which `calibrate`,
`diagnose` and `auto` model with one registration each (campaign.identify.cells).

Resuming on a cell whose fingerprint differs is refused in one line, before anything is started
or written, unless the caller allows it (``--allow-other-cell``): the change is then recorded
(event ``cell_changed``, meta ``cells`` lists every cell the run was measured on).
"""

from __future__ import annotations

import hashlib
import json
from dataclasses import dataclass
from pathlib import Path

import numpy as np

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
    return {"seed": int(cfg.sim.seed), "noise_m": float(cfg.sim.noise_m), "hidden_effects": effects,
            "placement": _placement(cfg)}


def _placement(cfg) -> dict | None:
    """Where the simulated world's tracker and robot stand: the scene's pose of the tracker frame
    in the cell (4, 4) and its ``robot_base`` (rounded to 0.1 µm / 0.1 µrad: the file's words, not
    their round-off); None when the scene cannot be read (the cell then fails with its own line)."""
    from campaign.errors import CampaignError
    from campaign.plan.scene import load_scene

    try:
        scene = load_scene(cfg.scene_path)
    except (CampaignError, OSError, TypeError):
        return None
    base = scene.robot_base
    return {"T_cell_L": np.round(np.asarray(scene.T_IL, dtype=float), 7).tolist(),
            "robot_base": None if base is None else
            [np.round(np.asarray(base[0], dtype=float), 7).tolist(),
             None if base[1] is None else np.round(np.asarray(base[1], dtype=float), 7).tolist()]}


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
    return {"kind": kind, "spec": spec, "fingerprint": _fingerprint(kind, detail), "detail": detail,
            "resolved": resolved}


def _fingerprint(kind: str, detail: dict) -> str:
    """16 hex digits of the SHA-256 of a cell's content (not where its files lie)."""
    what = {k: v for k, v in detail.items() if k not in ("spec", "source")}
    text = json.dumps({"kind": kind, **what}, sort_keys=True)
    return hashlib.sha256(text.encode()).hexdigest()[:16]


def same_cell(before: dict | None, now: dict | None) -> bool:
    """Whether two recorded cells (``cell_identity`` records) are one: the same fingerprint, or a
    record written before the simulated world held its ``placement`` whose fingerprint is ``now``'s
    without it (a run begun before that, resumed on the same world)."""
    if before is None or now is None:
        return before is now
    if before.get("fingerprint") == now.get("fingerprint"):
        return True
    for old, new in ((before, now), (now, before)):
        world = ((new.get("detail") or {}).get("world")) or {}
        old_world = ((old.get("detail") or {}).get("world")) or {}
        if "placement" in world and "placement" not in old_world and new.get("kind"):
            detail = dict(new["detail"])
            detail["world"] = {k: v for k, v in world.items() if k != "placement"}
            if _fingerprint(new["kind"], detail) == old.get("fingerprint"):
                return True
    return False


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
    if (before is None or same_cell(before, identity) or allow_other_cell
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
    if before is not None and not same_cell(before, identity):
        store.add_event("cell_changed", {"from": before, "to": identity,
                                         "allowed_by": "--allow-other-cell" if allowed else None})
    if not cells or not same_cell(cells[-1], identity):
        cells.append(identity)
    store.set_meta("cells", cells)
    store.set_meta("cell", identity)


# -- the cell segments of a run ---------------------------------------------------------------------
@dataclass(frozen=True)
class CellSegments:
    """Which measured poses were measured on which recorded cell: segment k (0-based) holds the
    poses of ``cells[k]``, the cells in the order first measured on (a session with no recorded
    cell, measured before cells were recorded, belongs to the session before it, else to the
    first recorded one). ``pose_ids`` (n,) in measuring order and ``segment`` (n,) their segment;
    ``event_segment``: the segment of each event by its log sequence number."""

    cells: tuple
    pose_ids: np.ndarray
    segment: np.ndarray
    session_event_seqs: tuple = ()
    session_segments: tuple = ()

    @property
    def n(self) -> int:
        return len(self.cells)

    @property
    def mixed(self) -> bool:
        """Measured poses from more than one cell: the run was resumed elsewhere (``--allow-other-cell``)
        and measured there (a cell where every pose failed leaves the run one cell's)."""
        return len(np.unique(self.segment)) > 1

    def of(self, pose_ids) -> np.ndarray:
        """The segment (n,) of each of ``pose_ids`` (0 for an id not stored by a session)."""
        index = {int(p): int(s) for p, s in zip(self.pose_ids, self.segment)}
        return np.array([index.get(int(p), 0) for p in np.asarray(pose_ids).reshape(-1)], dtype=np.int64)

    def event_segment(self, event_seq: int) -> int:
        """The segment of the event with log sequence number ``event_seq`` (its session's)."""
        k = int(np.searchsorted(np.asarray(self.session_event_seqs, dtype=np.int64), int(event_seq), side="right")) - 1
        return int(self.session_segments[k]) if k >= 0 and self.session_segments else 0

    def label(self, k: int) -> str:
        """``segment 2 (--cell mujoco, fingerprint 0123abcd...)``, 1-based as the command line counts."""
        cell = self.cells[k] or {}
        return f"segment {k + 1} ({cell.get('spec', 'an unrecorded cell')}, fingerprint {cell.get('fingerprint', '?')})"

    def describe(self, k: int, pose_ids=None) -> str:
        """``segment 2 (--sim, fingerprint ...): 30 poses, the 31st-60th measured (first id 1030, last 1059)``
        over ``pose_ids`` (the poses a stage uses; all stored ones when None)."""
        ids = self.pose_ids[self.segment == k]
        if pose_ids is not None:
            ids = ids[np.isin(ids, np.asarray(pose_ids))]
        order = np.flatnonzero(np.isin(self.pose_ids, ids))
        where = ("" if not len(order) else f", the {_ordinal(order[0] + 1)} measured" if len(order) == 1 else
                 f", the {_ordinal(order[0] + 1)}-{_ordinal(order[-1] + 1)} measured")
        span = f" (first id {ids[0]}, last {ids[-1]})" if len(ids) > 1 else f" (id {ids[0]})" if len(ids) else ""
        return f"{self.label(k)}: {len(ids)} pose{'' if len(ids) == 1 else 's'}{where}{span}"

    def as_json(self, pose_ids=None) -> list:
        """metrics.json / diagnosis.json ``cells.segments``: one entry per segment."""
        out = []
        for k, cell in enumerate(self.cells):
            ids = self.pose_ids[self.segment == k]
            if pose_ids is not None:
                ids = ids[np.isin(ids, np.asarray(pose_ids))]
            out.append({"segment": k + 1, "spec": (cell or {}).get("spec"), "kind": (cell or {}).get("kind"),
                        "fingerprint": (cell or {}).get("fingerprint"), "n_poses": int(len(ids)),
                        "first_pose_id": int(ids[0]) if len(ids) else None,
                        "last_pose_id": int(ids[-1]) if len(ids) else None})
        return out


def _ordinal(n: int) -> str:
    n = int(n)
    suffix = "th" if 10 <= n % 100 <= 20 else {1: "st", 2: "nd", 3: "rd"}.get(n % 10, "th")
    return f"{n}{suffix}"


def cell_segments(db, recorded: dict | None = None) -> CellSegments:
    """The :class:`CellSegments` of a measurement log (a sqlite3 connection, read only): sessions
    from its ``session_start`` events (their ``cell``), each stored pose in the session whose start
    precedes it (wall clock; a pose without one in the first). ``recorded``: the log's meta
    ``cell``, for a log without sessions (imported)."""
    has = {r[0] for r in db.execute("SELECT name FROM sqlite_master WHERE type = 'table'")}
    sessions = db.execute("SELECT seq, wall_time_unix_s, detail FROM events WHERE kind = 'session_start' "
                          "ORDER BY seq").fetchall() if "events" in has else []
    rows = db.execute("SELECT pose_id, wall_time_unix_s FROM poses WHERE status = 'measured' "
                      "ORDER BY wall_time_unix_s, seq, pose_id").fetchall() if "poses" in has else []
    pose_ids = np.array([r[0] for r in rows], dtype=np.int64)
    cells, seg_of_session, pending = [], [], 0
    for _, _, detail in sessions:
        try:
            cell = json.loads(detail).get("cell")
        except (ValueError, AttributeError):
            cell = None
        if not isinstance(cell, dict) or not cell.get("fingerprint"):
            seg_of_session.append(seg_of_session[-1] if seg_of_session else None)
            continue
        k = next((i for i, c in enumerate(cells) if same_cell(c, cell)), None)
        if k is None:
            cells.append(cell)
            k = len(cells) - 1
        seg_of_session.append(k)
    seg_of_session = [pending if k is None else k for k in seg_of_session]
    if not cells:
        return CellSegments((recorded,), pose_ids, np.zeros(len(pose_ids), dtype=np.int64))
    starts = np.array([w for _, w, _ in sessions], dtype=float)
    wall = np.array([np.nan if r[1] is None else r[1] for r in rows], dtype=float)
    at = np.searchsorted(starts, np.nan_to_num(wall, nan=-np.inf), side="right") - 1
    segment = np.asarray(seg_of_session, dtype=np.int64)[np.clip(at, 0, None)] if len(rows) else \
        np.zeros(0, dtype=np.int64)
    return CellSegments(tuple(cells), pose_ids, segment, tuple(int(s) for s, _, _ in sessions),
                        tuple(seg_of_session))


def segment_events(db, kind: str, segments: CellSegments | None = None) -> list:
    """[(segment, time_s, detail dict), ...] of the log's events of ``kind`` in order, each with
    the cell segment of the session it happened in (``segments``: the log's, when already read)."""
    segments = cell_segments(db) if segments is None else segments
    rows = db.execute("SELECT seq, time_s, detail FROM events WHERE kind = ? ORDER BY seq", (kind,)).fetchall()
    return [(segments.event_segment(seq), t, json.loads(d)) for seq, t, d in rows]
