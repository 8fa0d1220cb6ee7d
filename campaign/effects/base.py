"""Physical effects: the interface and the registry.

An effect is a small immutable object with a name, parameter names and units, a short
physical description, and its contribution to the model, in one or more of three places:

* :meth:`Effect.joint_offset` — Δq (n, N) rad added to the joint coordinates before the
  kinematic chain (joint compliance, backlash, cyclic transmission errors);
* :meth:`Effect.joint_twist` — for each pose and moving joint j a small twist
  ξ_j = (v, ω) (n, N, 6), m and rad, in joint j's frame after its motion, applied right after
  that joint: ``T = … A_j R_j(q_j) exp(ξ_j) A_{j+1} …`` (link bending, bearing run-out, an
  axis that tilts with its angle);
* :meth:`Effect.pose_map` — a map of the pose after the chain, ``T_IE -> T'_IE`` (base
  tilt of a compliant ground, thermal growth, tracker scale).

The full model of a measured pose is therefore ::

    T = pose_map_k( ... pose_map_1( FK_ξ(q + Σ Δq, p_e) ) )

with FK_ξ the chain with the twists Σ ξ inserted. Every hook receives the commanded q.
The same objects serve the simulator's hidden truth and the identification; the solver
differentiates the contributions numerically with respect to the effect parameters, so a
new effect is one new class — in this package decorated with :func:`register`, in a user's
file named ``path/to/file.py:ClassName`` in campaign.yaml, or an installed entry point of
group ``campaign.effects`` — and the solver does not change (docs/effects.md).
"""

from __future__ import annotations

import importlib
import pkgutil
import re
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from campaign.errors import CampaignError, ConfigError, DataError, PluginError

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


#: entry-point group through which installed packages offer effects
ENTRY_POINT_GROUP = "campaign.effects"


def available() -> dict:
    """All registered effects: name -> class (every module in campaign/effects is loaded)."""
    _discover()
    return dict(sorted(_REGISTRY.items()))


def entry_point_effects() -> dict:
    """Effects offered by installed packages (entry points of group ``campaign.effects``): name -> entry point."""
    from importlib.metadata import entry_points

    return {ep.name: ep for ep in entry_points(group=ENTRY_POINT_GROUP)}


def is_file_spec(spec: str) -> bool:
    """True for a user effect given as ``path/to/file.py:ClassName``."""
    path, sep, cls = str(spec).rpartition(":")
    return bool(sep) and path.endswith(".py") and cls.isidentifier()


_JOINTS_SUFFIX = re.compile(r"^(?P<base>.*[^:\s])\s*:(?P<joints>\s*\d+\s*(?:,\s*\d+\s*)*)$")


def split_joints(spec: str) -> tuple:
    """``(base spec, joints or None)`` of an effect spec: ``"joint_compliance:2,3,4"`` ->
    ``("joint_compliance", (2, 3, 4))``, ``"file.py:Class:4"`` -> ``("file.py:Class", (4,))``,
    ``"backlash"`` -> ``("backlash", None)``; joints 1-based as written."""
    spec = str(spec).strip()
    m = _JOINTS_SUFFIX.match(spec)
    if m is None:
        return spec, None
    return m["base"].strip(), tuple(int(j) for j in m["joints"].split(","))


def joint_spec(base: str, joints) -> str:
    """The spec of effect ``base`` over ``joints`` (1-based): ``"joint_compliance:2,4"``;
    ``base`` itself for None (the effect's own default joints)."""
    if joints is None:
        return str(base)
    return f"{base}:{','.join(str(int(j)) for j in joints)}"


def takes_joints(cls) -> bool:
    """Whether an effect class is joint-indexed: its ``__init__`` takes ``joints``."""
    import inspect

    try:
        return "joints" in inspect.signature(cls.__init__).parameters
    except (TypeError, ValueError):
        return False


def resolve_effect_spec(spec: str, base_dir=None) -> str:
    """A spec with a relative ``file.py:ClassName`` path made absolute against ``base_dir``
    (the folder of the campaign.yaml that names it; None: the current directory); a joint list
    (``:2,3``) is kept."""
    spec, joints = split_joints(spec)
    if not is_file_spec(spec):
        return joint_spec(spec, joints)
    path, _, cls = spec.rpartition(":")
    p = Path(path).expanduser()
    if not p.is_absolute():
        p = (Path(base_dir) if base_dir is not None else Path.cwd()) / p
    return joint_spec(f"{p.resolve()}:{cls}", joints)


