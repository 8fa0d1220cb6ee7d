"""The cross-validation grid as a list of training tasks mapped over a pluggable executor.

A task trains the K fold networks of one hidden size on one prior model's residuals (and, for
the paper's BR-LM, a final network on the whole training set). Every task is a plain dict of
numpy arrays and numbers in, a plain dict out (:func:`run_task`), so the same function runs

* in this process (:class:`SerialExecutor`),
* in local worker processes, one torch thread each (:class:`ProcessExecutor`, ``--workers N``),
* on a Dask distributed cluster (:class:`DaskExecutor`, ``--scheduler tcp://HOST:PORT``, or a
  local cluster of N workers).

Solvers: ``"adam"`` — the K folds of a task as one batched computation (campaign.ann.adam),
early stopping on a validation share of each fold's training part; the stage's network is the
ensemble of the chosen size's K fold networks (mean prediction). ``"br-lm"`` — the paper's
Bayesian-regularised LM (campaign.ann.network), one fold after the other inside a task, then a
final network of the chosen size on the whole training set, with its evidence quantities γ, α, β.

Tasks are dispatched largest first (cost ~ members × weights), so the two largest trainings of
the default grid ((128, 64) on both priors) start at once and the small ones fill the gaps.

Device: Adam trains on ``device``; ``"auto"`` is resolved where the task runs (a worker's GPU
when torch finds one there, else its CPU). BR-LM trains on the CPU.

Trust: Dask moves tasks and results with pickle over its sockets, and a scheduler runs whatever
code its clients send. The project reads nothing pickled from a socket otherwise; Dask is
opt-in, for a scheduler and workers you trust on a network you trust (or with Dask's TLS). The
local cluster (``dask=True``) listens on 127.0.0.1 only.
"""

from __future__ import annotations

import contextlib
import logging
import os
import queue
import threading
import time
from dataclasses import dataclass

import numpy as np

from campaign.ann.gain import heldout_gain
from campaign.errors import ConfigError, DataError

SOLVERS = ("adam", "br-lm")

#: after Ctrl-C, how long terminated worker processes get to exit before they are killed (s)
ABORT_JOIN_S = 2.0

#: a cross-validated size whose held-out RMSE of normalised Δz in some fold exceeds this (or is not
#: finite) diverged: a network predicting zero scores about 1, a fitted one below; 100 is a network
#: whose predictions left the data (BR-LM's weights grown without bound), not a poor fit
DIVERGED_RMSE_NORMALISED = 100.0

#: expected epochs per member, for the grid's ETA before any task has finished (measured on the
#: 14,000-pose benchmark: Adam members stop after 300-1,300 epochs, BR-LM after 130-1,400)
_EPOCH_GUESS = {"adam": 700, "br-lm": 500}


def fold_of(n: int, folds: int, seed: int) -> np.ndarray:
    """Fold index (n,) of each training row: a seeded random partition."""
    rng = np.random.default_rng(seed)
    return rng.permutation(n) % folds


def fit_and_val_rows(rows: np.ndarray, val_share: float, seed: int):
    """Split a member's training rows into fitting rows and early-stopping rows (seeded)."""
    perm = np.random.default_rng(seed).permutation(rows)
    n_val = max(1, int(round(val_share * len(rows)))) if val_share > 0 else 0
    return np.sort(perm[n_val:]), np.sort(perm[:n_val])


# -- the task function (runs wherever the executor puts it) ----------------------------------

_PROGRESS_QUEUE = None  # set in local worker processes by the pool's initializer


def _worker_init(q, threads):
    global _PROGRESS_QUEUE
    _PROGRESS_QUEUE = q
    import signal

    # Ctrl-C reaches the whole process group: the parent decides (it stops the workers at once)
    signal.signal(signal.SIGINT, signal.SIG_IGN)
    import torch

    torch.set_num_threads(int(threads))


