"""Priors on the error parameters: what a calibration engineer knows before measuring.

Every geometric error parameter gets a zero-mean Gaussian prior whose standard deviation is a
manufacturing tolerance of its kind (robot.yaml ``tolerances:``, else :data:`DEFAULT_TOLERANCES`,
of the size of the paper's Table 4); every effect parameter the one its class declares
(``Effect.prior_sigma``, else a few times its typical magnitude, else none). The same
:class:`Prior` serves the identification (MAP, campaign.identify.solver) and the optimal design
(Bayesian D-optimality, campaign.plan.selection), so it lives below both.

``--fix`` names (:func:`parse_fix`, :func:`resolve_fix`) hold parameters or whole groups at
nominal or at a given value: ``base`` (the six of T_I0), ``tool`` (the six of T_NE), ``joint<j>``
(the six of joint j's transform), ``offsets`` (every joint's zero offset), a parameter name, an
effect's ``<effect>.<param>``, or a shell-style pattern (``pL_I0_*``).
"""

from __future__ import annotations

import fnmatch
from dataclasses import dataclass

import numpy as np

from campaign.errors import ConfigError

#: Tolerances (1 σ) by kind, SI. The paper's Table 4 (its COMAU's identified base parameters) has
#: lengths of rms 1.3 mm and angles / joint offsets of a few mrad (rms 5.9 mrad with its two
#: 1-2 × 10⁻² rad entries); the base and the tool are set-up quantities of the same size (a
#: tracker at an unknown pose is registered first, and only the registration's remainder is left).
DEFAULT_TOLERANCES = {
    "length_m": 1.5e-3,
    "angle_rad": 5e-3,
    "joint_offset_rad": 5e-3,
    "joint_offset_m": 1.5e-3,
    "base_m": 3e-3,
    "base_rad": 5e-3,
    "tool_m": 1.5e-3,
    "tool_rad": 5e-3,
}

#: an effect without a declared prior_sigma: this many times its typical magnitude
EFFECT_PRIOR_TYPICAL_FACTOR = 3.0


@dataclass(frozen=True)
class Prior:
    """Zero-mean Gaussian prior: ``sigma`` (n_params,) of the geometric error parameters (m or
    rad), ``effect_sigma`` (k,) of the effect parameters in their units (``inf``: no prior);
    ``tolerances``: the kind -> σ table they came from (for the report)."""

    sigma: np.ndarray
    effect_sigma: np.ndarray
    tolerances: dict

    def precision(self) -> np.ndarray:
        """(n_params + k,) 1/σ² (0 where there is no prior)."""
        s = np.concatenate([self.sigma, self.effect_sigma])
        return np.where(np.isfinite(s) & (s > 0), 1.0 / np.where(s > 0, s, 1.0) ** 2, 0.0)

    def base_covariance(self, base) -> np.ndarray:
        """(r, r) prior covariance of the base parameters ``base.combination @ p_e``."""
        C = base.combination
        return (C * self.sigma ** 2) @ C.T

    def as_json(self) -> dict:
        return {"tolerances": dict(self.tolerances)}


@dataclass(frozen=True)
class BasePrior:
    """What the prior and the held parameters say about the base parameters ``b = C p``.

    ``mean`` (r,): the base parameters the held values imply (their own part of ``C p``);
    ``covariance`` (r, r): the prior covariance ``C Σ_u C^T`` of the parameters left free
    (zeros without a prior); ``held`` (r,) bool: base parameters that held values alone
    determine (every parameter in their combination held); ``split`` (n_params, r): the
    physical parameters' conditional mean given the base, ``p = p_held + split (b - mean)``
    (Σ_u Cᵀ (C Σ_u Cᵀ)⁺: the prior's split between correlated parameters);
    ``p_held`` (n_params,) and ``held_params`` (n_params,) bool: the held physical parameters."""

    mean: np.ndarray
    covariance: np.ndarray
    held: np.ndarray
    split: np.ndarray
    p_held: np.ndarray
    held_params: np.ndarray
    #: (n_params, n_params): the physical parameters' prior covariance given the base parameters
    conditional_covariance: np.ndarray

    def precision(self, free) -> np.ndarray:
        """(f, f): the prior precision of the base parameters ``free`` (indices, none of them held)."""
        return np.linalg.pinv(self.covariance[np.ix_(free, free)], hermitian=True)

    def physical(self, b, b_covariance=None):
        """The physical parameters (n_params,) the base parameters ``b`` (r,) stand for under the
        prior; with ``b_covariance`` (r, r) also their covariance (n_params, n_params): the
        posterior's, given the base parameters' (the prior's conditional spread plus the base's)."""
        p = self.p_held + self.split @ (np.asarray(b, dtype=float) - self.mean)
        if b_covariance is None:
            return p
        return p, self.conditional_covariance + self.split @ b_covariance @ self.split.T


