"""The MuJoCo model (MJCF) of a robot in its cell, built from the run's URDF and scene.

One body per chain frame of :mod:`campaign.model.robot` (the world is the robot's base frame
F_I): ``frame0`` (welded to the world, at ``T_I0``), ``frame1`` .. ``frameN`` (each at its
transform from the frame before, with a hinge, or a slide, along its z), and ``tool`` (welded
to ``frameN`` at ``T_NE``) carrying one site per reflector. The transforms are whatever the
caller passes (the twin: the truth, the nominal ones plus hidden manufacturing errors), so the
joint origins of the model are the truth's and the URDF's geometry rides on them unchanged.

Every URDF link goes to the body of the chain frame it moves with
(:attr:`RobotModel.link_frames`): its ``<collision>`` geometry (boxes, cylinders, spheres,
capsules, and meshes read by trimesh in any format it reads, handed to MuJoCo as vertices and
faces; MuJoCo collides with their convex hulls) and its ``<inertial>``, the inertials of one
body summed about their common centre of mass (what Pinocchio does with links joined by fixed
joints). The scene's obstacles (boxes and cylinders in F_I) are geoms of the world.

Each moving joint is driven by a position servo of finite stiffness ``kp`` (N·m/rad or N/m)
and damping ``kv`` on the velocity error (:func:`servo_command`): MuJoCo's ``general``
actuator with force ``kp·u − kp·q − kv·q̇`` and command ``u = q_cmd + (kv/kp)·q̇_cmd``, i.e.
``kp (q_cmd − q) + kv (q̇_cmd − q̇)``. At rest it holds the link where the spring balances
the gravity torque: the link side sags by ``τ_g / kp`` from the commanded (motor side) angle.
``armature`` (kg·m², the rotors' reflected inertia) keeps the servo's natural frequency within
what the time step integrates.

Contacts: robot geoms collide with the scene's and with each other except between adjacent
chain bodies (frames k and k+1, k < N; the tool, welded to frame N, never meets it, but meets
frame N - 1 as the planner checks it) and pairs the caller excludes (``exclude``: pairs of
chain frames always in contact, found by sampling). MuJoCo's own parent filter is switched
off so that exactly these rules apply; the world's geoms and frame 0 (welded to it) never meet.
"""

from __future__ import annotations

import xml.etree.ElementTree as ET

import numpy as np

#: inertia (kg·m²) and mass (kg) given to a moving body with none in the URDF: MuJoCo needs a
#: positive mass matrix, and the armature adds inertia only along the joint axis
MIN_MASS_KG = 1e-6
MIN_INERTIA_KGM2 = 1e-9
#: smallest side (m) of the cubes a collision mesh is cut into (:func:`mesh_pieces`)
MESH_PIECE_MIN_M = 0.03


def body_name(k: int, n_joints: int) -> str:
    """MuJoCo body name of chain frame k (0 .. N, N + 1: the tool)."""
    return "tool" if k == n_joints + 1 else f"frame{k}"


def _f(values) -> str:
    return " ".join(repr(float(v)) for v in np.ravel(values))


def _quat(R) -> np.ndarray:
    import mujoco

    q = np.empty(4)
    mujoco.mju_mat2Quat(q, np.ascontiguousarray(R, dtype=float).reshape(9))
    return q


def _place(el, T):
    el.set("pos", _f(T[:3, 3]))
    el.set("quat", _f(_quat(T[:3, :3])))


def chain_inertials(robot) -> list:
    """The URDF's inertials summed per chain frame: a list of N + 2 entries (mass kg, centre of
    mass (3,) m, inertia (3, 3) kg·m² about it), each in its nominal chain frame k (0 .. N + 1)."""
    sums = [[0.0, np.zeros(3), []] for _ in range(robot.n_joints + 2)]
    parts = [[] for _ in range(robot.n_joints + 2)]
    frames = robot.link_frames
    for link in robot.urdf.robot.links:
        inertial = link.inertial
        if link.name not in frames or inertial is None or not inertial.mass:
            continue
        k, T_kl = frames[link.name]
        origin = np.array(inertial.origin, dtype=float) if inertial.origin is not None else np.eye(4)
        T = np.asarray(T_kl) @ origin
        I_link = np.array(inertial.inertia, dtype=float) if inertial.inertia is not None else np.zeros((3, 3))
        parts[k].append((float(inertial.mass), T[:3, 3], T[:3, :3] @ I_link @ T[:3, :3].T))
    out = []
    for k in range(len(sums)):
        m = sum(p[0] for p in parts[k])
        if m <= 0:
            out.append((0.0, np.zeros(3), np.zeros((3, 3))))
            continue
        c = sum(p[0] * p[1] for p in parts[k]) / m
        inertia = np.zeros((3, 3))
        for mi, ci, Ii in parts[k]:
            d = ci - c
            inertia += Ii + mi * (d @ d * np.eye(3) - np.outer(d, d))  # parallel axis theorem
        out.append((m, c, inertia))
    return out


