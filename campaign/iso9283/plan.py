"""`campaign plan --iso9283`: the ISO 9283 pose accuracy and repeatability test as a plan.

The standard's test cube: the largest cube (edges along the cell's horizontal axes and its
vertical, from the robot's gravity) whose five test poses the robot reaches with one tool
orientation, each pose suitable for the tracker (range, cones, line of sight, clearance) and
every motion of the cycle collision-free. P1 is the cube's centre; P2..P5 lie on the diagonals
of the diagonal plane C1-C2-C7-C8 at a tenth of the diagonal from the corners (ISO 9283:1998,
6.8.2). Each cycle visits P1, P5, P4, P3, P2 (7.2.1), every pose approached the same way.

Pose ids: P_k of cycle c (0-based) is ``10·c + k`` (P3 of the first cycle 3, of the second 13);
the cycles of one pose are repeats of one joint vector, which gives the noise floor. ``RUN/plan/iso9283.json`` records the
cube, the targets (poses of E in F_I), the joint commands and, with ``--compensate CAL``, the
calibrated run whose model corrected the commands (``campaign compensate``).
"""

from __future__ import annotations

import time
from pathlib import Path

import numpy as np

from campaign.errors import ConfigError, PlanError
from campaign.fileio import atomic_write_json
from campaign.tolerances import CORRECTION_MAX_RAD
from campaign.versioned import plan_folder

#: the order of one cycle (ISO 9283, 7.2.1)
CYCLE_ORDER = (1, 5, 4, 3, 2)
#: P2..P5 lie this fraction of the diagonal from the corners (ISO 9283, 6.8.2: 0.1 ± 0.02)
CORNER_FRACTION = 0.1
#: the standard's number of cycles for pose accuracy and repeatability (7.2.1)
DEFAULT_CYCLES = 30
#: half-edges tried, largest first (m); the largest feasible one is refined by bisection
HALF_EDGES_M = (0.40, 0.32, 0.25, 0.20, 0.16, 0.13, 0.10, 0.08, 0.065, 0.05, 0.04, 0.03, 0.02)
#: candidate cube centres: suitable poses whose tool points lie nearest the middle of the suitable workspace
CENTRE_CANDIDATES = 48
BISECTION_STEPS = 5
#: the cube planned is this fraction of the largest that fits: its outer poses then keep their
#: distance from the workspace's boundary, so a calibrated robot, whose geometry differs by
#: millimetres, still reaches them with corrected commands (--compensate)
SIZE_MARGIN = 0.9
#: an inverse-kinematics solution must reach its target this well (m, rad)
IK_TOL_M, IK_TOL_RAD = 1e-7, 1e-6
#: every test pose keeps this far from each revolute joint's limits (rad): a calibrated robot's
#: corrected commands (--compensate) differ from the nominal ones by its geometric errors carried to
#: the joints; for the COMAU's Table 4 errors (35 mrad of tool orientation, 8-13 mm) up to 94 mrad on
#: the wrist joints over 6 calibrations, and CORRECTION_MAX_RAD bounds a plausible one (without the
#: margin, P5 of a cube sized to the joint limit fell 4.1° beyond joint 4's on 5 of 6 runs)
JOINT_MARGIN_RAD = CORRECTION_MAX_RAD


def cube_axes(gravity_in_I) -> np.ndarray:
    """(3, 3): columns u, v, w of the test cube in F_I: w up (against gravity), u the base axis
    most nearly horizontal, v = w × u."""
    g = np.asarray(gravity_in_I, dtype=float)
    w = -g / np.linalg.norm(g)
    e = np.eye(3)[int(np.argmin(np.abs(w)))]
    u = e - w * (e @ w)
    u /= np.linalg.norm(u)
    return np.column_stack([u, np.cross(w, u), w])


def test_points(centre, axes, half_edge) -> np.ndarray:
    """(5, 3): P1..P5 in F_I for a cube of half-edge ``half_edge`` (m) about ``centre`` (3,).

    The diagonal plane holds the edges C1-C2 (bottom, v = -h) and C7-C8 (top, v = +h); its
    diagonals are C1-C7 and C2-C8."""
    h = float(half_edge)
    c = {1: (-1, -1, -1), 2: (1, -1, -1), 7: (1, 1, 1), 8: (-1, 1, 1)}
    C = {k: np.asarray(v, dtype=float) * h for k, v in c.items()}
    f = CORNER_FRACTION
    local = [np.zeros(3), C[1] + f * (C[7] - C[1]), C[2] + f * (C[8] - C[2]), C[7] + f * (C[1] - C[7]),
             C[8] + f * (C[2] - C[8])]
    return np.asarray(centre, dtype=float) + np.asarray(local) @ np.asarray(axes).T


