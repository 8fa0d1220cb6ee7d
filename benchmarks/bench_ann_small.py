"""Benchmark of the neural compensator on small campaigns: does it learn a hidden effect, and does it
say "no significant gain" when there is nothing to learn?

    OPENBLAS_NUM_THREADS=1 python benchmarks/bench_ann_small.py [--poses 60,120,300,600] [--seeds 3]
        [--sizes 4x4,8x8,16x16] [--folds 5] [--solver br-lm] [--reference] [--out FILE]

For each campaign size n, seed and truth (``effect``: every joint's compliance hidden at its typical
size, ~1 mm left after the geometric model; ``noise``: hidden geometric errors and 10 µm tracker
noise only): n training poses and 400 held-out poses from one truth, the geometric model fitted on
the training poses, then the network grid of `calibrate` (campaign.ann.grid.run_grid, one process,
one torch thread) on its residuals. Recorded: the chosen size, whether it was switched off, the
cross-validated held-out RMSE ratio with its 95 % interval, the held-out ratio on the 400 poses,
the mean position error against the truth (noise-free, read after the fit) with and without the
network, the final γ of N_w and epochs, wall and CPU seconds and the load average. ``--reference``:
also an independent trainer of the same (8, 8) net (torch.nn layers, L-BFGS, fixed weight decay
λ ∈ {0.3, 1, 3}, its best on the held-out poses) on the effect campaigns.

Runs against whichever `campaign` is on PYTHONPATH: on a tree before the fix (no campaign.ann.gain,
no switch-off) the held-out ratio is computed here the same way, so before and after compare.
Writes benchmarks/results/ann_small.json (or --out).
"""

from __future__ import annotations

import argparse
import json
import math
import os
import subprocess
import time
from pathlib import Path

import numpy as np
import torch

from campaign.ann.grid import run_grid
from campaign.ann.mlp import torch_threads
from campaign.effects import make_effect
from campaign.identify.solver import CalibrationModel
from campaign.model.kinematics import pose_error
from campaign.model.robot import RobotModel
from campaign.sim.truth import make_truth, random_joint_poses, synthesize

HELD_OUT = 400


def ratio(before, after, scale):
    """RMSE of the normalised residual with over without the network (campaign.ann.gain's measure)."""
    b = np.sum((before / scale) ** 2, axis=1)
    a = np.sum((after / scale) ** 2, axis=1)
    return float(math.sqrt(a.mean() / b.mean()))


def reference_ratio(x_tr, t_tr, x_te, t_te):
    """Best held-out ratio of an independent L-BFGS fit of an (8, 8) net over three weight decays."""
    best = np.inf
    for lam in (0.3, 1.0, 3.0):
        torch.manual_seed(0)
        net = torch.nn.Sequential(torch.nn.Linear(x_tr.shape[1], 8), torch.nn.Tanh(), torch.nn.Linear(8, 8),
                                  torch.nn.Tanh(), torch.nn.Linear(8, t_tr.shape[1])).double()
        opt = torch.optim.LBFGS(net.parameters(), lr=1, max_iter=300, history_size=20, tolerance_grad=1e-9,
                                tolerance_change=1e-12, line_search_fn="strong_wolfe")
        xt, tt = torch.as_tensor(x_tr), torch.as_tensor(t_tr)

        def closure():
            opt.zero_grad()
            loss = ((net(xt) - tt) ** 2).sum() + lam * sum((p ** 2).sum() for p in net.parameters())
            loss.backward()
            return loss
        opt.step(closure)
        with torch.no_grad():
            pred = net(torch.as_tensor(x_te)).numpy()
        best = min(best, ratio(t_te, t_te - pred, np.ones(t_te.shape[1])))
    return best