def run_task(task: dict, report=None) -> dict:
    """Train one task's networks. Inputs and outputs are plain values (see :func:`make_tasks`).

    Returns ``{"id", "weights" (M, N_w), "target_mean" (M, N_out), "target_scale" (M, N_out),
    "heldout_pred" {"prior/fold": (n_k, N_out)}, "members": [info...], "wall_s", "cpu_s"}``
    (N_out = 6, or 3 for position-only residuals).
    report: optional callable(units) with the work done since the last call (members × epochs
    × weights); inside a local worker process the units go to the parent's progress queue.
    """
    import torch

    from campaign.ann.mlp import MLP
    from campaign.ann.network import ResidualNetwork

    if report is None and _PROGRESS_QUEUE is not None:
        report = lambda units: _PROGRESS_QUEUE.put((task["id"], units))  # noqa: E731
    if report is not None:
        report(0.0)  # started: the meter times the task from here
    t0, c0 = time.perf_counter(), time.process_time()
    device = resolve_device(task.get("device", "cpu"))  # "auto": this worker's GPU if it has one
    x, dz_of, hidden = task["x"], task["dz"], tuple(task["hidden"])
    n_w = task["n_weights"]
    members = task["members"]
    out = {"id": task["id"], "members": []}
    if task["solver"] == "adam":
        from campaign.ann.adam import AdamOptions, train_batched

        opts = AdamOptions(**task.get("options", {}))
        fits, vals, means, scales, targets = [], [], [], [], []
        for m in members:
            fit, val = fit_and_val_rows(m["train_rows"], opts.val_share, m["seed"])
            dz = dz_of[m["prior"]]
            mu, sd = dz[fit].mean(0), dz[fit].std(0)
            sd = np.where(sd > 0, sd, 1.0)
            fits.append(fit), vals.append(val), means.append(mu), scales.append(sd)
            targets.append((dz - mu) / sd)
        W, info = train_batched(hidden, x, np.stack(targets), fits, vals, seeds=[m["seed"] for m in members],
                                options=opts,
                                device=device,
                                progress=None if report is None else lambda ep, act: report(ep * act * n_w))
        out["members"] = info
    else:
        W, means, scales = [], [], []
        opts = dict(task.get("options", {}))
        for m in members:
            rows = m["train_rows"]
            last = [0]

            def tick(epoch, max_epochs, mse, gamma, _last=last):
                if report is not None:
                    report((epoch - _last[0]) * n_w)
                    _last[0] = epoch

            net = ResidualNetwork(hidden=hidden, q_lower=task["q_lower"], q_upper=task["q_upper"], seed=task["seed"],
                                  progress=tick, progress_every=5, **opts)
            net.fit(task["q"][rows], dz_of[m["prior"]][rows])
            if report is not None:
                report(("member", int(net.n_epochs_)))  # one member done: the meter learns its length
            W.append(net.weights_.cpu().numpy())
            means.append(net.target_mapping_.mean)
            scales.append(net.target_mapping_.scale)
            out["members"].append({"epochs": int(net.n_epochs_), "stop": net.stop_reason_, "gamma": net.gamma_,
                                   "alpha": net.alpha_, "beta": net.beta_, "n_weights": n_w,
                                   "mse_normalised": net.mse_normalised_})
        W = np.stack(W)
    net = MLP(task["n_in"], hidden, task["n_out"])
    preds = {}
    with torch.no_grad():
        for i, m in enumerate(members):
            if m.get("heldout_rows") is not None and len(m["heldout_rows"]):
                y, _ = net.forward(torch.as_tensor(W[i]), torch.as_tensor(x[m["heldout_rows"]]))
                preds[f"{m['prior']}/{int(m['fold'])}"] = y.numpy() * scales[i] + means[i]
    out.update({"weights": np.asarray(W), "target_mean": np.stack(means), "target_scale": np.stack(scales),
                "heldout_pred": preds, "device": device if task["solver"] == "adam" else "cpu",
                "wall_s": time.perf_counter() - t0, "cpu_s": time.process_time() - c0})
    return out


# -- executors --------------------------------------------------------------------------------

class SerialExecutor:
    """Tasks one after another in this process, with ``threads`` torch threads (default 1: on a
    shared machine more threads were 3-10× slower, docs/ann.md)."""

    name = "serial"
    workers = 1

    def __init__(self, threads: int | None = 1):
        self.threads = threads

    def map(self, fn, tasks, on_units, on_done, on_interrupt=None):
        from campaign.ann.mlp import torch_threads

        results = []
        try:
            with torch_threads(self.threads):
                for t in tasks:
                    r = fn(t, on_units and (lambda u, _id=t["id"]: on_units(_id, u)))
                    on_done(r)
                    results.append(r)
        except KeyboardInterrupt:  # Ctrl-C stopped the training in this process itself
            if on_interrupt:
                on_interrupt()
            raise
        return results

    def close(self):
        pass

    def abort(self):
        """Stop at once (Ctrl-C): nothing runs elsewhere, the interrupt itself stops this process's task."""


@contextlib.contextmanager
def _sigint_blocked():
    """SIGINT blocked in this thread while the block runs: a process spawned meanwhile inherits the
    blocked signal through fork and exec, so a Ctrl-C to the process group while a worker is still
    starting (before :func:`_worker_init` ignores it) prints no traceback of the worker's. A Ctrl-C
    meanwhile is not lost: it is delivered to this process when the block ends."""
    import signal

    if not hasattr(signal, "pthread_sigmask"):
        yield
        return
    signal.pthread_sigmask(signal.SIG_BLOCK, {signal.SIGINT})
    try:
        yield
    finally:
        signal.pthread_sigmask(signal.SIG_UNBLOCK, {signal.SIGINT})


