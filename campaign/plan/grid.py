"""Stage 1: the grid of candidate joint vectors, addressed by index, never materialised as objects.

The joint limits of eq. 17 are divided into cells per joint; each axis takes the cell
centres. Candidate ``i`` has cell indices ``np.unravel_index(i, cells)`` (q1 slowest). The
cells per joint come from campaign.yaml's ``plan.grid_cells`` (one per joint); without it
(:func:`default_cells`), the default COMAU takes the paper's 17, 10, 10, 14, 6, 10 =
1,428,000 candidates, and any other robot one common step for its revolute joints chosen
so that the grid holds at most :data:`DEFAULT_GRID_SIZE` candidates (a 7R Panda: 9 x 5 x 9
x 5 x 9 x 6 x 9 = 1,093,500), at least two cells a joint, :data:`PRISMATIC_CELLS` for a
prismatic joint.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from campaign.config import MAX_GRID_SIZE
from campaign.errors import ConfigError
from campaign.model.rotations import rot_z

PAPER_CELLS = (17, 10, 10, 14, 6, 10)
#: most candidates of a robot's default grid (the paper's grid holds 1,428,000)
DEFAULT_GRID_SIZE = 1_200_000
#: cells of a prismatic joint in a default grid
PRISMATIC_CELLS = 5


def default_cells(robot) -> tuple:
    """Cells per joint when campaign.yaml names none: the paper's for the default COMAU; else
    ``max(2, round(range_j / s))`` per revolute joint with the largest common step s (rad) whose
    grid holds at most :data:`DEFAULT_GRID_SIZE` candidates, and :data:`PRISMATIC_CELLS` per
    prismatic joint."""
    from campaign.paths import ROBOT_MODELS, DEFAULT_ROBOT

    if robot.urdf_path == (ROBOT_MODELS / DEFAULT_ROBOT / "robot.urdf").resolve() and robot.n_joints == 6:
        return PAPER_CELLS
    span = np.asarray(robot.q_upper, dtype=float) - np.asarray(robot.q_lower, dtype=float)
    prismatic = robot.prismatic

    def cells(step):
        return np.where(prismatic, PRISMATIC_CELLS, np.maximum(2, np.round(span / step))).astype(int)

    lo, hi = 1e-4, 4 * np.pi  # a step too fine and one coarse enough (two cells a joint)
    if np.prod(cells(hi).astype(float)) > DEFAULT_GRID_SIZE:
        return tuple(int(c) for c in cells(hi))
    for _ in range(100):  # the size falls as the step grows: bisect for the finest step that fits
        mid = 0.5 * (lo + hi)
        if np.prod(cells(mid).astype(float)) > DEFAULT_GRID_SIZE:
            lo = mid
        else:
            hi = mid
    return tuple(int(c) for c in cells(hi))


@dataclass(frozen=True)
class Grid:
    cells: tuple
    lower: np.ndarray
    upper: np.ndarray

    @classmethod
    def for_robot(cls, robot, cells=None) -> "Grid":
        """The grid of ``cells`` per joint (None: :func:`default_cells`) over the robot's limits."""
        cells = default_cells(robot) if cells is None else tuple(int(c) for c in cells)
        N = robot.n_joints
        if len(cells) != N or any(c < 1 for c in cells):
            raise ConfigError(f"plan.grid_cells: expected {N} positive integers (one per joint of {robot.name}), "
                              f"got {list(cells)}")
        if int(np.prod(np.array(cells, dtype=object))) >= MAX_GRID_SIZE:
            raise ConfigError(f"plan.grid_cells: {' x '.join(map(str, cells))} candidates exceed the "
                              f"{MAX_GRID_SIZE:,} a plan can address")
        return cls(cells, np.array(robot.q_lower, dtype=float), np.array(robot.q_upper, dtype=float))

    @property
    def size(self) -> int:
        return int(np.prod(self.cells))

    @property
    def n_joints(self) -> int:
        return len(self.cells)

    @property
    def step(self) -> np.ndarray:
        """Cell width per axis, rad (m for a prismatic joint)."""
        return (self.upper - self.lower) / np.array(self.cells)

    def axis_values(self, k: int) -> np.ndarray:
        """Joint values of axis k (0-based), rad or m: the cell centres."""
        return self.lower[k] + (np.arange(self.cells[k]) + 0.5) * self.step[k]

    def cell_indices(self, index) -> np.ndarray:
        """(n, N) integer cell indices of candidates."""
        return np.stack(np.unravel_index(np.asarray(index, dtype=np.int64), self.cells), axis=1)

    def q(self, index) -> np.ndarray:
        """(n, N) joint vectors of candidates, rad or m."""
        c = self.cell_indices(index)
        return self.lower + (c + 0.5) * self.step


def _axis_transforms(robot, grid: Grid, k: int):
    """Joint k's (0-based) transforms for each of its axis values: (R (m, 3, 3), offset (m, 3) or
    None): frame k+1 = parent · (R, t̄_{k+1} + offset). A revolute joint turns, R = R̄ Rz(q); a
    prismatic one slides, offset = R̄ e_z q."""
    v = grid.axis_values(k)
    Rn = robot.R_nominal[k + 1]
    if robot.joint_types[k] == "prismatic":
        return np.broadcast_to(Rn, (len(v), 3, 3)), v[:, None] * Rn[:, 2]
    return Rn @ rot_z(v), None