def one(robot, n, seed, kind, sizes, folds, solver, reference):
    effects = {}
    if kind == "effect":
        effects = {"joint_compliance": make_effect("joint_compliance", robot).typical_params(seed)}
    truth = make_truth(robot, seed=seed, effects=effects)
    meas = synthesize(truth, random_joint_poses(robot, n + HELD_OUT, seed=seed + 1), seed=seed + 2)
    tr = np.arange(n + HELD_OUT) < n
    te = ~tr
    geo = CalibrationModel(robot=robot).fit(meas.q[tr], meas.T_IE[tr])
    dz = geo.residuals(meas.q, meas.T_IE)
    load0 = os.getloadavg()
    t0, c0 = time.perf_counter(), time.process_time()
    fitted = run_grid(meas.q[tr], {"geometric": dz[tr]}, sizes=sizes, folds=folds, solver=solver, device="cpu",
                      q_lower=robot.q_lower, q_upper=robot.q_upper)
    wall, cpu = time.perf_counter() - t0, time.process_time() - c0
    net, cv = fitted["geometric"]
    scale = np.where(dz[tr].std(0) > 0, dz[tr].std(0), 1.0)
    pred = net.predict(meas.q[te])
    T_true = truth.pose_in_measured_frame(meas.q[te], meas.T_LI)  # the truth, read after the fit
    from campaign.ann import compensate_pose

    T_geo = geo.predict(meas.q[te])
    err_geo = pose_error(T_geo, T_true)
    err_ann = pose_error(compensate_pose(T_geo, pred), T_true)
    best = next(r for r in cv["sizes"] if r["hidden"] == cv["best"])
    fin = cv.get("final", {})
    row = {"poses": n, "seed": seed, "truth": kind, "solver": solver, "best": cv["best"],
           "switched_off": bool(getattr(net, "switched_off_", False)),
           "cv_ratio": best.get("heldout_gain", {}).get("ratio", None),
           "cv_ci95": best.get("heldout_gain", {}).get("ci95", None),
           "significant": best.get("heldout_gain", {}).get("significant", None),
           "cv_ratio_all_sizes": {f"{r['hidden'][0]}x{r['hidden'][1]}": (r.get("heldout_gain") or {}).get("ratio")
                                  for r in cv["sizes"]},
           "heldout_ratio": ratio(dz[te], dz[te] - pred, scale),
           "truth_mean_position_mm_geometric": float(np.linalg.norm(err_geo[:, :3], axis=1).mean() * 1e3),
           "truth_mean_position_mm_geometric_ann": float(np.linalg.norm(err_ann[:, :3], axis=1).mean() * 1e3),
           "gamma": fin.get("gamma"), "n_weights": int(net.net_.n_weights),
           "gamma_folds": best.get("gamma_folds"), "epochs_final": fin.get("epochs"), "epochs_folds": best["epochs"],
           "stop": fin.get("stop"), "wall_s": wall, "cpu_s": cpu, "load_before": load0, "load_after": os.getloadavg()}
    if reference and kind == "effect":
        x = net.input_mapping_.apply(meas.q)
        with torch_threads(1):
            row["reference_lbfgs_8x8_ratio"] = reference_ratio(x[tr], dz[tr] / scale, x[te], dz[te] / scale)
    return row


def main():
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--poses", default="60,120,300,600")
    ap.add_argument("--seeds", type=int, default=3)
    ap.add_argument("--sizes", default="4x4,8x8,16x16")
    ap.add_argument("--folds", type=int, default=5)
    ap.add_argument("--solver", default="br-lm", choices=("br-lm", "adam"))
    ap.add_argument("--reference", action="store_true")
    ap.add_argument("--out", default=str(Path(__file__).parent / "results" / "ann_small.json"))
    args = ap.parse_args()
    sizes = [tuple(int(v) for v in s.split("x")) for s in args.sizes.split(",")]
    robot = RobotModel.load()
    torch.set_num_threads(1)
    rows = []
    try:
        commit = subprocess.run(["git", "rev-parse", "--short", "HEAD"], capture_output=True, text=True,
                                cwd=Path(__file__).parent).stdout.strip()
    except OSError:
        commit = None
    for n in (int(v) for v in args.poses.split(",")):
        for seed in range(args.seeds):
            for kind in ("effect", "noise"):
                row = one(robot, n, seed, kind, sizes, args.folds, args.solver, args.reference)
                rows.append(row)
                print(f"{n:4d} poses seed {seed} {kind:6s}: best {row['best']} "
                      f"{'OFF' if row['switched_off'] else 'on '} cv {row['cv_ratio'] or float('nan'):.3f} "
                      f"held-out {row['heldout_ratio']:.3f} truth {row['truth_mean_position_mm_geometric']:.4f} -> "
                      f"{row['truth_mean_position_mm_geometric_ann']:.4f} mm, γ {row['gamma']} of {row['n_weights']}, "
                      f"ref {row.get('reference_lbfgs_8x8_ratio', float('nan')):.3f}, {row['wall_s']:.1f} s wall "
                      f"{row['cpu_s']:.1f} s cpu, load {row['load_before'][0]:.1f}", flush=True)
                Path(args.out).parent.mkdir(parents=True, exist_ok=True)
                Path(args.out).write_text(json.dumps({"commit": commit, "args": vars(args), "held_out_poses": HELD_OUT,
                                                      "rows": rows}, indent=1))


if __name__ == "__main__":
    main()
