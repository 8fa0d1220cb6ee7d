"""`campaign plan`: candidates → suitable poses → an ordered, collision-free tour.

Any serial arm (``--robot``): its URDF's collision geometry, its joints' limits for the grid,
its tool's reflectors (robot.yaml's, else the default triad) for the cone and line-of-sight
filters, placed in the cell where the scene's ``robot_base`` says (campaign.plan.scene).
Writes ``RUN/plan/poses.csv`` (``pose_id,q1..qN``, rad or m, visiting order; pose_id is the
candidate's grid index), ``RUN/plan/vias.csv`` (via poses to pass before a pose),
``RUN/plan/dropped.csv`` (poses dropped from the tour, with the reason),
``RUN/plan/summary.json`` and ``RUN/plan/tour.png``, and copies the configuration to
``RUN/campaign.yaml`` (with the robot, its tool and base frames and the grid's cells). A short
campaign by default and with a selection (campaign.plan.selection: ``--select``, ``--budget``,
``--target-mm``): only the chosen poses, random validation poses (``RUN/plan/validation.csv``)
and repeats (pose_id ``p + r·10⁹``, ``RUN/plan/repeats.csv``) are toured. ``--all``: every
suitable pose, the long campaign.
"""

from __future__ import annotations

import dataclasses
import resource
import time
from pathlib import Path

import numpy as np

from campaign import interrupt
from campaign.config import CampaignConfig, load_config
from campaign.errors import ConfigError, PlanError
from campaign.fileio import atomic_write_json
from campaign.versioned import plan_folder
from campaign.model.kinematics import frames
from campaign.plan import checks
from campaign.plan.grid import Grid, default_cells, iter_tool_points
from campaign.plan.geometry import nominal_frames_entry_first
from campaign.plan.outputs import write_tour
from campaign.plan.plot import plot_tour
from campaign.plan.repair import check_segments, repair_largest, tour_path
from campaign.plan.timing import GridTimes, path_time
from campaign.plan.tour import nearest_neighbour, neighbour_lists, or_opt, two_opt
from campaign.progress import Progress
from campaign.run import RunFolder

#: the paper's campaign: 13,919 poses measured in about 3.5 days
PAPER_POSES = 13919
PAPER_DURATION_S = 3.5 * 86400.0


def _filter_grid(robot, scene, grid, clearance, progress):
    """Stage 2 over the whole grid; returns (suitable candidate indices, counts, the clearance
    checker); ``counts["why_none"]``, when no candidate is suitable, says why in a sentence."""
    counts = {"candidates": grid.size}
    bar = Progress("stage 1-2: tool poses", grid.size, progress, " poses")
    removed = {"tracker_range": 0, "reflector_cone": 0, "line_of_sight_scene": 0, "line_of_sight_robot": 0,
               "clearance_fcl": 0}
    cand_after_visibility = []
    axes = np.array([r.axis_in_E for r in robot.reflectors])
    for s, P, A in iter_tool_points(robot, grid, robot.reflector_positions_in_E, axes):
        block = len(P)
        idx = np.arange(s, s + block)
        ok = checks.range_ok(scene, P)
        removed["tracker_range"] += int((~ok).sum())
        idx, P, A = idx[ok], P[ok], A[ok]
        ok = checks.cone_ok(robot, scene, P, A)
        removed["reflector_cone"] += int((~ok).sum())
        idx, P = idx[ok], P[ok]
        ok = checks.scene_line_of_sight_ok(scene, P)
        removed["line_of_sight_scene"] += int((~ok).sum())
        cand_after_visibility.append(idx[ok])
        bar.update(block)
    bar.close()
    idx = np.concatenate(cand_after_visibility)
    checker = checks.ClearanceChecker(robot, scene, clearance)
    bar = Progress("stage 2: LOS + FCL", len(idx), progress, " poses")
    survivors, hidden, near = _sight_and_clearance(robot, grid, checker, idx, removed, bar=bar)
    bar.close()
    if len(survivors) < checks.EXACT_SIGHT_BELOW and len(hidden):
        # the links' boxes left too few: the beams they stop are decided on the links' shapes
        seen = _seen_on_shapes(robot, grid, checker, hidden)
        removed["line_of_sight_robot"] -= len(seen)
        more, _, more_near = _sight_and_clearance(robot, grid, checker, seen, removed, sight=False)
        counts["line_of_sight_exact"] = {"poses": int(len(hidden)), "seen": int(len(seen)),
                                         "why": f"the links' bounding boxes left {len(survivors):,} suitable poses, "
                                                f"fewer than {checks.EXACT_SIGHT_BELOW:,}"}
        hidden = np.setdiff1d(hidden, seen)
        survivors, near = np.sort(np.concatenate([survivors, more])), np.concatenate([near, more_near])
    suitable = survivors
    counts["removed_by_filter"] = removed
    counts["filter_order"] = list(removed)
    counts["suitable"] = int(len(suitable))
    if len(suitable) == 0:
        counts["why_none"] = checks.why_no_pose(robot, scene, grid, checker, removed, hidden, near)
    return suitable, counts, checker


