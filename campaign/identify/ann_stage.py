"""The neural residual stages of `campaign calibrate` (the paper's section 5).

Two variants, as in the paper's Tables 5 and 6: the network learns the residual of the
nominal model (stage ``ann``) or of the identified model (stage ``<model>+ann``, e.g.
``geometric+ann``). For each, hidden sizes are chosen by K-fold cross-validation on the
training set only, the best size is retrained on the whole training set, and the test set
is evaluated once, at the end.

Any serial robot: the network's inputs are the robot's N joint values, normalised with its
joint limits. Its outputs are the 6-D residual (Δt, Δφ), or Δt alone (3 outputs) when the run
measured positions only (one reflector): the network learns what was measured, and the
compensation then corrects the position of the measured point, leaving the orientation to the
kinematic model.
"""

from __future__ import annotations

import html
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from campaign.errors import ConfigError
from campaign.fileio import atomic_write_json
from campaign.model.kinematics import pose_error

#: hidden sizes tried by default: the paper's four and one beyond
DEFAULT_SIZES = ((16, 16), (32, 16), (32, 32), (64, 32), (128, 64))

#: sizes tried besides DEFAULT_SIZES on a small campaign (fewer than SMALL_SIZES_BELOW_POSES training
#: poses): a (16, 16) net has 486 weights against the 720 residuals of 120 poses and over-fits them
#: (held-out RMSE ratio 1.15-1.4) where a (4, 4)-(8, 8) net removes 10-25 % of a hidden joint
#: compliance on held-out poses (docs/ann.md, "Small campaigns")
SMALL_SIZES = ((4, 4), (8, 8))
SMALL_SIZES_BELOW_POSES = 1000

#: training method by default: "auto" = the paper's BR-LM on small runs (fewer than
#: AUTO_ADAM_MIN_POSES training poses), where it measured better and faster, and batched Adam
#: with early stopping and the fold networks' ensemble on larger runs, where it measured better
#: on the test set and ~10× faster (docs/ann.md: 960 and 11,200 training poses measured)
DEFAULT_SOLVER = "auto"
AUTO_ADAM_MIN_POSES = 4000


def default_sizes(n_train: int) -> tuple:
    """The hidden sizes cross-validated when none are given: DEFAULT_SIZES, after SMALL_SIZES on a
    small campaign (fewer than SMALL_SIZES_BELOW_POSES training poses)."""
    return (SMALL_SIZES + DEFAULT_SIZES) if n_train < SMALL_SIZES_BELOW_POSES else DEFAULT_SIZES


def parse_sizes(text: str) -> tuple:
    """``"16x16,32x16"`` -> ((16, 16), (32, 16))."""
    sizes = []
    for item in str(text).split(","):
        item = item.strip().lower()
        if not item:
            continue
        try:
            n1, n2 = (int(v) for v in item.split("x"))
        except ValueError:
            raise ConfigError(f"--sizes: '{item}' is not of the form N1xN2 (e.g. 64x32)") from None
        if n1 < 1 or n2 < 1:
            raise ConfigError(f"--sizes: '{item}' must have positive sizes")
        sizes.append((n1, n2))
    if not sizes:
        raise ConfigError("--sizes: no hidden sizes given")
    return tuple(sizes)