def _load_file_class(spec: str):
    from campaign.userfiles import load_user_module

    path, _, cls_name = spec.rpartition(":")
    module = load_user_module(path, f"effect '{spec}'")
    cls = getattr(module, cls_name, None)
    if cls is None:
        raise ConfigError(f"effect '{spec}': {Path(path)} defines no class '{cls_name}'")
    return cls


def effect_class(spec: str):
    """The class of an effect spec: a built-in name, ``path/file.py:ClassName`` (absolute, or
    relative to the current directory) or the name of an entry point of group ``campaign.effects``."""
    spec, _ = split_joints(spec)
    if is_file_spec(spec):
        cls = _load_file_class(resolve_effect_spec(spec))
    else:
        effects = available()
        if spec in effects:
            return effects[spec]
        eps = entry_point_effects()
        if spec not in eps:
            known = sorted(set(effects) | set(eps))
            base, colon, tail = spec.rpartition(":")
            if colon and (base.strip() in known or is_file_spec(base.strip())):  # a joint list that is none
                said = f"joints '{tail.strip()}' are not joint numbers" if tail.strip() else "no joints after ':'"
                raise ConfigError(f"effect '{spec}': {said} (write {base.strip()}:2,3,4 with joints counted "
                                  f"from 1, or {base.strip()} for its default joints)")
            raise ConfigError(f"unknown effect '{spec}' (known: {', '.join(known) or 'none'}; "
                              "a user effect is 'path/to/file.py:ClassName')")
        try:
            cls = eps[spec].load()
        except Exception as exc:  # an installed package's code: one line, whatever it raised
            raise ConfigError(f"effect '{spec}': entry point {eps[spec].value} failed to load "
                              f"({exc.__class__.__name__}: {exc})") from None
    if not (isinstance(cls, type) and issubclass(cls, Effect)):
        raise ConfigError(f"effect '{spec}': {getattr(cls, '__name__', cls)!r} is not a subclass of "
                          "campaign.effects.Effect")
    if not getattr(cls, "name", ""):
        raise ConfigError(f"effect '{spec}': class {cls.__name__} sets no `name`")
    return cls


def make_effect(name: str, robot, **options) -> "Effect":
    """Build the effect ``name`` (a spec, see :func:`effect_class`) for ``robot``; a ConfigError
    names what is wrong."""
    cls = effect_class(name)
    _, joints = split_joints(name)
    if joints is not None:
        if not takes_joints(cls):
            raise ConfigError(f"effect '{name}': {cls.name} takes no joints (write it without ':{','.join(map(str, joints))}')")
        options = {**options, "joints": check_effect_joints(joints, robot, name)}
    try:
        effect = cls(robot, **options)
    except TypeError as exc:
        raise ConfigError(f"effect '{name}': {exc}") from None
    except CampaignError:
        raise
    except Exception as exc:  # the plug-in's own code: one line, whatever it raised
        raise PluginError(f"{_where(cls)}.__init__(robot) raised {exc.__class__.__name__}: {_clip(exc)}; "
                          "expected it to build the effect") from None
    if len(effect.param_names) != len(effect.param_units):
        raise ConfigError(f"effect '{name}': {len(effect.param_names)} param_names but "
                          f"{len(effect.param_units)} param_units")
    effect.spec = str(name)
    return effect


def effect_name(spec: str) -> str:
    """The short name of an effect spec (the class's ``name``), used in stage and parameter names."""
    return effect_class(spec).name


def check_effect_joints(joints, robot, where: str) -> tuple:
    """Joints (1-based) of a joint-indexed effect, checked against the robot: a non-empty list of
    distinct integers in 1..N; a ConfigError naming ``where`` otherwise. Returns them as a tuple."""
    joints = tuple(joints)
    n = getattr(robot, "n_joints", None)
    if not joints:
        raise ConfigError(f"effect '{where}': joints: the list is empty (name at least one joint)")
    for j in joints:
        if isinstance(j, bool) or not isinstance(j, (int, np.integer)):
            raise ConfigError(f"effect '{where}': joints: {j!r} is not a joint number")
        if j < 1 or (n is not None and j > n):
            raise ConfigError(f"effect '{where}': joint {j} is not a joint of {getattr(robot, 'name', 'the robot')} "
                              f"(joints 1..{n})")
    if len(set(joints)) < len(joints):
        raise ConfigError(f"effect '{where}': joints {list(joints)} name a joint twice")
    return tuple(int(j) for j in joints)


