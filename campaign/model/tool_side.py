"""What the robot carries beyond its tool frame (a hand, its fingers), read from the URDF's
collision geometry: where its meshes are, and how far it reaches along the tool frame's +z.

The default reflectors of a robot whose robot.yaml names none are mounted beyond it
(:meth:`campaign.model.robot.RobotModel.with_default_reflectors`), not inside the hand."""

from __future__ import annotations

from pathlib import Path

import numpy as np


def resolve_mesh_path(filename: str, urdf_path) -> Path:
    """The file a URDF's ``<mesh filename>`` names: ``package://``, ``file://``, absolute or
    relative to the URDF (yourdfpy's resolution: the package's name dropped, then the URDF's
    folder and its parents searched)."""
    import yourdfpy

    if filename.startswith("file://"):
        filename = filename[len("file://"):]
    return Path(yourdfpy.filename_handler_magic(filename, dir=str(Path(urdf_path).parent)))


def _corners(geometry, urdf_path) -> np.ndarray | None:
    """Points (m, 3) whose hull holds one collision geometry, in its own frame; None when it
    cannot be read (a missing mesh: the planner names it; here it is passed by)."""
    if geometry.box is not None:
        half = 0.5 * np.asarray(geometry.box.size, dtype=float)
        return np.array([[sx, sy, sz] for sx in (-1, 1) for sy in (-1, 1) for sz in (-1, 1)]) * half
    if geometry.cylinder is not None:
        r, h = float(geometry.cylinder.radius), 0.5 * float(geometry.cylinder.length)
        return np.array([[sx * r, sy * r, sz * h] for sx in (-1, 1) for sy in (-1, 1) for sz in (-1, 1)])
    if geometry.sphere is not None:
        r = float(geometry.sphere.radius)
        return np.array([[sx * r, sy * r, sz * r] for sx in (-1, 1) for sy in (-1, 1) for sz in (-1, 1)])
    if geometry.mesh is not None:
        try:
            import trimesh

            mesh = trimesh.load(str(resolve_mesh_path(geometry.mesh.filename, urdf_path)), force="mesh")
            scale = geometry.mesh.scale if geometry.mesh.scale is not None else 1.0
            return np.asarray(mesh.vertices, dtype=float) * np.asarray(scale, dtype=float)
        except Exception:  # noqa: BLE001  (a mesh trimesh cannot read: the planner says so in one line)
            return None
    return None


def tool_side_reach_m(robot) -> float:
    """How far (m) along the tool frame's +z the collision geometry the tool frame carries reaches
    (the tool frame's own link and what hangs from it: the Panda's hand and fingers); 0 without
    any (a bare flange such as the UR's tool0)."""
    tool = robot.n_joints + 1
    reach = 0.0
    for link in robot.urdf.robot.links:
        where = robot.link_frames.get(link.name)
        if where is None or where[0] != tool:
            continue
        for col in link.collisions:
            pts = _corners(col.geometry, robot.urdf_path)
            if pts is None or len(pts) == 0:
                continue
            T = where[1] @ (np.eye(4) if col.origin is None else np.asarray(col.origin, dtype=float))
            reach = max(reach, float(np.max(pts @ T[:3, :3].T[:, 2] + T[2, 3])))
    return reach
