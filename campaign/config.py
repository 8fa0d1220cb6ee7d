"""campaign.yaml: the configuration of a campaign (robot, scene, plan, run, sim, effects).

Parsed once, by :func:`load_config`, into a frozen :class:`CampaignConfig` whose every value
has been checked for its type, its range and finiteness; a bad value is one
:class:`~campaign.errors.ConfigError` line naming the file and the field, e.g.
``runs/x/campaign.yaml: plan.clearance_m: must be a finite number >= 0, got -0.5``,
raised before any work starts. Unknown keys are errors too. Paths are relative to the file
that names them. Without a file, the embedded default ``campaign.yaml`` is used.

The keys and their defaults are a contract (DESIGN.md): extend, never change them.
"""

from __future__ import annotations

import math
from dataclasses import asdict, dataclass, field, fields
from pathlib import Path

import yaml

from campaign.errors import ConfigError
from campaign.fileio import atomic_write, read_yaml_mapping  # noqa: F401  (read_yaml_mapping re-exported)
from campaign.paths import DEFAULT_CONFIG, DEFAULT_ROBOT, DEFAULT_SCENE

#: fault kinds the simulated cell injects (docs/protocol.md), each a rate per request in 0..1
FAULT_KINDS = ("drop", "late", "garble", "beam_lost", "robot_fault", "estop")
#: measure attempts of a pose use request-id slots 1..31 (campaign.measure.driver): retries <= 30
MAX_RETRIES = 30
#: longest wait the driver accepts for one reply, s (a day: anything longer is a typo)
MAX_TIMEOUT_S = 86400.0
#: finest motion sampling accepted, deg (100x the default's samples; finer only costs time)
MIN_MOTION_SAMPLE_DEG = 0.01
#: most cells per joint axis (the paper uses at most 17)
MAX_GRID_CELLS = 10_000
#: a plan's candidate index is its pose id, and the driver's request ids hold pose ids below 2**34
MAX_GRID_SIZE = 2**34


# -- one validator per kind of value: each returns what it checked ----------------------------

class _Where:
    """Names a field for error messages: ``FILE: section.key``."""

    def __init__(self, path, section: str):
        self.path, self.section = path, section

    def __call__(self, key) -> str:
        return f"{self.path}: {self.section}.{key}" if self.section else f"{self.path}: {key}"


def _is_number(v) -> bool:
    return not isinstance(v, bool) and isinstance(v, (int, float))


def check_number(value, where: str, *, low=None, high=None, low_open=False) -> float:
    """A finite float within [low, high] (``low_open``: > low); ConfigError naming ``where``."""
    ok = _is_number(value) and math.isfinite(value)
    if ok and low is not None:
        ok = value > low if low_open else value >= low
    if ok and high is not None:
        ok = value <= high
    if not ok:
        rng = []
        if low is not None:
            rng.append(f"{'>' if low_open else '>='} {low:g}")
        if high is not None:
            rng.append(f"<= {high:g}")
        raise ConfigError(f"{where}: must be a finite number{' ' + ' and '.join(rng) if rng else ''}, got {value!r}")
    return float(value)


def check_int(value, where: str, *, low=None, high=None) -> int:
    """An integer within [low, high] (floats and booleans refused); ConfigError naming ``where``."""
    ok = not isinstance(value, bool) and isinstance(value, int)
    if ok and low is not None:
        ok = value >= low
    if ok and high is not None:
        ok = value <= high
    if not ok:
        rng = " in " + f"{low}..{high}" if low is not None and high is not None else \
            (f" >= {low}" if low is not None else "")
        raise ConfigError(f"{where}: must be an integer{rng}, got {value!r}")
    return int(value)


def check_str(value, where: str, *, optional=False) -> str | None:
    if value is None and optional:
        return None
    if not isinstance(value, str) or not value.strip():
        raise ConfigError(f"{where}: must be a non-empty string{' or null' if optional else ''}, got {value!r}")
    return value