def format_table5(cv: dict) -> str:
    """Cross-validation results like the paper's Table 5, one block per variant."""
    lines = [f"{'hidden neurons':<16}{'RMSE Δz_tot':>14}{'max ‖Δr‖ mm':>14}{'max ‖Δφ‖ mrad':>15}  {'prior model':<20}"]
    for variant, block in cv.items():
        for row in block["sizes"]:
            mark = " *" if tuple(row["hidden"]) == tuple(block["best"]) else ""
            phi = row.get("max_orientation_mrad")
            phi = f"{phi:>15.3f}" if phi is not None else f"{'—':>15}"  # position-only data: no Δφ
            if row.get("diverged_folds"):  # its numbers are the divergence's, not an error
                folds = ", ".join(str(k + 1) for k in row["diverged_folds"])
                lines.append(f"{str(tuple(row['hidden'])):<16}{'diverged (fold ' + folds + ')':>43}  {variant:<20}{mark}")
                continue
            lines.append(f"{str(tuple(row['hidden'])):<16}{row['rmse_normalised']:>14.3f}"
                         f"{row['max_position_mm']:>14.3f}{phi}  {variant:<20}{mark}")
    solvers = {block.get("solver", "br-lm") for block in cv.values()}
    if solvers == {"adam"}:
        lines.append("* best by cross-validation (lowest RMSE of the normalised Δz_tot); the stage's network is the "
                     "mean of its fold networks (Adam, early stopping)")
    else:
        lines.append("* best by cross-validation (lowest RMSE of the normalised Δz_tot), retrained on the whole "
                     "training set")
    for variant, block in cv.items():
        fin = block.get("final", {})
        if "gamma" in fin:  # the BR-LM's evidence quantities of the final network
            lines.append(f"  {variant}: final {tuple(fin['hidden'])} γ = {fin['gamma']:.0f} of "
                         f"{fin.get('n_weights', '?')} weights, α = {fin['alpha']:.4g}, β = {fin['beta']:.4g}, "
                         f"{fin['epochs']} epochs ({fin.get('stop', '')})")
        elif fin.get("switched_off"):
            lines.append(f"  {variant}: {tuple(fin['hidden'])} switched off: {fin['reason']}")
    return "\n".join(lines)


@dataclass(frozen=True)
class AnnStages:
    """What the neural stages produced: the cross-validation of every prior (metrics.json's
    ``ann_cross_validation``, ann_cv.json), the saved networks (stage -> file beside
    params.yaml) and the paper's Table 5 as text."""

    cross_validation: dict
    files: dict
    table5: str
    #: stage -> the network's held-out gain over its prior model (metrics.json's ``ann_gain``,
    #: :func:`stage_gain`)
    gain: dict = field(default_factory=dict)

    def gain_lines(self) -> list:
        """One line per neural stage: its held-out gain, or that it has none worth the name."""
        from campaign.ann.gain import gain_text

        return [gain_text(stage, g) for stage, g in self.gain.items()]

    def report_html(self) -> str:
        """The report's Table 5 section."""
        gain = "".join(f"<p>{html.escape(line)}</p>" for line in self.gain_lines())
        return ("<h2>Cross-validation of the residual network (Table 5)</h2>"
                f"<pre>{html.escape(self.table5)}</pre>{gain}")