def _sight_and_clearance(robot, grid, checker, idx, removed, *, sight=True, bar=None, block=4096):
    """The second part of stage 2 for the candidates ``idx`` (grid indices the tracker sees past
    the scene): the robot's links out of the beams, by their bounding boxes, then the clearance
    (``sight`` False: the clearance alone). Returns (suitable, hidden by a link, too near) grid
    indices; adds to ``removed`` what each filter removed."""
    E = robot.n_joints + 1  # the tool frame's index in kinematics.frames
    out = {"ok": [], "hidden": [], "near": []}
    for s in range(0, len(idx), block):
        sub = idx[s : s + block]
        R, t = frames(robot, grid.q(sub))
        if sight:
            P, _ = checks.reflector_geometry(robot, R[:, E], t[:, E])
            ok = checks.robot_line_of_sight_ok(robot, checker.scene, P, R, t)
            removed["line_of_sight_robot"] += int((~ok).sum())
            out["hidden"].append(sub[~ok])
            sub, R, t = sub[ok], R[ok], t[ok]
        ok = checker.clear(R, t)
        removed["clearance_fcl"] += int((~ok).sum())
        out["near"].append(sub[~ok])
        out["ok"].append(sub[ok])
        if bar is not None:
            bar.update(min(block, len(idx) - s))
    return tuple(np.concatenate(out[k]) if out[k] else np.zeros(0, dtype=np.int64) for k in ("ok", "hidden", "near"))


def _seen_on_shapes(robot, grid, checker, idx, block=4096):
    """The grid indices of ``idx`` whose beams miss the robot's links on their shapes
    (:meth:`~campaign.plan.checks.ClearanceChecker.beams_clear`)."""
    E = robot.n_joints + 1
    seen = []
    for s in range(0, len(idx), block):
        sub = idx[s : s + block]
        R, t = frames(robot, grid.q(sub))
        P, _ = checks.reflector_geometry(robot, R[:, E], t[:, E])
        seen.append(sub[checker.beams_clear(R, t, P)])
    return np.concatenate(seen) if seen else np.zeros(0, dtype=np.int64)


#: a group of more poses than this is improved by three passes of 2-opt alone (TIAGo Pro's --all,
#: 34,209 poses: 0.65-0.85 s a pass; three passes 0.25 %, the next three 0.03 % of the tour's time,
#: Or-opt and 2-opt again 12 s for 0.07 %)
FULL_LOCAL_SEARCH_MAX = 10_000
#: 2-opt passes for a group of more than FULL_LOCAL_SEARCH_MAX poses
LARGE_GROUP_PASSES = 3


def _order_group(times, grid, members, start_cells):
    if len(members) == 0:
        return members
    C = grid.cell_indices(members)
    start = int(np.argmin(times.from_one(start_cells, C)))
    near = neighbour_lists(times, C, 8)
    order = nearest_neighbour(times, C, start, near)
    # 2-opt to convergence, single poses moved by Or-opt, 2-opt again (about 0.2 % shorter
    # than three 2-opt passes on the default cell, for about a second)
    if len(members) > FULL_LOCAL_SEARCH_MAX:
        return members[two_opt(times, C, order, passes=LARGE_GROUP_PASSES, near=near)]
    order = two_opt(times, C, order, passes=20, near=near)
    order = or_opt(times, C, order, near, max_len=1, passes=1)
    order = two_opt(times, C, order, passes=20, near=near)
    return members[order]


