"""Stage 1: the grid of candidate joint vectors, addressed by index, never materialised as objects.

The joint limits of eq. 17 are divided into cells (default 17, 10, 10, 14, 6, 10 =
1,428,000 candidates); each axis takes the cell centres. Candidate ``i`` has cell indices
``np.unravel_index(i, cells)`` (q1 slowest).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

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