class ProcessExecutor:
    """Tasks on N local worker processes (spawned, one torch thread each), progress through a queue."""

    name = "processes"

    def __init__(self, workers: int = 2, threads_per_worker: int = 1):
        import multiprocessing as mp
        from concurrent.futures import ProcessPoolExecutor

        self.workers = int(workers)
        ctx = mp.get_context("spawn")
        self._queue = ctx.Queue()
        self._pool = ProcessPoolExecutor(self.workers, mp_context=ctx, initializer=_worker_init,
                                         initargs=(self._queue, threads_per_worker))

    def map(self, fn, tasks, on_units, on_done, on_interrupt=None):
        from concurrent.futures import FIRST_COMPLETED, wait

        results = [None] * len(tasks)
        futures = {}
        try:
            with _sigint_blocked():  # the workers start here: Ctrl-C never reaches them, not even at start-up
                for i, t in enumerate(tasks):
                    futures[self._pool.submit(fn, t)] = i
            pending = set(futures)
            while pending:
                done, pending = wait(pending, timeout=0.5, return_when=FIRST_COMPLETED)
                self._drain(on_units)
                for f in done:
                    r = f.result()
                    results[futures[f]] = r
                    on_done(r)
        except KeyboardInterrupt:  # Ctrl-C: the workers ignore it, so they are stopped here, at once
            if on_interrupt:
                on_interrupt()
            self.abort()
            raise
        self._drain(on_units)
        return results

    def _drain(self, on_units):
        while True:
            try:
                tid, units = self._queue.get_nowait()
            except queue.Empty:
                return
            if on_units:
                on_units(tid, units)

    def close(self):
        self._pool.shutdown(wait=True, cancel_futures=True)

    def abort(self):
        """Stop at once (Ctrl-C): the workers are terminated mid-task (SIGTERM, then SIGKILL after
        ABORT_JOIN_S), the queued tasks cancelled; a later :meth:`close` returns at once."""
        procs = list((getattr(self._pool, "_processes", None) or {}).values())
        for p in procs:
            p.terminate()
        deadline = time.monotonic() + ABORT_JOIN_S
        for p in procs:
            p.join(max(0.0, deadline - time.monotonic()))
            if p.is_alive():
                p.kill()
                p.join(1.0)
        self._pool.shutdown(wait=False, cancel_futures=True)


class DaskExecutor:
    """Tasks on a Dask distributed cluster: an existing scheduler (``address``) or a local
    cluster of ``workers`` processes (one thread each, scheduler and workers listening on
    127.0.0.1 only). Progress is reported per finished task.

    Dask moves tasks and results between machines with pickle (arbitrary code on unpickling):
    only for a scheduler and workers you trust, on a network you trust, or with Dask's TLS
    security configured. Never point ``address`` at a scheduler someone else controls.
    """

    name = "dask"

    def __init__(self, address: str | None = None, workers: int | None = None):
        try:
            from distributed import Client, LocalCluster
        except ImportError:
            raise ConfigError("Dask is not installed: pip install 'campaign[dask]' (or dask[distributed])") from None
        self._cluster = None
        try:
            if address:
                self.client = Client(address, timeout="5s")
            else:
                self._cluster = LocalCluster(n_workers=int(workers or 2), threads_per_worker=1, processes=True,
                                             host="127.0.0.1", dashboard_address=None,
                                             silence_logs=logging.ERROR)
                self.client = Client(self._cluster)
        except (OSError, TimeoutError) as exc:
            raise ConfigError(f"--scheduler {address}: cannot reach the Dask scheduler ({exc})") from None
        self.workers = len(self.client.scheduler_info().get("workers", {})) or int(workers or 1)

    def map(self, fn, tasks, on_units, on_done, on_interrupt=None):
        from distributed import as_completed

        futures = [self.client.submit(fn, t, key=f"campaign-ann-{t['id']}-{os.getpid()}-{time.time_ns()}",
                                      pure=False) for t in tasks]
        self._futures = futures
        index = {f.key: i for i, f in enumerate(futures)}
        results = [None] * len(tasks)
        try:
            for f in as_completed(futures):
                r = f.result()
                results[index[f.key]] = r
                if on_units:
                    on_units(r["id"], None)
                on_done(r)
        except KeyboardInterrupt:  # Ctrl-C: this client's tasks cancelled on the cluster
            if on_interrupt:
                on_interrupt()
            self.abort()
            raise
        return results

    def close(self):
        self.client.close()
        if self._cluster is not None:
            self._cluster.close()

    def abort(self):
        """Stop at once (Ctrl-C): this client's tasks cancelled on the cluster, then closed."""
        try:
            self.client.cancel(getattr(self, "_futures", []), force=True)
        except Exception:  # a cluster that is gone cannot be asked: closing is all that is left
            pass


