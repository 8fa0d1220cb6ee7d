"""A plain identification script: the yardstick of `campaign calibrate`'s wall time (issue 22).

    python benchmarks/plain_identify.py MEASURED.csv [--urdf URDF] [--tool-frame E]

What a user would write with numpy and scipy alone, no `campaign` import: read the measured-pose
CSV (pose_id,time_s,q1..q6,x,y,z,rx,ry,rz; m, rad), read the serial chain from the URDF with the
standard library, give every transform of the chain 6 error parameters (a translation and a
Cardan x-y-z rotation after the nominal origin, 48 for a 6R arm), keep the identifiable ones
(QR with column pivoting of the Jacobian at zero), Gauss-Newton on them from zero with an
analytic Jacobian (the error's twist carried to the tool), on the same 80/20 split as `campaign`
(splitmix64 of pose_id ^ 20200101 < 0.2), and print the held-out mean position error and the
wall time. Same data, same model class, same accuracy as `campaign calibrate --no-ann`.
"""

from __future__ import annotations

import argparse
import time
import xml.etree.ElementTree as ET
from pathlib import Path

T_START = time.perf_counter()

import numpy as np  # noqa: E402
from scipy.linalg import qr  # noqa: E402
from scipy.spatial.transform import Rotation  # noqa: E402

DEFAULT_URDF = Path(__file__).resolve().parents[1] / "campaign" / "data" / "robot_models" / "comau_racer5_080" / \
    "robot.urdf"


def chain(urdf, tool):
    """[(origin (4, 4), moving)] from the root to ``tool`` (URDF rpy: Rz(y) Ry(p) Rx(r); z axes)."""
    joints = {j.find("child").get("link"): j for j in ET.parse(urdf).getroot().iter("joint")}
    out, link = [], tool
    while link in joints:
        j = joints[link]
        o = j.find("origin")
        T = np.eye(4)
        if o is not None:
            T[:3, :3] = Rotation.from_euler("xyz", [float(v) for v in o.get("rpy", "0 0 0").split()]).as_matrix()
            T[:3, 3] = [float(v) for v in o.get("xyz", "0 0 0").split()]
        out.append((T, j.get("type") != "fixed"))
        link = j.find("parent").get("link")
    return out[::-1]


def split_is_test(pose_id, seed=20200101, fraction=0.2):
    z = np.asarray(pose_id, dtype=np.uint64) ^ np.uint64(seed)
    with np.errstate(over="ignore"):
        z = z + np.uint64(0x9E3779B97F4A7C15)
        z = (z ^ (z >> np.uint64(30))) * np.uint64(0xBF58476D1CE4E5B9)
        z = (z ^ (z >> np.uint64(27))) * np.uint64(0x94D049BB133111EB)
        z = z ^ (z >> np.uint64(31))
    return (z >> np.uint64(11)).astype(np.float64) / float(1 << 53) < fraction


def transforms(links, q, p):
    """Per link k: origin · Trans(p_k[:3]) · Rx Ry Rz(p_k[3:]) · Rz(q_j) for a moving joint, (n, 4, 4) each."""
    n = len(q)
    out, j = [], 0
    for k, (O, moving) in enumerate(links):
        E = np.eye(4)
        E[:3, :3] = Rotation.from_euler("XYZ", p[6 * k + 3 : 6 * k + 6]).as_matrix()
        E[:3, 3] = p[6 * k : 6 * k + 3]
        T = np.broadcast_to(O @ E, (n, 4, 4)).copy()
        if moving:
            c, s = np.cos(q[:, j]), np.sin(q[:, j])
            Rz = np.zeros((n, 4, 4))
            Rz[:, 0, 0], Rz[:, 0, 1], Rz[:, 1, 0], Rz[:, 1, 1], Rz[:, 2, 2], Rz[:, 3, 3] = c, -s, s, c, 1, 1
            T = T @ Rz
            j += 1
        out.append(T)
    return out