def _targets(points, R_tool) -> np.ndarray:
    T = np.zeros((len(points), 4, 4))
    T[:, :3, :3] = R_tool
    T[:, :3, 3] = points
    T[:, 3, 3] = 1.0
    return T


class _Feasibility:
    """Whether the five test poses of cubes about candidate centres can be measured: IK from the
    centre pose, joint limits, the plan's pose filters, and the cycle's motions."""

    def __init__(self, robot, scene, checker, clearance_m, motion_clearance_m, max_step_rad, joint_margin_rad=0.0):
        self.robot, self.scene, self.checker = robot, scene, checker
        self.clearance, self.motion_clearance, self.max_step = clearance_m, motion_clearance_m, max_step_rad
        #: (N,) how far inside each joint's limits a pose must be (revolute joints: joint_margin_rad)
        self.margin = np.where(robot.prismatic, 0.0, float(joint_margin_rad))

    def poses_ok(self, Q) -> np.ndarray:
        """(m,) bool for joint vectors Q (m, N): within limits (less the margin) and suitable."""
        from campaign.model.kinematics import frames
        from campaign.plan import checks

        robot = self.robot
        ok = np.all((Q >= robot.q_lower + self.margin) & (Q <= robot.q_upper - self.margin), axis=1)
        if not ok.any():
            return ok
        R, t = frames(robot, Q)
        E = robot.n_joints + 1
        P, A = checks.reflector_geometry(robot, R[:, E], t[:, E])
        ok &= checks.range_ok(self.scene, P) & checks.cone_ok(robot, self.scene, P, A)
        ok &= checks.scene_line_of_sight_ok(self.scene, P)
        los = checks.robot_line_of_sight_ok(robot, self.scene, P, R, t)
        stopped = ok & ~los  # by a link's box, which is conservative: decided on the link's shape
        if stopped.any():
            los[stopped] = self.checker.beams_clear(R[stopped], t[stopped], P[stopped])
        ok &= los
        idx = np.flatnonzero(ok)
        if len(idx):
            ok[idx] = self.checker.clear(R[idx], t[idx], self.clearance)
        return ok

    def why_not(self, Q, Q_ref) -> list:
        """For each joint vector of Q (m, N): None when :meth:`poses_ok` at the true limits, else the
        first check it fails in words (a joint past its limit with the amount, and how far it moved
        from Q_ref (m, N), the commands it replaces)."""
        from campaign.model.kinematics import frames
        from campaign.plan import checks

        robot = self.robot
        out = []
        for q, q_ref in zip(np.asarray(Q, dtype=float), np.asarray(Q_ref, dtype=float)):
            past = np.maximum(robot.q_lower - q, q - robot.q_upper)
            if np.any(past > 0):
                j = int(np.argmax(past))
                unit, f = ("mm", 1e3) if robot.prismatic[j] else ("°", np.rad2deg(1.0))
                limit = robot.q_lower[j] if q[j] < robot.q_lower[j] else robot.q_upper[j]
                out.append(f"joint {j + 1} at {f * q[j]:.1f}{unit} is {f * past[j]:.1f}{unit} beyond its limit "
                           f"({f * limit:.1f}{unit}), the correction moved it {f * (q[j] - q_ref[j]):+.1f}{unit}")
                continue
            R, t = frames(robot, q[None])
            E = robot.n_joints + 1
            P, A = checks.reflector_geometry(robot, R[:, E], t[:, E])
            los = checks.robot_line_of_sight_ok(robot, self.scene, P, R, t)
            if not los[0]:
                los = self.checker.beams_clear(R, t, P)
            tests = (("out of the tracker's range", checks.range_ok(self.scene, P)),
                     ("a reflector outside its cone", checks.cone_ok(robot, self.scene, P, A)),
                     ("a beam blocked by the scene", checks.scene_line_of_sight_ok(self.scene, P)),
                     ("a beam blocked by the robot", los),
                     (f"closer than {self.clearance * 1e3:.0f} mm to the scene or itself",
                      self.checker.clear(R, t, self.clearance)))
            out.append(next((what for what, ok in tests if not np.asarray(ok)[0]), None))
        return out

    def cycle_ok(self, Q5) -> bool:
        """Whether the cycle P1 → P5 → P4 → P3 → P2 → P1 of Q5 (5, N), rows P1..P5, is collision-free."""
        from campaign.plan.repair import check_segments

        seq = Q5[[k - 1 for k in CYCLE_ORDER + (1,)]]
        return bool(check_segments(self.robot, self.checker, seq[:-1], seq[1:], self.max_step,
                                   self.motion_clearance).all())

    def solve(self, centres, R_tools, Q_seed, half_edge, axes):
        """For each candidate (centres (m, 3), R_tools (m, 3, 3), Q_seed (m, N)): the five joint
        vectors (m, 5, N) and whether the candidate works at this half-edge (m,) bool."""
        from campaign.model.ik import nominal_ik

        m, N = Q_seed.shape
        T = np.concatenate([_targets(test_points(c, axes, half_edge), R) for c, R in zip(centres, R_tools)])
        q, r, _ = nominal_ik(self.robot, T, np.repeat(Q_seed, 5, axis=0), max_iter=100)
        reached = (np.linalg.norm(r[:, :3], axis=1) <= IK_TOL_M) & (np.linalg.norm(r[:, 3:], axis=1) <= IK_TOL_RAD)
        good = (reached & self.poses_ok(q)).reshape(m, 5).all(axis=1)
        Q5 = q.reshape(m, 5, N)
        for i in np.flatnonzero(good):
            good[i] = self.cycle_ok(Q5[i])
        return Q5, good