def parse_effect_list(text, where: str = "--effects") -> tuple:
    """``"a,b"``, ``"joint_compliance:2,3,4,backlash:5"`` or a list (of specs, or of mappings
    ``{effect: NAME, joints: [2, 3]}``) -> tuple of specs (empty entries dropped). In a string,
    a bare number after ``name:j`` continues that effect's joint list. A spec given twice is a
    ConfigError naming ``where``."""
    from campaign.config import refuse_repeats

    if text is None:
        return ()
    if isinstance(text, str):
        items = []
        for part in (s.strip() for s in text.split(",")):
            if not part:  # "a,,b" and "name:2,,3": an empty entry is dropped, not a new effect
                continue
            if part.isdigit() and items and split_joints(items[-1])[1] is not None:
                items[-1] = f"{items[-1]},{part}"
            else:
                items.append(part)
    else:
        items = [effect_entry(v, where) if isinstance(v, dict) else v for v in text]
    # one spelling per spec ("joint_compliance : 4" -> "joint_compliance:4"), as every later comparison expects
    return refuse_repeats([joint_spec(*split_joints(s)) for s in items if str(s).strip()], where)


def effect_entry(value: dict, where: str) -> str:
    """The spec of a mapping entry ``{effect: NAME, joints: [2, 3]}`` (joints optional)."""
    extra = sorted(map(str, set(value) - {"effect", "joints"}))
    if extra:
        raise ConfigError(f"{where}: {', '.join(repr(k) for k in extra)} is not a field of an effect entry "
                          f"(its fields: effect, joints), got {value!r}")
    if not isinstance(value.get("effect"), str) or not value["effect"].strip():
        raise ConfigError(f"{where}: expected {{effect: NAME, joints: [j, ...]}}, got {value!r}")
    joints = value.get("joints")
    if joints is None:
        return value["effect"].strip()
    named, in_name = split_joints(value["effect"].strip())
    if in_name is not None:
        raise ConfigError(f"{where}: {value['effect'].strip()}: joints given twice, in the name and as joints: "
                          f"{joints!r} (write {{effect: {named}, joints: [...]}})")
    if isinstance(joints, int) and not isinstance(joints, bool):
        joints = [joints]
    if isinstance(joints, str) and re.fullmatch(r"\s*\d+\s*(,\s*\d+\s*)*", joints):  # "2,3,4" as on the command line
        joints = [int(j) for j in joints.split(",")]
    if not isinstance(joints, (list, tuple)) or not joints or \
            any(isinstance(j, bool) or not isinstance(j, int) or j < 1 for j in joints):
        raise ConfigError(f"{where}: {value['effect']}: joints must be a list of joint numbers (1-based), "
                          f"got {joints!r}")
    if len(set(joints)) < len(joints):
        raise ConfigError(f"{where}: {value['effect']}: joints {list(joints)} name a joint twice")
    return joint_spec(value["effect"].strip(), joints)


def merge_effects(current, new, robot=None) -> tuple:
    """``current`` specs with ``new`` ones added in order, no duplicates: a joint-indexed effect
    already there gets the new joints added to its list (a bare name stands for its default
    joints, known from ``robot``; without it the bare name stays as it is)."""
    out = [str(s) for s in current]
    for spec in new:
        base, joints = split_joints(spec)
        at = next((i for i, s in enumerate(out) if split_joints(s)[0] == base), None)
        if at is None:
            out.append(str(spec))
            continue
        have = split_joints(out[at])[1]
        if have is None and robot is not None and joints is not None:
            have = make_effect(base, robot).joints
        if have is not None and joints is not None:
            out[at] = joint_spec(base, sorted(set(have) | set(joints)))
    return tuple(out)


def without_joints(spec: str, drop, robot=None):
    """``spec`` with the joints ``drop`` taken out of its list (a bare name: of its default joints,
    from ``robot``); None when no joint is left."""
    base, joints = split_joints(spec)
    if joints is None:
        joints = make_effect(base, robot).joints
    left = [j for j in joints if j not in set(drop)]
    return joint_spec(base, left) if left else None