def _order_tour(robot, scene, grid, times, home, members):
    """Grid indices ``members`` in visiting order: front-of-wall and behind-wall groups, each
    a short tour, the group whose first pose is nearer the grid's middle first."""
    front = scene.side_of_wall(nominal_frames_entry_first(robot, grid.q(members))[1][robot.n_joints + 1].T)
    groups = {name: _order_group(times, grid, members[mask], home) for name, mask in (("front", front),
                                                                                     ("behind", ~front))}
    first = min(groups, key=lambda g: times.from_one(home, grid.cell_indices(groups[g][:1]))[0]
                if len(groups[g]) else np.inf)
    return np.concatenate([groups[first], groups["behind" if first == "front" else "front"]])


def prepare_plan(config, run_dir, grid_scale, robot=None, tool_frame=None, base_frame=None) -> tuple:
    """What every plan of a run starts from: (run folder, configuration, robot (with its default
    reflectors), scene, grid, the advice for a run that holds measurements). config: a
    campaign.yaml path, a CampaignConfig or None (the run's own, else the embedded default);
    robot, tool_frame, base_frame override it; the configuration records the grid's cells at
    scale 1. Refused (one line) for a bad grid scale, an unplannable robot, or a run that holds
    measurements."""
    if isinstance(grid_scale, bool) or not isinstance(grid_scale, (int, float)) or \
            not 0 < grid_scale < float("inf"):
        raise ConfigError(f"--grid-scale must be a finite number > 0, got {grid_scale!r}")
    run = RunFolder(run_dir)
    if isinstance(config, CampaignConfig):
        cfg = config
    elif config is not None:
        cfg = load_config(config)
    else:
        cfg = run.config  # the run's own, or the embedded default for a new folder
    cfg = cfg.with_robot(robot, tool_frame, base_frame)
    run = RunFolder(run_dir, config=cfg)
    model = run.robot().with_default_reflectors()
    from campaign.plan.geometry import check_plannable

    check_plannable(model)
    scene = run.scene()
    base_cells = cfg.plan.grid_cells if cfg.plan.grid_cells is not None else default_cells(model)
    cells = np.maximum(1, np.round(np.asarray(base_cells, dtype=float) * float(grid_scale))).astype(int)
    try:
        grid = Grid.for_robot(model, cells)
    except ConfigError as exc:
        raise ConfigError(f"{cfg.path}: {exc} (with --grid-scale {grid_scale:g})") from None
    # the run records the grid it was planned on (auto resolved), at scale 1
    cfg = dataclasses.replace(cfg, plan=dataclasses.replace(cfg.plan, grid_cells=tuple(int(c) for c in base_cells)))
    advice = f"plan into a new run folder (--run {Path(run_dir).name}-2)"
    run.refuse_if_measured("planning again", advice)
    return run, cfg, model, scene, grid, advice


