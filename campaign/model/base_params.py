"""Identifiable base parameters (Khalil & Gautier 1991) by QR of the regressor.

The regressor ``Θ = ∂Δz/∂p_e`` of random poses of the nominal model is decomposed by QR.
Its rank, from QR with column pivoting, is the number of identifiable parameters. Which
parameters stand for the base set follows a priority order (the paper's: lengths, then
joint offsets, then the remaining rotations): scanning the columns in that order, a column
is independent when the QR of the columns kept so far leaves a non-negligible remainder.
Each dependent column is then written as a combination of the independent ones,
``Θ_D = Θ_I X``, so the base parameters are ``p_b = p_I + X p_D``.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import scipy.linalg

from campaign.errors import IdentificationError
from campaign.model.kinematics import PARAM_NAMES, PARAM_UNITS, error_jacobian, forward
from campaign.model.robot import RobotModel
from campaign.tolerances import BASE_PARAM_COEFF_ATOL, BASE_PARAM_RANK_RTOL


def paper_priority(names=PARAM_NAMES):
    """Column order in which base parameters are chosen: lengths pL..., joint zero offsets
    (pq<j>, pd<j>), then rotations pR.... ``names``: the robot's ``param_names``."""
    lengths = [i for i, n in enumerate(names) if n.startswith("pL")]
    offsets = [i for i, n in enumerate(names) if n.startswith(("pq", "pd"))]
    rotations = [i for i, n in enumerate(names) if n.startswith("pR")]
    return lengths + offsets + rotations


@dataclass(frozen=True)
class BaseParameters:
    """The identifiable parameter set of a robot.

    ``independent``: indices (into the 6N + 12; 48 for the COMAU) of the parameters that
    stand for the base set, in priority order; ``combination``: (r, 6N + 12), so that
    ``p_b = combination @ p_e``; ``param_names`` / ``param_units``: the robot's.
    """

    independent: tuple
    combination: np.ndarray
    position_only: bool
    rank_pivoted: int
    singular_values: np.ndarray
    param_names: tuple = PARAM_NAMES
    param_units: tuple = PARAM_UNITS

    @property
    def n_params(self) -> int:
        return int(self.combination.shape[1])

    @property
    def n_base(self) -> int:
        return len(self.independent)

    @property
    def names(self) -> tuple:
        return tuple(self.param_names[i] for i in self.independent)

    @property
    def units(self) -> tuple:
        return tuple(self.param_units[i] for i in self.independent)

    def expand(self, p_b) -> np.ndarray:
        """The full vector with ``p_b`` at the independent parameters and zeros elsewhere."""
        p = np.zeros(self.n_params)
        p[list(self.independent)] = p_b
        return p

    def project(self, p_e) -> np.ndarray:
        """Base parameters that a full 48-vector ``p_e`` stands for (first order)."""
        return self.combination @ np.asarray(p_e, dtype=float)

    def min_norm(self, p_b) -> np.ndarray:
        """The 48-vector of least Euclidean norm whose base parameters are ``p_b``."""
        C = self.combination
        return C.T @ np.linalg.solve(C @ C.T, np.asarray(p_b, dtype=float))

    def expression(self, j: int, *, digits: int = 3) -> str:
        """Base parameter j as a readable combination, like the paper's Table 3."""
        row = self.combination[j]
        terms = []
        lead = self.independent[j]
        for i in [lead] + [i for i in range(self.n_params) if i != lead]:
            c = row[i]
            if abs(c) < max(BASE_PARAM_COEFF_ATOL, 0.5 * 10.0**-digits) and i != lead:
                continue
            name = self.param_names[i]
            mag = abs(c)
            coef = "" if abs(mag - 1.0) < 1e-9 else f"{mag:.{digits}f} "
            sign = "-" if c < 0 else "+"
            terms.append((sign, coef + name))
        text = ("-" if terms[0][0] == "-" else "") + terms[0][1]
        for sign, t in terms[1:]:
            text += f" {sign} {t}"
        return text

    def table(self) -> str:
        """The base parameters printed like the paper's Table 3."""
        kind = "position only" if self.position_only else "position + orientation"
        lines = [f"{self.n_base} identifiable base parameters of {self.n_params} ({kind}; rank by pivoted QR: "
                 f"{self.rank_pivoted})", f"{'#':>3}  {'unit':<4} combination"]
        for j in range(self.n_base):
            lines.append(f"{j + 1:>3}  {self.units[j]:<4} {self.expression(j)}")
        return "\n".join(lines)


