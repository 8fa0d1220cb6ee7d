"""Benchmark of the residual network's Bayesian-regularised training (issue 5).

    flock /tmp/campaign-bench.lock python benchmarks/bench_ann.py            # matrix-free (64, 32)
    flock /tmp/campaign-bench.lock python benchmarks/bench_ann.py --reference  # + full-Jacobian LM
    flock /tmp/campaign-bench.lock python benchmarks/bench_ann.py --cv-grid    # + the 5-fold CV grid
    ... --skip-cg   (only the other parts; keeps the stored matrix-free figures)
    nice -n 5 python benchmarks/bench_ann.py --skip-cg --adam-rules   # Adam stop rules (issue 15)

Data: a simulated campaign with hidden geometric errors, hidden smooth non-geometric effects
(joint compliance and cyclic transmission errors) and 10 µm tracker noise; the targets are
the residuals after geometric calibration on the training poses (11,000 by default, 2,000
held out). Times one (64, 32) training with the matrix-free solver; with --reference, the
same training with a plain full-Jacobian LM (JᵀJ assembled exactly in float64, Cholesky
solves, exact tr(H⁻¹)), and compares the final losses; with --cv-grid, the 5-fold CV over
the hidden sizes for both prior models. Each part's figures are merged into
benchmarks/results/ann.json (so the parts can be run separately), each with the load
average before and after. Every run is meant to hold the lock so benchmarks don't overlap.

The loss comparison: after every α, β re-estimate β·E_D + α·E_W equals N_d / 2 exactly
(that is the BR fixed point), so the raw final loss says nothing; the benchmark compares
(a) the normalised training MSE E_D / N_d, (b) the BR objective of both final weight vectors
at the reference's α, β, and (c) the held-out error.
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import time
from pathlib import Path

import numpy as np
import torch

from campaign.ann import ResidualNetwork, cross_validate
from campaign.effects import make_effect
from campaign.identify.solver import CalibrationModel
from campaign.model.kinematics import forward, pose_error
from campaign.model.robot import RobotModel
from campaign.sim.truth import make_truth, random_joint_poses, synthesize

RESULTS = Path(__file__).parent / "results" / "ann.json"


def data(n_train, n_test=2000, seed=0):
    robot = RobotModel.load()
    hidden = {"joint_compliance": make_effect("joint_compliance", robot).typical_params(seed),
              "cyclic": make_effect("cyclic", robot).typical_params(seed)}
    truth = make_truth(robot, seed=seed, effects=hidden)
    q = random_joint_poses(robot, n_train + n_test, seed=seed + 1)
    meas = synthesize(truth, q, seed=seed + 2)
    geo = CalibrationModel(robot=robot).fit(meas.q[:n_train], meas.T_IE[:n_train])
    dz_geo = geo.residuals(meas.q, meas.T_IE)
    dz_nom = pose_error(forward(robot, meas.q), meas.T_IE)
    return robot, meas.q, dz_geo, dz_nom, n_train


def train(robot, q, dz, n, solver, hidden=(64, 32), **options):
    marks = []
    t0 = time.perf_counter()

    def progress(epoch, max_epochs, mse, gamma):
        if epoch == 1 or epoch % 25 == 0:
            marks.append([epoch, round(time.perf_counter() - t0, 2), mse, gamma])
            print(f"  {solver} epoch {epoch}: {marks[-1][1]:.1f} s, normalised MSE {mse:.5f}, γ {gamma:.0f}",
                  flush=True)

    net = ResidualNetwork(hidden=hidden, q_lower=robot.q_lower, q_upper=robot.q_upper, solver=solver, seed=0,
                          progress=progress, progress_every=1, **options)
    net.fit(q[:n], dz[:n])
    wall = time.perf_counter() - t0
    res = dz[n:] - net.predict(q[n:])
    return net, {"solver": solver, "hidden": list(hidden), "options": options, "wall_s": wall,
                 "epochs": net.n_epochs_, "s_per_epoch": wall / net.n_epochs_, "stop": net.stop_reason_,
                 "cg_iterations": getattr(net, "cg_iterations_", None),
                 "mse_normalised": net.mse_normalised_, "E_D": net.E_D_, "E_W": net.E_W_,
                 "alpha": net.alpha_, "beta": net.beta_, "gamma": net.gamma_, "n_weights": net.net_.n_weights,
                 "test_mean_position_mm": float(np.linalg.norm(res[:, :3], axis=1).mean() * 1e3),
                 "test_mean_orientation_mrad": float(np.linalg.norm(res[:, 3:], axis=1).mean() * 1e3),
                 "progress": marks}


def compare(cg, full):
    """Loss ratios matrix-free / full-Jacobian (≤ 1.1 is the issue's bar)."""
    F = lambda r: full["beta"] * r["E_D"] + full["alpha"] * r["E_W"]  # noqa: E731
    return {"mse_ratio": cg["mse_normalised"] / full["mse_normalised"],
            "objective_at_reference_hyperparameters": {"matrix_free": F(cg), "full": F(full), "ratio": F(cg) / F(full)},
            "test_position_ratio": cg["test_mean_position_mm"] / full["test_mean_position_mm"],
            "test_orientation_ratio": cg["test_mean_orientation_mrad"] / full["test_mean_orientation_mrad"],
            "wall_ratio": cg["wall_s"] / full["wall_s"]}


def main():
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--train", type=int, default=11000)
    ap.add_argument("--threads", type=int, default=1, help="torch intra-op threads (default 1, see docs/ann.md)")
    ap.add_argument("--reference", action="store_true", help="also train with the full-Jacobian LM")
    ap.add_argument("--reference-epochs", type=int, default=2048, help="epoch bound of the reference")
    ap.add_argument("--cv-grid", action="store_true", help="time the full 5-fold CV grid")
    ap.add_argument("--sizes", default="16x16,32x16,32x32,64x32,128x64", help="CV grid sizes")
    ap.add_argument("--skip-cg", action="store_true", help="don't rerun the matrix-free training")
    ap.add_argument("--adam-rules", action="store_true",
                    help="batched Adam: 5 folds of --rule-size under several stop rules (patience, plateau schedule)")
    ap.add_argument("--rule-size", default="64x32")
    args = ap.parse_args()
    torch.set_num_threads(args.threads)
    out = json.loads(RESULTS.read_text()) if RESULTS.exists() else {}
    robot, q, dz_geo, dz_nom, n = data(args.train)
    out.update({"train_poses": n, "test_poses": len(q) - n, "threads": args.threads, "torch": torch.__version__,
                "cpu": platform.processor() or platform.machine(), "cores": os.cpu_count()})
    print(f"training poses {n}; residual after geometric calibration (test) "
          f"{np.linalg.norm(dz_geo[n:, :3], axis=1).mean() * 1e3:.3f} mm mean")

    def save():
        RESULTS.write_text(json.dumps(out, indent=2) + "\n")

    if not args.skip_cg:
        load0 = os.getloadavg()
        _, r = train(robot, q, dz_geo, n, "cg")
        r["load_average_before"], r["load_average_after"] = load0, os.getloadavg()
        out["matrix_free"] = r
        print(f"(64, 32) matrix-free BR-LM: {r['wall_s']:.1f} s, {r['epochs']} epochs ({r['stop']}), "
              f"{r['cg_iterations']} CG iterations, normalised MSE {r['mse_normalised']:.5f}, "
              f"γ {r['gamma']:.0f}/{r['n_weights']}, test {r['test_mean_position_mm']:.4f} mm / "
              f"{r['test_mean_orientation_mrad']:.4f} mrad", flush=True)
        save()
    if args.reference:
        load0 = os.getloadavg()
        _, f = train(robot, q, dz_geo, n, "full", max_epochs=args.reference_epochs)
        f["load_average_before"], f["load_average_after"] = load0, os.getloadavg()
        out["full_jacobian"] = f
        print(f"(64, 32) full-Jacobian BR-LM: {f['wall_s']:.1f} s, {f['epochs']} epochs ({f['stop']}), "
              f"normalised MSE {f['mse_normalised']:.5f}, test {f['test_mean_position_mm']:.4f} mm", flush=True)
        save()
    if "matrix_free" in out and "full_jacobian" in out:
        out["comparison"] = compare(out["matrix_free"], out["full_jacobian"])
        print("matrix-free / full:", json.dumps(out["comparison"]), flush=True)
        save()
    if args.cv_grid:
        # one cross_validate call per size (the same seeded folds), so every finished size is saved
        sizes = tuple(tuple(int(v) for v in s.split("x")) for s in args.sizes.split(","))
        grid = {}
        load0 = os.getloadavg()
        t0 = time.perf_counter()
        for name, dz in (("geometric", dz_geo), ("nominal", dz_nom)):
            rows = []
            for size in sizes:
                cv = cross_validate(q[:n], dz[:n], sizes=[size], folds=5, q_lower=robot.q_lower, q_upper=robot.q_upper)
                rows += cv["sizes"]
                r = rows[-1]
                print(f"  CV prior {name} {size}: {r['wall_s']:.0f} s, epochs {r['epochs']}, "
                      f"RMSE {r['rmse_normalised']:.3f}, max ‖Δr‖ {r['max_position_mm']:.3f} mm", flush=True)
                grid[name] = {"wall_s": sum(r["wall_s"] for r in rows), "sizes": rows,
                              "best": min(rows, key=lambda r: r["rmse_normalised"])["hidden"]}
                out["cv_grid"] = {"wall_s": time.perf_counter() - t0, "sizes": [list(s) for s in sizes], "folds": 5,
                                  "train_poses_per_fold": int(round(n * 4 / 5)),
                                  "complete": name == "nominal" and size == sizes[-1], "grids": grid,
                                  "load_average_before": load0, "load_average_after": os.getloadavg()}
                save()
            print(f"CV grid, prior {name}: {grid[name]['wall_s']:.0f} s; best {grid[name]['best']}", flush=True)
    if args.adam_rules:
        out["adam_stop_rules"] = adam_rules(robot, q, dz_geo, n, tuple(int(v) for v in args.rule_size.split("x")))
        save()
    out["load_average"] = os.getloadavg()
    save()


def adam_rules(robot, q, dz, n, hidden):
    """The batched Adam's stop rules measured: for each rule, the 5 fold networks of one size
    trained as one batch; CV RMSE (held-out folds), the fold ensemble's error on the held-out
    poses, epochs, CPU seconds."""
    from campaign.ann.grid import run_grid

    rules = {"patience 30, no schedule": dict(patience=30, lr_decay_after=0),
             "patience 60, no schedule": dict(patience=60, lr_decay_after=0),
             "patience 60, lr ×0.3 after 30 (default)": dict(),
             "patience 120, lr ×0.3 after 60": dict(patience=120, lr_decay_after=60),
             "patience 60, lr ×0.3 after 30, batch 128": dict(batch=128)}
    rows = {}
    for name, opts in rules.items():
        c0, t0 = time.process_time(), time.perf_counter()
        (net, cv), = run_grid(q[:n], {"geometric": dz[:n]}, sizes=[hidden], folds=5, solver="adam",
                              q_lower=robot.q_lower, q_upper=robot.q_upper, **opts).values()
        res = dz[n:] - net.predict(q[n:])
        row = cv["sizes"][0]
        rows[name] = {"options": opts, "cpu_s": time.process_time() - c0, "wall_s": time.perf_counter() - t0,
                      "epochs": row["epochs"], "cv_rmse_normalised": row["rmse_normalised"],
                      "cv_mean_position_mm": row["mean_position_mm"],
                      "test_mean_position_mm": float(np.linalg.norm(res[:, :3], axis=1).mean() * 1e3),
                      "test_max_position_mm": float(np.linalg.norm(res[:, :3], axis=1).max() * 1e3),
                      "test_mean_orientation_mrad": float(np.linalg.norm(res[:, 3:], axis=1).mean() * 1e3)}
        r = rows[name]
        print(f"  {name}: {r['cpu_s']:.0f} s CPU, epochs {r['epochs']}, CV RMSE {r['cv_rmse_normalised']:.4f}, "
              f"test mean {r['test_mean_position_mm']:.4f} mm / {r['test_mean_orientation_mrad']:.4f} mrad",
              flush=True)
    return {"hidden": list(hidden), "folds": 5, "rules": rows}


if __name__ == "__main__":
    main()