def plan_campaign(config=None, run_dir="runs/default", *, grid_scale: float = 1.0, progress: bool = False,
                  selection=None, all_poses: bool = False, robot: str | None = None, tool_frame: str | None = None,
                  base_frame: str | None = None, choose_among: str = "reachable") -> dict:
    """Plan a campaign; write the run's plan folder; return the summary (also in summary.json).

    config: a campaign.yaml path or a CampaignConfig; None: the run's own campaign.yaml when
    it has one, else the embedded default. robot (a name, URDF or robot.yaml), tool_frame,
    base_frame: plan for that robot instead of the configuration's (recorded in the run's
    campaign.yaml). selection: a :class:`campaign.plan.selection.SelectionOptions` (the most
    informative subset of the suitable poses, plus validation poses and repeats); None: the
    default short campaign for the physical model, ``SelectionOptions(n=DEFAULT_SELECT)`` for the
    geometry and the effects enabled in campaign.yaml (every suitable pose when there are fewer
    than it would take). all_poses: every suitable pose instead, the long campaign a neural
    compensator needs. choose_among: "reachable" (default) the design chooses among the poses of
    the largest set that collision-free motions join (campaign.plan.region; summary.json
    ``reachable`` counts the suitable poses outside it and the joint barriers that keep them out),
    "suitable" among every suitable pose, replacing the poses the tour drops by choosing again.
    The selection's accuracy prediction uses campaign.yaml's
    ``tracker: {noise_m}`` when given. Refused (one line, nothing written) when the run holds
    measurements, when another process holds the run's lock, or when no pose is suitable. The
    run's campaign.yaml and plan/ are written only once the plan is made.
    """
    if choose_among not in ("reachable", "suitable"):
        raise ConfigError(f"--choose-among must be reachable or suitable, got {choose_among!r}")
    if all_poses and selection is not None:
        raise ConfigError("--all plans every suitable pose: give it without --select, --budget or --target-mm")
    run, cfg, robot, scene, grid, advice = prepare_plan(config, run_dir, grid_scale, robot, tool_frame, base_frame)
    from campaign.plan.selection import DEFAULT_SELECT, SelectionOptions

    mode = "all" if all_poses else "default" if selection is None else "selection"
    if mode == "default":
        from campaign.effects.base import make_effect

        # the effects a plan can teach: not those whose context is known only when measuring
        effects = tuple(e for e in run.effects if not set(make_effect(e, robot).context_keys) - {"time_s"})
        selection = SelectionOptions(n=DEFAULT_SELECT, effects=effects)
    if selection is not None and selection.noise_m is None and cfg.tracker.noise_m is not None:
        selection = dataclasses.replace(selection, noise_m=cfg.tracker.noise_m)  # the user's tracker, for the prediction
    if selection is not None:
        from campaign.plan.selection import check_select_size

        check_select_size(robot, selection.check())  # before the filters, not after them
    with run.lock("plan"):
        run.refuse_if_measured("planning again", advice)  # again under the lock: a driver may have stored poses
        # every file of the plan into a new version of RUN/plan, current only once whole (campaign.versioned)
        with plan_folder(run.path).new_version() as version:
            return _plan(run, cfg, robot, scene, grid, progress, selection, mode, version, choose_among)


