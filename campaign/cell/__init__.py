"""A real cell: the adapter contract (docs/cell.md).

A user connects a robot controller and a laser tracker by writing two plain Python classes;
``campaign serve`` (campaign.cell.server) serves them over docs/protocol.md, so an adapter
never sees a frame, a request id or a socket.

A **controller** class::

    class Controller:
        joint_convention = "controller"      # optional: "controller" (default) or "model"
        def __init__(self, robot, options): ...
        def move(self, q): ...               # block until settled at q; raise RobotFault("why") if it cannot
        def joints(self): ...                # optional: the joint readout after the move (default: q)
        def close(self): ...                 # optional

``q`` (N,) is the target joint vector (rad, m for a prismatic joint) in the controller's joint
convention: the framework converts the model's joint vector with robot.yaml's ``controller:``
section (``q_model = coupling · diag(sign) · q_controller + offset``; identity when robot.yaml has
none), and converts ``joints()`` back. An adapter that works in the model's convention (a
simulator) sets ``joint_convention = "model"``. Targets outside the joint limits are refused by
the framework (fault ``joint_limit``) before ``move`` is called.

A **tracker** class::

    class Tracker:
        def __init__(self, robot, options): ...
        def measure(self, aims): ...         # {name: (3,) m or None} -> {name: (3,) m or None}
        def close(self): ...                 # optional

``aims`` maps each target to measure to its predicted centre in the tracker frame F_L (m, (3,)),
or None where it cannot be predicted yet (before the tracker's pose is known). ``measure``
returns, for each of those names, the measured centre (3,) in m in F_L, or None for a lost beam
(the driver re-measures as for any lost beam); a name left out counts as lost.

Both get ``robot``, the run's :class:`campaign.model.robot.RobotModel` (joint names and limits,
``reflectors`` with their positions in the tool frame, ``pinocchio_model``), and ``options``,
the ``controller:`` / ``tracker:`` section of ``--options FILE.yaml`` (a dict, empty without one).

Optional hooks for simulators (the built-in ``sim`` uses them; a real cell needs none):
``clock(self)`` on either class gives the cell's clock (s; default: the wall clock, continuing
from the run's last stored time); ``temperature_c(self)`` on the tracker gives the air
temperature of the last measurement (°C) or None; ``transport_fault(self, request_id, attempt)``
on either class may answer ``"drop"``, ``"late"`` or ``"garble"`` to test the driver.
:func:`request_id` gives the id of the request an adapter is serving, :func:`context` the
:class:`CellContext` (run folder, configuration, start clock, and a dict the two adapters of one
cell share).

Errors: :class:`RobotFault` from ``move`` fails that pose with its reason and the campaign goes
on (with ``code=`` other than the pose-only codes of docs/protocol.md, e.g.
``"emergency_stop"``, it stops the campaign). Any other exception from an adapter becomes an
error reply carrying its message and one line on the server's stderr; the server stays up.
"""

from __future__ import annotations

import contextvars
from dataclasses import dataclass, field
from pathlib import Path

from campaign.errors import CampaignError, ConfigError

__all__ = ["RobotFault", "CellContext", "load_adapters", "load_options", "adapter_class", "request_id",
           "context", "resolve_adapter", "close_quietly", "BUILTIN_CELLS", "ENTRY_POINT_GROUP"]

#: entry-point group of installed adapters: a name whose value is ``module:Class`` or ``module``
ENTRY_POINT_GROUP = "campaign.cell"
#: built-in cells: name -> module holding ``Controller`` and ``Tracker`` (imported when named)
BUILTIN_CELLS = {"sim": "campaign.sim.adapters", "mujoco": "campaign.cell.mujoco_twin"}
#: the class a spec that names a module or a file (no ``:Class``) means, per role
DEFAULT_CLASS = {"controller": "Controller", "tracker": "Tracker"}
#: what each role's class must have
REQUIRED_METHOD = {"controller": "move(self, q)", "tracker": "measure(self, aims)"}
#: the fault code of a RobotFault raised without one: the pose fails, the campaign goes on
POSE_FAULT = "move_rejected"


class RobotFault(CampaignError):
    """Raised by a controller adapter's ``move`` when the robot cannot reach the pose.

    ``RobotFault("reason")``: the pose is stored as failed with ``reason`` and the campaign goes
    on (protocol fault code ``move_rejected``). ``code``: another protocol fault code
    (``joint_limit``, ``unreachable`` also fail only the pose; any other, e.g.
    ``"emergency_stop"``, stops the campaign cleanly, resumable). Not to be confused with
    :class:`campaign.errors.RobotFault`, the driver's campaign-stopping fault.
    """

    def __init__(self, reason: str, *, code: str = POSE_FAULT):
        super().__init__(reason)
        self.reason, self.code = str(reason), str(code)