def check_names(value, where: str) -> tuple:
    """A list of strings (effect entries: built-in names or ``file.py:Class``, either with a joint
    list ``name:2,3``) or of mappings ``{effect: NAME, joints: [2, 3]}``, or a mapping name ->
    true/false (the enabled ones), or a comma-separated string. Returns the specs (strings)."""
    from campaign.effects.base import effect_entry, parse_effect_list

    if value is None:
        return ()
    if isinstance(value, str):
        value = list(parse_effect_list(value, where))
    if isinstance(value, dict):
        for k, v in value.items():
            if not isinstance(v, bool):
                raise ConfigError(f"{where}.{k}: must be true or false, got {v!r}")
        value = [k for k, v in value.items() if v]
    if not isinstance(value, (list, tuple)):
        raise ConfigError(f"{where}: must be a list of names, got {value!r}")
    out = []
    for i, v in enumerate(value):
        if isinstance(v, dict):
            v = effect_entry(v, f"{where}[{i}]")
        if not isinstance(v, str):
            raise ConfigError(f"{where}[{i}]: must be a string, got {v!r} (or a mapping {{effect: NAME, joints: [...]}})")
        if v.strip():
            out.append(v.strip())
    return refuse_repeats(out, where)


def one_spec_per_effect(specs, where: str) -> tuple:
    """``specs`` (the effects a calibration fits) when no effect comes twice, over two joint lists
    included (``joint_compliance:2`` and ``joint_compliance:3``: a calibration holds one block per
    effect); else a ConfigError giving the one spec to write."""
    from campaign.effects.base import merge_effects, split_joints

    seen = {}
    for spec in specs:
        base = split_joints(spec)[0]
        if base in seen:
            merged = merge_effects([seen[base]], [spec])[0]
            raise ConfigError(f"{where}: '{seen[base]}' and '{spec}' are one effect; name it once"
                              + (f": {merged}" if merged != seen[base] else ""))
        seen[base] = spec
    return tuple(specs)


def refuse_repeats(names, where: str) -> tuple:
    """``names`` as a tuple, or a ConfigError naming the first entry given twice (an effect
    named twice would be fitted twice over: its parameters undetermined, its stage unusable)."""
    seen = set()
    for name in names:
        if name in seen:
            raise ConfigError(f"{where}: '{name}' is named twice (name each effect once)")
        seen.add(name)
    return tuple(names)


def check_hidden_effects(value, where: str) -> tuple:
    """``sim.hidden_effects``: effect entries as :func:`check_names` takes them, each list entry
    also a mapping ``{effect: SPEC, params: [numbers, ...]}`` (SI, the effect's parameter order).
    Returns (specs, ((spec, params), ...) for the entries that state their parameters)."""
    if not isinstance(value, (list, tuple)):
        return check_names(value, where), ()
    specs, stated = [], []
    for i, v in enumerate(value):
        if isinstance(v, dict):
            from campaign.effects.base import effect_entry

            extra = sorted(set(v) - {"effect", "params", "joints"})
            if extra or "effect" not in v:
                raise ConfigError(f"{where}[{i}]: expected {{effect: NAME, joints: [...], params: [...]}}, got {v!r}")
            check_str(v["effect"], f"{where}[{i}].effect")
            spec = effect_entry({k: v[k] for k in ("effect", "joints") if k in v}, f"{where}[{i}]")
            params = v.get("params")
            if params is not None:
                if not isinstance(params, (list, tuple)) or not params:
                    raise ConfigError(f"{where}[{i}].params: must be a list of numbers, got {params!r}")
                params = tuple(check_number(p, f"{where}[{i}].params[{k}]") for k, p in enumerate(params))
                stated.append((spec, params))
            specs.append(spec)
        elif not isinstance(v, str):
            raise ConfigError(f"{where}[{i}]: must be a string or {{effect: NAME, params: [...]}}, got {v!r}")
        elif v.strip():
            specs.append(v.strip())
    return refuse_repeats(specs, where), tuple(stated)