def _plan(run: RunFolder, cfg: CampaignConfig, robot, scene, grid: Grid, progress, selection, mode,
          version, choose_among="reachable") -> dict:
    t_start = time.perf_counter()
    timing = {}  # seconds per stage, wall
    clock = [t_start]

    def lap(stage):  # a stage run again (the rounds of a chosen campaign) adds up
        interrupt.check()  # a Ctrl-C a library swallowed during the stage (campaign.interrupt)
        now = time.perf_counter()
        timing[stage] = timing.get(stage, 0.0) + now - clock[0]
        clock[0] = now

    pc = cfg.plan
    cells = grid.cells
    n_reflectors = len(robot.reflectors)
    out = version.path
    lap("setup")

    suitable, counts, checker = _filter_grid(robot, scene, grid, pc.clearance_m, progress)
    if len(suitable) == 0:
        raise PlanError(f"{cfg.path}: no suitable pose among {grid.size:,} candidates for {robot.name} in the scene "
                        f"{cfg.scene_path}: {counts['why_none']}")
    lap("filters")

    # stage 3: groups, order, check
    times = GridTimes(robot, grid)
    home = np.array(grid.cells) // 2
    members, choice, chosen = suitable, None, None
    if mode == "default" and len(suitable) < _default_size(selection):
        selection, mode = None, "all_few"  # fewer suitable poses than the short campaign takes: all of them
    max_step = np.deg2rad(pc.motion_sample_deg)
    mc = pc.motion_clearance_m
    candidates, region, margin = suitable, None, None
    if selection is not None and choose_among == "reachable":
        candidates, region = _reachable_candidates(robot, checker, grid, suitable, selection, max_step, mc, progress)
        lap("region")
    if selection is not None and pc.cone_margin_deg > 0:
        candidates, margin = _inside_cones(robot, scene, grid, candidates, selection, pc.cone_margin_deg)
    pool, rounds, replaced, why_short = candidates, 0, 0, None
    unreached = np.zeros(0, dtype=np.int64)  # grid indices the tours dropped
    dropped_per_round = []
    while True:  # a chosen campaign: poses the tour drops are replaced by choosing again without them
        rounds += 1
        if selection is not None:
            from campaign.plan.selection import choose_campaign

            try:
                chosen = choose_campaign(robot, grid, candidates, selection, settle_s=pc.settle_time_s,
                                         tracker_s=n_reflectors * pc.tracker_time_per_reflector_s,
                                         **_selection_times(robot, scene, grid, times, home, candidates))
            except ConfigError as exc:
                if choice is None and candidates is not suitable and region is not None:
                    # the reachable set is too small for this choice: among every suitable pose, as chosen
                    candidates = pool = suitable
                    region = dataclasses.replace(region, too_few=str(exc))
                    rounds -= 1
                    continue
                if choice is None:
                    raise
                why_short = f"choosing again without the {replaced} dropped poses failed: {exc}"
                break  # the previous round's tour stands
            members = chosen.members
            lap("selection")
        bar = Progress("stage 3: ordering", 1, progress, " tours")
        new_order = _order_tour(robot, scene, grid, times, home, members)
        bar.update(1)
        bar.close()
        if selection is not None:
            new_order = chosen.with_repeats(new_order)  # pose ids; repeats map back to their grid index
        Q = grid.q(_grid_index(new_order))
        lap("ordering")
        bar = Progress("stage 3: motion check", len(new_order), progress, " segments")
        # the tour's poses are suitable: clear by the pose clearance, which bounds the motions near them
        ok = check_segments(robot, checker, Q[:-1], Q[1:], max_step, mc, ends_clearance=pc.clearance_m) \
            if len(new_order) > 1 else np.ones(0, bool)
        bar.update(len(new_order))
        bar.close()
        lap("motion_check")
        order, repair = new_order, repair_largest(robot, checker, new_order, Q, ok, max_step, mc,
                                                  ends_clearance=pc.clearance_m)
        lap("repair")
        if selection is None:
            break
        choice = chosen
        dropped_per_round.append(len(repair.dropped))
        if not repair.dropped:
            break
        if rounds >= REPLACE_ROUNDS:
            why_short = f"{REPLACE_ROUNDS} rounds of choosing again did not reach every chosen pose"
            break
        gone = np.unique(_grid_index([p for p, _ in repair.dropped]))
        replaced += len(gone)
        unreached = np.union1d(unreached, gone)
        candidates = _nearer_toured(grid, pool, np.unique(_grid_index(order[repair.keep])), unreached)
    vias, dropped = repair.vias, repair.dropped
    order_final = order[repair.keep]
    Q_final = grid.q(_grid_index(order_final))
    path = tour_path(order_final, Q_final, vias)
    tour_time = path_time(robot, path) if len(path) > 1 else 0.0
    n = len(order_final)
    per_pose = pc.settle_time_s + n_reflectors * pc.tracker_time_per_reflector_s
    duration = tour_time + n * per_pose
    if n == 0:
        raise PlanError(f"{cfg.path}: every one of the {len(order):,} suitable poses was dropped from the tour "
                        f"(no collision-free motion at plan.motion_clearance_m = {mc:g} m)")
    write_tour(out, order_final, Q_final, vias, dropped)
    front_final = scene.side_of_wall(frames(robot, Q_final)[1][:, robot.n_joints + 1]) if n else np.zeros(0, bool)
    summary = {
        "plan_id": version.id, "robot": robot.name, "tool_frame": robot.tool_frame, "reflectors": [r.name for r in robot.reflectors],
        "scene": str(scene.path), "grid_cells": [int(c) for c in cells],
        "candidates": counts["candidates"],
        "removed_by_filter": counts["removed_by_filter"], "filter_order": counts["filter_order"],
        "suitable": counts["suitable"], "suitable_fraction": counts["suitable"] / counts["candidates"],
        **({"line_of_sight_exact": counts["line_of_sight_exact"]} if "line_of_sight_exact" in counts else {}),
        "groups": {"front_of_wall": int(front_final.sum()), "behind_wall": int((~front_final).sum())},
        "tour": {"poses": n, "via_poses": int(sum(len(v) for v in vias.values())), "dropped": len(dropped),
                 "path_search": {"motions": repair.searched, "checks": repair.search_checks},
                 "motion_time_s": tour_time, "clearance_m": pc.clearance_m, "motion_clearance_m": mc,
                 "motion_sample_deg": pc.motion_sample_deg},
        "estimated_campaign": {
            "motion_s": tour_time, "settle_s": n * pc.settle_time_s,
            "tracker_s": n * n_reflectors * pc.tracker_time_per_reflector_s, "total_s": duration,
            "total_days": duration / 86400.0,
            "paper": {"poses": PAPER_POSES, "duration_days": PAPER_DURATION_S / 86400.0,
                      "seconds_per_pose": PAPER_DURATION_S / PAPER_POSES},
            "seconds_per_pose": duration / n if n else None,
        },
        "disabled_link_pairs": [list(p) for p in checker.disabled_pairs],
    }
    from campaign.plan.selection import write_choice

    write_choice(out, choice, order_final)  # without a choice: no validation.csv, repeats.csv
    summary["campaign"] = _campaign_kind(mode, len(suitable), selection)
    if margin is not None:
        summary["cone_margin"] = margin
    if region is not None:
        summary["reachable"] = {**region.summary(), "chosen_among": "reachable" if pool is not suitable else "suitable"}
        if region.too_few:
            summary["reachable"]["why_suitable"] = f"too few reachable poses to choose among: {region.too_few}"
    if choice is not None:
        summary["selection"] = _as_toured(robot, grid, suitable, choice, selection, order_final)
        summary["selection"]["replacement"] = {"rounds": rounds, "replaced": replaced,
                                                  "dropped_per_round": dropped_per_round, "why_short": why_short}
        pred = summary["selection"]["predicted"]
        if "sample" in pred and pred["sample"]["of"] < len(suitable):  # say that the pool is not every suitable pose
            from campaign.plan.selection import sample_text

            before = sample_text(pred["sample"])
            pred["sample"] = {**pred["sample"], "suitable": int(len(suitable))}
            pred["evaluated_over"] = pred["evaluated_over"].replace(before, sample_text(pred["sample"]))
        summary["tour"]["repeats"] = int(np.sum(_grid_index(order_final) != order_final))
        from campaign.plan.selection import repeats_in_tour

        summary["tour"]["repeats_back_to_back"] = repeats_in_tour(order_final)
    summary["drift_monitor"] = _drift_monitor(robot, checker, order_final, Q_final, cfg.run.drift_check_every,
                                              max_step, mc, pose_clearance=pc.clearance_m)
    lap("outputs")
    try:
        plot_tour(out / "tour.png", robot, scene, Q_final, front_final)
    except Exception as exc:  # a plot must never lose a plan
        summary["plot_error"] = str(exc)
    lap("plot")
    summary["timing_s"] = {**timing, "total": time.perf_counter() - t_start}
    summary["peak_rss_mb"] = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024
    atomic_write_json(out / "summary.json", summary)
    run.write_config(cfg)  # last: a plan that fails on the way leaves the run's campaign.yaml as it was
    return summary