def _inertial(body, mass, com, inertia, moving):
    if mass <= 0 and not moving:
        return
    if mass <= 0:
        mass, com, inertia = MIN_MASS_KG, np.zeros(3), MIN_INERTIA_KGM2 * np.eye(3)
    el = ET.SubElement(body, "inertial")
    el.set("pos", _f(com))
    el.set("mass", repr(float(mass)))
    inertia = 0.5 * (inertia + inertia.T)
    if np.all(np.linalg.eigvalsh(inertia) < MIN_INERTIA_KGM2):
        inertia = MIN_INERTIA_KGM2 * np.eye(3)
    el.set("fullinertia", _f([inertia[0, 0], inertia[1, 1], inertia[2, 2], inertia[0, 1], inertia[0, 2],
                              inertia[1, 2]]))


def mesh_pieces(vertices, faces, size) -> list:
    """A mesh cut into pieces whose convex hulls hug it: its triangles grouped by the cube of
    side ``max(min(size), MESH_PIECE_MIN_M)`` of its bounding box (``size``, centred on the
    frame's origin) that holds their centroid; a piece too flat or small for a hull joins the
    next. Each piece (vertices (V, 3), faces (F, 3)) holds whole triangles, so the hulls cover
    the surface. MuJoCo collides a mesh as its convex hull: a long or bent link's single hull
    would touch what the link itself does not."""
    v, f = np.asarray(vertices, dtype=float), np.asarray(faces, dtype=np.int64)
    ext = np.maximum(np.asarray(size, dtype=float), 1e-9)
    side = max(float(ext.min()), MESH_PIECE_MIN_M)
    dims = np.maximum(1, np.ceil(ext / side - 1e-9)).astype(int)
    cell = np.clip(np.floor((v[f].mean(axis=1) + 0.5 * ext) / side).astype(int), 0, dims - 1)
    key = np.ravel_multi_index(cell.T, dims)
    order = np.argsort(key, kind="stable")
    groups = np.split(order, np.flatnonzero(np.diff(key[order])) + 1)
    pieces, carry = [], np.zeros(0, dtype=np.int64)
    for group in groups:
        tri = np.concatenate([carry, group])
        used, inverse = np.unique(f[tri], return_inverse=True)
        pv = v[used]
        if len(used) < 4 or np.linalg.matrix_rank(pv - pv.mean(axis=0), tol=1e-6) < 3:
            carry = tri
            continue
        pieces.append((pv, inverse.reshape(-1, 3)))
        carry = np.zeros(0, dtype=np.int64)
    if len(carry):
        if not pieces:
            return [(v, f)]
        pv, pf = pieces.pop()
        used, inverse = np.unique(f[carry], return_inverse=True)
        pieces.append((np.vstack([pv, v[used]]), np.vstack([pf, inverse.reshape(-1, 3) + len(pv)])))
    return pieces


def _geom(parent, name, kind, size, T, assets, mesh=None):
    """Geoms of one collision shape at pose T (4, 4) of ``parent`` (a mesh: one per piece,
    named ``name.k``, their vertices and faces added to ``assets``)."""
    if kind == "mesh":
        pieces = mesh_pieces(mesh.vertices, mesh.faces, size)
        for k, (v, f) in enumerate(pieces):
            a = ET.Element("mesh", name=f"mesh{len(assets)}")
            a.set("vertex", _f(v))
            a.set("face", " ".join(str(int(i)) for i in np.ravel(f)))
            # the convex hull's volume (MuJoCo collides with the hull): open or flat meshes compile too
            a.set("inertia", "convex")
            assets.append(a)
            _contact_geom(parent, name if len(pieces) == 1 else f"{name}.{k}", T, type="mesh", mesh=a.get("name"))
        return
    if kind == "box":
        extents = 0.5 * np.asarray(size, dtype=float)
    elif kind in ("cylinder", "capsule"):
        extents = [size[0], 0.5 * size[1]]
    elif kind == "sphere":
        extents = [size[0]]
    else:
        raise ValueError(f"geometry kind {kind!r}")
    _contact_geom(parent, name, T, type=kind, size=_f(extents))