def make_executor(workers: int | None = None, scheduler: str | None = None, dask: bool = False):
    """The executor for these options: a Dask scheduler address, a local Dask cluster
    (``dask=True``), N worker processes (N > 1), or this process."""
    if scheduler:
        return DaskExecutor(address=scheduler)
    if dask:
        return DaskExecutor(workers=workers or 2)
    if workers is not None and int(workers) < 1:
        raise ConfigError(f"--workers must be at least 1, not {workers}")
    if workers and int(workers) > 1:
        return ProcessExecutor(int(workers))
    return SerialExecutor()


def resolve_device(device="auto") -> str:
    """The torch device to train on: ``"auto"`` (or None) is ``"cuda"`` when torch finds a GPU,
    else ``"cpu"``; anything else is checked (a ConfigError naming ``--device`` for a device torch
    does not know, one it cannot use here, or one other than cpu / cuda) and returned."""
    import torch

    if device is None or device == "auto":
        return "cuda" if torch.cuda.is_available() else "cpu"
    try:
        dev = torch.device(device)
    except (RuntimeError, TypeError):
        raise ConfigError(f"--device {device!r}: not a torch device (auto, cpu, cuda, cuda:1, ...)") from None
    if dev.type == "cuda" and not torch.cuda.is_available():
        raise ConfigError(f"--device {device}: torch finds no CUDA GPU on this machine")
    if dev.type not in ("cpu", "cuda"):
        raise ConfigError(f"--device {device}: only auto, cpu and cuda devices are supported")
    return str(device)


def default_workers() -> int:
    """Worker processes for the local run: the usable cores, at most 2 per the issue's machine."""
    try:
        return max(1, len(os.sched_getaffinity(0)))
    except AttributeError:  # not on Linux
        return max(1, os.cpu_count() or 1)


# -- the grid ---------------------------------------------------------------------------------

@dataclass(frozen=True)
class GridProgress:
    """Whole-grid progress (what the progress bar shows): work units (members × epochs ×
    weights) done and expected in all, tasks finished of all, and the time left (``eta_s``, from
    the measured seconds per epoch of each training: :class:`GridMeter`). ``str()`` is one
    status line."""

    done: float
    total: float
    tasks_done: int
    tasks: int
    elapsed_s: float
    last: str = ""
    eta_s: float = float("inf")

    def __str__(self) -> str:
        eta = f"ETA {self.eta_s:.0f} s" if np.isfinite(self.eta_s) else "ETA (measuring)"
        return (f"ANN grid: {self.tasks_done}/{self.tasks} trainings, {100 * self.done / max(self.total, 1):.0f} %, "
                f"{eta} {self.last}")


#: before two sizes have been timed, the time per epoch is taken to grow as n_weights^this
#: (a forward/backward pass grows as n_weights, the LM system as up to its square; measured
#: 1.2-1.6 on the default grid)
EPOCH_TIME_EXPONENT = 1.4


