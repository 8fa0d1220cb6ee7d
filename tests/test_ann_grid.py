"""The batched cross-validation grid (issue 15): batched Adam against single trainings with
torch.optim.Adam, the executors (this process, worker processes, a two-worker Dask
LocalCluster) against each other, BR-LM through the grid against the sequential
cross-validation, ensembles saved and reloaded, device and scheduler errors named."""

import json

import numpy as np
import pytest
import torch

from campaign.ann import ResidualNetwork, cross_validate
from campaign.ann.adam import AdamOptions, train_batched
from campaign.ann.grid import GridProgress, ProcessExecutor, run_grid
from campaign.ann.mlp import MLP, joint_mapping
from campaign.errors import ConfigError

LO, HI = -np.ones(6) * 2.5, np.ones(6) * 2.5


def smooth_data(n, seed=0):
    rng = np.random.default_rng(seed)
    q = rng.uniform(LO, HI, size=(n, 6))
    dz = np.stack([1e-4 * np.sin(q[:, 1]) * np.cos(q[:, 2]), 2e-4 * np.sin(q[:, 0] + q[:, 1]),
                   1e-4 * np.cos(2 * q[:, 2]), 1e-3 * np.sin(q[:, 3]), 5e-4 * np.cos(q[:, 4]),
                   1e-3 * np.sin(q[:, 1] - q[:, 2])], axis=1)
    return q, dz + rng.normal(0, 1e-6, dz.shape)


def test_batched_adam_equals_each_member_trained_alone_with_torch_adam():
    """Three members with their own rows and targets, batched, against torch.optim.Adam on one
    network at a time with the same initial weights and mini-batches (float64)."""
    q, dz = smooth_data(90)
    x = joint_mapping(LO, HI).apply(q)
    net = MLP(6, (5, 4), 6)
    rng = np.random.default_rng(3)
    fits = [np.sort(rng.permutation(90)[:60]) for _ in range(3)]
    vals = [np.setdiff1d(np.arange(90), f)[:20] for f in fits]
    targets = np.stack([dz / dz.std(0) * (1 + b) for b in range(3)])
    seeds = [11, 12, 13]
    opts = AdamOptions(lr=1e-2, batch=16, max_epochs=4, patience=100, eval_every=1, lr_decay_after=0,
                       dtype="float64")
    W, info = train_batched((5, 4), x, targets, fits, vals, seeds=seeds, options=opts)
    for b in range(3):
        w = net.init(torch.Generator().manual_seed(seeds[b]), torch.float64).requires_grad_(True)
        adam = torch.optim.Adam([w], lr=1e-2, betas=(0.9, 0.999), eps=1e-8)
        gen = torch.Generator().manual_seed(seeds[b] + 7919)
        X, Y = torch.as_tensor(x), torch.as_tensor(targets[b])
        best, best_w = np.inf, None
        for _ in range(4):
            order = torch.as_tensor(fits[b])[torch.randperm(60, generator=gen)]
            for i in range(0, 60, 16):
                idx = order[i:i + 16]
                adam.zero_grad()
                loss = ((net.forward(w, X[idx])[0] - Y[idx]) ** 2).mean()
                loss.backward()
                adam.step()
            with torch.no_grad():
                v = float(((net.forward(w, X[vals[b]])[0] - Y[vals[b]]) ** 2).mean())
            if v < best:
                best, best_w = v, w.detach().clone()
        np.testing.assert_allclose(W[b], best_w.numpy(), rtol=1e-9, atol=1e-11)
        assert info[b]["val_mse"] == pytest.approx(best, rel=1e-9)


@pytest.fixture(scope="module")
def grid_data():
    q, dz = smooth_data(330, seed=1)
    return q[:300], {"a": dz[:300], "b": dz[:300] ** 2 * 1e3}, q[300:], dz[300:]


def _grid(grid_data, **kw):
    q, priors, _, _ = grid_data
    reports = []
    out = run_grid(q, priors, sizes=[(6, 4), (8, 6)], folds=3, q_lower=LO, q_upper=HI,
                   progress=lambda m: reports.append(m), **kw)
    return out, reports


