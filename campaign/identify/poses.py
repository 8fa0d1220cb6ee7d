"""The measured poses as the model sees them, and how many it needs: answered once, below both
`calibrate` (campaign.identify.calibrate) and `diagnose` (campaign.diagnose), which ask the same
questions of a run (how many equations a pose gives, how many distinct poses identify a model
and its folds, the data registered into F_I at the measured point or frame)."""

from __future__ import annotations

from dataclasses import replace

import numpy as np

from campaign.errors import DataError
from campaign.measure import plausibility
from campaign.measure.reflectors import transform_points
from campaign.model.kinematics import forward


def equations_per_pose(position_only: bool) -> int:
    """Equations a pose gives the identification: 3 (positions only) or 6 (with orientation)."""
    return 3 if position_only else 6


def training_poses_needed(n_unknowns: int, position_only: bool) -> int:
    """The fewest distinct poses whose equations outnumber ``n_unknowns`` (identifiable, and one
    degree of freedom left for the noise estimate)."""
    return n_unknowns // equations_per_pose(position_only) + 1


def informative_equations(n_seen) -> int:
    """Equations a pose of raw reflectors gives the parameters, on average over poses with
    ``n_seen`` (n,) reflectors seen: 3 for one, 5 for two (not the rotation about their line), 6
    for three or more (the rest of their 3 per reflector only see the noise); at least 3."""
    n_seen = np.asarray(n_seen)
    if not len(n_seen):
        return 3
    per = np.select([n_seen >= 3, n_seen == 2], [6, 5], 3)
    return max(3, int(per.sum()) // len(per))


def check_pose_count(run_dir, robot, n_train: int, n_test: int, position_only: bool, *, n_effect_params: int = 0,
                     fold_rule=None, validation: bool = False, points=None, rows_per_pose: int | None = None) -> None:
    """One line (DataError) when a run has too few distinct poses to identify the base
    parameters (plus ``n_effect_params``) and test them: how many are needed and why.

    n_train: distinct training poses; fold_rule: a :class:`campaign.identify.split.FoldRule`
    when every fold is fitted too (`diagnose`): its smallest fold fit must identify them;
    validation: the test set is a plan's validation poses (not the 80/20 split); points: raw
    reflectors' nominal positions (k, 3) m in the tool frame, identified from their positions,
    ``rows_per_pose`` equations per pose (:func:`informative_equations`)."""
    from campaign.identify.split import EXACT_SPLIT_BELOW, poses_for_training
    from campaign.model.base_params import base_parameters

    rows = equations_per_pose(position_only) if points is None else max(int(rows_per_pose or 3), 1)
    if points is None:
        n_base = base_parameters(robot, position_only=position_only).n_base
        need = training_poses_needed(n_base + n_effect_params, position_only)
    else:
        n_base = base_parameters(robot, position_only=True, points=points).n_base
        need = (n_base + n_effect_params) // rows + 1
    fits = n_train if fold_rule is None else fold_rule.fit_poses
    if fits >= need and n_test >= 1:
        return
    unknowns = f"{n_base} identifiable base parameters" + (f" and {n_effect_params} effect parameters"
                                                          if n_effect_params else "")
    what = ("positions only" if rows == 3 else "position and orientation") if points is None else \
        "raw reflectors, on average: 3 for one seen, 5 for two, 6 for three or more"
    if fold_rule is None:
        need_train, who = need, "calibrate needs"
    else:  # the fewest training poses whose every fold fit has `need` poses (the same fold rule)
        from campaign.identify.split import FoldRule, choose_folds

        need_train = need + 1
        while FoldRule(fold_rule.k if fold_rule.asked else choose_folds(need_train).k, need_train).fit_poses < need:
            need_train += 1
        folds = "each held-out pose (leave-one-out)" if fold_rule.leave_one_out else f"each of {fold_rule.k} folds"
        who = f"diagnose, which fits the model again without {folds}, needs"
    if validation:
        total = f"besides the plan's validation poses"
    else:
        n_total = poses_for_training(need_train)
        total = f"{'about ' if n_total >= EXACT_SPLIT_BELOW else ''}{n_total} poses with the 80/20 split"
    raise DataError(f"{run_dir}: {n_train} training poses (and {n_test} test) are too few: {robot.name} has {unknowns} "
                    f"and a pose gives {rows} equations ({what}), so {who} at least {need_train} distinct training "
                    f"poses and one test pose ({total})")


def distinct_poses(q) -> int:
    """Distinct joint vectors among ``q`` (n, N): a pose measured again adds no equation of its own."""
    return int(len(np.unique(np.asarray(q), axis=0))) if len(q) else 0


def measured_point(robot, poses, train=None):
    """Where one-reflector data were measured in the tool frame, (3,) m (None for other kinds):
    robot.yaml's single reflector; where it names none, the tool frame's origin, unless the
    training poses ``train`` (all when None) place the point on the nominal model far from it
    (:func:`campaign.measure.plausibility.off_origin_point`, with the tracker's pose for data in
    its frame): a marker stuck on the hand is rarely at the tool frame's origin, and the tolerance
    priors of the tool and the base must hold around where it is, not around a guess centimetres
    off."""
    point = plausibility.measured_point(robot, poses.kind)
    if point is None:
        return None
    train = np.ones(len(poses), bool) if train is None else train
    found = plausibility.off_origin_point(robot, poses.q[train], poses.xyz[train], poses.frame)
    return point if found is None else found[1]


def tool_mounting(robot, poses, train=None):
    """The frame 6-D or raw-reflector data were measured in, in the URDF's tool frame, (4, 4), when
    the ``train`` poses (all when None) place it on the nominal model far from the tool frame
    (:func:`campaign.measure.plausibility.tool_mounting`: a marker plate or a flange the URDF does
    not describe) and the nominal model fits the data there as a real robot's errors allow
    (:func:`campaign.measure.plausibility.nominal_limit_m`); else None (other kinds too).
    The tolerance priors of the tool then hold around the mounting, as they do around a one-reflector
    measured point (:func:`measured_point`)."""
    rows = np.flatnonzero(np.ones(len(poses), bool) if train is None else train)
    fit = plausibility.mounting_fit(robot, poses, rows)
    return None if fit is None or not fit[2] < min(fit[1], plausibility.nominal_limit_m(robot)) else fit[0]


def mounting_json(X) -> dict:
    """A tool mounting (4, 4) as params.yaml writes it: translation (m) and rotation vector (rad)."""
    from campaign.model.rotations import matrix_to_rotvec

    return {"translation_m": [float(v) for v in X[:3, 3]],
            "rotation_vector_rad": [float(v) for v in matrix_to_rotvec(np.asarray(X)[:3, :3])]}


def mounting_from_json(d, source) -> np.ndarray:
    """params.yaml's ``tool_mounting_in_tool`` back to (4, 4); DataError naming ``source`` when malformed."""
    from campaign.model.rotations import rotvec_to_matrix

    try:
        t = np.asarray(d["translation_m"], dtype=float).reshape(3)
        r = np.asarray(d["rotation_vector_rad"], dtype=float).reshape(3)
    except (KeyError, TypeError, ValueError):
        raise DataError(f"{source}: tool_mounting_in_tool must hold translation_m and rotation_vector_rad "
                        "(3 numbers each)") from None
    X = np.eye(4)
    X[:3, :3], X[:3, 3] = rotvec_to_matrix(r), t
    return X


def prepare_measured(robot, poses, train, point=None, mounting=None):
    """The data as the model sees them: (poses in F_I, the robot whose tool frame is the measured
    point or frame, the tracker registration or None). One-reflector data are fitted at the measured
    point (``point``, else :func:`measured_point` on the ``train`` poses), 6-D and raw-reflector data
    in the measured frame (``mounting``, else :func:`tool_mounting`); data in the tracker's frame are
    registered (:func:`register_tracker`) on the ``train`` poses. Used by calibrate and diagnose alike."""
    if point is None:
        point = measured_point(robot, poses, train)
    if point is not None:
        robot = robot.with_tool_point(point)
    if mounting is None:
        mounting = tool_mounting(robot, poses, train)
    if mounting is not None:
        robot = robot.with_tool_transform(mounting)
    tracker = None
    if poses.frame == "tracker":
        poses, tracker = register_tracker(robot, poses, train)
    return poses, robot, tracker


def register_tracker(robot, poses, train):
    """Measurements in the tracker's frame L into the robot's frame: the closed-form rigid
    registration T_LI0 of the nominal model's tool points to the measured ones on the training
    poses (Kabsch; raw reflectors: of every seen reflector's nominal position to its measured one). The remaining tracker-pose error is identified by the base transform's six
    parameters (pL_I0_*, pR_I0_*), which are the same unknowns as a tracker pose. Returns the
    poses in F_I and a record of the registration."""
    from campaign.measure.reflectors import invert, register_points

    if poses.kind == "markers" and poses.markers is not None:
        # raw reflectors: every seen reflector of the training poses, also of poses with fewer than three
        T_nom = forward(robot, poses.q[train])
        P_nom = transform_points(T_nom, np.broadcast_to(poses.marker_positions, poses.markers[train].shape))
        P_nom, P_meas = P_nom.reshape(-1, 3), poses.markers[train].reshape(-1, 3)
        seen = np.isfinite(P_meas).all(axis=1)
        P_nom, P_meas = P_nom[seen], P_meas[seen]
    else:
        P_nom, P_meas = forward(robot, poses.q[train])[:, :3, 3], poses.xyz[train]
    T_LI0 = register_points(P_nom, P_meas)
    T_I = invert(T_LI0) @ poses.T_IE
    if not poses.has_orientation:
        T_I[:, :3, :3] = np.eye(3)
    fitted = P_nom @ T_LI0[:3, :3].T + T_LI0[:3, 3]
    rms = float(np.sqrt(np.nanmean(np.sum((fitted - P_meas) ** 2, axis=1))))
    if poses.markers is not None:
        poses = replace(poses, markers=transform_points(invert(T_LI0), poses.markers))
    return replace(poses, T_IE=T_I), tracker_block(T_LI0, rms)


def tracker_to_robot(tracker):
    """(4, 4): the map of readings in the tracker's frame into the registered robot frame (the
    inverse of ``tracker["T_L_I"]``, :func:`register_tracker`), or None without a registration."""
    from campaign.measure.reflectors import invert

    return None if tracker is None else invert(np.asarray(tracker["T_L_I"], dtype=float))


def tracker_block(T_L_I, rms_m: float) -> dict:
    """metrics.json's ``tracker``: ``T_L_I`` (4, 4), the pose of the model's base frame F_I in the
    tracker's frame L, which maps predict's output, compensate's targets and the exported URDF's
    root frame into the tracker's frame (the tracker's pose error beyond it is the base transform's
    identified error, inside the model); ``registration_rms_mm``; and the deprecated aliases
    ``T_L_I_registration`` and ``tracker_pose_identified`` of ``T_L_I`` (the latter held, until
    2026-11, the registration times the base transform's error, which maps no output of the model)."""
    T = np.asarray(T_L_I, dtype=float).tolist()
    return {"T_L_I": T, "registration_rms_mm": rms_m * 1e3, "T_L_I_registration": T, "tracker_pose_identified": T}