def find_cube(robot, scene, checker, q_suitable, *, clearance_m, motion_clearance_m, max_step_rad, seed=0,
              progress=None) -> dict:
    """The largest test cube about one of the suitable poses ``q_suitable`` (m, N) nearest the middle
    of the suitable workspace (its tool orientation kept for all five poses). Returns {"centre_m",
    "axes", "half_edge_m", "R_tool", "q" (5, N) rows P1..P5, "targets" (5, 4, 4)}; PlanError when no
    cube of the smallest half-edge fits."""
    from campaign.model.kinematics import forward

    T_seed = forward(robot, q_suitable)
    middle = np.median(T_seed[:, :3, 3], axis=0)
    near = np.argsort(np.linalg.norm(T_seed[:, :3, 3] - middle, axis=1))[: 8 * CENTRE_CANDIDATES]
    rng = np.random.default_rng(seed)
    pick = np.sort(rng.choice(near, size=min(CENTRE_CANDIDATES, len(near)), replace=False))
    pick = pick[np.argsort(np.linalg.norm(T_seed[pick, :3, 3] - middle, axis=1))]  # nearest the middle first
    centres, R_tools, Q_seed = T_seed[pick, :3, 3], T_seed[pick, :3, :3], q_suitable[pick]
    axes = cube_axes(robot.gravity_in_I)
    feas = _Feasibility(robot, scene, checker, clearance_m, motion_clearance_m, max_step_rad, JOINT_MARGIN_RAD)
    found, larger = None, None
    for h in HALF_EDGES_M:
        if progress:
            progress(h)
        Q5, good = feas.solve(centres, R_tools, Q_seed, h, axes)
        if good.any():
            i = int(np.flatnonzero(good)[0])  # the candidate nearest the middle
            found = (i, h, Q5[i])
            break
        larger = h
    if found is None:
        raise PlanError(f"no ISO 9283 test cube of half-edge {HALF_EDGES_M[-1] * 1e3:.0f} mm fits about the "
                        f"{len(pick)} suitable poses nearest the middle of the workspace (IK, limits, tracker, "
                        "clearance or the cycle's motions); check the scene and plan.clearance_m")
    i, h, Q5 = found
    if larger is not None:  # bisection between the feasible and the next larger half-edge, same centre
        lo, hi = h, larger
        for _ in range(BISECTION_STEPS):
            mid = 0.5 * (lo + hi)
            Q5m, ok = feas.solve(centres[i : i + 1], R_tools[i : i + 1], Q_seed[i : i + 1], mid, axes)
            if ok[0]:
                lo, Q5 = mid, Q5m[0]
            else:
                hi = mid
        h = lo
    if h * SIZE_MARGIN >= HALF_EDGES_M[-1]:  # back off from the boundary the bisection found
        Q5m, ok = feas.solve(centres[i : i + 1], R_tools[i : i + 1], Q_seed[i : i + 1], h * SIZE_MARGIN, axes)
        if ok[0]:
            h, Q5 = h * SIZE_MARGIN, Q5m[0]
    targets = _targets(test_points(centres[i], axes, h), R_tools[i])
    return {"centre_m": centres[i], "axes": axes, "half_edge_m": float(h), "R_tool": R_tools[i], "q": Q5,
            "targets": targets}


#: P_k of cycle c has pose id ``ID_STRIDE·c + k``
ID_STRIDE = 10


