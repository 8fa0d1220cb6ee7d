"""campaign.yaml: the configuration of a campaign (robot, scene, plan, run, sim, effects).

Unknown keys are errors (one line naming the file and the key); paths are relative to the
file that names them. Without a file, the embedded default ``campaign.yaml`` is used.
"""

from __future__ import annotations

import copy
from pathlib import Path

import yaml

from campaign.errors import ConfigError
from campaign.paths import DEFAULT_CONFIG

SECTIONS = {
    "plan": {"grid_cells": [17, 10, 10, 14, 6, 10], "clearance_m": 0.035, "motion_clearance_m": 0.01,
             "motion_sample_deg": 1.0, "settle_time_s": 2.0, "tracker_time_per_reflector_s": 5.0},
    "run": {"timeout_s": 5.0, "move_timeout_s": 120.0, "retries": 3, "reconnect_attempts": 5,
            "backoff_s": 0.2, "drift_check_every": 500, "drift_threshold_mm": 0.05},
    "sim": {"seed": 0, "time_factor": 0.0, "noise_m": 10e-6, "hidden_effects": ["ground_compliance"],
            "faults": {"drop": 0.0, "late": 0.0, "garble": 0.0, "beam_lost": 0.0, "robot_fault": 0.0}},
    "calibrate": {"effects": None},
}
TOP_KEYS = {"robot", "scene", "effects", *SECTIONS}


def read_yaml_mapping(path, error=ConfigError) -> dict:
    """A YAML file whose top level is a mapping (an empty file is {}); ``error`` (an exception
    class) names the file on any failure."""
    path = Path(path)
    try:
        doc = yaml.safe_load(path.read_text())
    except OSError as exc:
        raise error(f"{path}: cannot read ({exc.strerror})") from None
    except yaml.YAMLError as exc:
        raise error(f"{path}: not valid YAML ({str(exc).splitlines()[0]})") from None
    if doc is None:
        return {}
    if not isinstance(doc, dict):
        raise error(f"{path}: expected a mapping at the top level")
    return doc


def load_config(path=None) -> dict:
    """The configuration with defaults filled in; ``_path`` and ``_dir`` record where it came from."""
    path = Path(path) if path is not None else DEFAULT_CONFIG
    doc = read_yaml_mapping(path)
    extra = sorted(set(doc) - TOP_KEYS)
    if extra:
        raise ConfigError(f"{path}: unknown key '{extra[0]}' (allowed: {', '.join(sorted(TOP_KEYS))})")
    cfg = {"robot": doc.get("robot", "comau_racer5_080"), "scene": doc.get("scene", "scene/default_cell.yaml"),
           "effects": list(doc.get("effects") or [])}
    for name, defaults in SECTIONS.items():
        section = doc.get(name) or {}
        if not isinstance(section, dict):
            raise ConfigError(f"{path}: {name}: expected a mapping")
        unknown = sorted(set(section) - set(defaults))
        if unknown:
            raise ConfigError(f"{path}: unknown key '{name}.{unknown[0]}' (allowed: {', '.join(sorted(defaults))})")
        merged = copy.deepcopy(defaults)
        merged.update(section)
        cfg[name] = merged
    cfg["_path"] = str(path.resolve())
    cfg["_dir"] = str(path.resolve().parent)
    return cfg


def resolve(cfg, value) -> Path:
    """A path from the config, relative to the config file's folder."""
    p = Path(value)
    return p if p.is_absolute() else Path(cfg["_dir"]) / p


def write_run_config(cfg, run_dir) -> Path:
    """Copy the configuration into a run folder (paths made absolute), as RUN/campaign.yaml."""
    out = {k: v for k, v in cfg.items() if not k.startswith("_")}
    out["scene"] = str(resolve(cfg, cfg["scene"]))
    robot = Path(str(cfg["robot"]))
    if not robot.is_absolute() and (Path(cfg["_dir"]) / robot).is_dir():
        out["robot"] = str(Path(cfg["_dir"]) / robot)
    path = Path(run_dir) / "campaign.yaml"
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_text("# the configuration this run was made with; edit `effects:` to add physical effects\n"
                    + yaml.safe_dump(out, sort_keys=False))
    return path