def test_grid_on_worker_processes_and_on_dask_gives_the_local_selection_and_errors(grid_data):
    opts = dict(solver="adam", max_epochs=40, patience=15)
    local, reports = _grid(grid_data, **opts)
    bars = [r for r in reports if isinstance(r, GridProgress)]
    # small sizes: one task per size holds both priors' folds (MERGE_PRIORS_BELOW_WEIGHTS)
    assert bars[-1].tasks_done == bars[-1].tasks == 2 and bars[-1].done == pytest.approx(bars[-1].total)
    assert all(b.done <= b.total + 1e-9 for b in bars)
    ex = ProcessExecutor(2)
    try:
        procs, _ = _grid(grid_data, executor=ex, **opts)
    finally:
        ex.close()
    pytest.importorskip("distributed")
    from campaign.ann.grid import DaskExecutor

    dask = DaskExecutor(workers=2)
    try:
        assert dask.workers == 2
        # the local cluster listens on the loopback only (Dask speaks pickle)
        info = dask.client.scheduler_info()
        assert info["address"].startswith("tcp://127.0.0.1:")
        assert len(info["workers"]) == 2 and all(w.startswith("tcp://127.0.0.1:") for w in info["workers"])
        on_dask, _ = _grid(grid_data, executor=dask, **opts)
    finally:
        dask.close()
    q_test, dz_test = grid_data[2], grid_data[3]
    for other in (procs, on_dask):
        for prior in ("a", "b"):
            net, cv = local[prior]
            net2, cv2 = other[prior]
            assert cv2["best"] == cv["best"]
            for r, r2 in zip(cv["sizes"], cv2["sizes"]):
                assert r2["rmse_normalised"] == pytest.approx(r["rmse_normalised"], rel=1e-5)
                assert r2["epochs"] == r["epochs"]
            np.testing.assert_allclose(net2.predict(q_test), net.predict(q_test), rtol=1e-5, atol=1e-10)
        # the same test errors (prior "a" is the held-out data's own residual)
        err, err2 = (np.linalg.norm(dz_test[:, :3] - n.predict(q_test)[:, :3], axis=1)
                     for n in (local["a"][0], other["a"][0]))
        assert err2.mean() == pytest.approx(err.mean(), rel=1e-5)
        assert err2.max() == pytest.approx(err.max(), rel=1e-5)


def test_br_lm_through_the_grid_equals_the_sequential_cross_validation(grid_data):
    q, priors, _, _ = grid_data
    out, reports = _grid(grid_data, solver="br-lm", max_epochs=8)
    ref = cross_validate(q, priors["a"], sizes=[(6, 4), (8, 6)], folds=3, q_lower=LO, q_upper=HI, max_epochs=8)
    _, cv = out["a"]
    assert cv["best"] == ref["best"]
    for r, r2 in zip(cv["sizes"], ref["sizes"]):
        assert r["rmse_normalised"] == pytest.approx(r2["rmse_normalised"], rel=1e-9)
        assert r["epochs"] == r2["epochs"]
    fin = cv["final"]  # the evidence quantities of the final BR-LM network are reported
    assert 0 < fin["gamma"] <= fin["n_weights"] and fin["alpha"] > 0 and fin["beta"] > 0
    single = ResidualNetwork(hidden=tuple(cv["best"]), q_lower=LO, q_upper=HI, max_epochs=8).fit(q, priors["a"])
    np.testing.assert_allclose(out["a"][0].predict(q), single.predict(q), rtol=1e-9, atol=1e-12)
    assert out["a"][0].gamma_ == pytest.approx(single.gamma_, rel=1e-9)


def test_an_ensemble_predicts_its_members_mean_and_reloads_identically(tmp_path, grid_data):
    q, priors, q_test, _ = grid_data
    rng = np.random.default_rng(0)
    net = MLP(6, (6, 4), 6)
    W = rng.normal(0, 0.5, (3, net.n_weights))
    mu, sd = rng.normal(0, 1e-4, (3, 6)), rng.uniform(1e-4, 1e-3, (3, 6))
    mapping = joint_mapping(LO, HI)
    ens = ResidualNetwork.from_members((6, 4), W, mapping, mu, sd)
    singles = [ResidualNetwork.from_members((6, 4), W[k], mapping, mu[k], sd[k]).predict(q_test) for k in range(3)]
    # member k by hand: tanh layers on the mapped joints, mapped back
    x = torch.as_tensor(mapping.apply(q_test))
    by_hand = net.forward(torch.as_tensor(W[1]), x)[0].numpy() * sd[1] + mu[1]
    np.testing.assert_allclose(singles[1], by_hand, rtol=1e-12)
    np.testing.assert_allclose(ens.predict(q_test), np.mean(singles, axis=0), rtol=1e-12, atol=1e-15)
    ens.save(tmp_path / "ens.pt")
    np.testing.assert_array_equal(ResidualNetwork.load(tmp_path / "ens.pt").predict(q_test), ens.predict(q_test))