def cycle_ids(cycles: int) -> np.ndarray:
    """(5·cycles,) pose ids in visiting order: P_k of cycle c is 10·c + k."""
    return np.array([k + c * ID_STRIDE for c in range(cycles) for k in CYCLE_ORDER], dtype=np.int64)


def pose_number(pose_id) -> np.ndarray:
    """k (1..5) of the test pose P_k that pose ids measure."""
    return np.asarray(pose_id, dtype=np.int64) % ID_STRIDE


def plan_iso9283(config=None, run_dir="runs/iso9283", *, cycles: int = DEFAULT_CYCLES, compensate=None,
                 grid_scale: float = 1.0, progress: bool = False, robot=None, tool_frame=None,
                 base_frame=None) -> dict:
    """Plan the ISO 9283 test into ``run_dir``; return the summary (also RUN/plan/summary.json).

    cycles: visits of the five poses (the standard's 30 by default). compensate: a calibrated run
    folder: the joint commands are corrected by its current model (`campaign compensate`) so that
    the calibrated robot reaches the same targets, for the test after calibration. The cube is
    found on the run's grid (``grid_scale`` as `campaign plan`); the same configuration gives the
    same cube. Writes RUN/plan/poses.csv, vias.csv, dropped.csv, summary.json, iso9283.json and
    the run's campaign.yaml; refused (one line, nothing written) when the run holds measurements.
    """
    from campaign.plan import checks
    from campaign.plan.pipeline import prepare_plan, suitable_poses

    if isinstance(cycles, bool) or not isinstance(cycles, int) or not 2 <= cycles <= 10000:
        raise ConfigError(f"--cycles must be a whole number from 2 to 10000, got {cycles!r}")
    t0 = time.perf_counter()
    run, cfg, model, scene, grid, advice = prepare_plan(config, run_dir, grid_scale, robot, tool_frame, base_frame)
    calibrated = None
    if compensate is not None:
        from campaign.identify.use import CalibratedRobot

        calibrated = CalibratedRobot(compensate)
        if calibrated.robot.name != model.name or calibrated.robot.n_joints != model.n_joints:
            raise ConfigError(f"--compensate {compensate}: calibrated for robot {calibrated.robot.name!r}, "
                              f"this plan is for {model.name!r}")
        if calibrated.context_keys:
            raise ConfigError(f"--compensate {compensate}: its model needs {', '.join(calibrated.context_keys)} "
                              "at every pose, which a plan cannot know")
    pc = cfg.plan
    with run.lock("plan"):
        run.refuse_if_measured("planning again", advice)
        suitable = suitable_poses(model, scene, grid, pc.clearance_m, progress)
        if len(suitable) == 0:
            raise PlanError(f"{cfg.path}: no suitable pose among {grid.size:,} candidates; no ISO 9283 cube can be "
                            "placed (check the scene and plan.clearance_m)")
        checker = checks.ClearanceChecker(model, scene, pc.clearance_m)
        max_step = np.deg2rad(pc.motion_sample_deg)
        cube = find_cube(model, scene, checker, grid.q(suitable), clearance_m=pc.clearance_m,
                         motion_clearance_m=pc.motion_clearance_m, max_step_rad=max_step)
        q_nominal = cube["q"]
        q_command = q_nominal
        compensation = None
        if calibrated is not None:
            q_command, res, conv = calibrated.compensate(cube["targets"], q_nominal)
            feas = _Feasibility(model, scene, checker, pc.clearance_m, pc.motion_clearance_m, max_step)
            why = [f"P{k + 1} did not converge" for k in np.flatnonzero(~conv)]
            why += [f"P{k + 1}: {w}" for k, w in enumerate(feas.why_not(q_command, q_nominal)) if w]
            if not why and not feas.cycle_ok(q_command):
                why.append("a motion of the cycle collides")
            if why:
                raise PlanError(f"--compensate {compensate}: the corrected commands fail: {'; '.join(why)}. The "
                                f"cube keeps {np.rad2deg(JOINT_MARGIN_RAD):.1f}° from every joint limit for the "
                                "corrections of a calibrated robot; larger ones mean a calibration far from the nominal "
                                "model: check its warnings (large_corrections) and the robot's joint convention")
            compensation = {"run": str(Path(compensate).resolve()), "stage": calibrated.stage,
                            "residual_position_mm": (1e3 * np.linalg.norm(res[:, :3], axis=1)).tolist()}
            inside, sigma = calibrated.in_domain(q_command), calibrated.sigma_mm(q_command)
            # each corrected command against the calibration's domain (None: a calibration without domain.json)
            compensation["in_domain"] = None if inside is None else [bool(v) for v in inside]
            compensation["sigma_mm"] = None if sigma is None else [float(v) for v in sigma]
        ids = cycle_ids(cycles)
        Q = np.asarray(q_command)[pose_number(ids) - 1]
        summary = _write(run, cfg, model, scene, grid, suitable, cube, q_nominal, q_command, ids, Q, cycles,
                         compensation, t0)
    return summary