def effect_yaml(spec: str):
    """How campaign.yaml writes an effect spec: a joint list as ``{effect: NAME, joints: [...]}``,
    else the spec itself."""
    base, joints = split_joints(spec)
    return base if joints is None else {"effect": base, "joints": list(joints)}


def effect_label(spec: str) -> str:
    """An effect in words for a line: ``joint_compliance:4`` -> "joint_compliance of joint 4"."""
    base, joints = split_joints(spec)
    name = base.rpartition(":")[2] if is_file_spec(base) else base
    if joints is None:
        return name
    return f"{name} of joint{'s' if len(joints) > 1 else ''} {_and(joints)}"


def _and(items) -> str:
    items = [str(i) for i in items]
    return items[0] if len(items) == 1 else ", ".join(items[:-1]) + " and " + items[-1]


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
        #: how the effect was named (built-in name, file spec or entry point); set by make_effect
        self.spec = self.name

    #: parameter names and units (instances may compute them, e.g. per harmonic)
    param_names: tuple = ()
    param_units: tuple = ()
    #: the zero-mean prior's standard deviation of each parameter, in its unit (MAP identification,
    #: docs/priors.md); None: three times |typical_params(0)| where defined, else no prior
    prior_sigma: tuple | None = None

    @property
    def n_params(self) -> int:
        return len(self.param_names)

    def initial_params(self) -> np.ndarray:
        return np.zeros(self.n_params)

    def joint_offset(self, params, q, context):
        """Δq (n, N) rad to add to the joint coordinates, or None."""
        return None

    def joint_twist(self, params, q, context):
        """Twists (n, N, 6) = (vx, vy, vz [m], ωx, ωy, ωz [rad]) in joint j's frame after its
        motion, applied right after joint j; or None."""
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

    def __post_init__(self):
        by_name = {}
        for e in self.effects:  # two specs of one effect (a built-in and a file of the same name)
            other = by_name.get(e.name)
            if other is not None and not _other_joints(other, e):
                raise ConfigError(f"effects '{other.spec}' and '{e.spec}' are both named '{e.name}': "
                                  "a model holds each effect once")
            by_name[e.name] = e

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

    def _hook(self, effect, hook: str, result_shape, optional: bool, *args):
        """``effect.<hook>(*args)`` checked: a PluginError line (the file, the class, the hook,
        what was expected and what came back) when it raises, or returns another shape than
        ``result_shape`` or values that are not finite; None passes when ``optional``."""
        expected = f"None or an array of shape {result_shape}" if optional else f"an array of shape {result_shape}"
        sig = HOOK_SIGNATURES[hook]
        try:
            out = getattr(effect, hook)(*args)
        except CampaignError:  # said on purpose, in one line already
            raise
        except Exception as exc:  # the plug-in's own code: one line, whatever it raised
            raise PluginError(f"{_where(type(effect))}.{hook}{sig} raised {exc.__class__.__name__}: "
                              f"{_clip(exc)}; expected {expected}") from None
        if out is None and optional:
            return None
        try:
            arr = np.asarray(out, dtype=float)
        except (TypeError, ValueError):
            arr = None
        if arr is None or arr.shape != tuple(result_shape):
            got = f"shape {arr.shape}" if arr is not None else f"a {type(out).__name__}"
            raise PluginError(f"{_where(type(effect))}.{hook}{sig} returned {got}; expected {expected}")
        bad = ~np.isfinite(arr)
        if bad.any() and all(np.isfinite(np.asarray(a, dtype=float)).all() for a in args[:-1]):
            context = (args[-1] or {}) if args else {}
            lacking = [k for k in effect.context_keys if k in context
                       and not np.isfinite(np.asarray(context[k], dtype=float)).all()]
            if lacking:  # not the plug-in's fault: the data lack what it needs
                n = int(sum((~np.isfinite(np.asarray(context[k], dtype=float))).sum() for k in lacking))
                raise DataError(f"effect '{effect.name}' needs the context {', '.join(lacking)} for every pose; "
                                f"{n} values are missing (the measurements have no {lacking[0]} column?)")
            kinds = sorted({"NaN" if np.isnan(v) else "inf" for v in arr[bad][:1000]})
            raise PluginError(f"{_where(type(effect))}.{hook}{sig} returned {int(bad.sum())} of {arr.size} values "
                              f"not finite ({', '.join(kinds)}) for finite parameters and joints; expected {expected}, "
                              "every value finite")
        return arr

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
        return np.concatenate([self._hook(e, "initial_params", (e.n_params,), False) for e in self.effects])

    def check_context(self, context, n):
        for e in self.effects:
            e.check_context(context or {}, n)

    def joint_offset(self, theta, q, context):
        """Σ Δq over the effects, (n, 6) rad."""
        dq = np.zeros_like(q)
        for e, th in zip(self.effects, self.split(theta)):
            d = self._hook(e, "joint_offset", q.shape, True, th, q, context)
            if d is not None:
                dq = dq + d
        return dq

    def joint_twist(self, theta, q, context):
        """Σ ξ over the effects, (n, N, 6), or None when no effect has twists."""
        total = None
        for e, th in zip(self.effects, self.split(theta)):
            xi = self._hook(e, "joint_twist", (*q.shape, 6), True, th, q, context)
            if xi is not None:
                total = xi if total is None else total + xi
        return total

    def twist_params(self) -> np.ndarray:
        """Boolean mask over the flat parameter vector: parameters of effects that define joint_twist."""
        return np.array([has_twist(e) for e in self.effects for _ in range(e.n_params)], dtype=bool)

    def pose_map(self, theta, T_IE, q, context):
        for e, th in zip(self.effects, self.split(theta)):
            T_IE = self._hook(e, "pose_map", np.shape(T_IE), False, th, T_IE, q, context)
        return T_IE


