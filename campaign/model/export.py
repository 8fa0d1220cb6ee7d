"""The calibrated geometric model as a URDF (`campaign export RUN --urdf OUT.urdf`).

The robot's own URDF is read with yourdfpy, the chain's joint origins are replaced by the
calibrated transforms and the file is written by yourdfpy again, so every link, inertia,
geometry and joint outside the chain is kept. For moving joint j with model-frame transform
``T̂_j(0)`` (the identified ``[R̄ R(a, b, c), t̂]`` with the zero offset folded in: ``Rz(pq_j)``
for a revolute joint, a translation ``pd_j`` along z for a prismatic one):

    origin_j' = F_j⁻¹ · S_{j-1} · T̂_j(0) · S_jᵀ

where ``F_j`` is the product of the fixed joints between joint j-1 and joint j (unchanged) and
``S_j`` the model frame's axis alignment (campaign.model.robot). The base transform's error
``D_0 = T̄_0⁻¹ T̂_0`` is folded into joint 1's origin; the tool's ``D_E = T̄_E⁻¹ T̂_E`` into the
last fixed joint before the tool frame (a tool mounting fitted by calibrate, ``RobotModel.tool_mounting``,
in front of it: the tool link becomes the measured frame), or, when the tool frame is the last moving joint's
child link itself, into a new fixed joint ``<tool>_calibration`` above the tool link (its
parent becomes a new empty link ``<tool>_uncalibrated``). The joint axes stay as written.
One-reflector data measured at a point off the tool frame (``RobotModel.tool_point``, p): the
tool link is the calibrated model's frame at the point moved back by p, and a new link
``<tool>_measured_point`` hangs from it at p: there the URDF gives what `campaign predict` gives.
Relative mesh file names are made absolute so the written file finds them from anywhere.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from campaign.errors import ConfigError
from campaign.fileio import atomic_write, check_writable_file
from campaign.model.robot import RobotModel
from campaign.model.rotations import cardan_xyz


def _T(R, t) -> np.ndarray:
    T = np.eye(4)
    T[:3, :3] = R
    T[:3, 3] = t
    return T


def calibrated_transforms(robot: RobotModel, p_e) -> list:
    """The N + 2 calibrated transforms at q = 0, zero offsets folded in: list of (4, 4)."""
    p = np.asarray(p_e, dtype=float)
    if p.shape != (robot.n_params,):
        raise ConfigError(f"p_e must have {robot.n_params} values for {robot.name}, got {p.shape}")
    out = []
    N = robot.n_joints
    for k in range(N + 2):
        a, b, c = p[6 * k + 3 : 6 * k + 6]
        Rn, tn = robot.R_nominal[k], robot.t_nominal[k]
        if 1 <= k <= N and robot.joint_types[k - 1] == "prismatic":
            R = Rn @ cardan_xyz(a, b, p[6 * k + 2])
            t = tn + Rn @ np.array([p[6 * k], p[6 * k + 1], 0.0]) + R[:, 2] * c
        else:
            R = Rn @ cardan_xyz(a, b, c)
            t = tn + p[6 * k : 6 * k + 3]
        out.append(_T(R, t))
    return out


def measured_point_link(robot: RobotModel) -> str:
    """The exported URDF's link at the measured point of one-reflector data (below the tool frame)."""
    return f"{robot.tool_frame}_measured_point"


