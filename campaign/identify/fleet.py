"""Calibrate many runs (a fleet of robots) through the ANN grid's executors.

Each run is one task ``{"id": run folder, "run": path, "options": {...}}`` for
:func:`campaign.ann.grid`'s executors: in this process, on local worker processes, or on a Dask
distributed cluster (``make_executor(scheduler="tcp://HOST:PORT")``), the same call
:func:`calibrate_task` everywhere. A run calibrated on a worker trains its own network grid in
that worker (one process: workers cannot start processes of their own), and writes its
calibration folder where the run folder is, so a remote cluster needs the run folders on a
shared file system.
"""

from __future__ import annotations

from pathlib import Path


def calibrate_task(task: dict, report=None) -> dict:
    """Calibrate one run; returns ``{"id", "metrics", "wall_s", "cpu_s"}`` (metrics.json's content)."""
    import time

    from campaign.errors import CampaignError
    from campaign.identify.calibrate import calibrate

    t0, c0 = time.perf_counter(), time.process_time()
    opts = dict(task.get("options", {}))
    collect = opts.pop("collect_errors", False)
    ann_options = dict(opts.pop("ann_options", {}) or {})
    ann_options.setdefault("workers", 1)  # the run's own grid stays inside this worker
    try:
        result = calibrate(task["run"], ann_options=ann_options, **opts)
    except CampaignError as exc:
        if not collect:
            raise
        return {"id": task["id"], "error": str(exc), "members": [],
                "wall_s": time.perf_counter() - t0, "cpu_s": time.process_time() - c0}
    return {"id": task["id"], "metrics": result.metrics, "members": [],
            "wall_s": time.perf_counter() - t0, "cpu_s": time.process_time() - c0}


def calibrate_runs(run_dirs, *, executor=None, progress=None, errors: str = "raise", **options) -> dict:
    """Calibrate every run in ``run_dirs`` (each as `campaign calibrate` does, with ``options``:
    ``effects``, ``ann``, ``ann_options``, ...) on ``executor`` (default: this process).
    Returns {run folder: metrics dict}. progress: optional callable(str) per finished run.
    errors: ``"raise"`` (default) stops at a run that fails; ``"collect"`` calibrates the others
    and gives a failed run ``{"error": message}`` in place of its metrics."""
    from campaign.ann.grid import SerialExecutor
    from campaign.errors import ConfigError

    if errors not in ("raise", "collect"):
        raise ConfigError(f"errors must be 'raise' or 'collect', not {errors!r}")
    options = {**options, "collect_errors": errors == "collect"}
    tasks = [{"id": str(Path(r)), "run": str(Path(r)), "options": dict(options)} for r in run_dirs]
    own = executor is None
    executor = executor or SerialExecutor()

    def done(r):
        if progress is not None:
            progress(f"failed {r['id']}: {r['error']}" if "error" in r else
                     f"calibrated {r['id']} ({r['wall_s']:.0f} s)")

    try:
        results = executor.map(calibrate_task, tasks, None, done)
    finally:
        if own:
            executor.close()
    return {r["id"]: {"error": r["error"]} if "error" in r else r["metrics"] for r in results}
