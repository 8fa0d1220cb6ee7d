"""Benchmark of `campaign diagnose`: a 14,000-pose run with a hidden effect, the model-free test's cost.

    nice -n 5 python benchmarks/bench_diagnose.py [--poses 14000] [--hidden ground_compliance]
        [--tracker-noise-um 10] [--stage-effects NAME,...]

Synthesises the run (truth kept apart), imports it, states the tracker noise in the run's
campaign.yaml (the noise floor; synthesised data have no repeated poses), times `diagnose`
(library call, no report) and reports the wall time, the flexible regressor's cost (fits on
the folds and permutation importance) and the verdict. ``--stage-effects`` diagnoses a model
that already holds those effects (e.g. the hidden one: then the answer must be null, at the
floor). Writes benchmarks/results/diagnose.json (one entry per hidden/stage combination).
"""

from __future__ import annotations

import argparse
import json
import os

# one BLAS thread unless the caller says otherwise: on the shared 2-core machine OpenBLAS's
# threads spin against the other processes (14,000 poses: 247 s with its default threads at
# load 6, 54 s with one); set OPENBLAS_NUM_THREADS to measure another setting
os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")
import subprocess
import sys
import tempfile
import time
from pathlib import Path


def main():
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--poses", type=int, default=14000)
    ap.add_argument("--hidden", default="ground_compliance")
    ap.add_argument("--seed", type=int, default=5)
    ap.add_argument("--tracker-noise-um", type=float, default=10.0,
                    help="tracker noise stated in the run's campaign.yaml, µm (0: state none)")
    ap.add_argument("--stage-effects", default="", help="effects already in the model (comma-separated)")
    args = ap.parse_args()
    import yaml

    from campaign.diagnose import diagnose

    load_before = os.getloadavg()[0]
    with tempfile.TemporaryDirectory() as tmp:
        csv = Path(tmp) / "m.csv"
        run = Path(tmp) / "run"
        exe = [sys.executable, "-m", "campaign.cli"]
        subprocess.run(exe + ["synth", "--csv", str(csv), "--poses", str(args.poses), "--seed", str(args.seed),
                              "--hidden", args.hidden], check=True, stdout=subprocess.DEVNULL)
        subprocess.run(exe + ["import", str(csv), "--run", str(run)], check=True, stdout=subprocess.DEVNULL)
        cfg_path = run / "campaign.yaml"
        cfg = yaml.safe_load(cfg_path.read_text()) if cfg_path.is_file() else {}
        if args.tracker_noise_um > 0:
            cfg["tracker"] = {"noise_m": args.tracker_noise_um * 1e-6}
        cfg["effects"] = [e for e in args.stage_effects.split(",") if e]
        cfg_path.write_text(yaml.safe_dump(cfg, sort_keys=False))
        t0 = time.perf_counter()
        d = diagnose(run)
        wall = time.perf_counter() - t0
    s = d.structure
    print(d.text())
    print(f"\ndiagnose of {args.poses} poses ({d.n_train} training) with hidden {args.hidden!r}"
          f"{' and model effects ' + args.stage_effects if args.stage_effects else ''}: {wall:.1f} s wall, of which "
          f"the flexible regressor {s.fit_time_s:.1f} s (fits on {s.n_fit_poses} poses per fold) + "
          f"{s.importance_time_s:.1f} s permutation importance; load average {load_before:.2f} before, "
          f"{os.getloadavg()[0]:.2f} after; OPENBLAS_NUM_THREADS={os.environ.get('OPENBLAS_NUM_THREADS', 'unset')}")
    out = Path(__file__).parent / "results" / "diagnose.json"
    out.parent.mkdir(exist_ok=True)
    try:
        results = json.loads(out.read_text())
        runs = results.get("runs", []) if isinstance(results, dict) else []
    except (OSError, json.JSONDecodeError):
        runs = []
    threads = os.environ.get("OPENBLAS_NUM_THREADS", "unset")
    key = (args.poses, args.hidden, args.stage_effects, threads)
    runs = [r for r in runs if (r.get("poses"), r.get("hidden"), r.get("stage_effects", ""),
                                r.get("openblas_threads")) != key]
    j = d.as_json()
    runs.append({"poses": args.poses, "hidden": args.hidden, "stage_effects": args.stage_effects, "wall_s": wall,
                 "regressor_fit_s": s.fit_time_s, "permutation_importance_s": s.importance_time_s,
                 "regressor_fit_poses_per_fold": s.n_fit_poses, "verdict": d.verdict,
                 "noise_floor_mm": j["noise_floor_mm"], "model_to_noise": j["model_to_noise"],
                 "unexplained": {k: j["unexplained"][k] for k in ("significant", "heldout_gain", "depends_on")},
                 "ranking": j["ranking"], "load_average_before": load_before,
                 "openblas_threads": os.environ.get("OPENBLAS_NUM_THREADS", "unset"),
                 "command": "python benchmarks/bench_diagnose.py " + " ".join(sys.argv[1:])})
    out.write_text(json.dumps({"runs": runs}, indent=2))


if __name__ == "__main__":
    main()