def parse_faults(section, where="campaign.yaml"):
    """({kind: rate per request in [0, 1]}, late_delay_s) from the ``sim.faults`` mapping."""
    section = section or {}
    if not isinstance(section, dict):
        raise ConfigError(f"{where}: sim.faults must be a mapping of fault kind to rate")
    rates, late_delay_s = {}, 1.0
    for key, value in section.items():
        if key == "late_delay_s":
            if not _is_number(value) or not 0 <= value <= 3600:
                raise ConfigError(f"{where}: sim.faults.late_delay_s must be a number of seconds in 0..3600, "
                                  f"got {value!r}")
            late_delay_s = float(value)
            continue
        if key not in FAULT_KINDS:
            raise ConfigError(f"{where}: unknown fault 'sim.faults.{key}' (allowed: {', '.join(FAULT_KINDS)}, "
                              "late_delay_s)")
        if not _is_number(value) or not 0 <= value <= 1:
            raise ConfigError(f"{where}: sim.faults.{key} must be a rate in 0..1, got {value!r}")
        rates[key] = float(value)
    return rates, late_delay_s


# -- the sections -----------------------------------------------------------------------------

@dataclass(frozen=True)
class PlanConfig:
    """``plan:``. grid_cells: joint-limit cells per joint (eq. 17), or None (``auto``: the
    paper's 17 x 10 x 10 x 14 x 6 x 10 for the default COMAU, about a million candidates for
    any other robot: campaign.plan.grid.default_cells); distances m; times s."""

    grid_cells: tuple | None = None
    clearance_m: float = 0.035
    motion_clearance_m: float = 0.01
    motion_sample_deg: float = 1.0
    settle_time_s: float = 2.0
    tracker_time_per_reflector_s: float = 5.0
    #: the short campaign chooses poses whose reflectors lie this far inside their nests' cones
    #: (deg): the real tool is turned by the robot's errors (Table 4's size: up to ~1.6° at the
    #: tool), so a nest at its cone's edge in the nominal model may be past it in the cell
    cone_margin_deg: float = 2.0

    @classmethod
    def parse(cls, doc: dict, where: _Where) -> "PlanConfig":
        kw = {}
        if "grid_cells" in doc and doc["grid_cells"] not in (None, "auto"):
            g = doc["grid_cells"]
            if not isinstance(g, (list, tuple)) or not g:
                raise ConfigError(f"{where('grid_cells')}: must be a list of integers >= 1 "
                                  f"(cells per joint) or auto, got {g!r}")
            kw["grid_cells"] = tuple(check_int(v, f"{where('grid_cells')}[{i}]", low=1, high=MAX_GRID_CELLS)
                                     for i, v in enumerate(g))
            if math.prod(kw["grid_cells"]) >= MAX_GRID_SIZE:
                raise ConfigError(f"{where('grid_cells')}: {' x '.join(map(str, kw['grid_cells']))} candidates "
                                  f"exceed the {MAX_GRID_SIZE:,} a plan can address")
        for key in ("clearance_m", "motion_clearance_m", "settle_time_s", "tracker_time_per_reflector_s"):
            if key in doc:
                kw[key] = check_number(doc[key], where(key), low=0.0)
        if "cone_margin_deg" in doc:
            kw["cone_margin_deg"] = check_number(doc["cone_margin_deg"], where("cone_margin_deg"), low=0.0, high=45.0)
        if "motion_sample_deg" in doc:
            kw["motion_sample_deg"] = check_number(doc["motion_sample_deg"], where("motion_sample_deg"),
                                                   low=MIN_MOTION_SAMPLE_DEG, high=180.0)
        return cls(**kw)