def _other_joints(a, b) -> bool:
    """Two instances of one joint-indexed effect class over disjoint joints (their parameters
    apart: a candidate on new joints beside the model's own, in diagnose)."""
    ja, jb = getattr(a, "joints", None), getattr(b, "joints", None)
    return (type(a) is type(b) and takes_joints(type(a)) and ja is not None and jb is not None
            and not set(ja) & set(jb))


#: how each checked hook is called (named in a plug-in's error line)
HOOK_SIGNATURES = {"initial_params": "()", "joint_offset": "(params, q, context)",
                   "joint_twist": "(params, q, context)", "pose_map": "(params, T_IE, q, context)"}


def _where(cls) -> str:
    """``/path/file.py:ClassName`` of a plug-in's class (its module when it has no file)."""
    import inspect

    try:
        where = inspect.getsourcefile(cls) or cls.__module__
    except TypeError:
        where = cls.__module__
    return f"effect {where}:{cls.__name__}"


def _clip(exc, n: int = 200) -> str:
    text = " ".join(str(exc).split())
    return text if len(text) <= n else text[: n - 1] + "…"


def has_twist(effect) -> bool:
    """Whether an effect overrides :meth:`Effect.joint_twist`."""
    return type(effect).joint_twist is not Effect.joint_twist


def effect_context(context, time_s) -> dict:
    """The per-pose context an effect sees: the measured extra columns plus ``time_s``."""
    out = dict(context or {})
    out["time_s"] = np.asarray(time_s, dtype=float)
    return out


def chain_pose(robot, q, p_e=None, effects: EffectSet = EffectSet(), theta=None, context=None):
    """The chain before the pose maps: ``FK_ξ(q + Δq, p_e)``, (n, 4, 4)."""
    from campaign.model.kinematics import forward

    q = np.asarray(q, dtype=float)
    context = context or {}
    if not effects.effects:
        return forward(robot, q, p_e)
    theta = effects.initial_params() if theta is None else np.asarray(theta, dtype=float)
    dq = effects.joint_offset(theta, q, context)
    return forward(robot, q + dq, p_e, joint_twists=effects.joint_twist(theta, q, context))


def model_pose(robot, q, p_e=None, effects: EffectSet = EffectSet(), theta=None, context=None):
    """The full model: ``pose_map(FK_ξ(q + Δq, p_e))``, (n, 4, 4)."""
    q = np.asarray(q, dtype=float)
    context = context or {}
    T = chain_pose(robot, q, p_e, effects, theta, context)
    if not effects.effects:
        return T
    theta = effects.initial_params() if theta is None else np.asarray(theta, dtype=float)
    return effects.pose_map(theta, T, q, context)
