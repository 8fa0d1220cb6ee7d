"""Robots by name: `--robot ur10`, `--robot panda`, ... and `campaign robots`.

The embedded robots (``campaign/data/robot_models/``) and, when PyPI's ``example-robot-data`` is
installed, the serial arms it ships, each with its usual tool frame (and base frame where the
URDF's root is not the arm's). A name stands for its URDF path and frames; an explicit
``--tool-frame`` / ``--base-frame`` still wins.
"""

from __future__ import annotations

from dataclasses import dataclass
from importlib import metadata
from pathlib import Path

from campaign.paths import ROBOT_MODELS


@dataclass(frozen=True)
class KnownRobot:
    """A robot name: its URDF (relative to example-robot-data's ``robots`` folder, or an embedded
    model's folder), its usual tool and base frames, and a line of description."""

    name: str
    path: str
    tool_frame: str | None
    base_frame: str | None
    description: str
    source: str = "example-robot-data"


#: example-robot-data's serial arms, by the names users know them by
EXAMPLE_ROBOTS = (
    KnownRobot("ur3", "ur_description/urdf/ur3_robot.urdf", "tool0", None, "Universal Robots UR3, 6R"),
    KnownRobot("ur5", "ur_description/urdf/ur5_robot.urdf", "tool0", None, "Universal Robots UR5, 6R"),
    KnownRobot("ur10", "ur_description/urdf/ur10_robot.urdf", "tool0", None, "Universal Robots UR10, 6R"),
    KnownRobot("panda", "panda_description/urdf/panda.urdf", "panda_hand", None, "Franka Emika Panda, 7R"),
    KnownRobot("xarm7", "xarm_description/urdf/xarm7.urdf", "link_eef", None, "UFACTORY xArm7, 7R"),
    KnownRobot("z1", "z1_description/urdf/z1.urdf", "gripperStator", None, "Unitree Z1, 6R"),
    KnownRobot("tiago", "tiago_description/robots/tiago.urdf", "arm_tool_link", "base_footprint",
               "PAL TIAGo torso and arm, P + 7R"),
)


EMBEDDED_DESCRIPTIONS = {"comau_racer5_080": "COMAU Racer5-0.80, 6R: the paper's robot, the default"}


def example_robots_dir() -> Path | None:
    """example-robot-data's ``robots`` folder, or None when the package is not installed."""
    try:
        dist = metadata.distribution("example-robot-data")
    except metadata.PackageNotFoundError:
        return None
    path = Path(dist.locate_file("cmeel.prefix/share")) / "example-robot-data" / "robots"
    return path if path.is_dir() else None


def lookup(name) -> KnownRobot | None:
    """The example-robot-data robot called ``name`` (case-insensitive), or None."""
    key = str(name).strip().lower()
    return next((r for r in EXAMPLE_ROBOTS if r.name == key), None)


def urdf_of(robot: KnownRobot) -> Path | None:
    """The installed URDF of an example-robot-data robot, or None when the package is missing."""
    root = example_robots_dir()
    return None if root is None else root / robot.path


def known_robots() -> list:
    """[(KnownRobot, installed path or None)]: the embedded models, then example-robot-data's."""
    out = []
    if ROBOT_MODELS.is_dir():
        for d in sorted(p for p in ROBOT_MODELS.iterdir() if (p / "robot.yaml").is_file()):
            text = EMBEDDED_DESCRIPTIONS.get(d.name, "embedded (robot.yaml beside its URDF)")
            out.append((KnownRobot(d.name, str(d), None, None, text, "embedded"), d / "robot.yaml"))
    for r in EXAMPLE_ROBOTS:
        path = urdf_of(r)
        out.append((r, path if path is not None and path.is_file() else None))
    return out
