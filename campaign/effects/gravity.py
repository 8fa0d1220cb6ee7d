"""Gravity loads from the URDF's inertias via Pinocchio, for effects (built-in and users').

The public interface (docs/effects.md, "Gravity loads"): :func:`gravity_torques`,
:func:`overturning_moment`, :func:`weight_and_com`, :func:`moving_mass`,
:func:`gravity_vector`, :func:`horizontal_axes`. Every vector is in the chain's base frame
F_I, gravity as the robot model states it (robot.yaml ``gravity_m_s2``, default −z of F_I).

The solver evaluates effect hooks many times on the same joint array (finite differences
in the effect parameters), so the loads are cached by a digest of the array's bytes, and per
joint vector for arrays that share poses (diagnose's folds).
"""

from __future__ import annotations

import hashlib
from collections import OrderedDict

import numpy as np

_CACHE: OrderedDict = OrderedDict()
#: arrays of loads kept: diagnose scores each candidate on every fold, and its fitting and
#: held-out poses are 2 × 5 joint arrays per load (torques, centre of mass) besides the full
#: set's; with 8 the folds evicted each other and every load effect computed them again
#: (about 0.4 MB each on 9,000 poses)
_CACHE_SIZE = 32


def _key(robot, q, what):
    q = np.ascontiguousarray(q, dtype=float)
    return (robot.name, str(robot.urdf_path), what, q.shape, hashlib.blake2b(q.tobytes(), digest_size=16).digest())


#: joint vectors whose loads are known, by (robot, load) and the vector's bytes, at most this many
#: a load: diagnose's folds are subsets of one set of poses, each computed once
_ROWS: dict = {}
_ROWS_SIZE = 200_000


def _cached(robot, q, what, compute):
    """``compute(q)`` for a joint array q (n, N): an array seen before from the cache, else the
    rows seen before from theirs and only the others computed (compute is per pose)."""
    key = _key(robot, q, what)
    if key in _CACHE:
        _CACHE.move_to_end(key)
        return _CACHE[key]
    q = np.ascontiguousarray(q, dtype=float)
    rows = _ROWS.setdefault(key[:3], {})
    names = [row.tobytes() for row in q]
    missing = [i for i, name in enumerate(names) if name not in rows]
    if len(rows) + len(missing) > _ROWS_SIZE:
        rows.clear()
        missing = list(range(len(q)))
    if missing:
        rows.update(zip((names[i] for i in missing), compute(q[missing])))
    value = np.array([rows[name] for name in names]) if len(q) else compute(q)
    value.setflags(write=False)
    _CACHE[key] = value
    if len(_CACHE) > _CACHE_SIZE:
        _CACHE.popitem(last=False)
    return value


def _pin_q(robot, q):
    """Pinocchio configurations (n, nq) of joint vectors (n, N) of any chain."""
    if hasattr(robot, "pinocchio_q"):
        return robot.pinocchio_q(q)
    return np.asarray(q, dtype=float).reshape(-1, 6)


def gravity_torques(robot, q) -> np.ndarray:
    """Joint torques τ (n, 6) N·m that hold the arm against gravity (Pinocchio, URDF inertias); the
    recursion's round-off is 0 (a joint whose axis lies along gravity carries exactly none)."""
    import pinocchio as pin

    from campaign.tolerances import GRAVITY_TORQUE_ROUND_OFF

    def compute(q):
        model = robot.pinocchio_model
        data = model.createData()
        qq = _pin_q(robot, q)
        tau = np.array([pin.computeGeneralizedGravity(model, data, qi) for qi in qq])
        scale = moving_mass(robot) * float(np.linalg.norm(model.gravity.linear)) * 1.0  # N·m: the weight at 1 m
        tau[np.abs(tau) <= GRAVITY_TORQUE_ROUND_OFF * scale] = 0.0
        return tau

    return _cached(robot, q, "tau", compute)


def weight_and_com(robot, q):
    """Moving mass (kg, :func:`moving_mass`) and its centre of mass in F_I, (n, 3) m."""
    import pinocchio as pin

    def compute(q):
        model = robot.pinocchio_model
        data = model.createData()
        com = []
        for qi in _pin_q(robot, q):
            pin.centerOfMass(model, data, qi)  # data.com[1]: joint 1's subtree, in joint 1's frame
            com.append(data.oMi[1].act(data.com[1]))  # in the URDF's root frame
        com = np.array(com)
        if robot.T_root_base is not None:  # the root frame -> F_I
            T = np.asarray(robot.T_root_base, dtype=float)
            com = (com - T[:3, 3]) @ T[:3, :3]
        return com

    com = _cached(robot, q, "com", compute)
    return moving_mass(robot), com


def moving_mass(robot) -> float:
    """Mass of the bodies that joint 1 carries (the chain's first moving joint; joints outside
    the chain are locked to their bodies), kg."""
    import pinocchio as pin

    model = robot.pinocchio_model
    data = model.createData()
    pin.centerOfMass(model, data, _pin_q(robot, np.zeros(robot.n_joints))[0])
    return float(data.mass[1])