def _inside_cones(robot, scene, grid, candidates, selection, margin_deg):
    """The candidates whose reflectors lie ``margin_deg`` inside their nests' cones (the design
    chooses among them; every one of them when too few would remain), and summary.json's
    ``cone_margin``."""
    from campaign.model.kinematics import forward

    keep = np.zeros(len(candidates), dtype=bool)
    for s in range(0, len(candidates), 65536):
        T = forward(robot, grid.q(candidates[s : s + 65536]))
        P, A = checks.reflector_geometry(robot, T[:, :3, :3], T[:, :3, 3])
        keep[s : s + 65536] = checks.cone_ok(robot, scene, P, A, np.deg2rad(margin_deg))
    out = {"deg": float(margin_deg), "candidates": int(len(candidates)), "inside": int(keep.sum())}
    # a budget or a target chooses its own size: then at least half the candidates must stay
    needed = _default_size(selection) if selection.n is not None else max(2 * selection.min_validation,
                                                                          len(candidates) // 2)
    if keep.sum() < needed:
        out["used"] = False
        out["why_not"] = (f"only {int(keep.sum()):,} candidates lie {margin_deg:g}° inside their cones, fewer than "
                          f"{needed}: chosen among all of them")
        return candidates, out
    out["used"] = True
    return candidates[keep], out


def _reachable_candidates(robot, checker, grid, suitable, selection, max_step, clearance, progress):
    """(grid indices the design chooses among, the Region): the suitable poses of the set one
    tour can visit (campaign.plan.region), among a random pool of them for a large set; every
    suitable pose when that set cannot hold the poses ``--select`` asks for and their validation
    poses."""
    from campaign.plan.region import reachable_region

    bar = Progress("stage 3: reachable set", None, progress, " rounds")
    region = reachable_region(robot, checker, grid, suitable, max_step, clearance, progress=bar,
                              pose_clearance=checker.clearance)
    bar.close()
    inside = suitable[region.pool[region.in_pool]]
    if selection.n is not None and len(inside) < _default_size(selection):
        why = f"{len(inside):,} reachable poses, fewer than the {_default_size(selection)} chosen and validation poses"
        return suitable, dataclasses.replace(region, too_few=why)
    return inside, region


#: rounds of choosing again (:func:`_plan`) while the tour drops chosen poses
REPLACE_ROUNDS = 6


def _nearer_toured(grid, suitable, toured, unreached, block=4096):
    """The suitable grid indices that the next round may choose: those nearer (largest joint
    difference) to a pose of the tour ``toured`` than to any pose a tour dropped (``unreached``),
    which are left out themselves. Poses the tour could not reach come in regions (a UR10: the
    ranges of joint 2 beyond the upper arm pointing into the pedestal); this keeps the next
    choice out of them."""
    keep = ~np.isin(suitable, unreached)
    rest = suitable[keep]
    known_q = grid.q(np.concatenate([toured, unreached]))
    is_toured = np.arange(len(known_q)) < len(toured)
    near_toured = np.empty(len(rest), dtype=bool)
    for s in range(0, len(rest), block):
        q = grid.q(rest[s : s + block])
        d = np.max(np.abs(q[:, None, :] - known_q[None, :, :]), axis=2)
        near_toured[s : s + block] = is_toured[np.argmin(d, axis=1)]
    return rest[near_toured]


def _as_toured(robot, grid, suitable, choice, selection, order_final) -> dict:
    """summary.json's ``selection`` for the poses the tour keeps: the counts of the chosen poses,
    validation poses and repeated poses toured and, when the tour dropped any, the prediction
    for the toured ones over all ``suitable`` poses (the selection's own otherwise)."""
    base = _grid_index(order_final)
    toured = set(int(b) for b in base)
    selected = [int(p) for p in choice.selected if int(p) in toured]
    out = {**choice.summary, "chosen": int(len(choice.selected)), "selected": len(selected),
           "validation": int(sum(int(p) in toured for p in choice.validation)),
           "repeated_poses": int(len(set(int(b) for b, p in zip(base, order_final) if b != p)))}
    if len(selected) < len(choice.selected) or out["repeated_poses"] < choice.summary["repeated_poses"]:
        from campaign.plan.selection import evaluation_sample, information_model, predict_accuracy, sample_text

        info = information_model(robot, grid.q(suitable), effects=selection.effects,
                                 noise_m=choice.summary["tracker_noise_m"])
        where = {int(g): i for i, g in enumerate(suitable)}
        chosen = set(int(p) for p in choice.selected)
        train = np.array([where[int(b)] for b in base if int(b) in chosen], dtype=np.int64)  # repeats too
        ev, sample = evaluation_sample(info, train)
        kept = choice.summary["predicted"]["evaluated_over"].replace(
            sample_text(choice.summary["predicted"]["sample"]), sample_text(sample))
        out["predicted"] = {**choice.summary["predicted"], **predict_accuracy(info, train, ev).as_dict(),
                            "evaluated_over": kept, "sample": sample, "for": "the chosen poses the tour keeps"}
    return out


def _drift_monitor(robot, checker, order, Q, every, max_step, clearance, pose_clearance=None) -> dict:
    """summary.json's ``drift_monitor``: when the driver re-measures the reference pose (the tour's
    first; ``run.drift_check_every``, campaign.measure.driver.drift_check_interval) and whether its
    motions, straight in joint space from the pose before to the reference and back to the next
    pose, are clear by ``clearance`` (m) as the tour's are (the driver moves there directly);
    ``pose_clearance``: the clearance (m) the tour's poses keep (check_segments' ends_clearance)."""
    from campaign.measure.driver import drift_check_interval

    n = drift_check_interval(every, len(order))
    after = np.arange(n, len(order), n) - 1 if n else np.zeros(0, dtype=int)  # stored poses - 1
    after = after[after + 1 < len(order)]
    out = {"every": int(n), "checks": int(len(after)), "reference_pose_id": int(order[0]) if len(order) else None}
    if len(after):
        ref = np.repeat(Q[:1], len(after), axis=0)
        clear = check_segments(robot, checker, Q[after], ref, max_step, clearance, ends_clearance=pose_clearance) & \
            check_segments(robot, checker, ref, Q[after + 1], max_step, clearance, ends_clearance=pose_clearance)
        out["motions_clear"] = int(clear.sum())
        out["not_clear_after_pose_ids"] = [int(order[k]) for k in after[~clear]]
    out["text"] = ("the driver re-measures the first pose every "
                   f"{n} stored poses for the drift (µm per hour in diagnose and the reports), moving there "
                   "directly: its motions are checked here; the driver skips a check whose motions are not clear"
                   if n else "no drift checks (run.drift_check_every: 0)")
    return out


def _default_size(selection) -> int:
    """Suitable poses the default short campaign takes: the selection and its validation poses."""
    n = selection.n
    return n + max(selection.min_validation, int(round(selection.validation_fraction * n)))


def _campaign_kind(mode, n_suitable, selection) -> dict:
    """summary.json's ``campaign``: which campaign was planned (``short`` or ``all``) and why."""
    text = {
        "default": (f"the default short campaign: the {selection.n if selection else 0} most informative poses for "
                    "the physical model, validation poses and repeats (--all plans every suitable pose)"),
        "selection": "a short campaign of the most informative poses (--select, --budget or --target-mm)",
        "all": "every suitable pose (--all): the long campaign a neural compensator needs",
        "all_few": f"every suitable pose: only {n_suitable:,}, fewer than the default short campaign takes",
    }[mode]
    return {"kind": "all" if mode.startswith("all") else "short", "mode": mode, "text": text}


def _grid_index(pose_ids):
    from campaign.plan.selection import base_pose_id

    return base_pose_id(pose_ids)


def _selection_times(robot, scene, grid, times, home, suitable):
    """Travel-time callables for a selection by budget (seconds)."""
    cells = grid.cell_indices(suitable)
    return {"travel_from": lambda k: times.from_one(cells[k], cells), "start_s": times.from_one(home, cells),
            "tour_time": lambda ids: path_time(robot, grid.q(_order_tour(robot, scene, grid, times, home, ids)))}


def suitable_poses(robot, scene, grid: Grid, clearance_m: float, progress: bool = False) -> np.ndarray:
    """Indices into ``grid`` of the suitable poses: stage 2's filters (tracker range, reflector
    cones, line of sight, clearance ≥ ``clearance_m`` by FCL), as `campaign plan` finds them
    before it selects and tours (for studies of the suitable set: benchmarks, tests);
    ``progress``: progress bars on stderr."""
    return _filter_grid(robot, scene, grid, clearance_m, progress)[0]
