"""`campaign run` as a library call: lock the run, start the simulated cell if asked, drive."""

from __future__ import annotations

import contextlib
import os
from dataclasses import replace

from campaign.errors import CampaignError, ConfigError
from campaign.measure.driver import RunOptions, RunResult, measured_robot, read_plan, run_campaign
from campaign.run import RunFolder


def check_simulated_cell(cfg, robot) -> None:
    """ConfigError (one line) for what the simulated cell of ``cfg`` would refuse: an unknown
    hidden effect, hidden parameters that do not fit it, or a hook of it that fails at the robot's
    middle pose with the context the cell gives (time and temperature), which the cell would
    otherwise meet at its first measurement, as an error reply to the set-up."""
    import numpy as np

    from campaign.effects.base import EffectSet, effect_context, make_effect, model_pose
    from campaign.sim.truth import hidden_effect_params

    for i, (spec, params) in enumerate(cfg.hidden_effects()):
        try:
            effect = make_effect(spec, robot)
        except ConfigError as exc:  # a joint the robot lacks: the file and the entry named
            raise ConfigError(f"{cfg.path}: sim.hidden_effects[{i}]: {exc}") from None
        theta = hidden_effect_params(effect, cfg.sim.seed, params)
        try:
            model_pose(robot, np.array([robot.q_mid], dtype=float), None, EffectSet((effect,)), theta,
                       effect_context({"temperature_c": np.array([20.0])}, np.array([0.0])))
        except CampaignError as exc:  # the user's hook: what it raised, named by the entry
            raise ConfigError(f"{cfg.path}: sim.hidden_effects[{i}]: {exc}") from None


def measure_run(run_dir, *, sim: bool = False, controller=None, tracker=None, config=None, progress: bool = False,
                log=None, max_poses=None, poses_csv=None, retry_failed: bool = False,
                verbose: bool = False, frame: str = "robot", cell: str | None = None, options=None,
                token_file=None, allow_other_cell: bool = False) -> RunResult:
    """Measure the planned poses of ``run_dir`` that have no stored outcome yet.

    sim: start the simulated cell (a child process, stopped at the end) and drive it; cell:
    start `campaign serve` for that SPEC (``sim``, ``mujoco``, a FILE.py or module with classes
    Controller and Tracker; ``options``: their options file) the same way; otherwise controller
    and tracker are (host, port), with ``token_file`` the shared secret when they authenticate
    frames. config: a campaign.yaml to use
    instead of RUN/campaign.yaml. Everything is checked before the run is touched: the
    configuration, the robot, the plan; then the run's lock is taken (RunBusy when another
    process drives it) before the cell is started or contacted and before the log is opened.
    The simulated clock resumes at the run's last stored time. Other arguments as
    :func:`campaign.measure.driver.run_campaign`.
    """
    run = RunFolder(run_dir, config=config)
    cfg = run.config
    robot = run.robot()
    run.check_recorded_robot()
    opts = replace(RunOptions.from_config(cfg.run), tracker_noise_m=cfg.tracker.noise_m)
    if max_poses is not None and max_poses < 0:
        raise ConfigError(f"--max-poses must be >= 0, got {max_poses}")
    if cell is not None and str(cell).strip() == "sim":
        sim, cell = True, None
    if options is not None and cell is None:
        raise ConfigError("--options goes with --cell (the adapters' options; `campaign serve --options` otherwise)")
    if cell is not None:
        from campaign.cell.launcher import cell_specs

        cell_specs(cell)
    key = None
    if token_file is not None:
        from campaign.measure.auth import read_token

        key = read_token(token_file)
    if not sim and cell is None and (controller is None or tracker is None):
        raise ConfigError("give the controller and the tracker (HOST:PORT each), or use the simulated cell")
    plan = read_plan(run.path, poses_csv)
    robot.check_joints(plan[1], field=str(poses_csv or run.poses_csv), pose_ids=plan[0])
    measured_robot(robot)  # refused before the run is touched
    if sim:  # what the simulated cell would refuse, refused before it is started
        check_simulated_cell(cfg, robot)
    from campaign.measure.cell_identity import cell_identity, check_cell

    identity = cell_identity(cfg, sim=sim, cell=cell, options=options, controller=controller, tracker=tracker)
    kw = dict(progress=progress, log=log, max_poses=max_poses, poses_csv=poses_csv, retry_failed=retry_failed,
              verbose=verbose, plan=plan, frame=frame, key=key, cell_identity=identity,
              allow_other_cell=allow_other_cell)
    with run.lock("run"), _no_empty_log(run):
        check_cell(run.path, identity, allow_other_cell)  # before the cell is started or the log written
        if sim:
            from campaign.sim.launcher import SimulatedCell

            with SimulatedCell(cfg.path, run.path, start_clock_s=run.clock_s()) as served:
                return run_campaign(run.path, robot, served.controller, served.tracker, opts, **kw)
        if cell is not None:
            from campaign.cell.launcher import ServeProcess

            with ServeProcess(cell, cfg.path, run.path, start_clock_s=run.clock_s(), options=options) as served:
                return run_campaign(run.path, robot, served.controller, served.tracker, opts, **kw)
        return run_campaign(run.path, robot, controller, tracker, opts, **kw)


@contextlib.contextmanager
def _no_empty_log(run):
    """A log this session created is removed again when the session fails before it stored a
    pose (a full disk before the first pose, a cell that cannot be reached): the run folder is
    then as it was."""
    created = not run.measurements_path.exists()
    try:
        yield
    except BaseException:
        try:
            empty = created and run.measurements_path.exists() and RunFolder(run.path).stored_pose_count() == 0
        except CampaignError:
            empty = False
        if empty:
            for suffix in ("", "-wal", "-shm", "-journal"):
                with contextlib.suppress(OSError):
                    os.unlink(f"{run.measurements_path}{suffix}")
        raise
