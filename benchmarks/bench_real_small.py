"""Real small campaigns checked from outside (issue 24): `campaign calibrate --model lsq|map|auto`
against an independent fit on the same training and test poses.

    OPENBLAS_NUM_THREADS=1 python benchmarks/bench_real_small.py DATASET=CSV [DATASET=CSV ...]
        [--work DIR] [--ridge 1e-3] [--splits 30] [--out benchmarks/results/real_small.json]

DATASET is one of the presets below (the public files are not in this repository; pass their
paths): ``tiago`` is FIGAROH's TIAGo mocap file
(figaroh-examples examples/tiago/data/calibration/mocap/qualysis_base_hand_calibration.csv: a
Qualysis marker on the hand, x1,y1,z1 in the mocap frame, the torso's prismatic joint and 7 arm
joints); ``ur10`` is FIGAROH's UR10 file (examples/ur10/data/calibration.csv: positions and
roll-pitch-yaw of the flange). For each, as a user would: a copy with a ``pose_id`` column,
``campaign import`` and ``campaign calibrate RUN --no-ann --model M`` for M in lsq, map, auto;
the test poses from metrics.json's ``test_pose_ids``; then the independent fit on the other poses.
``--splits K``: also K random splits of the same sizes (seeded), each given to `calibrate` as the
run's validation poses (RUN/plan/validation.csv), for lsq and auto against the independent fit:
one split's 5-7 test poses scatter by more than the models differ.

The independent fit uses none of campaign's kinematics: Pinocchio reads the URDF and computes the
forward kinematics of a redundant model, every joint's placement perturbed by a 6-D twist
(``M_j exp6(δ_j)``), every joint's zero offset, the measured point in the tool frame (positions),
or a 6-D tool twist (poses), and the tracker's pose; a tiny ridge on the robot's parameters
(``--ridge``: rows ``ridge · p`` beside residuals in m) and scipy's trust-region least squares,
started at a rigid registration of the nominal model.
"""

from __future__ import annotations

import argparse
import csv
import json
import os
import subprocess
import sys
import tempfile
import time
from dataclasses import dataclass
from importlib import metadata
from pathlib import Path

import numpy as np
import pinocchio as pin
from scipy.optimize import least_squares

ERD = "cmeel.prefix/share/example-robot-data/robots"


@dataclass(frozen=True)
class Preset:
    robot: str                  # campaign's name
    urdf: str                   # example-robot-data's path
    tool_frame: str
    joints: tuple[str, ...]     # the file's joint columns, in chain order
    point: tuple[str, str, str]
    rpy: tuple[str, str, str] | None  # orientation columns (roll, pitch, yaw about fixed axes)
    import_args: tuple[str, ...]


PRESETS = {
    "tiago": Preset("tiago", "tiago_description/robots/tiago.urdf", "arm_tool_link",
                    ("torso_lift_joint",) + tuple(f"arm_{i}_joint" for i in range(1, 8)),
                    ("x1", "y1", "z1"), None, ("--frame", "tracker", "--limit-slack", "1")),
    "ur10": Preset("ur10", "ur_description/urdf/ur10_robot.urdf", "tool0",
                   ("shoulder_pan_joint", "shoulder_lift_joint", "elbow_joint", "wrist_1_joint",
                    "wrist_2_joint", "wrist_3_joint"),
                   ("x1", "y1", "z1"), ("phix1", "phiy1", "phiz1"), ("--frame", "tracker", "--rotation", "rpy")),
}


def read_table(path):
    with open(path, newline="") as f:
        rows = list(csv.reader(f))
    header = [h.strip() for h in rows[0]]
    return header, np.array([[float(v) for v in r] for r in rows[1:] if r], dtype=float)


def write_with_ids(src, dst):
    """The file as it is, with a pose_id column (0, 1, ...) in front."""
    header, values = read_table(src)
    with open(dst, "w", newline="") as f:
        w = csv.writer(f)
        w.writerow(["pose_id", *header])
        for i, r in enumerate(values):
            w.writerow([i, *(repr(float(v)) for v in r)])
    return header, values