def model(links, q, p):
    """Tool poses (n, 4, 4) and the Jacobian (n, 6, 6K) of [position; rotation] w.r.t. p."""
    Ts = transforms(links, q, p)
    n, K = len(q), len(links)
    W = np.broadcast_to(np.eye(4), (n, 4, 4)).copy()
    frames = []  # the frame right after link k's error transform (before its joint), in the base
    for k, (O, moving) in enumerate(links):
        E = np.eye(4)
        E[:3, :3] = Rotation.from_euler("XYZ", p[6 * k + 3 : 6 * k + 6]).as_matrix()
        E[:3, 3] = p[6 * k : 6 * k + 3]
        frames.append(W @ O @ E)
        W = W @ Ts[k]
    tool = W[:, :3, 3]
    J = np.empty((n, 6, 6 * K))
    for k, F in enumerate(frames):
        R, o = F[:, :3, :3], F[:, :3, 3]
        lever = tool - o
        for a in range(3):  # translation along the frame's axis a, rotation about it
            ax = R[:, :, a]
            J[:, :3, 6 * k + a] = ax
            J[:, 3:, 6 * k + a] = 0.0
            J[:, :3, 6 * k + 3 + a] = np.cross(ax, lever)
            J[:, 3:, 6 * k + 3 + a] = ax
    return W, J


def pose_error(T_meas, T_model):
    dt = T_meas[:, :3, 3] - T_model[:, :3, 3]
    dR = np.einsum("nij,nkj->nik", T_meas[:, :3, :3], T_model[:, :3, :3])
    return np.concatenate([dt, Rotation.from_matrix(dR).as_rotvec()], axis=1)


def main():
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("csv")
    ap.add_argument("--urdf", default=str(DEFAULT_URDF))
    ap.add_argument("--tool-frame", default="E")
    args = ap.parse_args()
    data = np.loadtxt(args.csv, delimiter=",", skiprows=1)
    pose_id, q, xyz, rv = data[:, 0].astype(np.int64), data[:, 2:8], data[:, 8:11], data[:, 11:14]
    T_meas = np.broadcast_to(np.eye(4), (len(q), 4, 4)).copy()
    T_meas[:, :3, :3], T_meas[:, :3, 3] = Rotation.from_rotvec(rv).as_matrix(), xyz
    links = chain(args.urdf, args.tool_frame)
    test = split_is_test(pose_id)
    tr = ~test
    w = np.array([1, 1, 1, 0.1, 0.1, 0.1])  # m and 0.1 m per rad: both rows in metres at the tool

    p = np.zeros(6 * len(links))
    _, J0 = model(links, q[tr][:2000], p)
    A = (J0 * w[None, :, None]).reshape(-1, len(p))
    _, Rq, piv = qr(A, mode="economic", pivoting=True)
    d = np.abs(np.diag(Rq))
    keep = np.sort(piv[: int(np.sum(d > 1e-8 * d[0]))])  # the identifiable parameters
    for it in range(20):
        T, J = model(links, q[tr], p)
        r = (pose_error(T_meas[tr], T) * w).reshape(-1)
        A = (J[:, :, keep] * w[None, :, None]).reshape(-1, len(keep))
        step = np.linalg.lstsq(A, r, rcond=None)[0]
        p[keep] += step
        if np.max(np.abs(step)) < 1e-12:
            break
    T, _ = model(links, q[test], p)
    e = np.linalg.norm(pose_error(T_meas[test], T)[:, :3], axis=1) * 1e3
    T0, _ = model(links, q[test], np.zeros_like(p))
    e0 = np.linalg.norm(pose_error(T_meas[test], T0)[:, :3], axis=1) * 1e3
    print(f"{len(keep)} parameters identified in {it + 1} iterations on {int(tr.sum())} poses; held-out mean "
          f"position error {e0.mean():.3f} -> {e.mean():.4f} mm (max {e.max():.4f}, q90 {np.quantile(e, 0.9):.4f}); "
          f"wall {time.perf_counter() - T_START:.2f} s")


if __name__ == "__main__":
    main()
