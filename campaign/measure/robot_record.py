"""The robot a measurement log was measured with, recorded in the log itself.

When the first measurement or import is stored, the log's meta table gets ``robot_record``::

    {"name", "spec", "urdf_sha256", "tool_frame", "base_frame", "n_joints",
     "controller": null | {"matrix": [[...]], "offset": [...]}}

``spec`` is what the robot was loaded from (a name under robot_models/ or an absolute path);
``urdf_sha256`` the SHA-256 of the URDF file's bytes (the nominal model the data belong to);
``controller`` robot.yaml's joint convention q_model = A q_controller + b. A command whose
configuration names a robot that differs in the URDF, a frame, the joint count or the
controller convention is refused in one line (:func:`check_same_robot`); a run whose
campaign.yaml names no robot uses the recorded one (campaign.run.RunFolder.config). Logs
written before the record keep working (nothing to compare).
"""

from __future__ import annotations

import hashlib
from pathlib import Path

import numpy as np

from campaign.errors import ConfigError

META_KEY = "robot_record"
#: the fields that make two robots the same for the data (the name is said, not compared)
COMPARED = ("urdf_sha256", "tool_frame", "base_frame", "n_joints", "controller")


def file_sha256(path) -> str:
    h = hashlib.sha256()
    with open(path, "rb") as fh:
        for block in iter(lambda: fh.read(1 << 20), b""):
            h.update(block)
    return h.hexdigest()


def robot_record(robot) -> dict:
    """The record of a :class:`campaign.model.robot.RobotModel` (JSON-ready)."""
    controller = None
    if robot.controller_matrix is not None:
        controller = {"matrix": np.asarray(robot.controller_matrix, dtype=float).tolist(),
                      "offset": np.asarray(robot.controller_offset, dtype=float).tolist()}
    spec = str(robot.spec)
    if Path(spec).exists():
        spec = str(Path(spec).resolve())
    return {"name": robot.name, "spec": spec, "urdf_sha256": file_sha256(robot.urdf_path),
            "tool_frame": robot.tool_frame, "base_frame": robot.base_frame, "n_joints": int(robot.n_joints),
            "controller": controller}


def differences(recorded: dict, robot) -> list:
    """The compared fields in which ``robot`` is not the recorded robot: [(field, recorded, now)]."""
    now = robot_record(robot)
    out = []
    for key in COMPARED:
        a, b = recorded.get(key), now.get(key)
        if key == "controller" and a is not None and b is not None:
            same = all(np.allclose(np.asarray(a[k], dtype=float), np.asarray(b[k], dtype=float), rtol=0, atol=1e-12)
                       for k in ("matrix", "offset")) if np.shape(a["matrix"]) == np.shape(b["matrix"]) else False
        else:
            same = a == b
        if key in recorded and not same:
            out.append((key, a, b))
    return out


def check_same_robot(recorded: dict | None, robot, log_path, config_path) -> None:
    """ConfigError (one line) when ``robot`` (from ``config_path``) is not the robot the log at
    ``log_path`` records; nothing to check for a log without a record."""
    if not recorded:
        return
    diff = differences(recorded, robot)
    if not diff:
        return
    words = {"urdf_sha256": "URDF content", "tool_frame": "tool frame", "base_frame": "base frame",
             "n_joints": "joint count", "controller": "controller joint convention"}
    what = "; ".join(f"{words[k]} {_short(k, a)} measured, {_short(k, b)} configured" for k, a, b in diff)
    raise ConfigError(f"{config_path}: robot {robot.name!r} is not the robot {recorded.get('name')!r} "
                      f"({recorded.get('spec')}) that {log_path} was measured with ({what}); name that robot in "
                      "campaign.yaml, or measure into a new run folder")


def _short(key, value) -> str:
    if value is None:
        return "none"
    if key == "urdf_sha256":
        return f"sha256 {str(value)[:12]}…"
    if key == "controller":
        return "A q + b"
    return repr(value)
