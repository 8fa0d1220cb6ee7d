"""Stage 1: the grid of candidate joint vectors, addressed by index, never materialised as objects.

The joint limits of eq. 17 are divided into cells (default 17, 10, 10, 14, 6, 10 =
1,428,000 candidates); each axis takes the cell centres. Candidate ``i`` has cell indices
``np.unravel_index(i, cells)`` (q1 slowest).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from campaign.config import MAX_GRID_SIZE
from campaign.errors import ConfigError
from campaign.model.rotations import rot_z

PAPER_CELLS = (17, 10, 10, 14, 6, 10)


@dataclass(frozen=True)
class Grid:
    cells: tuple
    lower: np.ndarray
    upper: np.ndarray

    @classmethod
    def for_robot(cls, robot, cells=PAPER_CELLS) -> "Grid":
        cells = tuple(int(c) for c in cells)
        if len(cells) != 6 or any(c < 1 for c in cells):
            raise ConfigError(f"plan.grid_cells: expected 6 positive integers, got {list(cells)}")
        if int(np.prod(np.array(cells, dtype=object))) >= MAX_GRID_SIZE:
            raise ConfigError(f"plan.grid_cells: {' x '.join(map(str, cells))} candidates exceed the "
                              f"{MAX_GRID_SIZE:,} a plan can address")
        return cls(cells, np.array(robot.q_lower, dtype=float), np.array(robot.q_upper, dtype=float))

    @property
    def size(self) -> int:
        return int(np.prod(self.cells))

    @property
    def step(self) -> np.ndarray:
        """Cell width per axis, rad."""
        return (self.upper - self.lower) / np.array(self.cells)

    def axis_values(self, k: int) -> np.ndarray:
        """Joint values of axis k (0-based), rad: the cell centres."""
        return self.lower[k] + (np.arange(self.cells[k]) + 0.5) * self.step[k]

    def cell_indices(self, index) -> np.ndarray:
        """(n, 6) integer cell indices of candidates."""
        return np.stack(np.unravel_index(np.asarray(index, dtype=np.int64), self.cells), axis=1)

    def q(self, index) -> np.ndarray:
        """(n, 6) joint vectors of candidates, rad."""
        c = self.cell_indices(index)
        return self.lower + (c + 0.5) * self.step


def tool_frames(robot, grid: Grid):
    """Pose of F_E for every candidate, exploiting the grid's structure: the pose of link k
    depends only on q1..qk, so each level multiplies the previous level's poses by the few
    transforms of one axis. Returns R (N, 3, 3), t (N, 3) in candidate-index order."""
    R = robot.R_nominal[0][None]
    t = robot.t_nominal[0][None]
    for k in range(6):
        Rk = robot.R_nominal[k + 1] @ rot_z(grid.axis_values(k))  # (m, 3, 3)
        tk = robot.t_nominal[k + 1]
        # the origin of frame k+1 depends only on the parent; every child value shares it
        t = np.broadcast_to((t + R @ tk)[:, None, :], (R.shape[0], Rk.shape[0], 3)).reshape(-1, 3)
        R = (R[:, None] @ Rk[None]).reshape(-1, 3, 3)
    t = t + R @ robot.t_nominal[7]
    R = R @ robot.R_nominal[7]
    return R, t


def iter_tool_points(robot, grid: Grid, points_in_E, vectors_in_E, chunk: int = 4096):
    """Points and directions fixed in F_E, in F_I, for every candidate, block by block, without
    forming the candidates' 3×3 rotations: the poses of frame 5 are built level by level as in
    :func:`tool_frames` (a tenth of the grid's size), then, for ``chunk`` frame-5 poses at a
    time, the points and vectors turned by every value of q6 are mapped by one product.

    points_in_E (r, 3) m, vectors_in_E (s, 3). Yields (first candidate index, P (n, r, 3) m,
    V (n, s, 3)) for consecutive blocks of candidates, in candidate-index order."""
    points_in_E = np.asarray(points_in_E, dtype=float).reshape(-1, 3)
    vectors_in_E = np.asarray(vectors_in_E, dtype=float).reshape(-1, 3)
    r, c6 = len(points_in_E), grid.cells[5]
    R = robot.R_nominal[0][None]
    t = robot.t_nominal[0][None]
    for k in range(5):  # frames 1..5
        Rk = robot.R_nominal[k + 1] @ rot_z(grid.axis_values(k))
        t = np.broadcast_to((t + R @ robot.t_nominal[k + 1])[:, None, :], (R.shape[0], Rk.shape[0], 3)).reshape(-1, 3)
        R = (R[:, None] @ Rk[None]).reshape(-1, 3, 3)
    # p in F_E lies at t6 + R5 R̄6 Rz(q6) (t̄7 + R̄7 p) in F_I; a vector v at R5 R̄6 Rz(q6) R̄7 v
    t6 = t + R @ robot.t_nominal[6]
    M = R @ robot.R_nominal[6]  # (m, 3, 3)
    R7, t7 = robot.R_nominal[7], robot.t_nominal[7]
    Z = rot_z(grid.axis_values(5))  # (c6, 3, 3)
    # columns (q6 value, point) and (q6 value, vector), in frame 6 before its joint's turn
    ZP = np.ascontiguousarray(np.einsum("qij,kj->iqk", Z, t7 + points_in_E @ R7.T).reshape(3, -1))
    ZV = np.ascontiguousarray(np.einsum("qij,kj->iqk", Z, vectors_in_E @ R7.T).reshape(3, -1))
    for s in range(0, len(M), chunk):
        Mc, tc = M[s : s + chunk], t6[s : s + chunk]
        P = (np.einsum("mij,jc->mci", Mc, ZP).reshape(len(Mc), c6, r, 3) + tc[:, None, None, :]).reshape(-1, r, 3)
        V = np.ascontiguousarray(np.einsum("mij,jc->mci", Mc, ZV)).reshape(len(P), -1, 3)
        yield s * c6, P, V