def import_run(preset, csv_path, run):
    cols = [f"q{i + 1}={j}" for i, j in enumerate(preset.joints)]
    cols += [f"{a}={c}" for a, c in zip("xyz", preset.point)]
    if preset.rpy:
        cols += [f"{a}={c}" for a, c in zip(("rx", "ry", "rz"), preset.rpy)]
    subprocess.run(["campaign", "import", str(csv_path), "--run", str(run), "--robot", preset.robot,
                    "--columns", ",".join(cols), "--quiet", *preset.import_args], check=True,
                   capture_output=True, text=True)


def run_campaign(preset, csv_path, work, model, test_ids=None):
    """Import and calibrate with --model ``model``; ``test_ids``: the validation poses (else the
    run's own 80/20 split). Returns (held-out figures, the test pose ids)."""
    run = Path(work) / f"{preset.robot}_{model}"
    run.parent.mkdir(parents=True, exist_ok=True)
    import_run(preset, csv_path, run)
    if test_ids is not None:
        (run / "plan").mkdir(exist_ok=True)
        (run / "plan" / "validation.csv").write_text("pose_id\n" + "".join(f"{i}\n" for i in test_ids))
    env = {**os.environ}
    t0 = time.perf_counter()
    subprocess.run(["campaign", "calibrate", str(run), "--no-ann", "--no-report", "--quiet", "--model", model],
                   check=True, env=env, capture_output=True, text=True)
    wall = time.perf_counter() - t0
    m = json.loads((run / "calibration" / "metrics.json").read_text())
    test = m["stages"]["geometric"]["test"]
    return {"heldout_mean_mm": test["position_mm"]["mean"], "heldout_max_mm": test["position_mm"]["max"],
            "train_poses": m["stages"]["geometric"]["train"]["n_poses"], "test_poses": test["n_poses"],
            "choice": m["model"]["choice"], "strength": m["model"]["strength"], "reason": m["model"]["reason"],
            "calibrate_s": wall}, m["test_pose_ids"]


class RedundantChain:
    """Pinocchio's model of the chain from the URDF root to ``tool_frame``, with its parameters
    p = [δ_j (6 per chain joint: translation, rotation vector of exp6), dq_j (per chain joint),
    tool (3: the point in the tool frame; or 6: a twist of the tool frame), tracker (6: twist of
    the tracker-from-root pose, left of its start)]."""

    def __init__(self, urdf, tool_frame, joint_names, pose):
        self.model = pin.buildModelFromUrdf(urdf)
        self.data = self.model.createData()
        self.fid = self.model.getFrameId(tool_frame)
        self.jids = [self.model.getJointId(n) for n in joint_names]
        self.nominal = [pin.SE3(self.model.jointPlacements[j]) for j in self.jids]
        self.pose = pose
        self.n_robot = 7 * len(self.jids) + (6 if pose else 3)
        self.T0 = pin.SE3.Identity()

    def tool_poses(self, p, q):
        """Poses of the tool frame (SE3 list) in the URDF root for joint readings q (n, k)."""
        k = len(self.jids)
        for i, j in enumerate(self.jids):
            self.model.jointPlacements[j] = self.nominal[i] * pin.exp6(p[6 * i:6 * i + 6])
        dq = p[6 * k:7 * k]
        out = []
        qfull = pin.neutral(self.model)
        for row in q:
            for i, j in enumerate(self.jids):
                qfull[self.model.joints[j].idx_q] = row[i] + dq[i]
            pin.framesForwardKinematics(self.model, self.data, qfull)
            out.append(pin.SE3(self.data.oMf[self.fid]))
        for i, j in enumerate(self.jids):
            self.model.jointPlacements[j] = self.nominal[i]
        return out

    def predict(self, p, q):
        """(n, 3) points, or (n, 6) position and rotation vector, in the tracker's frame."""
        tool = p[7 * len(self.jids):self.n_robot]
        T = pin.exp6(p[self.n_robot:self.n_robot + 6]) * self.T0
        rows = []
        for M in self.tool_poses(p, q):
            if self.pose:
                X = T * M * pin.exp6(tool)
                rows.append(np.concatenate([X.translation, pin.log3(X.rotation)]))
            else:
                rows.append((T * M).act(tool))
        return np.array(rows)

    def residuals(self, p, q, y, rot_weight_m):
        pred = self.predict(p, q)
        r = pred[:, :3] - y[:, :3]
        if not self.pose:
            return r.ravel()
        rot = np.array([pin.log3(pin.exp3(a).T @ pin.exp3(b)) for a, b in zip(y[:, 3:], pred[:, 3:])])
        return np.hstack([r, rot_weight_m * rot]).ravel()