class GridMeter:
    """Turns the tasks' reports into GridProgress. Work (units of members × epochs × weights):
    the finished tasks' actual epochs, for the others members × the mean epochs of finished
    members (a measured guess per solver before any has finished).

    Time left (``eta_s``), from what was measured: each running task's own seconds per epoch
    (since its first report); for tasks not started, seconds per epoch fitted over the timed
    tasks as c · n_weights^a. Epochs left of a running task: for the member in training, the
    typical member's epochs (the mean of the task's own finished members, else of all finished
    members, else the solver's guess) or, when more, as many again as it has run (a quarter more
    once members of its own task have finished: their length is the better guess; a member past
    the typical length is not about to stop: sizes differ tenfold in epochs); its members still
    to train as long as its finished ones, else at least as long as that one has run. The
    tasks are laid out over the executor's ``workers`` in dispatch order (the largest first).
    ``clock``: the time source (s), for tests."""

    def __init__(self, tasks, solver, progress, workers: int = 1, clock=time.perf_counter):
        self.progress = progress
        self.clock = clock
        self.t0 = clock()
        self.order = [t["id"] for t in tasks]
        self.n_w = {t["id"]: float(t["n_weights"]) for t in tasks}
        self.members = {t["id"]: len(t["members"]) for t in tasks}
        self.size = {tid: self.members[tid] * self.n_w[tid] for tid in self.order}
        self.done_units = {tid: 0.0 for tid in self.order}
        self.member_epochs = {tid: [] for tid in self.order}  # members finished inside a running task
        self.started = {}  # task -> time of its first report
        self.finished = {}  # task -> (units, wall s, member epochs)
        self.epochs_seen = []
        self.guess = _EPOCH_GUESS[solver]
        self.sequential = solver == "br-lm"  # its members train one after another (adam: as one batch)
        self.lock = threading.Lock()
        self.n = len(tasks)
        self.workers = max(1, int(workers))

    def units(self, tid, units):
        """A report of task ``tid``: work units done since its last report, or ("member", epochs)
        when one of its members finished; None: nothing to count (a finished Dask task)."""
        # a worker's progress queue is flushed by a feeder thread, so its last report of a task
        # may arrive after the task's result, even during the next grid on the same pool
        # (the final trainings): reports of finished or unknown tasks are late, not news
        if units is None:
            return
        with self.lock:
            if tid not in self.done_units or tid in self.finished:
                return
            self.started.setdefault(tid, self.clock())
            if isinstance(units, tuple):  # ("member", epochs): the member's whole length, ticks or not
                self.member_epochs[tid].append(float(units[1]))
                self.done_units[tid] = sum(self.member_epochs[tid]) * self.n_w[tid]
            else:
                self.done_units[tid] += units
        self._emit()

    def done(self, result):
        with self.lock:
            eps = [m["epochs"] for m in result["members"]]
            self.epochs_seen += eps
            n_w = self.size[result["id"]] / max(1, len(eps))
            units = sum(eps) * n_w
            self.finished[result["id"]] = (units, float(result["wall_s"]), float(sum(eps)))
            self.done_units[result["id"]] = units
        self._emit(last=f"(last: {result['id']}, {result['wall_s']:.0f} s)")

    def _epochs_left(self, tid, typical_all) -> float:
        """Member epochs task ``tid`` still has to train (see the class)."""
        done_ep = self.done_units[tid] / self.n_w[tid]
        own = self.member_epochs[tid]
        typical = float(np.mean(own)) if own else typical_all
        members_left = self.members[tid] - len(own)
        if members_left <= 0:
            return 0.0
        if self.sequential:
            current = done_ep - sum(own)
            expected = max(typical, (1.25 if own else 2.0) * current)
            return expected - current + (members_left - 1) * (typical if own else max(typical, current))
        per_member = done_ep / self.members[tid]  # a batch: every member at the same epoch
        return self.members[tid] * (max(typical, 2.0 * per_member) - per_member)

    def eta_s(self, now=None) -> float:
        """Seconds left (inf until a training has been timed)."""
        now = self.clock() if now is None else now
        typical_all = float(np.mean(self.epochs_seen)) if self.epochs_seen else self.guess
        timed = {tid: wall / max(ep, 1.0) for tid, (_, wall, ep) in self.finished.items()}
        for tid, t_start in self.started.items():
            ep = self.done_units[tid] / self.n_w[tid]
            if tid not in self.finished and ep > 0 and now > t_start:
                timed[tid] = (now - t_start) / ep
        if not timed:
            return float("inf")
        x = np.log([self.n_w[t] for t in timed])
        y = np.log(list(timed.values()))
        a = np.polyfit(x, y, 1)[0] if len(timed) >= 2 and np.ptp(x) > 0.1 else EPOCH_TIME_EXPONENT
        a = float(np.clip(a, 0.5, 2.5))
        c = float(np.exp(np.mean(y - a * x)))
        running, queued = [], []
        for tid in self.order:
            if tid in self.finished:
                continue
            left = self._epochs_left(tid, typical_all) * timed.get(tid, c * self.n_w[tid] ** a)
            (running if tid in self.started else queued).append(left)
        free = sorted(running + [0.0] * max(0, self.workers - len(running)))
        for t in queued:  # the next task goes to the first worker free
            free[0] += t
            free.sort()
        return float(max(free, default=0.0))

    def _emit(self, last=""):
        if self.progress is None:
            return
        mean_ep = float(np.mean(self.epochs_seen)) if self.epochs_seen else self.guess
        total = 0.0
        for tid, size in self.size.items():
            if tid in self.finished:
                total += self.finished[tid][0]
            else:
                total += max(size * mean_ep, self.done_units[tid] * 1.05)
        done = sum(self.done_units.values())
        now = self.clock()
        self.progress(GridProgress(done, total, len(self.finished), self.n, now - self.t0, last, self.eta_s(now)))


#: with the adam solver, sizes with fewer weights than this train both priors' folds in one batch
#: (small products: the per-step overhead, not the flops, sets their time, and a batch of 10
#: members costs little more than one of 5); larger sizes get one task per prior, so that the
#: two workers share the largest trainings
MERGE_PRIORS_BELOW_WEIGHTS = 2000