def _write(run, cfg, robot, scene, grid, suitable, cube, q_nominal, q_command, ids, Q, cycles, compensation, t0):
    # every file of the plan into a new version of RUN/plan, current only once whole (campaign.versioned)
    with plan_folder(run.path).new_version() as version:
        return _write_version(version, run, cfg, robot, scene, grid, suitable, cube, q_nominal, q_command, ids, Q,
                              cycles, compensation, t0)


def _write_version(version, run, cfg, robot, scene, grid, suitable, cube, q_nominal, q_command, ids, Q, cycles,
                   compensation, t0):
    from campaign.model.kinematics import frames
    from campaign.plan.outputs import write_tour
    from campaign.plan.timing import path_time

    pc = cfg.plan
    out = version.path
    write_tour(out, ids, Q, {}, [])
    motion_s = path_time(robot, Q) if len(Q) > 1 else 0.0
    per_pose = pc.settle_time_s + len(robot.reflectors) * pc.tracker_time_per_reflector_s
    total = motion_s + len(Q) * per_pose
    h = cube["half_edge_m"]
    names = [f"P{k}" for k in range(1, 6)]
    iso = {
        "standard": "ISO 9283:1998, pose accuracy and pose repeatability (7.2)",
        "cycles": cycles, "order": [f"P{k}" for k in CYCLE_ORDER],
        "cube": {"centre_m": cube["centre_m"].tolist(), "edge_m": 2 * h, "axes_in_I": cube["axes"].T.tolist(),
                 "diagonal_plane": "C1-C2-C7-C8", "corner_fraction": CORNER_FRACTION,
                 "diagonal_m": 2 * h * np.sqrt(3.0)},
        "tool_rotation_in_I": cube["R_tool"].tolist(),
        "poses": [{"name": n, "pose_id": k + 1, "target_T_IE": cube["targets"][k].tolist(),
                   "q_nominal": q_nominal[k].tolist(), "q_command": np.asarray(q_command)[k].tolist()}
                  for k, n in enumerate(names)],
        "compensated_with": compensation,
    }
    atomic_write_json(out / "iso9283.json", iso)
    front = scene.side_of_wall(frames(robot, Q)[1][:, robot.n_joints + 1])
    summary = {
        "plan_id": version.id, "robot": robot.name, "tool_frame": robot.tool_frame, "reflectors": [r.name for r in robot.reflectors],
        "scene": str(scene.path), "grid_cells": [int(c) for c in grid.cells], "candidates": int(grid.size),
        "suitable": int(len(suitable)), "suitable_fraction": len(suitable) / grid.size,
        "groups": {"front_of_wall": int(front.sum()), "behind_wall": int((~front).sum())},
        "campaign": {"kind": "iso9283", "mode": "iso9283",
                     "text": f"the ISO 9283 pose test: P1..P5 of a {2e3 * h:.0f} mm cube, {cycles} cycles"},
        "iso9283": {"cycles": cycles, "edge_m": 2 * h, "centre_m": cube["centre_m"].tolist(),
                    "compensated_with": None if compensation is None else compensation["run"],
                    "outside_domain": [] if not (compensation or {}).get("in_domain") else
                    [f"P{k + 1}" for k, v in enumerate(compensation["in_domain"]) if not v]},
        "tour": {"poses": int(len(Q)), "via_poses": 0, "dropped": 0, "motion_time_s": motion_s,
                 "clearance_m": pc.clearance_m, "motion_clearance_m": pc.motion_clearance_m,
                 "motion_sample_deg": pc.motion_sample_deg, "repeats": int(len(Q) - 5)},
        "estimated_campaign": {"motion_s": motion_s, "settle_s": len(Q) * pc.settle_time_s,
                               "tracker_s": len(Q) * len(robot.reflectors) * pc.tracker_time_per_reflector_s,
                               "total_s": total, "total_days": total / 86400.0,
                               "seconds_per_pose": total / len(Q)},
    }
    summary["timing_s"] = {"total": time.perf_counter() - t0}
    atomic_write_json(out / "summary.json", summary)
    run.write_config(cfg)  # last: a plan that fails on the way leaves the run's campaign.yaml as it was
    return summary