def base_prior(base, prior: Prior | None, held: dict | None = None) -> BasePrior:
    """The prior of the base parameters of ``base`` (campaign.model.base_params.BaseParameters)
    with the physical parameters ``held`` ({name: value}) held; ``prior`` None: no prior (a
    zero covariance; only the held values and what they determine)."""
    names = list(base.param_names)
    C = base.combination
    mask = np.zeros(len(names), dtype=bool)
    p_held = np.zeros(len(names))
    for name, value in (held or {}).items():
        i = names.index(name)
        mask[i], p_held[i] = True, float(value or 0.0)
    mean = C @ p_held
    determined = ~np.any(np.abs(C[:, ~mask]) > 0, axis=1)
    if prior is None:
        r = C.shape[0]
        return BasePrior(mean, np.zeros((r, r)), determined, np.zeros((len(names), r)), p_held, mask,
                         np.zeros((len(names), len(names))))
    var = np.where(mask, 0.0, prior.sigma ** 2)
    S = (C * var) @ C.T
    split = (var[:, None] * C.T) @ np.linalg.pinv(S, hermitian=True)
    cond = np.diag(var) - split @ C * var[None, :]
    return BasePrior(mean, S, determined, split, p_held, mask, 0.5 * (cond + cond.T))


def parameter_kinds(robot) -> list:
    """The tolerance kind of each of the robot's 6N + 12 error parameters."""
    n = robot.n_joints
    kinds = []
    for name, unit in zip(robot.param_names, robot.param_units):
        transform = name.split("_")[1] if "_" in name else None
        if name.startswith(("pq", "pd")):
            kinds.append("joint_offset_rad" if unit == "rad" else "joint_offset_m")
        elif transform == "I0":
            kinds.append("base_m" if unit == "m" else "base_rad")
        elif transform == f"{n}E":
            kinds.append("tool_m" if unit == "m" else "tool_rad")
        else:
            kinds.append("length_m" if unit == "m" else "angle_rad")
    return kinds


def robot_tolerances(robot) -> dict:
    """The kind -> σ table of ``robot``: robot.yaml's ``tolerances:`` over the defaults; a bad
    entry is a ConfigError naming the file and the field."""
    tol = dict(DEFAULT_TOLERANCES)
    if robot.meta_path is None:
        return tol
    from campaign.fileio import read_yaml_mapping

    given = read_yaml_mapping(robot.meta_path).get("tolerances")
    if given is None:
        return tol
    if not isinstance(given, dict):
        raise ConfigError(f"{robot.meta_path}: field 'tolerances' must map kinds ({', '.join(DEFAULT_TOLERANCES)}) "
                          "to standard deviations (SI)")
    for key, v in given.items():
        if key not in DEFAULT_TOLERANCES:
            raise ConfigError(f"{robot.meta_path}: tolerances.{key} is not a kind (one of "
                              f"{', '.join(DEFAULT_TOLERANCES)})")
        if isinstance(v, bool) or not isinstance(v, (int, float)) or not np.isfinite(v) or v <= 0:
            raise ConfigError(f"{robot.meta_path}: tolerances.{key} must be a positive number (SI), got {v!r}")
        tol[key] = float(v)
    return tol