DEVICES = ["cpu"] + (["cuda"] if torch.cuda.is_available() else [])


@pytest.mark.parametrize("device", DEVICES)
def test_the_grid_on_a_device_in_float32_agrees_with_the_cpu_in_float64(grid_data, device):
    """The batched Adam on each available device (the CPU always, a GPU where torch finds one)
    with float32 products, through the whole grid (tasks, executor, early stopping, ensembles),
    against the same grid in float64 on the CPU: same selection and stopping epochs, CV errors
    and test predictions within float32 round-off (measured on the CPU: 1e-8 relative)."""
    q, priors, q_test, _ = grid_data
    opts = dict(sizes=[(6, 4), (8, 6)], folds=3, q_lower=LO, q_upper=HI, solver="adam", max_epochs=40, patience=15)
    ref = run_grid(q, priors, device="cpu", dtype="float64", **opts)
    got = run_grid(q, priors, device=device, dtype="float32", **opts)
    for prior in priors:
        (net, cv), (net2, cv2) = ref[prior], got[prior]
        assert cv["devices"] == ["cpu"] and cv2["devices"] == [device]
        assert cv2["best"] == cv["best"]
        for r, r2 in zip(cv["sizes"], cv2["sizes"]):
            assert r2["epochs"] == r["epochs"]
            assert r2["rmse_normalised"] == pytest.approx(r["rmse_normalised"], rel=1e-5)
        p, p2 = net.predict(q_test), net2.predict(q_test)
        assert p2.dtype == np.float64
        np.testing.assert_allclose(p2, p, rtol=0, atol=1e-5 * np.abs(p).max())


def test_device_auto_is_the_gpu_where_torch_finds_one():
    from campaign.ann.grid import resolve_device

    assert resolve_device("auto") == resolve_device(None) == ("cuda" if torch.cuda.is_available() else "cpu")
    assert resolve_device("cpu") == "cpu"


def test_device_and_solver_errors_are_named(grid_data):
    q, priors, _, _ = grid_data
    with pytest.raises(ConfigError, match="--device"):
        run_grid(q, priors, sizes=[(4, 4)], folds=3, q_lower=LO, q_upper=HI, device="tpu:0")
    if not torch.cuda.is_available():
        with pytest.raises(ConfigError, match="no CUDA GPU"):
            run_grid(q, priors, sizes=[(4, 4)], folds=3, q_lower=LO, q_upper=HI, device="cuda")
    with pytest.raises(ConfigError, match="--ann-solver"):
        run_grid(q, priors, sizes=[(4, 4)], folds=3, q_lower=LO, q_upper=HI, solver="sgd")
    with pytest.raises(ConfigError, match="not used by the adam solver"):
        run_grid(q, priors, sizes=[(4, 4)], folds=3, q_lower=LO, q_upper=HI, solver="adam", cg_maxiter=3)


def test_an_unreachable_scheduler_and_a_bad_worker_count_are_named():
    pytest.importorskip("distributed")
    from campaign.ann.grid import make_executor

    with pytest.raises(ConfigError, match=r"--scheduler tcp://127\.0\.0\.1:9: cannot reach"):
        make_executor(scheduler="tcp://127.0.0.1:9")
    with pytest.raises(ConfigError, match="--workers must be at least 1"):
        make_executor(workers=0)


