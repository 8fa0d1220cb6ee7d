"""The plan's files: RUN/plan/poses.csv, vias.csv, dropped.csv (DESIGN.md, "Files that cross
the boundary"), each written atomically."""

from __future__ import annotations

from campaign.fileio import atomic_write


def _rows(rows) -> str:
    return "\n".join(rows) + "\n"


def write_tour(out, order, Q, vias, dropped) -> None:
    """poses.csv (``pose_id,q1..qN``, rad or m, visiting order), vias.csv (``before_pose_id,q1..qN``:
    postures passed before that pose) and dropped.csv (``pose_id,reason``) in the folder ``out``.
    Q (n, N)."""
    joints = ",".join(f"q{j + 1}" for j in range(Q.shape[1]))
    poses = [f"pose_id,{joints}"]
    poses += [f"{int(p)}," + ",".join(repr(float(v)) for v in q) for p, q in zip(order, Q)]
    atomic_write(out / "poses.csv", _rows(poses))
    vl = [f"before_pose_id,{joints}"]
    for pid in order:
        for v in vias.get(int(pid), []):
            vl.append(f"{int(pid)}," + ",".join(repr(float(x)) for x in v))
    atomic_write(out / "vias.csv", _rows(vl))
    atomic_write(out / "dropped.csv", _rows(["pose_id,reason"] + [f"{p},{r}" for p, r in dropped]))
