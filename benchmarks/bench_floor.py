"""Benchmark of issue 20 item 2: the floor is the noise, the drift is the drift.

    python benchmarks/bench_floor.py [--before /work/main] [--grid-scale 1.0] [--g 3e-4]

The default short campaign (`campaign plan`, 120 poses + validation + repeats) of the default cell
with a warm-up hidden in the simulated truth (the arm grows by g·(1 − exp(−t / 1 h)), 0.3 mm per
metre of reach once warm), run on the simulated cell, then `campaign diagnose --json`: the noise
floor it states against the true noise (the measurements against the truth, read afterwards),
the drift it states against the reference pose's true displacement, and ``at_noise_floor``.
``--before DIR``: the same with the `campaign` source tree in DIR (e.g. /work/main, the code
before the change) in the same run. Writes benchmarks/results/floor.json.
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np
import yaml

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT / "tests"))

from test_diagnose_open_world import WarmUp, write_user_effect  # noqa: E402

from campaign.effects.base import EffectSet, effect_context, make_effect  # noqa: E402
from campaign.measure.store import open_run  # noqa: E402
from campaign.model.kinematics import pose_error  # noqa: E402
from campaign.run import RunFolder  # noqa: E402
from campaign.sim.truth import TruthRobot  # noqa: E402


def campaign(args, code, cwd):
    """`campaign ARGS` with the source tree ``code`` (run from ``cwd``: `python -m` puts the
    current folder first on the path); (stdout, wall s)."""
    env = {**os.environ, "PYTHONPATH": str(code), "OPENBLAS_NUM_THREADS": "1"}
    t0 = time.perf_counter()
    proc = subprocess.run([sys.executable, "-m", "campaign.cli", *args], capture_output=True, text=True, env=env,
                          cwd=cwd)
    if proc.returncode:
        raise SystemExit(f"campaign {' '.join(args)} ({code}): {proc.stderr.strip()}")
    return proc.stdout, time.perf_counter() - t0


def truth_of(run, robot, effect_spec):
    """The simulator's truth (read after the pipeline), its hidden effects by the spec given
    (a truth.yaml written before the fix names a user effect file by its class name only)."""
    doc = yaml.safe_load((run / "sim" / "truth.yaml").read_text())
    effects, thetas = [], []
    for name, th in (doc.get("effects") or {}).items():
        effects.append(make_effect(effect_spec if name.endswith("WarmUp") or name == "warm_up" else name, robot))
        thetas.append(np.asarray(th, dtype=float))
    return TruthRobot(robot, np.asarray(doc["p_e"]), np.asarray(doc["T_LI"]), float(doc["noise_m"]),
                      float(doc["resolution_m"]), EffectSet(tuple(effects)),
                      np.concatenate(thetas) if thetas else np.zeros(0))


def one(code, folder, grid_scale, spec) -> dict:
    run = folder / "run"
    _, t_plan = campaign(["plan", "--run", str(run), "--grid-scale", str(grid_scale), "--quiet"], code, folder)
    cfg = yaml.safe_load((run / "campaign.yaml").read_text())
    cfg["sim"]["hidden_effects"] = [spec]
    (run / "campaign.yaml").write_text(yaml.safe_dump(cfg))
    _, t_run = campaign(["run", str(run), "--sim", "--quiet"], code, folder)
    out, t_diag = campaign(["diagnose", str(run), "--json", "--no-report"], code, folder)
    d = json.loads(out)
    summary = json.loads((run / "plan" / "summary.json").read_text())
    # only now the truth
    robot = RunFolder(run).robot()
    with open_run(run) as store:
        poses, T_LI = store.load_measured(), np.array(store.get_meta("T_LI"))
        checks = store.events("drift_check")
        ref = store.get_meta("drift_reference")
    truth = truth_of(run, robot, spec)
    T = truth.pose_in_measured_frame(poses.q, T_LI, effect_context(poses.context, poses.time_s))
    true_mm = float(np.linalg.norm(pose_error(T, poses.T_IE)[:, :3], axis=1).mean() * 1e3)
    # the reference pose's true displacement over the campaign, as a rate (µm/h)
    t_ref = float(poses.time_s[poses.pose_id == ref["pose_id"]].min())
    t_end = float(np.nanmax(poses.time_s))
    T_ref = truth.pose(np.repeat([ref["q"]], 2, axis=0), {"time_s": np.array([t_ref, t_end])})
    moved_um = float(np.linalg.norm(T_ref[1, :3, 3] - T_ref[0, :3, 3]) * 1e6)
    repeats = [int(p) for p in np.unique(poses.pose_id % 1_000_000_000) if (poses.pose_id % 1_000_000_000 == p).sum() > 1]
    spread_h = [float(np.ptp(poses.time_s[poses.pose_id % 1_000_000_000 == p]) / 3600) for p in repeats]
    return {
        "code": str(code), "poses": int(len(poses)), "drift_checks": len(checks),
        "repeated_poses": len(repeats), "repeat_spread_h": spread_h,
        "tour_repeats_back_to_back": summary["tour"].get("repeats_back_to_back"),
        "noise_floor_mm": d["noise_floor_mm"], "noise_floor_detail": d["noise_floor"]["detail"],
        "true_noise_mm": true_mm, "floor_over_true": d["noise_floor_mm"] / true_mm,
        "model_to_noise": d["model_to_noise"], "model_to_true_noise": d["heldout_mean_position_mm"] / true_mm,
        "at_noise_floor": d["at_noise_floor"], "structure_significant": d["unexplained"]["significant"],
        "verdict": d["verdict"], "drift_um_per_h": d.get("drift_um_per_h"), "drift": d.get("drift"),
        "reference_true_displacement_um": moved_um, "campaign_h": (t_end - t_ref) / 3600,
        "reference_true_mean_rate_um_per_h": moved_um / max((t_end - t_ref) / 3600, 1e-9),
        "wall_s": {"plan": t_plan, "run": t_run, "diagnose": t_diag},
    }


def main():
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--before", default=None, help="a campaign source tree to compare (the code before the change)")
    ap.add_argument("--grid-scale", type=float, default=1.0)
    ap.add_argument("--g", type=float, default=3e-4, help="the warm-up's growth once warm (1)")
    args = ap.parse_args()
    res = {"grid_scale": args.grid_scale, "warm_up_g": args.g}
    with tempfile.TemporaryDirectory(prefix="bench-floor-") as tmp:
        tmp = Path(tmp)
        spec = write_user_effect(tmp, WarmUp)
        (tmp / "warm_up.py").write_text((tmp / "warm_up.py").read_text() + textwrap_sim(args.g))
        spec = f"{tmp / spec.replace(':WarmUp', ':SimWarmUp')}"
        for name, code in (("after", ROOT), ("before", args.before)):
            if code is None:
                continue
            (tmp / name).mkdir()
            res[name] = one(Path(code), tmp / name, args.grid_scale, spec)
            r = res[name]
            print(f"{name}: floor {r['noise_floor_mm']:.4f} mm vs true noise {r['true_noise_mm']:.4f} mm "
                  f"({r['floor_over_true']:.2f}x; {r['noise_floor_detail']}); model {r['model_to_noise']:.2f}x the floor "
                  f"said, {r['model_to_true_noise']:.2f}x the true noise; at_noise_floor {r['at_noise_floor']}; "
                  f"drift {r['drift_um_per_h']} um/h (true mean rate of the reference "
                  f"{r['reference_true_mean_rate_um_per_h']:.0f} um/h over {r['campaign_h']:.2f} h)")
    res["load_average"] = os.getloadavg()
    name = "floor.json" if args.g == 3e-4 else f"floor_g{args.g:g}.json"  # the default case, or another warm-up
    (ROOT / "benchmarks" / "results" / name).write_text(json.dumps(res, indent=2))


def textwrap_sim(g):
    return f"\n\nclass SimWarmUp(WarmUp):\n    def typical_params(self, seed=0):\n        return np.array([{g!r}])\n"


if __name__ == "__main__":
    main()
