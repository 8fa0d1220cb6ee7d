"""The kinematic part of a URDF read with the standard library (xml.etree): robot name, links,
and per joint its name, type, parent, child, origin, axis, limits and mimic.

That is all a robot's chain needs (campaign.model.robot). yourdfpy reads the same, and more
(geometry, meshes), but importing it imports trimesh, about half a second for every command
that loads a robot; it stays the reader of record for the scene graph, the meshes, the export,
and for every file this reader does not take (campaign.model.robot falls back to it, so a
malformed file is worded as before). The records have yourdfpy's attribute names and values:
``origin`` the 4×4 of ``<origin xyz rpy>`` (URDF's rpy: R = Rz(y) Ry(p) Rx(r)) or None without
an ``<origin>``, ``axis`` the ``<axis xyz>`` values (1 0 0 without), ``limit`` with ``lower``,
``upper``, ``velocity``, ``effort`` (None where not given) or None, ``mimic`` with ``joint``,
``multiplier`` (1), ``offset`` (0) or None. tests/test_urdf_chain.py compares them with yourdfpy's on
every URDF at hand.
"""

from __future__ import annotations

import xml.etree.ElementTree as ET
from dataclasses import dataclass

import numpy as np

JOINT_TYPES = ("revolute", "continuous", "prismatic", "fixed", "floating", "planar")


class NotReadHere(ValueError):
    """A URDF this reader does not take: the caller reads it with yourdfpy instead."""


@dataclass(frozen=True)
class Limit:
    effort: float | None = None
    velocity: float | None = None
    lower: float | None = None
    upper: float | None = None


@dataclass(frozen=True)
class Mimic:
    joint: str
    multiplier: float | None = None
    offset: float | None = None


@dataclass(frozen=True)
class Joint:
    name: str
    type: str
    parent: str
    child: str
    origin: np.ndarray | None = None
    axis: np.ndarray | None = None
    limit: Limit | None = None
    mimic: Mimic | None = None


@dataclass(frozen=True)
class Link:
    name: str


@dataclass(frozen=True)
class Robot:
    name: str
    links: list
    joints: list


@dataclass(frozen=True)
class URDF:
    """yourdfpy's ``URDF`` as far as a chain goes: ``.robot`` with ``name``, ``links``, ``joints``."""

    robot: Robot


def _floats(text, n, where):
    try:
        v = [float(x) for x in str(text).split()]
    except ValueError:
        raise NotReadHere(f"{where}: {text!r} is not {n} numbers") from None
    if len(v) != n:
        raise NotReadHere(f"{where}: {text!r} is not {n} numbers")
    return v


def _number(el, key):
    value = el.get(key)
    if value is None:
        return None
    try:
        return float(value)
    except ValueError:
        raise NotReadHere(f"{key}={value!r} is not a number") from None


def _default(value, default):
    return default if value is None else value


def _origin(el) -> np.ndarray | None:
    if el is None:
        return None
    x, y, z = _floats(el.get("xyz", "0 0 0"), 3, "origin xyz")
    r, p, w = _floats(el.get("rpy", "0 0 0"), 3, "origin rpy")
    cr, sr, cp, sp, cw, sw = np.cos(r), np.sin(r), np.cos(p), np.sin(p), np.cos(w), np.sin(w)
    T = np.eye(4)
    T[:3, :3] = [[cw * cp, cw * sp * sr - sw * cr, cw * sp * cr + sw * sr],
                 [sw * cp, sw * sp * sr + cw * cr, sw * sp * cr - cw * sr],
                 [-sp, cp * sr, cp * cr]]  # Rz(w) Ry(p) Rx(r)
    T[:3, 3] = (x, y, z)
    return T


def read_chain(path) -> URDF:
    """The URDF at ``path`` (its kinematic part); :class:`NotReadHere` (or an XML or OS error)
    for a file to be read by yourdfpy instead."""
    root = ET.parse(path).getroot()
    if root.tag != "robot":
        raise NotReadHere(f"root element <{root.tag}>, not <robot>")
    links = [Link(el.get("name")) for el in root.findall("link")]
    joints = []
    for el in root.findall("joint"):
        name, kind = el.get("name"), el.get("type")
        parent, child = el.find("parent"), el.find("child")
        missing = [what for what, gone in (("a name", name is None),
                                            (f"a type of {', '.join(JOINT_TYPES)}", kind not in JOINT_TYPES),
                                            ("<parent link=...>", parent is None or parent.get("link") is None),
                                            ("<child link=...>", child is None or child.get("link") is None)) if gone]
        if missing:
            raise NotReadHere(f"joint {name!r}: no {', no '.join(missing)}")
        axis = el.find("axis")
        limit = el.find("limit")
        mimic = el.find("mimic")
        joints.append(Joint(
            name, kind, parent.get("link"), child.get("link"), _origin(el.find("origin")),
            np.array(_floats("1 0 0" if axis is None else axis.get("xyz", "1 0 0"), 3, f"joint {name} axis")),
            None if limit is None else Limit(*(_number(limit, k) for k in ("effort", "velocity", "lower", "upper"))),
            None if mimic is None else Mimic(mimic.get("joint"), _default(_number(mimic, "multiplier"), 1.0),
                                             _default(_number(mimic, "offset"), 0.0))))
    if any(lk.name is None for lk in links) or root.get("name") is None:
        raise NotReadHere("a link or the robot without a name")
    return URDF(Robot(root.get("name"), links, joints))
