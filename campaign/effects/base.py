"""Physical effects: the interface and the registry.

An effect is a small immutable object with a name, parameter names and units, a short
physical description, and its contribution to the model, in one or both of two places:

* :meth:`Effect.joint_offset` — Δq (n, 6) rad added to the joint coordinates before the
  kinematic chain (joint compliance, backlash, cyclic transmission errors);
* :meth:`Effect.pose_map` — a map of the pose after the chain, ``T_IE -> T'_IE`` (base
  tilt of a compliant ground, thermal growth, tracker scale).

The full model of a measured pose is therefore ::

    T = pose_map_k( ... pose_map_1( FK(q + Σ Δq_j, p_e) ) )

The same objects serve the simulator's hidden truth and the identification; the solver
differentiates the contributions numerically with respect to the effect parameters (they
are cheap: no kinematics is re-run), so a new effect is one new file in this package,
decorated with :func:`register`, and the solver does not change.
"""

from __future__ import annotations

import importlib
import pkgutil
from dataclasses import dataclass

import numpy as np

from campaign.errors import ConfigError

_REGISTRY: dict = {}


def register(cls):
    """Class decorator: make an :class:`Effect` subclass available by its ``name``."""
    if not getattr(cls, "name", None):
        raise TypeError(f"{cls.__name__} has no name")
    _REGISTRY[cls.name] = cls
    return cls


def _discover():
    import campaign.effects as pkg

    for mod in pkgutil.iter_modules(pkg.__path__):
        if mod.name not in ("base",) and not mod.name.startswith("_"):
            importlib.import_module(f"campaign.effects.{mod.name}")


def available() -> dict:
    """All registered effects: name -> class (every module in campaign/effects is loaded)."""
    _discover()
    return dict(sorted(_REGISTRY.items()))


def make_effect(name: str, robot, **options) -> "Effect":
    """Build the effect called ``name`` for ``robot``; unknown names are a ConfigError."""
    effects = available()
    if name not in effects:
        raise ConfigError(f"unknown effect '{name}' (known: {', '.join(effects) or 'none'})")
    try:
        return effects[name](robot, **options)
    except TypeError as exc:
        raise ConfigError(f"effect '{name}': {exc}") from None


def parse_effect_list(text) -> tuple:
    """``"a,b"`` or a list -> tuple of names (empty entries dropped)."""
    if text is None:
        return ()
    if isinstance(text, str):
        items = text.split(",")
    else:
        items = list(text)
    return tuple(s.strip() for s in items if str(s).strip())


class Effect:
    """Base class of physical effects. Subclasses set the class attributes and override
    :meth:`joint_offset` and/or :meth:`pose_map`.

    Instances are immutable descriptions; parameters are passed in, never stored.
    """

    #: registry name, used in campaign.yaml and ``--effects``
    name: str = ""
    #: one-line physical description
    description: str = ""
    #: context fields the effect needs (e.g. ``("temperature_c",)``); missing ones are an error
    context_keys: tuple = ()

    def __init__(self, robot):
        self.robot = robot

    #: parameter names and units (instances may compute them, e.g. per harmonic)
    param_names: tuple = ()
    param_units: tuple = ()

    @property
    def n_params(self) -> int:
        return len(self.param_names)

    def initial_params(self) -> np.ndarray:
        return np.zeros(self.n_params)

    def joint_offset(self, params, q, context):
        """Δq (n, 6) rad to add to the joint coordinates, or None."""
        return None

    def pose_map(self, params, T_IE, q, context):
        """The mapped poses (n, 4, 4); the default leaves them unchanged."""
        return T_IE

    def check_context(self, context, n):
        for key in self.context_keys:
            if key not in context:
                raise ConfigError(f"effect '{self.name}' needs the per-pose context column '{key}'")
            if np.asarray(context[key]).shape != (n,):
                raise ConfigError(f"effect '{self.name}': context '{key}' must have one value per pose")

    def __repr__(self):
        return f"<effect {self.name}: {', '.join(f'{n} [{u}]' for n, u in zip(self.param_names, self.param_units))}>"


@dataclass(frozen=True)
class EffectSet:
    """An ordered tuple of effects with a flat parameter vector spanning all of them."""

    effects: tuple = ()

    @property
    def n_params(self) -> int:
        return sum(e.n_params for e in self.effects)

    @property
    def names(self) -> tuple:
        return tuple(e.name for e in self.effects)

    @property
    def param_names(self) -> tuple:
        return tuple(f"{e.name}.{p}" for e in self.effects for p in e.param_names)

    @property
    def param_units(self) -> tuple:
        return tuple(u for e in self.effects for u in e.param_units)

    def split(self, theta):
        """Flat vector -> list of per-effect parameter arrays."""
        theta = np.asarray(theta, dtype=float)
        out, i = [], 0
        for e in self.effects:
            out.append(theta[i : i + e.n_params])
            i += e.n_params
        return out

    def initial_params(self) -> np.ndarray:
        if not self.effects:
            return np.zeros(0)
        return np.concatenate([e.initial_params() for e in self.effects])

    def check_context(self, context, n):
        for e in self.effects:
            e.check_context(context or {}, n)

    def joint_offset(self, theta, q, context):
        """Σ Δq over the effects, (n, 6) rad."""
        dq = np.zeros_like(q)
        for e, th in zip(self.effects, self.split(theta)):
            d = e.joint_offset(th, q, context)
            if d is not None:
                dq = dq + d
        return dq

    def pose_map(self, theta, T_IE, q, context):
        for e, th in zip(self.effects, self.split(theta)):
            T_IE = e.pose_map(th, T_IE, q, context)
        return T_IE


def effect_context(context, time_s) -> dict:
    """The per-pose context an effect sees: the measured extra columns plus ``time_s``."""
    out = dict(context or {})
    out["time_s"] = np.asarray(time_s, dtype=float)
    return out


def model_pose(robot, q, p_e=None, effects: EffectSet = EffectSet(), theta=None, context=None):
    """The full model: ``pose_map(FK(q + Δq, p_e))``, (n, 4, 4)."""
    from campaign.model.kinematics import forward

    q = np.asarray(q, dtype=float)
    context = context or {}
    if not effects.effects:
        return forward(robot, q, p_e)
    theta = effects.initial_params() if theta is None else np.asarray(theta, dtype=float)
    dq = effects.joint_offset(theta, q, context)
    T = forward(robot, q + dq, p_e)
    return effects.pose_map(theta, T, q, context)
