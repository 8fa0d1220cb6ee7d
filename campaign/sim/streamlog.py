"""`campaign sim RUN --stream-out LOG`: the simulated cell runs RUN's program (RUN/program/stops.csv)
and its tracker logs continuously, as a real tracker's software does while a controller runs the
program: ``time_s,x,y,z,target`` at ``rate_hz``, motion included, in the tracker's frame (m).

The world is the simulated cell's (campaign.sim.cell.World: the truth robot with its hidden errors
and effects, the tracker's pose and noise, the faults of ``sim.faults``). Each motion is Ruckig's
rest-to-rest trajectory between the stops (the plan's timing); at a stop the robot settles
(``plan.settle_time_s``), then the tracker measures each reflector in turn for
``plan.tracker_time_per_reflector_s`` (the last STREAM_SIM_SWITCH_S of it the beam moving to the
next, without samples); in motion it follows the first reflector. A lost beam (``beam_lost``, drawn
per stop and reflector) logs nothing from there to the next stop, where the beam is found again; a
point beyond the tracker's range is not logged. The log is written stop by stop: memory does not
grow with the campaign. The truth stays in RUN/sim/truth.yaml.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

#: the beam moving from one reflector to the next: no samples (s)
STREAM_SIM_SWITCH_S = 0.2
#: request ids of the stream's fault draws: apart from the driver's (campaign.measure.driver)
_STREAM_ID = 1 << 43


def _motion(robot, qa, qb, dt, t0):
    """(times (m,), joint vectors (m, N)) of Ruckig's rest-to-rest move qa → qb sampled every dt
    from the phase t0 (s) after its start; and its duration (s)."""
    from campaign.plan.timing import ruckig_trajectory

    if np.allclose(qa, qb):
        return np.zeros(0), np.zeros((0, len(qa))), 0.0
    duration, traj = ruckig_trajectory(robot, qa, qb)
    ts = np.arange(t0, duration, dt)
    Q = np.array([traj.at_time(float(t))[0] for t in ts]).reshape(len(ts), len(qa))
    return ts, Q, duration


def write_stream_log(run_dir, out, *, rate_hz: float = 100.0, config=None, progress=None) -> dict:
    """Drive the simulated cell of ``run_dir`` through its stops and write the tracker's log to
    ``out``; returns {"samples", "stops", "lost", "duration_s", "truth"}. progress: callable
    receiving the fraction of stops done."""
    from campaign.errors import ConfigError
    from campaign.fileio import atomic_open
    from campaign.measure.reflectors import transform_points
    from campaign.program.stops import read_stops_csv, stops_path
    from campaign.program.stream.logwrite import format_rows, log_header
    from campaign.run import RunFolder
    from campaign.sim.cell import World
    from campaign.sim.commands import sim_config

    if not (np.isfinite(rate_hz) and 1.0 <= rate_hz <= 10_000.0):
        raise ConfigError(f"--rate must be a sample rate in 1..10000 Hz, got {rate_hz}")
    run = RunFolder(run_dir, config=config)
    stops = read_stops_csv(stops_path(run.path))
    cfg = sim_config(run)
    with run.sim_lock("sim --stream-out"):
        world = World(cfg, run.path, run.clock_s())
        robot, truth = world.robot, world.truth
        if len(stops[0].q) != robot.n_joints:
            raise ConfigError(f"{stops_path(run.path)}: {len(stops[0].q)} joints, the cell's robot {robot.name} "
                              f"has {robot.n_joints}")
        names = tuple(world.reflectors)
        P_E = np.array([world.reflectors[n] for n in names])
        dt = 1.0 / rate_hz
        lost = samples = 0
        t = world.clock_s
        phase = 0.0  # the sampling phase carried from one piece to the next (s)
        q = np.array(stops[0].q)
        with atomic_open(out, "wb") as fh:
            fh.write(log_header(len(names) > 1).encode())
            beam_on = True
            for k, s in enumerate(stops):
                qs = np.array(s.q)
                ts, Q, duration = _motion(robot, q, qs, dt, phase)
                T_rel = [ts]
                Q_all = [Q]
                G = [np.zeros(len(ts), dtype=np.int64)]
                ok = [np.full(len(ts), beam_on)]
                t_piece = duration
                phase = (ts[-1] + dt - duration) if len(ts) else max(phase - duration, 0.0)
                beam_on = True  # found again at the stop
                if s.dwell_s > 0:
                    settle = min(cfg.plan.settle_time_s, s.dwell_s)
                    slot = (s.dwell_s - settle) / len(names)
                    pieces = [(0, settle, settle)] + [(c, slot - STREAM_SIM_SWITCH_S, slot) for c in range(len(names))]
                    for c, (code, logged, length) in enumerate(pieces):
                        tp = np.arange(phase, max(logged, 0.0), dt)
                        phase = (tp[-1] + dt - length) if len(tp) else max(phase - length, 0.0)
                        if c > 0 and world.fault("beam_lost", _STREAM_ID + 16 * s.stop + c):
                            beam_on = False
                        T_rel.append(t_piece + tp)
                        Q_all.append(np.repeat(qs[None], len(tp), axis=0))
                        G.append(np.full(len(tp), code))
                        ok.append(np.full(len(tp), beam_on))
                        t_piece += length
                    lost += not beam_on
                tr, Qk, g, keep = (np.concatenate(a) for a in (T_rel, Q_all, G, ok))
                tk = t + tr
                if len(tk):
                    ctx = {"time_s": tk, "temperature_c": 20.0 + 5.0 * np.sin(2 * np.pi * tk / 86400.0)}
                    T_LE = truth.T_LI @ truth.pose(Qk, ctx)
                    P = transform_points(T_LE, P_E[g][:, None, :])[:, 0]
                    dist = np.linalg.norm(P, axis=1)
                    keep &= (dist >= world.scene.min_range_m) & (dist <= world.scene.max_range_m)
                    rng = np.random.default_rng([world.seed, 7, s.stop])
                    if truth.noise_m > 0:
                        P = P + rng.normal(0.0, truth.noise_m, P.shape)
                        if truth.resolution_m > 0:
                            P = np.round(P / truth.resolution_m) * truth.resolution_m
                    fh.write(format_rows(tk[keep], P[keep], g[keep] if len(names) > 1 else None, names))
                    samples += int(keep.sum())
                t += t_piece
                q = qs
                if progress is not None:
                    progress((k + 1) / len(stops))
    return {"samples": samples, "stops": len(stops), "lost": lost, "duration_s": t - world.clock_s,
            "truth": str(world.truth_path), "rate_hz": rate_hz, "out": str(Path(out))}