def make_tasks(q, dz_by_prior: dict, *, sizes, folds, seed, solver, input_mapping, options=None,
               device="cpu") -> list:
    """The CV trainings as tasks: per size, the K folds of each prior as members, in one task
    per prior, or (adam, small sizes) one task for all priors."""
    from campaign.ann.mlp import MLP

    x = input_mapping.apply(q)
    fold = fold_of(len(q), folds, seed)
    n_out = np.shape(next(iter(dz_by_prior.values())))[1]
    tasks = []
    for hidden in sizes:
        groups = [[p] for p in dz_by_prior]
        if solver == "adam" and MLP(q.shape[1], tuple(hidden), n_out).n_weights < MERGE_PRIORS_BELOW_WEIGHTS:
            groups = [list(dz_by_prior)]
        for group in groups:
            members = [{"prior": p, "fold": k, "train_rows": np.flatnonzero(fold != k),
                        "heldout_rows": np.flatnonzero(fold == k), "seed": seed + 101 * k}
                       for p in group for k in range(folds)]
            tasks.append(_task(f"{'+'.join(group)}/{hidden[0]}x{hidden[1]}/cv", q, x,
                               {p: dz_by_prior[p] for p in group}, hidden, members, seed, solver,
                               input_mapping, options, device))
    return tasks


def _task(tid, q, x, dz, hidden, members, seed, solver, input_mapping, options, device):
    from campaign.ann.mlp import MLP

    n_in, n_out = q.shape[1], np.shape(next(iter(dz.values())))[1]
    return {"id": tid, "hidden": [int(h) for h in hidden], "solver": solver, "seed": int(seed),
            "q": q, "x": x, "dz": dz, "members": members, "options": dict(options or {}), "device": device,
            "q_lower": input_mapping.mean - np.sqrt(3.0) * input_mapping.scale,
            "q_upper": input_mapping.mean + np.sqrt(3.0) * input_mapping.scale,
            "n_in": int(n_in), "n_out": int(n_out), "n_weights": MLP(n_in, tuple(hidden), n_out).n_weights}


def diverged_folds(dz_true, dz_pred, fold, target_scale) -> list:
    """The folds (0-based) whose held-out RMSE of normalised Δz exceeds DIVERGED_RMSE_NORMALISED
    or is not finite (dz (n, k), fold (n,), target_scale (k,))."""
    out = []
    for k in np.unique(fold):
        res = (dz_true[fold == k] - dz_pred[fold == k]) / target_scale
        with np.errstate(over="ignore", invalid="ignore"):
            rmse = float(np.sqrt(np.mean(res ** 2)))
        if not rmse <= DIVERGED_RMSE_NORMALISED:
            out.append(int(k))
    return out


def cv_row_text(row) -> str:
    """``CV (32, 16): RMSE 0.412, max ‖Δr‖ 0.093 mm``, or that the size diverged (in which folds)."""
    folds = row.get("diverged_folds") or []
    if folds:
        return (f"CV {tuple(row['hidden'])}: diverged in fold{'s' if len(folds) > 1 else ''} "
                f"{', '.join(str(k + 1) for k in folds)} (held-out error beyond {DIVERGED_RMSE_NORMALISED:g}× the "
                "residuals' spread): not chosen")
    return f"CV {tuple(row['hidden'])}: RMSE {row['rmse_normalised']:.3f}, max ‖Δr‖ {row['max_position_mm']:.3f} mm"


def best_row(rows, say=None) -> dict:
    """The size with the lowest held-out RMSE among those that did not diverge (all diverged: the
    least bad, said through ``say``)."""
    usable = [row for row in rows if not row.get("diverged_folds")]
    if not usable and say:
        say("every size diverged in some fold: the least bad is kept")
    return min(usable or rows, key=lambda row: row["rmse_normalised"] if np.isfinite(row["rmse_normalised"])
               else np.inf)


def cv_stats(dz_true, dz_pred, target_scale) -> dict:
    """Table 5 statistics of held-out predictions: RMSE of normalised Δz_tot, max ‖Δr‖ mm, max ‖Δφ‖ mrad
    (None for position-only residuals, (n, 3))."""
    res = dz_true - dz_pred
    return {"rmse_normalised": float(np.sqrt(np.mean((res / target_scale) ** 2))),
            "max_position_mm": float(np.max(np.linalg.norm(res[:, :3], axis=1)) * 1e3),
            "max_orientation_mrad": float(np.max(np.linalg.norm(res[:, 3:], axis=1)) * 1e3) if res.shape[1] == 6
            else None,
            "mean_position_mm": float(np.mean(np.linalg.norm(res[:, :3], axis=1)) * 1e3)}


