"""Where the embedded defaults live: package data, found from any working directory."""

from __future__ import annotations

from pathlib import Path

#: Folder of the package data shipped with `campaign` (default robot, scene and campaign.yaml).
DATA_DIR = Path(__file__).resolve().parent / "data"
#: Robot folders addressable by name (``--robot comau_racer5_080``).
ROBOT_MODELS = DATA_DIR / "robot_models"
#: The embedded default configuration.
DEFAULT_CONFIG = DATA_DIR / "campaign.yaml"
#: The embedded default cell.
DEFAULT_SCENE = DATA_DIR / "scene" / "default_cell.yaml"
#: The embedded default robot's name.
DEFAULT_ROBOT = "comau_racer5_080"
