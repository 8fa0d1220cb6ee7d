"""A plain baseline for the neural stage (issue 15): a tanh MLP 6-64-32-6 trained with Adam on
the residuals of the geometric model, early stopping on a validation share of the training set.

    nice -n 5 python benchmarks/bench_baseline.py [--case compliance+cyclic|compliance-0.5mm]
              [--poses 14000] [--runs 2] [--threads 1]

Independent of campaign.ann on purpose: torch.nn layers, torch.optim.Adam, mini-batches, the
textbook recipe. Same data as bench_calibrate (benchmarks/campaign_data.py, same seeds), same
80/20 split and geometric model as `campaign calibrate` (its stage ``geometric``), so the test
statistics compare one to one with bench_calibrate's ``geometric+ann``. Inputs: q mapped to
mean 0 / variance 1 over the joint limits; targets standardised on the fitting share.
Writes benchmarks/results/baseline.json (one entry per case).
"""

from __future__ import annotations

import argparse
import json
import math
import os
import resource
import shutil
import sys
import tempfile
import time
from pathlib import Path

import numpy as np
import torch

sys.path.insert(0, str(Path(__file__).parent))
from campaign_data import CASES, make_run  # noqa: E402

from campaign.identify.calibrate import calibrate  # noqa: E402
from campaign.identify.metrics import error_stats  # noqa: E402
from campaign.model.rotations import rotvec_to_matrix  # noqa: E402

RESULTS = Path(__file__).parent / "results" / "baseline.json"


def train_baseline(q_fit, y_fit, q_val, y_val, *, seed, lr=1e-3, batch=128, max_epochs=2000, patience=100,
                   time_budget_s=None):
    """Adam on mini-batches, best validation weights kept; returns (model, info)."""
    torch.manual_seed(seed)
    model = torch.nn.Sequential(torch.nn.Linear(6, 64), torch.nn.Tanh(), torch.nn.Linear(64, 32), torch.nn.Tanh(),
                                torch.nn.Linear(32, 6)).double()
    opt = torch.optim.Adam(model.parameters(), lr=lr)
    xf, yf = torch.as_tensor(q_fit), torch.as_tensor(y_fit)
    xv, yv = torch.as_tensor(q_val), torch.as_tensor(y_val)
    gen = torch.Generator().manual_seed(seed)
    best, best_state, best_epoch, epoch = math.inf, None, 0, 0
    t0 = time.perf_counter()
    for epoch in range(1, max_epochs + 1):
        perm = torch.randperm(len(xf), generator=gen)
        for i in range(0, len(xf), batch):
            idx = perm[i:i + batch]
            opt.zero_grad()
            loss = torch.mean((model(xf[idx]) - yf[idx]) ** 2)
            loss.backward()
            opt.step()
        with torch.no_grad():
            val = float(torch.mean((model(xv) - yv) ** 2))
        if val < best:
            best, best_epoch = val, epoch
            best_state = {k: v.clone() for k, v in model.state_dict().items()}
        if epoch - best_epoch >= patience:
            break
        if time_budget_s is not None and time.perf_counter() - t0 > time_budget_s:
            break
    model.load_state_dict(best_state)
    return model, {"epochs": epoch, "best_epoch": best_epoch, "val_mse_normalised": best,
                   "wall_s": time.perf_counter() - t0}