def write_calibrated_urdf(robot: RobotModel, p_e, out_path, notes=()) -> Path:
    """Write the URDF of ``robot`` with the calibrated chain ``p_e`` (6N + 12,) to ``out_path``;
    ``notes`` (sentences: the joint convention, the gravity, what is left out) head the file as
    an XML comment."""
    import yourdfpy

    out_path = Path(out_path)
    check_writable_file(out_path, "--urdf", "calibrated.urdf")  # before any work
    u = yourdfpy.URDF.load(str(robot.urdf_path), load_meshes=False, build_scene_graph=False,
                           build_collision_scene_graph=False)
    joints = {j.name: j for j in u.robot.joints}
    N = robot.n_joints
    That = calibrated_transforms(robot, p_e)
    S = [np.eye(3)] + [np.asarray(s) for s in robot.axis_alignment]  # S_0 = I, S_1..S_N

    def fixed_T(name):
        j = joints[name]
        T = np.array(j.origin, dtype=float) if j.origin is not None else np.eye(4)
        if j.type != "fixed":  # a joint of the chain locked in robot.yaml
            from campaign.model.robot import _motion

            T = T @ _motion(j, robot.locked_joints.get(j.name, 0.0))
        return T

    D0 = np.linalg.solve(_T(robot.R_nominal[0], robot.t_nominal[0]), That[0])
    for k in range(1, N + 1):
        names = robot.transform_joints[k]
        F = np.eye(4)
        for nm in names[:-1]:
            F = F @ fixed_T(nm)
        origin = np.linalg.solve(F, _T(S[k - 1], np.zeros(3)) @ That[k] @ _T(S[k].T, np.zeros(3)))
        if k == 1:
            origin = D0 @ origin
        joints[names[-1]].origin = origin
    DE = np.linalg.solve(_T(robot.R_nominal[N + 1], robot.t_nominal[N + 1]), That[N + 1])
    if robot.tool_mounting is not None:  # the nominal tool transform is the URDF's times the mounting
        DE = robot.tool_mounting @ DE
    point = None if robot.tool_point is None else _T(np.eye(3), robot.tool_point)
    if point is not None:  # the nominal tool transform is the URDF's moved to the point: the tool link
        DE = point @ DE @ np.linalg.inv(point)  # the point's frame moved back, the point a frame below it
    tool_names = robot.transform_joints[N + 1]
    if tool_names:
        last = joints[tool_names[-1]]
        last.origin = (np.array(last.origin, dtype=float) if last.origin is not None else np.eye(4)) @ DE
    else:
        tool = robot.tool_frame
        jN = joints[robot.joint_names[-1]]
        hook = f"{tool}_uncalibrated"
        if hook in {lk.name for lk in u.robot.links}:
            raise ConfigError(f"{robot.urdf_path}: link '{hook}' exists already; cannot add the tool's calibration")
        u.robot.links.append(yourdfpy.Link(name=hook))
        jN.child = hook
        u.robot.joints.append(yourdfpy.Joint(name=f"{tool}_calibration", type="fixed", parent=hook, child=tool,
                                             origin=DE))
    if point is not None:
        name = measured_point_link(robot)
        if name in {lk.name for lk in u.robot.links}:
            raise ConfigError(f"{robot.urdf_path}: link '{name}' exists already; cannot add the measured point")
        u.robot.links.append(yourdfpy.Link(name=name))
        u.robot.joints.append(yourdfpy.Joint(name=f"{name}_joint", type="fixed", parent=robot.tool_frame,
                                             child=name, origin=point))
    base_dir = Path(robot.urdf_path).parent
    for link in u.robot.links:
        for item in list(link.visuals or []) + list(link.collisions or []):
            mesh = item.geometry.mesh if item.geometry is not None else None
            if mesh is not None and mesh.filename and "://" not in mesh.filename \
                    and not Path(mesh.filename).is_absolute():
                mesh.filename = str((base_dir / mesh.filename).resolve())
    from lxml import etree  # yourdfpy's XML library: the bytes its write_xml_file writes

    text = etree.tostring(u.write_xml(), xml_declaration=True, pretty_print=True).decode("ascii")
    return atomic_write(out_path, _with_comment(text, notes).encode("ascii", "xmlcharrefreplace"))  # ASCII declared


def _with_comment(text: str, notes) -> str:
    """``notes`` as one XML comment after the declaration of the XML ``text``."""
    if not notes:
        return text
    body = "\n".join(f"  {n}" for n in notes)
    head, sep, rest = text.partition("?>")
    inner = f"\n  The calibrated geometric model, as `campaign export` writes it.\n{body}\n"
    while "--" in inner:  # a comment may not hold "--" (XML 1.0, 2.5)
        inner = inner.replace("--", "- -")
    return head + sep + f"\n<!--{inner}-->" + rest if sep else f"<!--{inner}-->\n" + text