def _contact_geom(parent, name, T, **attrs):
    g = ET.SubElement(parent, "geom", name=name, **attrs)
    _place(g, T)
    g.set("contype", "1")
    g.set("conaffinity", "1")


def build_mjcf(robot, chain_T, obstacles, *, kp, kv, armature, timestep_s, exclude=(), name=None) -> str:
    """The MJCF text of ``robot`` in a cell.

    robot: RobotModel (with the reflectors the run measures). chain_T: (N + 2, 4, 4) the chain's
    transforms at q = 0 (``T_I0``, ``T_01`` .. ``T_(N-1)N``, ``T_NE``; zero offsets folded in),
    m. obstacles: the scene's Obstacles in F_I (``Scene.placed(robot).obstacles``). kp, kv,
    armature: (N,) servo stiffness (N·m/rad | N/m), damping (N·m·s/rad | N·s/m), reflected rotor
    inertia (kg·m² | kg). timestep_s: MuJoCo's step (s). exclude: extra pairs (i, j) of chain
    frames (0 .. N + 1) whose contacts are ignored. Gravity: ``robot.gravity_in_I``.
    """
    from campaign.plan.geometry import robot_primitives

    N = robot.n_joints
    chain_T = np.asarray(chain_T, dtype=float)
    if chain_T.shape != (N + 2, 4, 4):
        raise ValueError(f"chain_T must be ({N + 2}, 4, 4), got {chain_T.shape}")
    root = ET.Element("mujoco", model=name or f"campaign twin of {robot.name}")
    ET.SubElement(root, "compiler", angle="radian", inertiafromgeom="false", autolimits="true")
    opt = ET.SubElement(root, "option", timestep=repr(float(timestep_s)), integrator="implicitfast",
                        gravity=_f(robot.gravity_in_I))
    ET.SubElement(opt, "flag", filterparent="disable")
    assets = []
    world = ET.SubElement(root, "worldbody")
    for obs in obstacles:
        _geom(world, f"scene:{obs.name}", obs.kind, obs.size, np.asarray(obs.T_I), assets)
    inertials = chain_inertials(robot)
    bodies = []
    parent = world
    for k in range(N + 2):
        b = ET.SubElement(parent, "body", name=body_name(k, N))
        _place(b, chain_T[k])
        if 1 <= k <= N:
            j = ET.SubElement(b, "joint", name=robot.joint_names[k - 1],
                              type="slide" if robot.joint_types[k - 1] == "prismatic" else "hinge")
            j.set("axis", "0 0 1")
            j.set("armature", repr(float(armature[k - 1])))
        _inertial(b, *inertials[k], moving=1 <= k)
        bodies.append(b)
        parent = b
    for i, p in enumerate(robot_primitives(robot)):
        _geom(bodies[p.frame], f"{p.link}:{i}", p.kind, p.size, np.asarray(p.T), assets, p.mesh)
    tool = bodies[N + 1]
    ET.SubElement(tool, "site", name="E", pos="0 0 0")
    for r in robot.reflectors:
        ET.SubElement(tool, "site", name=f"reflector:{r.name}", pos=_f(r.position_in_E), size="0.0191")
    if assets:
        a = ET.Element("asset")
        a.extend(assets)
        root.insert(2, a)
    contact = ET.SubElement(root, "contact")
    pairs = {(k, k + 1) for k in range(N)} | {tuple(sorted(p)) for p in exclude}
    for i, j in sorted(pairs):
        if i != j:
            ET.SubElement(contact, "exclude", body1=body_name(i, N), body2=body_name(j, N))
    act = ET.SubElement(root, "actuator")
    for j in range(N):
        ET.SubElement(act, "general", name=f"servo:{robot.joint_names[j]}", joint=robot.joint_names[j],
                      gaintype="fixed", gainprm=repr(float(kp[j])), biastype="affine",
                      biasprm=_f([0.0, -kp[j], -kv[j]]))
    return ET.tostring(root, encoding="unicode")


def servo_command(q_cmd, qd_cmd, kp, kv) -> np.ndarray:
    """Actuator controls (N,) that make the servos apply ``kp (q_cmd − q) + kv (q̇_cmd − q̇)``."""
    return np.asarray(q_cmd, dtype=float) + (np.asarray(kv) / np.asarray(kp)) * np.asarray(qd_cmd, dtype=float)