def kabsch(A, B):
    """SE3 T minimising ‖T·A − B‖ (rows are points)."""
    ca, cb = A.mean(0), B.mean(0)
    U, _, Vt = np.linalg.svd((A - ca).T @ (B - cb))
    D = np.diag([1, 1, np.sign(np.linalg.det(Vt.T @ U.T))])
    R = Vt.T @ D @ U.T
    return pin.SE3(R, cb - R @ ca)


def independent_fit(urdf, preset, q, y, train, ridge, rot_weight_m=0.1):
    chain = RedundantChain(urdf, preset.tool_frame, preset.joints, pose=preset.rpy is not None)
    p = np.zeros(chain.n_robot + 6)
    M = chain.tool_poses(p, q[train])
    chain.T0 = kabsch(np.array([m.translation for m in M]), y[train, :3])
    n_rob = chain.n_robot
    # first the measured point (or tool) and the tracker alone, then everything
    free0 = np.zeros(p.size, bool)
    free0[7 * len(chain.jids):] = True

    def fun(x, free):
        pp = p.copy()
        pp[free] = x
        r = chain.residuals(pp, q[train], y[train], rot_weight_m)
        return np.concatenate([r, ridge * pp[:n_rob]])

    sol = least_squares(fun, p[free0], args=(free0,), method="trf", x_scale="jac")
    p[free0] = sol.x
    free = np.ones(p.size, bool)
    sol = least_squares(fun, p, args=(free,), method="trf", x_scale="jac", max_nfev=2000)
    p = sol.x
    return chain, p


def evaluate(chain, p, q, y):
    e = np.linalg.norm(chain.predict(p, q)[:, :3] - y[:, :3], axis=1) * 1e3
    return {"heldout_mean_mm": float(e.mean()), "heldout_max_mm": float(e.max())}


def random_splits(work, preset, dst, urdf, q, y, n_test, k, ridge, rot_weight_m):
    """k random splits (seed 0) with n_test test poses: lsq and auto against the independent fit."""
    rng = np.random.default_rng(0)
    rows = []
    for i in range(k):
        ids = sorted(int(v) for v in rng.choice(len(q), n_test, replace=False))
        test = np.isin(np.arange(len(q)), ids)
        row = {"test_pose_ids": ids}
        for model in ("lsq", "auto"):
            out, got = run_campaign(preset, dst, Path(work) / f"split{i}", model, ids)
            assert got == ids, (got, ids)
            row[model] = {k: out[k] for k in ("heldout_mean_mm", "heldout_max_mm", "choice", "strength")}
        chain, p = independent_fit(urdf, preset, q, y, ~test, ridge, rot_weight_m)
        row["independent"] = evaluate(chain, p, q[test], y[test])
        rows.append(row)
    ratio = np.array([r["auto"]["heldout_mean_mm"] / r["independent"]["heldout_mean_mm"] for r in rows])
    lsq = np.array([r["lsq"]["heldout_mean_mm"] / r["independent"]["heldout_mean_mm"] for r in rows])
    return {"splits": k, "auto_over_independent_mean": float(ratio.mean()),
            "auto_over_independent_worst": float(ratio.max()),
            "auto_more_than_2pct_behind": int((ratio > 1.02).sum()),
            "lsq_over_independent_mean": float(lsq.mean()), "cases": rows}