def _interruptible(executor, tasks, meter, say):
    """``executor.map(run_task, ...)``; on Ctrl-C it says so at once, then the executor stops its
    work (worker processes terminated, cluster tasks cancelled) and the interrupt goes on up."""
    def stopping():
        if say:
            say(f"interrupted (Ctrl-C): stopping the network's training on {executor.name}; nothing is written")

    return executor.map(run_task, tasks, meter.units, meter.done, on_interrupt=stopping)


def run_grid(q, dz_by_prior: dict, *, sizes, folds=5, seed=0, solver="adam", q_lower=None, q_upper=None,
             executor=None, progress=None, device="auto", switch_off=True, **options):
    """Cross-validate every size for every prior model and build each prior's network.

    q (n, N) training poses (rad, m), N the robot's joints; dz_by_prior: prior name -> residuals
    (n, 6) (m, rad) of that prior model on the same poses, or (n, 3) (m) for position-only data
    (all priors alike). q_lower, q_upper: the robot's joint limits (N,) for the input mapping
    (None: the embedded robot's, 6 joints). Returns {prior: (ResidualNetwork, cv dict)} where the cv dict
    is the Table 5 block: ``{"sizes": [row...], "best", "folds", "solver", "final": {...}}``.
    options: AdamOptions fields (solver "adam") or ResidualNetwork hyperparameters ("br-lm").
    progress: optional callable receiving :class:`GridProgress` reports and status lines (str).
    switch_off: a prior whose chosen size shows no significant held-out gain in the cross-validation
    (campaign.ann.gain: the upper end of the 95 % interval of its RMSE ratio at or above 1) gets a
    network of zero weights (``switched_off_``: the prior model unchanged), its ``final`` block saying
    why; no final network is trained for it.
    """
    from campaign.ann.mlp import MLP, joint_limits, joint_mapping
    from campaign.ann.network import ResidualNetwork

    if solver not in SOLVERS:
        raise ConfigError(f"--ann-solver must be one of {', '.join(SOLVERS)}, not {solver!r}")
    q = np.asarray(q, dtype=float)
    if q.ndim != 2 or q.shape[1] < 1 or len(q) < max(folds, 2):  # folds == n: leave-one-out
        raise DataError(f"ANN cross-validation: need q (n, N) with n >= {max(folds, 2)}, got {q.shape}")
    widths = {np.shape(dz)[1] if np.ndim(dz) == 2 else None for dz in dz_by_prior.values()}
    for prior, dz in dz_by_prior.items():
        if np.ndim(dz) != 2 or np.shape(dz)[0] != len(q) or len(widths) != 1 or np.shape(dz)[1] not in (3, 6) \
                or not np.all(np.isfinite(dz)):
            raise DataError(f"ANN cross-validation: residuals of {prior} must be finite (n, 6), or (n, 3) for "
                            f"position-only data, alike for every prior; got {np.shape(dz)}")
    if not (np.all(np.isfinite(q))):
        raise DataError("ANN cross-validation: q must be finite")
    mapping = joint_mapping(*joint_limits(q_lower, q_upper, q.shape[1]))
    device = "auto" if device is None or device == "auto" else resolve_device(device)  # auto: per worker
    if solver == "adam":
        if "max_epochs" in options and options["max_epochs"] is None:
            options.pop("max_epochs")
        from campaign.ann.adam import AdamOptions

        unknown = set(options) - set(AdamOptions.__dataclass_fields__)
        if unknown:
            raise ConfigError(f"options not used by the adam solver: {', '.join(sorted(unknown))}")
    tasks = make_tasks(q, {p: np.asarray(d, dtype=float) for p, d in dz_by_prior.items()}, sizes=sizes,
                       folds=folds, seed=seed, solver=solver, input_mapping=mapping, options=options, device=device)
    tasks.sort(key=lambda t: -len(t["members"]) * t["n_weights"])  # largest first
    own = executor is None
    executor = executor or SerialExecutor()
    say = progress if progress is not None else None
    meter = GridMeter(tasks, solver, say, executor.workers)
    try:
        t0 = time.perf_counter()
        results = _interruptible(executor, tasks, meter, say)
        cv_wall = time.perf_counter() - t0
        # (prior, size) -> [(fold, member index in its task, task result)]
        where = {}
        for t, r in zip(tasks, results):
            for i, m in enumerate(t["members"]):
                where.setdefault((m["prior"], tuple(t["hidden"])), []).append((m["fold"], i, r))
        out = {}
        fold = fold_of(len(q), folds, seed)
        finals = []
        for prior, dz in dz_by_prior.items():
            dz = np.asarray(dz, dtype=float)
            scale = np.where(dz.std(axis=0) > 0, dz.std(axis=0), 1.0)
            rows = []
            for hidden in sizes:
                parts = where[(prior, tuple(hidden))]
                r = parts[0][2]
                pred = np.empty_like(dz)
                for k, _, rk in parts:
                    pred[fold == k] = rk["heldout_pred"][f"{prior}/{k}"]
                diverged = diverged_folds(dz, pred, fold, scale)
                infos = [rk["members"][i] for _, i, rk in parts]
                rows.append({"hidden": list(hidden), **cv_stats(dz, pred, scale),
                             "heldout_gain": heldout_gain(dz, dz - pred, scale),
                             "epochs": [m["epochs"] for m in infos],
                             **({"gamma_folds": [float(m["gamma"]) for m in infos]} if solver == "br-lm" else {}),
                             "diverged_folds": diverged,
                             "task": r["id"], "task_wall_s": r["wall_s"], "task_cpu_s": r["cpu_s"]})
                if say:
                    say(f"[{prior}] {cv_row_text(rows[-1])} ({r['wall_s']:.0f} s)")
            best = best_row(rows, None if say is None else lambda msg: say(f"[{prior}] {msg}"))
            out[prior] = {"sizes": rows, "best": list(best["hidden"]), "heldout_gain": best["heldout_gain"],
                          "folds": folds, "solver": solver,
                          "executor": executor.name, "workers": executor.workers, "cv_wall_s": cv_wall,
                          "devices": sorted({r.get("device", "cpu") for r in results})}
            if switch_off and not best["heldout_gain"]["significant"]:
                continue  # no network for this prior (below); nothing to retrain
            if solver == "br-lm":
                members = [{"prior": prior, "fold": None, "train_rows": np.arange(len(q)), "heldout_rows": None,
                            "seed": seed}]
                finals.append(_task(f"{prior}/{best['hidden'][0]}x{best['hidden'][1]}/final", q, mapping.apply(q),
                                    {prior: dz}, best["hidden"], members, seed, solver, mapping, options, device))
        nets = {}
        if finals:
            fmeter = GridMeter(finals, solver, say, executor.workers)
            for r in _interruptible(executor, finals, fmeter, say):
                prior = r["id"].split("/")[0]
                m = r["members"][0]
                nets[prior] = ResidualNetwork.from_members(
                    out[prior]["best"], r["weights"][0], mapping, r["target_mean"][0], r["target_scale"][0],
                    alpha_=m["alpha"], beta_=m["beta"], gamma_=m["gamma"], n_epochs_=m["epochs"],
                    stop_reason_=m["stop"])
                out[prior]["final"] = {"hidden": out[prior]["best"], "epochs": m["epochs"], "gamma": m["gamma"],
                                       "alpha": m["alpha"], "beta": m["beta"], "n_weights": m["n_weights"],
                                       "stop": m["stop"], "wall_s": r["wall_s"]}
        elif solver == "adam":
            for prior in dz_by_prior:
                if switch_off and not out[prior]["heldout_gain"]["significant"]:
                    continue
                hidden = out[prior]["best"]
                parts = sorted(where[(prior, tuple(hidden))], key=lambda p: p[0])
                infos = [rk["members"][i] for _, i, rk in parts]
                nets[prior] = ResidualNetwork.from_members(
                    hidden, np.stack([rk["weights"][i] for _, i, rk in parts]), mapping,
                    np.stack([rk["target_mean"][i] for _, i, rk in parts]),
                    np.stack([rk["target_scale"][i] for _, i, rk in parts]),
                    n_epochs_=max(m["epochs"] for m in infos), stop_reason_="early_stopping")
                out[prior]["final"] = {"hidden": list(hidden), "kind": f"ensemble of the {folds} fold networks",
                                       "epochs": [m["epochs"] for m in infos],
                                       "best_epochs": [m["best_epoch"] for m in infos]}
        for prior in dz_by_prior:
            if prior not in nets:  # switched off: the cross-validation found no significant held-out gain
                hidden = out[prior]["best"]
                n_out = np.shape(dz_by_prior[prior])[1]
                nets[prior] = ResidualNetwork.from_members(
                    hidden, np.zeros(MLP(q.shape[1], tuple(hidden), n_out).n_weights), mapping, np.zeros(n_out),
                    np.ones(n_out), gamma_=0.0, stop_reason_="switched_off", switched_off_=True)
                best = next(r for r in out[prior]["sizes"] if r["hidden"] == list(hidden))
                out[prior]["final"] = {"hidden": list(hidden), "switched_off": True,
                                       "n_weights": nets[prior].net_.n_weights,
                                       "reason": "no significant held-out gain in the cross-validation: the prior "
                                                 "model is kept (the network predicts zero)",
                                       **({"gamma_folds": best["gamma_folds"]} if "gamma_folds" in best else {})}
        return {prior: (nets[prior], out[prior]) for prior in dz_by_prior}
    finally:
        if own:
            executor.close()
