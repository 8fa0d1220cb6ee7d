"""Measured poses: the data object that crosses from `run`/`import` to `calibrate`."""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from campaign.model.rotations import matrix_to_rotvec, rotvec_to_matrix

#: pose ids are SQLite INTEGERs (int64) and are read from CSVs as float64: exact below 2**53
MAX_STORED_POSE_ID = 2**53
#: Columns of the measured-pose CSV (DESIGN.md), in order.
CSV_COLUMNS = ("pose_id", "time_s", "q1", "q2", "q3", "q4", "q5", "q6", "x", "y", "z", "rx", "ry", "rz")


@dataclass(frozen=True)
class MeasuredPoses:
    """n measured poses.

    pose_id: (n,) int; time_s: (n,) s since campaign start (NaN when not measured); q: (n, N)
    commanded joint coordinates, rad (m for prismatic joints); T_IE: (n, 4, 4) measured pose of
    F_E in F_I (or, with ``frame`` "tracker", in the tracker's frame), m; context: extra named
    per-pose values (e.g. ``temperature_c``), each (n,).

    ``kind``: "pose" (6-D), "point" (one reflector: only T_IE's translation is measured, its
    rotation is the identity and means nothing) or "markers" (raw reflector centres
    ``markers`` (n, k, 3), NaN where missed, nominal positions ``marker_positions`` (k, 3) in
    the tool frame; T_IE is their rigid fit, NaN where fewer than three were seen).
    """

    pose_id: np.ndarray
    time_s: np.ndarray
    q: np.ndarray
    T_IE: np.ndarray
    context: dict = field(default_factory=dict)
    #: pose of F_I in F_L used to derive T_IE (from the set-up points), if known
    T_LI: np.ndarray | None = None
    kind: str = "pose"
    frame: str = "robot"
    markers: np.ndarray | None = None
    marker_positions: np.ndarray | None = None

    @property
    def has_orientation(self) -> bool:
        """Whether orientations were measured (6-D poses or reflector sets)."""
        return self.kind != "point"

    def __len__(self) -> int:
        return int(self.pose_id.shape[0])

    @classmethod
    def from_vectors(cls, pose_id, time_s, q, xyz, rotvec, context=None, **kw) -> "MeasuredPoses":
        n = len(pose_id)
        T = np.zeros((n, 4, 4))
        rv = np.asarray(rotvec, dtype=float).reshape(n, 3)
        T[:, :3, :3] = rotvec_to_matrix(np.nan_to_num(rv))
        T[np.isnan(rv).any(axis=1), :3, :3] = np.nan if kw.get("kind") == "markers" else np.eye(3)
        T[:, :3, 3] = np.asarray(xyz, dtype=float).reshape(n, 3)
        T[:, 3, 3] = 1.0
        return cls(np.asarray(pose_id, dtype=np.int64), np.asarray(time_s, dtype=float),
                   np.asarray(q, dtype=float).reshape(n, -1), T,
                   {k: np.asarray(v) for k, v in (context or {}).items()}, **kw)

    @property
    def xyz(self) -> np.ndarray:
        return self.T_IE[:, :3, 3]

    @property
    def rotvec(self) -> np.ndarray:
        """(n, 3) rad; NaN where no orientation was derived."""
        R = self.T_IE[:, :3, :3]
        ok = np.isfinite(R).all(axis=(1, 2))
        if ok.all():
            return matrix_to_rotvec(R)
        out = np.full((len(R), 3), np.nan)
        out[ok] = matrix_to_rotvec(R[ok])
        return out

    def subset(self, index) -> "MeasuredPoses":
        index = np.asarray(index)
        return MeasuredPoses(self.pose_id[index], self.time_s[index], self.q[index], self.T_IE[index],
                             {k: v[index] for k, v in self.context.items()}, self.T_LI, self.kind, self.frame,
                             None if self.markers is None else self.markers[index], self.marker_positions)