def effect_prior_sigma(effect) -> np.ndarray:
    """(k,) σ of one effect's parameters: its ``prior_sigma``, else EFFECT_PRIOR_TYPICAL_FACTOR ×
    |typical_params| (where that is non-zero), else inf (no prior)."""
    declared = getattr(effect, "prior_sigma", None)
    if declared is not None:
        s = np.asarray(declared, dtype=float).reshape(-1)
        if s.shape != (effect.n_params,) or np.any(~(s > 0)):
            raise ConfigError(f"effect '{effect.name}': prior_sigma must be {effect.n_params} positive numbers")
        return s
    typical = getattr(effect, "typical_params", None)
    if typical is None:
        return np.full(effect.n_params, np.inf)
    t = np.abs(np.asarray(typical(0), dtype=float).reshape(-1))
    return np.where(t > 0, EFFECT_PRIOR_TYPICAL_FACTOR * t, np.inf)


def make_prior(robot, effects=()) -> Prior:
    """The prior of ``robot``'s error parameters and of the effects (Effect objects)."""
    tol = robot_tolerances(robot)
    sigma = np.array([tol[k] for k in parameter_kinds(robot)])
    eff = [effect_prior_sigma(e) for e in effects]
    return Prior(sigma, np.concatenate(eff) if eff else np.zeros(0), tol)


# -- --fix -------------------------------------------------------------------------------------

def parse_fix(text) -> dict:
    """``NAME[=VALUE],...`` -> {name: value or None (nominal)}; values SI. ConfigError on a bad entry."""
    out = {}
    for item in (text or "").split(","):
        item = item.strip()
        if not item:
            continue
        name, eq, value = item.partition("=")
        name = name.strip()
        if not name:
            raise ConfigError(f"--fix: empty name in {item!r}")
        if eq:
            try:
                v = float(value)
            except ValueError:
                v = float("nan")
            if not np.isfinite(v):
                raise ConfigError(f"--fix {name}: the value must be a finite number in SI units (m, rad), "
                                  f"got {value!r}")
            out[name] = v
        else:
            out[name] = None
    return out


def fix_groups(robot) -> dict:
    """Group name -> parameter names: ``base``, ``tool``, ``offsets``, ``joint1`` .. ``jointN``."""
    names = robot.param_names
    n = robot.n_joints
    groups = {"base": names[:6], "tool": names[6 * (n + 1):], "offsets": tuple(
        p for p in names if p.startswith(("pq", "pd")))}
    for j in range(1, n + 1):
        groups[f"joint{j}"] = names[6 * j:6 * (j + 1)]
    return groups


def resolve_fix(robot, fix: dict, effect_names=()) -> dict:
    """{name or group or pattern: value or None} -> {parameter name: value or None (nominal)};
    names among the robot's error parameters and ``effect_names``. ConfigError for a name that
    matches nothing."""
    known = tuple(robot.param_names) + tuple(effect_names)
    groups = fix_groups(robot)
    out = {}
    for key, value in (fix or {}).items():
        if key in groups:
            hit = groups[key]
        elif key in known:
            hit = (key,)
        else:
            hit = tuple(p for p in known if fnmatch.fnmatchcase(p, key))
        if not hit:
            raise ConfigError(f"--fix {key}: no such parameter or group (groups: {', '.join(groups)}; parameters "
                              f"like {known[0]}, {known[6 + 5]}; patterns like pL_I0_*)")
        for p in hit:
            out[p] = None if value is None else float(value)
    return out


def unknowns_precision(base, prior: Prior) -> np.ndarray:
    """(r + k, r + k): the prior precision of the identification's unknowns, the base parameters
    of ``base`` (the prior carried to them, ``(C Σ Cᵀ)⁺``) and then the k effect parameters
    (diagonal; 0 where an effect parameter has no prior). For Bayesian D-optimal design
    (campaign.plan.selection): information of the poses plus this."""
    r, k = base.n_base, len(prior.effect_sigma)
    P = np.zeros((r + k, r + k))
    P[:r, :r] = np.linalg.pinv(prior.base_covariance(base), hermitian=True)
    P[r:, r:] = np.diag(prior.precision()[len(prior.sigma):])
    return P