def test_a_fleet_of_runs_calibrated_on_dask_matches_the_local_calibrations(tmp_path, robot):
    pytest.importorskip("distributed")
    from campaign.ann.grid import DaskExecutor
    from campaign.identify.calibrate import calibrate
    from campaign.identify.fleet import calibrate_runs
    from campaign.measure.csvio import write_measured_csv
    from campaign.measure.store import import_csv
    from campaign.sim.truth import make_truth, random_joint_poses, synthesize

    runs = []
    for seed in (3, 4):  # two robots of one type, each with its own errors
        meas = synthesize(make_truth(robot, seed=seed), random_joint_poses(robot, 200, seed=seed + 10), seed=seed + 20)
        write_measured_csv(tmp_path / f"m{seed}.csv", meas)
        import_csv(tmp_path / f"m{seed}.csv", tmp_path / f"run{seed}", robot)
        runs.append(tmp_path / f"run{seed}")
    ex = DaskExecutor(workers=2)
    try:
        remote = calibrate_runs(runs, executor=ex, effects=(), ann=False, write=False)
    finally:
        ex.close()
    for run in runs:
        local = calibrate(run, effects=(), ann=False, write=False).metrics
        got = remote[str(run)]
        assert got["order"] == local["order"] == ["nominal", "geometric"]
        for stage in local["order"]:
            for block in ("position_mm", "orientation_mrad"):
                for key in ("max", "mean"):
                    assert got["stages"][stage]["test"][block][key] == pytest.approx(
                        local["stages"][stage]["test"][block][key], rel=1e-9)
    # the two robots differ: the fleet did not calibrate one run twice
    a, b = (remote[str(r)]["stages"]["nominal"]["test"]["position_mm"]["mean"] for r in runs)
    assert abs(a - b) > 1e-3


def test_a_late_progress_report_from_an_earlier_grid_or_a_finished_task_is_ignored():
    """A worker's progress queue is flushed by a feeder thread: its last report of a CV task can
    arrive after the task's result, while the same pool trains the final networks under a new
    meter (seen once as KeyError 'nominal/8x8/cv'). Such reports change nothing."""
    from campaign.ann.grid import GridMeter

    seen = []
    tasks = [{"id": "a/final", "members": [0, 1], "n_weights": 10}, {"id": "b/final", "members": [0], "n_weights": 20}]
    meter = GridMeter(tasks, "adam", seen.append)
    meter.units("a/final", 30.0)
    assert seen[-1].done == 30.0 and seen[-1].tasks_done == 0
    meter.units("nominal/8x8/cv", 500.0)  # from the grid before, on the same worker pool
    assert len(seen) == 1
    meter.done({"id": "a/final", "members": [{"epochs": 4}, {"epochs": 6}], "wall_s": 1.0})
    done = seen[-1].done
    assert done == (4 + 6) * 10 and seen[-1].tasks_done == 1
    meter.units("a/final", 7.0)  # the finished task's last report, after its result
    assert seen[-1].done == done and len(seen) == 2
    meter.units("b/final", 5.0)
    assert seen[-1].done == done + 5.0


def test_campaign_calibrate_of_several_runs_calibrates_each_as_alone_and_names_the_one_that_fails(tmp_path, robot,
                                                                                                capsys):
    """`campaign calibrate RUN_A RUN_B MISSING --workers 2`: each run's metrics.json equals its
    calibration alone; the folder that is no run is one line naming it, the others still finish,
    exit 1."""
    from campaign.cli import main
    from campaign.identify.calibrate import calibrate
    from campaign.measure.csvio import write_measured_csv
    from campaign.measure.store import import_csv
    from campaign.sim.truth import make_truth, random_joint_poses, synthesize

    runs = []
    for seed in (5, 6):
        meas = synthesize(make_truth(robot, seed=seed), random_joint_poses(robot, 150, seed=seed + 10), seed=seed + 20)
        write_measured_csv(tmp_path / f"m{seed}.csv", meas)
        import_csv(tmp_path / f"m{seed}.csv", tmp_path / f"run{seed}", robot)
        runs.append(tmp_path / f"run{seed}")
    missing = tmp_path / "nothing_here"
    code = main(["calibrate", *map(str, runs), str(missing), "--no-ann", "--no-report", "--workers", "2", "--quiet"])
    out, err = capsys.readouterr()
    assert code == 1
    err_lines = err.strip().splitlines()
    assert len(err_lines) == 1 and str(missing) in err_lines[0], err
    assert "calibrated 2 of 3 runs on processes" in out
    for run in runs:
        written = json.loads((run / "calibration" / "metrics.json").read_text())
        alone = calibrate(run, effects=(), ann=False, write=False).metrics
        assert written["order"] == alone["order"] == ["nominal", "geometric"]
        got, want = written["stages"]["geometric"]["test"], alone["stages"]["geometric"]["test"]
        assert got["position_mm"]["mean"] == pytest.approx(want["position_mm"]["mean"], rel=1e-9)
        assert f"{run}: geometric: held-out mean position {want['position_mm']['mean']:.4g} mm" in out