def _descend_level(robot, grid: Grid, R, t, k: int):
    """Frames k+1 (rotations (M·m, 3, 3), origins (M·m, 3)) for frames k given as R (M, 3, 3),
    t (M, 3) and each of joint k's (0-based) m axis values, the parent's rows slowest."""
    Rk, off = _axis_transforms(robot, grid, k)  # (m, 3, 3)
    tk = robot.t_nominal[k + 1]
    if off is None:
        # the origin of frame k+1 depends only on the parent; every child value shares it
        t = np.broadcast_to((t + R @ tk)[:, None, :], (R.shape[0], Rk.shape[0], 3)).reshape(-1, 3)
    else:
        t = ((t + R @ tk)[:, None, :] + np.einsum("pij,mj->pmi", R, off)).reshape(-1, 3)
    return (R[:, None] @ Rk[None]).reshape(-1, 3, 3), t


def _descend(robot, grid: Grid, levels: int):
    """Rotations (M, 3, 3) and origins (M, 3) of frame ``levels`` for every combination of the
    first ``levels`` joints' axis values (q1 slowest), built level by level: the pose of link k
    depends only on q1..qk, so each level multiplies the previous level's poses by the few
    transforms of one axis."""
    R = robot.R_nominal[0][None]
    t = robot.t_nominal[0][None]
    for k in range(levels):
        R, t = _descend_level(robot, grid, R, t, k)
    return R, t


#: most frame poses :func:`_descend_blocks` holds at once (about 100 B each)
DESCEND_ROWS = 1 << 18


def _descend_blocks(robot, grid: Grid, levels: int, max_rows: int = DESCEND_ROWS):
    """:func:`_descend` in consecutive blocks of at most ``max_rows`` poses (one block of more only
    when a single value of the first joint spans more): yields (R, t) of frame ``levels``, in
    order. Peak memory does not grow with the grid's size."""
    cells = grid.cells[:levels]
    top = 0  # the first joints built whole; each of their rows then spans prod(cells[top:]) poses
    while top < levels and int(np.prod(cells[top:], dtype=np.int64)) > max_rows:
        top += 1
    R0, t0 = _descend(robot, grid, top)
    group = max(1, max_rows // int(np.prod(cells[top:], dtype=np.int64)))
    for s in range(0, len(R0), group):
        R, t = R0[s : s + group], t0[s : s + group]
        for k in range(top, levels):
            R, t = _descend_level(robot, grid, R, t, k)
        yield R, t


def tool_frames(robot, grid: Grid):
    """Pose of F_E for every candidate, exploiting the grid's structure (:func:`_descend`).
    Returns R (size, 3, 3), t (size, 3) in candidate-index order."""
    N = robot.n_joints
    R, t = _descend(robot, grid, N)
    t = t + R @ robot.t_nominal[N + 1]
    R = R @ robot.R_nominal[N + 1]
    return R, t


def iter_tool_points(robot, grid: Grid, points_in_E, vectors_in_E, chunk: int = 4096):
    """Points and directions fixed in F_E, in F_I, for every candidate, block by block, without
    forming the candidates' 3×3 rotations: the poses of frame N-1 are built level by level as
    in :func:`tool_frames` (a fraction 1/cells_N of the grid's size), then, for ``chunk``
    frame-(N-1) poses at a time, the points and vectors moved by every value of q_N are mapped
    by one product.

    points_in_E (r, 3) m, vectors_in_E (s, 3). Yields (first candidate index, P (n, r, 3) m,
    V (n, s, 3)) for consecutive blocks of candidates, in candidate-index order."""
    points_in_E = np.asarray(points_in_E, dtype=float).reshape(-1, 3)
    vectors_in_E = np.asarray(vectors_in_E, dtype=float).reshape(-1, 3)
    N = robot.n_joints
    r, cN = len(points_in_E), grid.cells[N - 1]
    RE, tE = robot.R_nominal[N + 1], robot.t_nominal[N + 1]
    v = grid.axis_values(N - 1)
    prismatic = robot.joint_types[N - 1] == "prismatic"
    Z = np.broadcast_to(np.eye(3), (cN, 3, 3)) if prismatic else rot_z(v)  # (cN, 3, 3)
    # columns (q_N value, point) and (q_N value, vector), in frame N before its joint's motion
    ZP = np.einsum("qij,kj->iqk", Z, tE + points_in_E @ RE.T)
    if prismatic:
        ZP = ZP + np.einsum("i,q->iq", np.array([0.0, 0.0, 1.0]), v)[:, :, None]
    ZP = np.ascontiguousarray(ZP.reshape(3, -1))
    ZV = np.ascontiguousarray(np.einsum("qij,kj->iqk", Z, vectors_in_E @ RE.T).reshape(3, -1))
    first = 0  # frames N-1 so far
    for R, t in _descend_blocks(robot, grid, N - 1):  # frames N-1, block by block
        # p in F_E lies at t_N + R_{N-1} R̄_N (Z(q_N) (t̄_E + R̄_E p) + d(q_N)) in F_I; a vector v at
        # R_{N-1} R̄_N Z(q_N) R̄_E v (Z = Rz for a revolute last joint, d = q_N e_z for a prismatic one)
        tN = t + R @ robot.t_nominal[N]
        M = R @ robot.R_nominal[N]  # (m, 3, 3)
        for s in range(0, len(M), chunk):
            Mc, tc = M[s : s + chunk], tN[s : s + chunk]
            P = (np.einsum("mij,jc->mci", Mc, ZP).reshape(len(Mc), cN, r, 3) + tc[:, None, None, :]).reshape(-1, r, 3)
            V = np.ascontiguousarray(np.einsum("mij,jc->mci", Mc, ZV)).reshape(len(P), -1, 3)
            yield (first + s) * cN, P, V
        first += len(M)