@dataclass(frozen=True)
class CellContext:
    """What a served cell knows beyond the robot and the options: the run folder (Path or None),
    its validated CampaignConfig (or None), the clock to start from (s, the run's last stored
    time), and ``shared``, one dict for both adapters of the cell."""

    run_dir: Path | None = None
    config: object = None
    start_clock_s: float = 0.0
    shared: dict = field(default_factory=dict)


_REQUEST = contextvars.ContextVar("campaign_cell_request", default=None)
_CONTEXT = contextvars.ContextVar("campaign_cell_context", default=None)


def request_id() -> int | None:
    """The id of the protocol request the calling adapter is serving (None outside a request)."""
    return _REQUEST.get()


def context() -> CellContext:
    """The :class:`CellContext` of the cell the calling adapter belongs to (valid in
    ``__init__`` and in every call the framework makes)."""
    ctx = _CONTEXT.get()
    return ctx if ctx is not None else CellContext()


def _split(spec: str):
    """(source, class name or None): ``file.py[:Class]``, ``module[:Class]``, a built-in or an
    entry-point name."""
    spec = str(spec).strip()
    src, sep, cls = spec.rpartition(":")
    if sep and cls.isidentifier() and src and not src.endswith(("\\", "/")):
        return src, cls
    return spec, None


def _entry_points() -> dict:
    from importlib.metadata import entry_points

    return {ep.name: ep for ep in entry_points(group=ENTRY_POINT_GROUP)}


def _find_file(src: str, base_dir) -> Path:
    p = Path(src).expanduser()
    if p.is_absolute():
        return p
    for d in (Path.cwd(), Path(base_dir) if base_dir is not None else None):
        if d is not None and (d / p).is_file():
            return (d / p).resolve()
    return p


def adapter_source(spec: str, base_dir=None) -> Path | None:
    """The file holding the adapters a SPEC names (a FILE.py, relative to the current directory or
    ``base_dir``; a module's or a built-in's source), found without importing it; None when
    there is none (a missing file, an entry point, a module that cannot be found)."""
    import importlib.util

    src, _ = _split(spec)
    if src.endswith(".py"):
        p = _find_file(src, base_dir)
        return p if p.is_file() else None
    try:
        found = importlib.util.find_spec(BUILTIN_CELLS.get(src, src))
    except (ImportError, ValueError):
        return None
    return Path(found.origin) if found is not None and found.origin and Path(found.origin).is_file() else None


def adapter_class(spec: str, role: str, base_dir=None):
    """The class a SPEC names for ``role`` (see :func:`resolve_adapter`)."""
    return resolve_adapter(spec, role, base_dir)[0]


def resolve_adapter(spec: str, role: str, base_dir=None):
    """(class, where) for a SPEC and ``role`` ("controller" or "tracker"): ``sim``, ``mujoco``,
    ``FILE.py:Class`` or ``FILE.py`` (class ``Controller``/``Tracker``; relative to the current
    directory, else to ``base_dir``), ``package.module[:Class]`` or the name of an entry point of
    group ``campaign.cell``; ``where`` names the file and the class for messages. Every problem
    is one ConfigError line naming the file and the class."""
    import importlib

    if role not in DEFAULT_CLASS:
        raise ValueError(f"role must be 'controller' or 'tracker', got {role!r}")
    src, cls_name = _split(spec)
    if not src:
        raise ConfigError(f"--{role}: empty adapter spec")
    where = f"--{role} {spec}"
    if src.endswith(".py"):
        from campaign.userfiles import load_user_module

        path = _find_file(src, base_dir)
        cls_name = cls_name or DEFAULT_CLASS[role]
        where = f"--{role} {path}:{cls_name}"
        module = load_user_module(path, where)
    else:
        eps = _entry_points() if src not in BUILTIN_CELLS and cls_name is None else {}
        if src in eps:
            try:
                obj = eps[src].load()
            except Exception as exc:  # an installed package's code: one line, whatever it raised
                raise ConfigError(f"{where}: entry point {eps[src].value} failed to load "
                                  f"({exc.__class__.__name__}: {exc})") from None
            if isinstance(obj, type):
                return _checked(obj, role, where)
            module = obj
        else:
            name = BUILTIN_CELLS.get(src, src)
            if src not in BUILTIN_CELLS and ("." not in src and cls_name is None):
                known = ", ".join(sorted(set(BUILTIN_CELLS) | set(_entry_points())))
                raise ConfigError(f"{where}: unknown adapter (known: {known}; or FILE.py[:Class], "
                                  "package.module:Class)")
            try:
                module = importlib.import_module(name)
            except Exception as exc:  # the adapter's imports (a vendor SDK, mujoco): one line
                raise ConfigError(f"{where}: cannot import {name} ({exc.__class__.__name__}: {exc})") from None
        cls_name = cls_name or DEFAULT_CLASS[role]
        # a built-in cell is named as the user named it, not by the package's own file
        where = (f"--{role} {spec}" if src in BUILTIN_CELLS else
                 f"--{role} {getattr(module, '__file__', None) or src}:{cls_name}")
    cls = getattr(module, cls_name, None)
    if cls is None:
        defined = sorted(k for k, v in vars(module).items() if isinstance(v, type) and not k.startswith("_")
                         and getattr(v, "__module__", None) == module.__name__)
        raise ConfigError(f"{where}: no class {cls_name!r} (defined there: {', '.join(defined) or 'none'})")
    return _checked(cls, role, where)