def main():
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--case", default="compliance+cyclic", choices=CASES)
    ap.add_argument("--poses", type=int, default=14000)
    ap.add_argument("--runs", type=int, default=2, help="trainings with different seeds")
    ap.add_argument("--val-share", type=float, default=0.15)
    ap.add_argument("--patience", type=int, default=100)
    ap.add_argument("--max-epochs", type=int, default=2000)
    ap.add_argument("--time-budget", type=float, default=None, help="seconds per training at most")
    ap.add_argument("--threads", type=int, default=1)
    ap.add_argument("--seed", type=int, default=0, help="data seed (as bench_calibrate)")
    args = ap.parse_args()
    torch.set_num_threads(args.threads)
    folder = Path(tempfile.mkdtemp(prefix="bench_baseline_"))
    try:
        run, hidden = make_run(folder, args.case, args.poses, args.seed)
        res = calibrate(run, effects=(), ann=False, write=False)
        from campaign.measure.store import open_run

        with open_run(run) as store:
            poses = store.load_measured()
    finally:
        shutil.rmtree(folder, ignore_errors=True)
    robot = res.model.robot
    te = res.is_test
    tr = ~te
    dz = res.model.residuals(poses.q, poses.T_IE)
    lo, hi = robot.q_lower, robot.q_upper
    x = (poses.q - 0.5 * (lo + hi)) / ((hi - lo) / math.sqrt(12.0))
    idx_tr = np.flatnonzero(tr)
    runs = []
    for r in range(args.runs):
        rng = np.random.default_rng(1000 + r)
        val = np.zeros(len(idx_tr), bool)
        val[rng.permutation(len(idx_tr))[:int(round(args.val_share * len(idx_tr)))]] = True
        fit_i, val_i = idx_tr[~val], idx_tr[val]
        mu, sd = dz[fit_i].mean(0), dz[fit_i].std(0)
        cpu0 = time.process_time()
        model, info = train_baseline(x[fit_i], (dz[fit_i] - mu) / sd, x[val_i], (dz[val_i] - mu) / sd, seed=r,
                                     patience=args.patience, max_epochs=args.max_epochs,
                                     time_budget_s=args.time_budget)
        info["cpu_s"] = time.process_time() - cpu0
        with torch.no_grad():
            dz_hat = model(torch.as_tensor(x)).numpy() * sd + mu
        # compensated model pose: t - Δt̂, exp(-Δφ̂) R  ->  residual of the compensated pose
        T = res.model.predict(poses.q)
        T[:, :3, 3] -= dz_hat[:, :3]
        T[:, :3, :3] = rotvec_to_matrix(-dz_hat[:, 3:]) @ T[:, :3, :3]
        from campaign.model.kinematics import pose_error

        dz_after = pose_error(T, poses.T_IE)
        nominal = res.stages["nominal"]["test"]
        test = error_stats(dz_after[te])
        ratio = {b: {k: test[b][k] / nominal[b][k] for k in ("max", "mean", "q90")}
                 for b in ("position_mm", "orientation_mrad")}
        runs.append({"seed": r, **info, "test": test, "ratio_to_nominal_test": ratio})
        print(f"run {r}: {info['wall_s']:.0f} s wall, {info['cpu_s']:.0f} s CPU, {info['epochs']} epochs "
              f"(best {info['best_epoch']}); test position max {test['position_mm']['max']:.4f} mm "
              f"mean {test['position_mm']['mean']:.4f} mm ({100 * ratio['position_mm']['max']:.2f} % / "
              f"{100 * ratio['position_mm']['mean']:.2f} %), orientation max {test['orientation_mrad']['max']:.4f} "
              f"mean {test['orientation_mrad']['mean']:.4f} mrad", flush=True)
    out = json.loads(RESULTS.read_text()) if RESULTS.exists() else {}
    out[args.case] = {
        "command": "nice -n 5 python benchmarks/bench_baseline.py " + " ".join(sys.argv[1:]),
        "poses": args.poses, "hidden_effects": hidden, "network": "tanh 6-64-32-6, Adam lr 1e-3, batch 128, float64",
        "val_share": args.val_share, "patience": args.patience, "threads": args.threads,
        "test_nominal": res.stages["nominal"]["test"], "test_geometric": res.stages["geometric"]["test"],
        "runs": runs, "load_average_after": os.getloadavg(),
        "max_rss_mb": resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024,
        "note": "shared 2-core machine (other sessions running); wall and CPU seconds as measured",
    }
    RESULTS.write_text(json.dumps(out, indent=2) + "\n")


if __name__ == "__main__":
    main()