@dataclass(frozen=True)
class RunConfig:
    """``run:``: how the driver waits and retries. Times in s; ``drift_threshold_mm`` in mm."""

    timeout_s: float = 5.0
    move_timeout_s: float = 120.0
    retries: int = 3
    reconnect_attempts: int = 5
    backoff_s: float = 0.2
    #: re-measure the reference pose every N stored poses (0: never); "auto": about
    #: DRIFT_CHECKS_PER_CAMPAIGN times a campaign, at least every 500 poses (campaign.measure.driver)
    drift_check_every: int | str = "auto"
    #: a drift check's reading farther than this from the reference's earlier readings is a
    #: warning; "auto": from the noise floor (campaign.measure.drift.moved_threshold_m)
    drift_threshold_mm: float | str = "auto"

    @classmethod
    def parse(cls, doc: dict, where: _Where) -> "RunConfig":
        kw = {}
        for key in ("timeout_s", "move_timeout_s"):
            if key in doc:
                kw[key] = check_number(doc[key], where(key), low=0.0, low_open=True, high=MAX_TIMEOUT_S)
        if "backoff_s" in doc:
            kw["backoff_s"] = check_number(doc["backoff_s"], where("backoff_s"), low=0.0, high=3600.0)
        if "drift_threshold_mm" in doc and doc["drift_threshold_mm"] != "auto":
            kw["drift_threshold_mm"] = check_number(doc["drift_threshold_mm"], where("drift_threshold_mm"), low=0.0)
        if "retries" in doc:
            kw["retries"] = check_int(doc["retries"], where("retries"), low=0, high=MAX_RETRIES)
        if "reconnect_attempts" in doc:
            kw["reconnect_attempts"] = check_int(doc["reconnect_attempts"], where("reconnect_attempts"), low=0,
                                                 high=1000)
        if "drift_check_every" in doc and doc["drift_check_every"] != "auto":
            kw["drift_check_every"] = check_int(doc["drift_check_every"], where("drift_check_every"), low=0)
        return cls(**kw)


@dataclass(frozen=True)
class SimConfig:
    """``sim:``: the simulated cell. ``noise_m`` tracker σ per coordinate (m); ``faults``
    rates per request (0..1) by kind; ``late_delay_s`` how long a late reply is held (s)."""

    seed: int = 0
    time_factor: float = 0.0
    noise_m: float = 10e-6
    hidden_effects: tuple = ("ground_compliance",)
    faults: dict = field(default_factory=dict)
    late_delay_s: float = 1.0
    #: ((spec, params), ...): hidden parameters stated in campaign.yaml (``{effect: spec, params: [...]}``, SI)
    hidden_params: tuple = ()

    @classmethod
    def parse(cls, doc: dict, where: _Where) -> "SimConfig":
        kw = {}
        if "seed" in doc:
            kw["seed"] = check_int(doc["seed"], where("seed"), low=0, high=2**63 - 1)
        if "time_factor" in doc:
            kw["time_factor"] = check_number(doc["time_factor"], where("time_factor"), low=0.0, high=1000.0)
        if "noise_m" in doc:
            kw["noise_m"] = check_number(doc["noise_m"], where("noise_m"), low=0.0, high=1.0)
        if "hidden_effects" in doc:
            kw["hidden_effects"], kw["hidden_params"] = check_hidden_effects(doc["hidden_effects"],
                                                                             where("hidden_effects"))
        if "faults" in doc:
            kw["faults"], kw["late_delay_s"] = parse_faults(doc["faults"], where.path)
        return cls(**kw)


@dataclass(frozen=True)
class TrackerConfig:
    """``tracker:``: what the user states about the instrument. ``noise_m``: σ per coordinate
    of a reflector centre (m): the noise floor of `diagnose` when no pose is measured twice, and
    the noise under which `plan` predicts a short campaign's accuracy (10 µm when not given)."""

    noise_m: float | None = None

    @classmethod
    def parse(cls, doc: dict, where: _Where) -> "TrackerConfig":
        kw = {}
        if doc.get("noise_m") is not None:
            kw["noise_m"] = check_number(doc["noise_m"], where("noise_m"), low=0.0, high=0.01, low_open=True)
        return cls(**kw)