def _checked(cls, role, where):
    if not isinstance(cls, type):
        raise ConfigError(f"{where}: {getattr(cls, '__name__', cls)!r} is not a class")
    method = REQUIRED_METHOD[role].split("(")[0]
    if not callable(getattr(cls, method, None)):
        raise ConfigError(f"{where}: a {role} adapter needs a method {REQUIRED_METHOD[role]}")
    conv = getattr(cls, "joint_convention", "controller")
    if role == "controller" and conv not in ("controller", "model"):
        raise ConfigError(f"{where}: joint_convention must be 'controller' or 'model', got {conv!r}")
    return cls, where


def load_options(path) -> dict:
    """``--options FILE.yaml``: {"controller": {...}, "tracker": {...}} (either may be absent;
    None: both empty). Other top-level keys are a ConfigError."""
    if path is None:
        return {"controller": {}, "tracker": {}}
    from campaign.fileio import read_yaml_mapping

    doc = read_yaml_mapping(path)
    extra = sorted(set(doc) - set(DEFAULT_CLASS))
    if extra:
        raise ConfigError(f"{path}: unknown section {extra[0]!r} (an options file has 'controller:' and 'tracker:')")
    out = {}
    for role in DEFAULT_CLASS:
        sec = doc.get(role) or {}
        if not isinstance(sec, dict):
            raise ConfigError(f"{path}: section '{role}' must be a mapping")
        out[role] = dict(sec)
    return out


def load_adapters(controller_spec, tracker_spec, robot, options=None, base_dir=None, *, cell_context=None):
    """Load and build the cell's two adapters: (controller, tracker) instances.

    controller_spec, tracker_spec: SPECs (see :func:`adapter_class`); both classes named from
    one file or module come from one module instance. robot: the run's RobotModel. options:
    the mapping of :func:`load_options` (or None). base_dir: where relative files are looked up
    after the current directory (the folder of the run's campaign.yaml). cell_context: the
    :class:`CellContext` the adapters see through :func:`context`. Each class is called as
    ``cls(robot, options[role])``; whatever its ``__init__`` raises is one ConfigError line
    naming the file and the class.
    """
    options = options if options is not None else {}
    ctx = cell_context if cell_context is not None else CellContext()
    classes = {role: resolve_adapter(spec, role, base_dir)
               for role, spec in (("controller", controller_spec), ("tracker", tracker_spec))}
    built = {}
    token = _CONTEXT.set(ctx)
    try:
        for role, (cls, where) in classes.items():
            try:
                built[role] = cls(robot, dict(options.get(role) or {}))
            except Exception as exc:  # the user's __init__: one line, whatever it raised
                for other in built.values():
                    close_quietly(other)
                if isinstance(exc, ConfigError):  # an adapter's own one-line refusal, said as it is
                    raise ConfigError(f"{where}: {exc}") from None
                raise ConfigError(f"{where}: {cls.__name__}(robot, options) failed "
                                  f"({exc.__class__.__name__}: {exc})") from None
    finally:
        _CONTEXT.reset(token)
    return built["controller"], built["tracker"]


def close_quietly(adapter) -> str | None:
    """Call the adapter's optional ``close()``; what it raised as one line, or None."""
    close = getattr(adapter, "close", None)
    if not callable(close):
        return None
    try:
        close()
    except Exception as exc:  # shutting down: report, never raise
        return f"{exc.__class__.__name__}: {exc}"
    return None