def point_rows(J, d) -> np.ndarray:
    """Position rows of points off the tool point: ``J`` (n, 6, p) the pose error's derivative
    (δt at the tool point, δφ in F_I), ``d`` (n, k, 3) m from the tool point to each point in F_I.
    A point moves by ``δt + δφ × d``: (n, k, 3, p)."""
    return J[:, None, :3, :] - np.cross(d[:, :, :, None], J[:, None, 3:, :], axis=2)


def regressor(robot: RobotModel, n_poses: int = 200, seed: int = 0, position_only: bool = False, points=None):
    """The stacked nominal regressor of random poses, (6 n or 3 n, 6N + 12); with ``points``
    (k, 3) m in the tool frame (position_only): the positions of those points, (3 k n, 6N + 12)."""
    rng = np.random.default_rng(seed)
    q = rng.uniform(robot.q_lower, robot.q_upper, size=(n_poses, robot.n_joints))
    J = error_jacobian(robot, q)
    if points is not None:
        d = np.asarray(points, dtype=float).reshape(-1, 3) @ np.swapaxes(forward(robot, q)[:, :3, :3], 1, 2)
        J = point_rows(J, d)
    elif position_only:
        J = J[:, :3, :]
    return J.reshape(-1, robot.n_params)


def base_parameters(robot: RobotModel, *, position_only: bool = False, n_poses: int = 200,
                    seed: int = 0, priority=None, points=None) -> BaseParameters:
    """Compute the base parameter set of ``robot`` from a random-pose regressor. points: (k, 3) m
    in the tool frame, measured by position only (position_only): the set of their positions
    (default: the tool point's)."""
    if points is not None and not position_only:
        raise IdentificationError("base_parameters: points are measured by position only (position_only=True)")
    W = regressor(robot, n_poses, seed, position_only, points)
    # columns in m and rad: scale to unit norm so the rank test compares like with like
    norms = np.linalg.norm(W, axis=0)
    zero_cols = norms < 1e-12 * max(norms.max(), 1.0)
    Ws = W / np.where(zero_cols, 1.0, norms)
    Ws[:, zero_cols] = 0.0
    _, R_piv, _ = scipy.linalg.qr(Ws, mode="economic", pivoting=True)
    d = np.abs(np.diag(R_piv))
    rank = int(np.sum(d > BASE_PARAM_RANK_RTOL * d[0]))

    n_params = robot.n_params
    order = list(paper_priority(robot.param_names) if priority is None else priority)
    if sorted(order) != list(range(n_params)):
        raise IdentificationError(f"priority must be a permutation of the {n_params} parameter indices")
    _, R_ord = scipy.linalg.qr(Ws[:, order], mode="economic")
    d_ord = np.abs(np.diag(R_ord))
    keep = d_ord > BASE_PARAM_RANK_RTOL * d[0]
    independent = [order[i] for i in range(n_params) if keep[i]]
    dependent = [order[i] for i in range(n_params) if not keep[i]]
    if len(independent) != rank:
        raise IdentificationError(
            f"base-parameter analysis is ill-conditioned: ordered QR keeps {len(independent)} columns, "
            f"pivoted QR finds rank {rank}")
    X, *_ = np.linalg.lstsq(W[:, independent], W[:, dependent], rcond=None)
    resid = np.linalg.norm(W[:, independent] @ X - W[:, dependent]) / max(np.linalg.norm(W), 1.0)
    if resid > 1e-8:
        raise IdentificationError(f"dependent columns are not combinations of the base set (residual {resid:.2e})")
    C = np.zeros((rank, n_params))
    for j, i in enumerate(independent):
        C[j, i] = 1.0
    for col, i in enumerate(dependent):
        C[:, i] = X[:, col]
    C[np.abs(C) < BASE_PARAM_COEFF_ATOL] = 0.0
    C.setflags(write=False)
    sv = np.linalg.svd(Ws, compute_uv=False)
    sv.setflags(write=False)
    return BaseParameters(tuple(independent), C, position_only, rank, sv, robot.param_names, robot.param_units)