SECTIONS = {"plan": PlanConfig, "run": RunConfig, "sim": SimConfig, "tracker": TrackerConfig}
#: keys of each section as written in campaign.yaml
SECTION_KEYS = {
    "plan": {f.name for f in fields(PlanConfig)},
    "run": {f.name for f in fields(RunConfig)},
    "sim": {f.name for f in fields(SimConfig)} - {"late_delay_s", "hidden_params"},
    "calibrate": {"effects"},
    "tracker": {f.name for f in fields(TrackerConfig)},
}
TOP_KEYS = {"robot", "scene", "tool_frame", "base_frame", "effects", *SECTION_KEYS}


@dataclass(frozen=True)
class CampaignConfig:
    """A validated campaign.yaml. Build it with :func:`load_config`.

    robot: a name under campaign/data/robot_models/ or a path (folder, robot.yaml or URDF)
    relative to the file; scene: path of the cell's YAML relative to the file; tool_frame,
    base_frame: the run's tool and base frame in the robot's URDF (None: the robot's own);
    effects: physical effects enabled for calibration, as written (built-in names or
    ``file.py:Class`` entries relative to this file).
    """

    path: Path
    robot: str = DEFAULT_ROBOT
    scene: str = str(DEFAULT_SCENE)
    tool_frame: str | None = None
    base_frame: str | None = None
    effects: tuple = ()
    plan: PlanConfig = field(default_factory=PlanConfig)
    run: RunConfig = field(default_factory=RunConfig)
    sim: SimConfig = field(default_factory=SimConfig)
    tracker: TrackerConfig = field(default_factory=TrackerConfig)

    @property
    def dir(self) -> Path:
        """The folder of the file: relative paths in it start here."""
        return self.path.parent

    def resolve(self, value) -> Path:
        """A path from the config, relative to the config file's folder."""
        p = Path(value)
        return p if p.is_absolute() else self.dir / p

    @property
    def scene_path(self) -> Path:
        return self.resolve(self.scene)

    @property
    def robot_spec(self) -> str:
        """What :meth:`RobotModel.load` takes: the path the file names when it exists
        (relative to the file), else the robot's name under campaign/data/robot_models/."""
        p = self.resolve(self.robot)
        return str(p) if p.exists() else self.robot

    def with_robot(self, robot=None, tool_frame=None, base_frame=None) -> "CampaignConfig":
        """This configuration for ``robot`` (a name, or a path, made absolute, relative to the
        current directory as a command line gives it) and its frames, as given (`--robot`,
        `--tool-frame`, `--base-frame`); frames alone: new frames on this configuration's robot;
        nothing given: this configuration."""
        from dataclasses import replace

        if robot is None and tool_frame is None and base_frame is None:
            return self
        kw = {"tool_frame": tool_frame, "base_frame": base_frame}
        if robot is not None:
            from campaign.model.robot import robot_spec

            kw["robot"] = robot_spec(robot)  # a path made absolute; a name stays a name
        else:
            kw = {k: v if v is not None else getattr(self, k) for k, v in kw.items()}
        return replace(self, **kw)

    def hidden_effects(self) -> tuple:
        """The simulated cell's hidden effects: ((spec, params or None), ...), user effect files made
        absolute against this file's folder; params (SI, the effect's order) as campaign.yaml states
        them, None to draw them (campaign.sim.truth.hidden_effect_params)."""
        from campaign.effects.base import resolve_effect_spec

        stated = dict(self.sim.hidden_params)
        return tuple((resolve_effect_spec(e, self.dir), stated.get(e)) for e in self.sim.hidden_effects)

    def hidden_effects_yaml(self, absolute: bool = False) -> list:
        """``sim.hidden_effects`` as campaign.yaml holds it (``absolute``: user files made absolute)."""
        stated = dict(self.sim.hidden_params)
        out = []
        from campaign.effects.base import effect_yaml

        for (resolved, params), spec in zip(self.hidden_effects(), self.sim.hidden_effects):
            entry = effect_yaml(resolved if absolute else spec)
            if params is not None:
                entry = {**(entry if isinstance(entry, dict) else {"effect": entry}), "params": list(params)}
            out.append(entry)
        return out

    def as_yaml_dict(self, *, absolute: bool = False) -> dict:
        """The keys as campaign.yaml holds them (``absolute``: paths made absolute, for a copy
        of the file elsewhere)."""
        sim = asdict(self.sim)
        faults = dict(sim.pop("faults"))
        late = sim.pop("late_delay_s")
        if faults.get("late") or late != 1.0:
            faults["late_delay_s"] = late
        sim["faults"] = faults
        sim["hidden_effects"] = self.hidden_effects_yaml(absolute)
        sim.pop("hidden_params")
        plan = asdict(self.plan)
        plan["grid_cells"] = "auto" if plan["grid_cells"] is None else list(plan["grid_cells"])
        out = {"robot": self.robot_spec if absolute else self.robot,
               "scene": str(self.scene_path) if absolute else self.scene}
        if self.tool_frame is not None:
            out["tool_frame"] = self.tool_frame
        if self.base_frame is not None:
            out["base_frame"] = self.base_frame
        from campaign.effects.base import effect_yaml, resolve_effect_spec

        effects = [effect_yaml(resolve_effect_spec(e, self.dir) if absolute else e) for e in self.effects]
        out.update({"effects": effects, "plan": plan, "run": asdict(self.run), "sim": sim})
        if self.tracker.noise_m is not None:
            out["tracker"] = asdict(self.tracker)
        return out