def run_dataset(name, src, work, ridges, splits=0, rot_weight_m=0.1):
    preset = PRESETS[name]
    dst = Path(work) / f"{name}.csv"
    header, values = write_with_ids(src, dst)
    ours, test_ids = {}, None
    for model in ("lsq", "map", "auto"):
        ours[model], ids = run_campaign(preset, dst, work, model)
        assert test_ids is None or ids == test_ids
        test_ids = ids
    col = {h: i for i, h in enumerate(header)}
    q = values[:, [col[j] for j in preset.joints]]
    y = values[:, [col[c] for c in preset.point]]
    if preset.rpy:
        R = [pin.rpy.rpyToMatrix(*r) for r in values[:, [col[c] for c in preset.rpy]]]
        y = np.hstack([y, np.array([pin.log3(r) for r in R])])
    test = np.isin(np.arange(len(values)), test_ids)
    urdf = str(metadata.distribution("example-robot-data").locate_file(f"{ERD}/{preset.urdf}"))
    indep = {}
    for ridge in ridges:
        t0 = time.perf_counter()
        chain, p = independent_fit(urdf, preset, q, y, ~test, ridge, rot_weight_m)
        indep[f"{ridge:g}"] = {**evaluate(chain, p, q[test], y[test]), **{"train_" + k[8:]: v for k, v in
                               evaluate(chain, p, q[~test], y[~test]).items()}, "fit_s": time.perf_counter() - t0}
    out = {"dataset": name, "file": str(src), "poses": len(values), "train_poses": int((~test).sum()),
           "test_poses": int(test.sum()), "test_pose_ids": test_ids, "ours": ours, "independent": indep}
    if splits:
        out["random_splits"] = random_splits(work, preset, dst, urdf, q, y, int(test.sum()), splits, ridges[0],
                                             rot_weight_m)
    return out


def main():
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("datasets", nargs="+", help="NAME=CSV, NAME one of " + ", ".join(PRESETS))
    ap.add_argument("--work", help="folder for the runs (default: a temporary one)")
    ap.add_argument("--ridge", default="1e-3", help="the independent fit's ridge weights, comma-separated")
    ap.add_argument("--splits", type=int, default=0, help="also this many random splits (lsq, auto)")
    ap.add_argument("--rot-weight-m", type=float, default=0.1,
                    help="6-D data: the independent fit's weight of orientation rows, m per rad")
    ap.add_argument("--out", default=str(Path(__file__).parent / "results" / "real_small.json"))
    args = ap.parse_args()
    ridges = [float(v) for v in args.ridge.split(",")]
    results = []
    with tempfile.TemporaryDirectory() as tmp:
        work = Path(args.work or tmp)
        for spec in args.datasets:
            name, _, path = spec.partition("=")
            if name not in PRESETS or not path:
                sys.exit(f"{spec}: expected NAME=CSV with NAME one of {', '.join(PRESETS)}")
            (work / name).mkdir(parents=True, exist_ok=True)
            r = run_dataset(name, path, work / name, ridges, args.splits, args.rot_weight_m)
            results.append(r)
            for k, v in r["ours"].items():
                print(f"{name:6s} ours {k:4s} ({v['choice']}, s={v['strength']}): mean {v['heldout_mean_mm']:.3f} max "
                      f"{v['heldout_max_mm']:.3f} mm ({r['train_poses']} train / {r['test_poses']} test)")
            for k, v in r["independent"].items():
                print(f"{name:6s} independent ridge {k}: mean {v['heldout_mean_mm']:.3f} max {v['heldout_max_mm']:.3f} mm "
                      f"(train mean {v['train_mean_mm']:.3f})")
            if "random_splits" in r:
                rs = r["random_splits"]
                print(f"{name:6s} {rs['splits']} random splits: auto / independent mean {rs['auto_over_independent_mean']:.3f}, "
                      f"worst {rs['auto_over_independent_worst']:.3f}, {rs['auto_more_than_2pct_behind']} more than 2 % "
                      f"behind; lsq / independent mean {rs['lsq_over_independent_mean']:.3f}", flush=True)
    first = f"{ridges[0]:g}"
    headline = {f"{r['dataset']}_auto_over_independent": r["ours"]["auto"]["heldout_mean_mm"]
                / r["independent"][first]["heldout_mean_mm"] for r in results}
    headline.update({f"{r['dataset']}_splits_auto_over_independent_mean": r["random_splits"]["auto_over_independent_mean"]
                     for r in results if "random_splits" in r})
    Path(args.out).write_text(json.dumps({"description": __doc__.splitlines()[0], **headline,
                                          "rot_weight_m": args.rot_weight_m, "results": results,
                                          "load_average": list(os.getloadavg())}, indent=2))
    print(f"written {args.out}")


if __name__ == "__main__":
    main()