def gravity_vector(robot) -> np.ndarray:
    """Gravity (3,) m/s² in the robot's root frame F_I: ``robot.gravity_in_root`` when the model
    states it, else ``robot.gravity_in_I``."""
    g = getattr(robot, "gravity_in_root", None)
    if g is None:
        g = robot.gravity_in_I
    return np.asarray(g, dtype=float)


def horizontal_axes(robot):
    """Two unit vectors of F_I perpendicular to gravity, (2, 3), and their labels.

    Each is the root axis least aligned with gravity, made exactly perpendicular to it
    (Gram-Schmidt), so a robot whose gravity lies along a root axis gets the other two
    axes themselves (COMAU: gravity along −y, horizontal axes x and z)."""
    g = gravity_vector(robot)
    up = -g / np.linalg.norm(g)
    order = np.argsort(np.abs(up), kind="stable")[:2]
    order = np.sort(order)
    axes = []
    for i in order:
        e = np.eye(3)[i]
        h = e - (e @ up) * up
        for a in axes:
            h = h - (h @ a) * a
        axes.append(h / np.linalg.norm(h))
    return np.array(axes), tuple("xyz"[i] for i in order)


def overturning_moment(robot, q, payload_kg=None, tool_position=None) -> np.ndarray:
    """Moment of the moving arm's (and payload's) weight about the base axis, (n, 3) N·m in F_I.

    The base axis is the vertical (along gravity, :func:`gravity_vector`) through F_I's
    origin. A payload (kg, per pose) acts at ``tool_position`` (n, 3) m.
    """
    mass, com = weight_and_com(robot, q)
    g = gravity_vector(robot)
    vertical = g / np.linalg.norm(g)
    lever = com - (com @ vertical)[:, None] * vertical
    M = np.cross(lever, mass * g)
    if payload_kg is not None and tool_position is not None:
        p = np.asarray(tool_position, dtype=float)
        lever_p = p - (p @ vertical)[:, None] * vertical
        M = M + np.cross(lever_p, np.asarray(payload_kg, dtype=float)[:, None] * g)
    return M


def loaded_joints(robot, min_share: float | None = None) -> tuple:
    """The joints (1-based) with a gravity torque worth identifying: RMS torque over random poses
    in the limits at least ``min_share`` (default :data:`~campaign.tolerances.GRAVITY_JOINT_MIN_SHARE`)
    of the most loaded joint's. The defaults of gravity-load effects (joint compliance, backlash)."""
    from campaign.tolerances import GRAVITY_JOINT_MIN_SHARE

    rms = _rms_torques(robot)
    share = GRAVITY_JOINT_MIN_SHARE if min_share is None else min_share
    if not rms.max() > 0:
        return ()
    return tuple(int(j) + 1 for j in np.flatnonzero(rms >= share * rms.max()))


def _rms_torques(robot) -> np.ndarray:
    """RMS gravity torque (N,) N·m of each joint over GRAVITY_JOINT_POSES random poses (fixed seed)."""
    from campaign.tolerances import GRAVITY_JOINT_POSES

    key = (robot.name, str(getattr(robot, "urdf_path", "")), "rms_tau")
    if key not in _RMS:
        rng = np.random.default_rng(20261127)
        lo, hi = np.asarray(robot.q_lower, dtype=float), np.asarray(robot.q_upper, dtype=float)
        q = rng.uniform(lo, hi, size=(GRAVITY_JOINT_POSES, robot.n_joints))
        _RMS[key] = np.sqrt(np.mean(gravity_torques(robot, q) ** 2, axis=0))
    return _RMS[key]


_RMS: dict = {}


def lever_joints(robot, k: int = 3) -> tuple:
    """The ``k`` joints (1-based, in chain order) whose axes lie farthest from the tool point on
    average over random poses: the joints whose small angle errors move the tool most (the
    default of the cyclic transmission error)."""
    from campaign.model.kinematics import frames
    from campaign.tolerances import GRAVITY_JOINT_POSES

    rng = np.random.default_rng(20261127)
    lo, hi = np.asarray(robot.q_lower, dtype=float), np.asarray(robot.q_upper, dtype=float)
    q = rng.uniform(lo, hi, size=(GRAVITY_JOINT_POSES, robot.n_joints))
    R, p = frames(robot, q)
    idx = list(robot.joint_frame_index)
    tool = p[:, -1]
    lever = np.empty(robot.n_joints)
    for j, f in enumerate(idx):
        axis = R[:, f, :, 2]  # the joint's axis: z of its frame after its motion
        d = tool - p[:, f]
        lever[j] = np.mean(np.linalg.norm(d - np.sum(d * axis, axis=1)[:, None] * axis, axis=1))
    best = np.sort(np.argsort(-lever, kind="stable")[:min(k, robot.n_joints)])
    return tuple(int(j) + 1 for j in best)