def parse_config(doc: dict, path) -> CampaignConfig:
    """Validate a campaign.yaml mapping ``doc`` read from ``path`` (named in every error)."""
    path = Path(path)
    extra = sorted(set(doc) - TOP_KEYS)
    if extra:
        raise ConfigError(f"{path}: unknown key '{extra[0]}' (allowed: {', '.join(sorted(TOP_KEYS))})")
    top = _Where(path, "")
    kw = {"path": path.resolve()}
    for key in ("robot", "scene"):
        if doc.get(key) is not None:
            kw[key] = check_str(doc[key], top(key))
    for key in ("tool_frame", "base_frame"):
        kw[key] = check_str(doc.get(key), top(key), optional=True)
    for name in SECTION_KEYS:
        section = doc.get(name)
        if section is None:
            section = {}
        if not isinstance(section, dict):
            raise ConfigError(f"{path}: {name}: expected a mapping, got {section!r}")
        unknown = sorted(set(section) - SECTION_KEYS[name])
        if unknown:
            raise ConfigError(f"{path}: unknown key '{name}.{unknown[0]}' "
                              f"(allowed: {', '.join(sorted(SECTION_KEYS[name]))})")
        if name in SECTIONS:
            kw[name] = SECTIONS[name].parse(section, _Where(path, name))
    effects = one_spec_per_effect(check_names(doc.get("effects"), top("effects")), top("effects"))
    if not effects and isinstance(doc.get("calibrate"), dict):
        effects = one_spec_per_effect(check_names(doc["calibrate"].get("effects"), top("calibrate.effects")),
                                      top("calibrate.effects"))
    kw["effects"] = effects
    return CampaignConfig(**kw)


def load_config(path=None) -> CampaignConfig:
    """The validated configuration of ``path`` (None: the embedded default), defaults filled in."""
    path = Path(path) if path is not None else DEFAULT_CONFIG
    if path.is_dir():
        path = path / "campaign.yaml"
    return parse_config(read_yaml_mapping(path), path)


def write_config(cfg: CampaignConfig, path, *, header: str = "") -> Path:
    """Write ``cfg`` as campaign.yaml at ``path`` (paths made absolute), atomically."""
    text = (header + "\n" if header else "") + yaml.safe_dump(cfg.as_yaml_dict(absolute=True), sort_keys=False)
    return atomic_write(Path(path), text)


def write_run_config(cfg: CampaignConfig, run_dir) -> Path:
    """Copy the configuration into a run folder (paths made absolute), as RUN/campaign.yaml."""
    return write_config(cfg, Path(run_dir) / "campaign.yaml",
                        header="# the configuration this run was made with; edit `effects:` to add physical effects")