def run_ann_stages(run_dir, robot, poses, is_test, T_prior: dict, options: dict, progress=None, out_dir=None):
    """Train the residual networks; return ({stage: Δz (n, 6)}, :class:`AnnStages`).

    robot: the run's robot (its N joints' limits map the inputs); poses: the measured poses
    (q (n, N)); with positions only (``poses.has_orientation`` false) the networks learn and
    correct Δt alone. T_prior: stage name of the prior model -> its poses (n, 4, 4) for every
    measured pose, e.g. {"nominal": ..., "geometric": ...}. The ANN stage after "nominal" is
    called ``ann``; after any other model ``<model>+ann``. options: ``sizes``, ``folds``,
    ``solver`` ("auto" default, "adam" or "br-lm"), ``workers`` (local processes; default: the
    usable cores), ``scheduler`` (a Dask scheduler address: a trusted one, Dask uses pickle),
    ``dask`` (a local Dask cluster of ``workers`` on 127.0.0.1), ``device`` ("auto" default:
    "cuda" where torch finds a GPU, else "cpu"; or a torch device), and the solver's own
    hyperparameters (e.g. ``max_epochs``). All (prior, size) trainings of the grid are one map
    over the executor. out_dir: where the networks and ann_cv.json go (default RUN/calibration;
    `calibrate` gives the new calibration's folder).
    """
    try:
        from campaign.ann import compensate_pose
        from campaign.ann.grid import default_workers, make_executor, resolve_device, run_grid
    except ImportError as exc:
        raise ConfigError(f"the neural compensator is unavailable ({exc}); run with --no-ann") from None

    out = Path(out_dir) if out_dir is not None else Path(run_dir) / "calibration"
    out.mkdir(parents=True, exist_ok=True)
    tr = ~np.asarray(is_test, dtype=bool)
    options = dict(options)
    sizes = tuple(options.pop("sizes", None) or default_sizes(int(tr.sum())))
    folds = int(options.pop("folds", 5))
    solver = options.pop("solver", None) or DEFAULT_SOLVER
    if solver == "auto":
        solver = "adam" if int(tr.sum()) >= AUTO_ADAM_MIN_POSES else "br-lm"
    workers = options.pop("workers", None)
    scheduler = options.pop("scheduler", None)
    use_dask = bool(options.pop("dask", False))
    device = options.pop("device", None) or "auto"
    resolve_device(device)  # an unusable device is one line before any work
    executor = make_executor(workers=default_workers() if workers is None and not scheduler else workers,
                             scheduler=scheduler, dask=use_dask)
    dz_by_prior, stage_of = {}, {}
    outputs = slice(0, 6) if poses.has_orientation else slice(0, 3)  # what was measured
    for prior, T_model in T_prior.items():
        stage_of[prior] = "ann" if prior == "nominal" else f"{prior}+ann"
        dz_by_prior[prior] = pose_error(T_model, poses.T_IE)[:, outputs]
    if progress:
        where = f"auto: {resolve_device('auto')} here" if device == "auto" else device
        progress(f"ANN: {len(sizes)} sizes × {folds} folds × {len(T_prior)} priors, {robot.n_joints} joints → "
                 f"{outputs.stop} outputs, solver {solver}, "
                 f"{executor.name} ({executor.workers} worker{'s' if executor.workers != 1 else ''}), {where}")
    try:
        fitted = run_grid(poses.q[tr], {p: dz[tr] for p, dz in dz_by_prior.items()}, sizes=sizes, folds=folds,
                          solver=solver, q_lower=robot.q_lower, q_upper=robot.q_upper, executor=executor,
                          progress=progress, device=device, **options)
    finally:
        executor.close()
    residuals, cv_all, files, gain = {}, {}, {}, {}
    te = ~tr
    for prior, (net, cv) in fitted.items():
        stage = stage_of[prior]
        dz_hat = net.predict(poses.q)
        residuals[stage] = pose_error(compensate_pose(T_prior[prior], dz_hat), poses.T_IE)
        cv_all[prior] = cv
        gain[stage] = stage_gain(prior, net, cv, dz_by_prior[prior], residuals[stage][:, outputs], tr, te)
        fname = "ann_nominal.pt" if prior == "nominal" else "ann_geometric.pt"
        net.save(out / fname)
        files[stage] = fname
    atomic_write_json(out / "ann_cv.json", cv_all)
    return residuals, AnnStages(cross_validation=cv_all, files=files, table5=format_table5(cv_all), gain=gain)


def stage_gain(prior, net, cv, dz_prior, dz_after, tr, te) -> dict:
    """A neural stage's held-out gain (metrics.json's ``ann_gain[stage]``): ``prior``, ``solver``,
    ``hidden``, ``n_weights``, ``gamma`` (BR-LM's final network; None for Adam or when switched
    off), ``gamma_folds`` (BR-LM: the chosen size's fold networks'), ``switched_off`` (no
    significant gain in the cross-validation: the network predicts zero, the stage is its prior
    model), ``cv`` (the chosen size's out-of-fold predictions on the training poses) and ``test``
    (the test poses) as :func:`campaign.ann.gain.heldout_gain`, and ``significant`` (the
    cross-validation's: the test set is scored, not used to decide).
    dz_prior, dz_after: (n, k) residuals of every pose without and with the network."""
    from campaign.ann.gain import heldout_gain

    scale = dz_prior[tr].std(axis=0)
    scale = np.where(scale > 0, scale, 1.0)
    fin = cv.get("final", {})
    gamma = fin.get("gamma")
    best = next((r for r in cv.get("sizes", ()) if r["hidden"] == list(cv["best"])), {})
    cv_gain = cv.get("heldout_gain") or {"ratio": None, "significant": False}
    return {"prior": prior, "solver": cv.get("solver"), "hidden": list(cv["best"]),
            "n_weights": int(net.net_.n_weights),
            "gamma": None if gamma is None or not np.isfinite(gamma) else float(gamma),
            "gamma_folds": best.get("gamma_folds"),
            "switched_off": bool(fin.get("switched_off", False)), "cv": cv_gain,
            "test": heldout_gain(dz_prior[te], dz_after[te], scale), "significant": bool(cv_gain["significant"])}
