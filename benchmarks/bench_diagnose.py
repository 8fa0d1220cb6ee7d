"""Benchmark of `campaign diagnose`: a 14,000-pose run with a hidden effect, the model-free test's cost.

    nice -n 5 python benchmarks/bench_diagnose.py [--poses 14000] [--hidden ground_compliance]
        [--tracker-noise-um 10] [--stage-effects NAME,... ...]

Synthesises the run (truth kept apart), imports it, states the tracker noise in the run's
campaign.yaml (the noise floor; synthesised data have no repeated poses), then times `diagnose`
(library call, no report) once per model setting on the same run: by default the geometric
model alone (the hidden effect must be found) and the model that already holds the hidden
effect (the candidates are then fitted on top of an effect: at the floor, the answer must be
null). Reports each wall time with its phases (the current model's fits, the flexible
regressor's fits and permutation importance, the candidates) and the verdict, and the load
average (the machine is shared). Writes benchmarks/results/diagnose.json (one entry per
hidden/stage combination).
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
    ap.add_argument("--stage-effects", nargs="*", default=None,
                    help="model settings to time, each the effects already in the model (comma-separated; '' for the "
                         "geometric model alone); default: '' and the hidden effect")
    args = ap.parse_args()
    import yaml

    stages = ["", args.hidden] if args.stage_effects is None else args.stage_effects
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
        for stage in stages:
            cfg["effects"] = [e for e in stage.split(",") if e]
            cfg_path.write_text(yaml.safe_dump(cfg, sort_keys=False))
            record(args, stage, *timed_diagnose(run))


def timed_diagnose(run):
    """diagnose(run) with its wall time, load averages and the time of each phase (s)."""
    from campaign.diagnose import diagnose

    marks = []
    load_before = os.getloadavg()[0]
    t0 = time.perf_counter()
    d = diagnose(run, progress=lambda msg: marks.append((time.perf_counter() - t0, msg)))
    wall = time.perf_counter() - t0
    marks.append((wall, "end"))
    phases = {"current_model_s": 0.0, "structure_test_s": 0.0, "candidates_s": 0.0, "rest_s": 0.0}
    for (t, msg), (t_next, _) in zip(marks, marks[1:]):
        key = ("current_model_s" if msg.startswith("current model") else "structure_test_s"
               if msg.startswith(("model-free", "signature")) else "candidates_s" if msg.lstrip().startswith(("candidate", "  "))
               else "rest_s")
        phases[key] += t_next - t
    phases["rest_s"] += marks[0][0] if marks else 0.0
    return d, wall, phases, load_before, os.getloadavg()[0]


def record(args, stage, d, wall, phases, load_before, load_after):
    s = d.structure
    print(d.text())
    print(f"\ndiagnose of {args.poses} poses ({d.n_train} training) with hidden {args.hidden!r}, model: geometric"
          f"{''.join(' + ' + e for e in stage.split(',') if e)}: {wall:.1f} s wall (current model "
          f"{phases['current_model_s']:.1f} s, structure test {phases['structure_test_s']:.1f} s of which the "
          f"regressor's fits {s.fit_time_s:.1f} s on {s.n_fit_poses} poses per fold + permutation importance "
          f"{s.importance_time_s:.1f} s, candidates {phases['candidates_s']:.1f} s); load average {load_before:.2f} "
          f"before, {load_after:.2f} after; OPENBLAS_NUM_THREADS={os.environ.get('OPENBLAS_NUM_THREADS', 'unset')}\n")
    out = Path(__file__).parent / "results" / "diagnose.json"
    out.parent.mkdir(exist_ok=True)
    try:
        results = json.loads(out.read_text())
        runs = results.get("runs", []) if isinstance(results, dict) else []
    except (OSError, json.JSONDecodeError):
        runs = []
    threads = os.environ.get("OPENBLAS_NUM_THREADS", "unset")
    key = (args.poses, args.hidden, stage, threads)
    runs = [r for r in runs if (r.get("poses"), r.get("hidden"), r.get("stage_effects", ""),
                                r.get("openblas_threads")) != key]
    j = d.as_json()
    runs.append({"poses": args.poses, "hidden": args.hidden, "stage_effects": stage, "wall_s": wall,
                 "phases_s": phases, "regressor_fit_s": s.fit_time_s, "permutation_importance_s": s.importance_time_s,
                 "regressor_fit_poses_per_fold": s.n_fit_poses, "verdict": d.verdict,
                 "noise_floor_mm": j["noise_floor_mm"], "model_to_noise": j["model_to_noise"],
                 "unexplained": {k: j["unexplained"][k] for k in ("significant", "heldout_gain", "depends_on")},
                 "signature": j["unexplained"]["signature"],
                 "ranking": j["ranking"], "load_average_before": load_before, "load_average_after": load_after,
                 "openblas_threads": threads,
                 "command": "python benchmarks/bench_diagnose.py " + " ".join(sys.argv[1:])})
    out.write_text(json.dumps({"runs": runs}, indent=2))


if __name__ == "__main__":
    main()
