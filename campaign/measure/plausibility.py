"""Plausibility: measured data and an identified model checked against physics, said out loud.

A metrology tool's worst failure is a confident wrong answer: data in metres read as mm fit a
robot shrunk a thousandfold to 0.000 mm; joints read in another controller's convention give a
95 mm "calibration". Each check here compares what was measured or identified with what a real
robot and a real laser tracker can give, and when they disagree returns a :class:`Finding` that
says what is implausible, the likely cause and the fix (docs/csv_import.md, "Plausibility").

Checks on the data (after `import`, and again in `calibrate`), :func:`check_data`:

* ``workspace_scale`` — the measured positions span a workspace of another size than the
  nominal model's (a length unit: 1000× is metres read as mm or mm read as metres);
* ``reflector_layout`` — raw reflectors as far apart as their nominal positions say (a
  ``--markers`` file in mm, reflectors in another order);
* ``nominal_residual`` — the nominal model and the measurements, registered rigidly, disagree
  by more than any real robot's geometric errors; ``joint_convention`` then names the usual
  controller convention (a missing J2/J3 coupling, a sign flip, a 90°/180° offset) whose
  registration fits, re-fitted here for each candidate;
* ``measured_point`` — one-reflector data that fit the nominal model measured at a point off the
  tool frame's origin, robot.yaml naming none (a marker stuck on the hand): said with the point,
  which `calibrate` then fits at, instead of ``nominal_residual``;
* ``tool_mounting`` — 6-D or raw-reflector data that fit the nominal model measured in a frame
  moved and turned from the URDF's tool frame (a marker plate, a flange the URDF does not
  describe): said with its angle and distance, which `calibrate` then fits in, instead of
  ``nominal_residual`` (whose joint-convention hint stays for data that no mounting explains);
* ``base_frame`` — robot-frame data that fit the nominal model only after a rigid move;
* ``rotation_reading`` / ``orientation_residual`` — the orientation columns read in another
  convention (roll-pitch-yaw, KUKA's A, B, C) agree with the nominal orientations.

Checks on a fit (after `calibrate`), :func:`check_fit`: ``large_corrections`` (identified
translations or rotations large against the robot), ``noise_below_floor`` (the fit leaves less
than the tracker's noise: it fits what the measurements cannot carry), ``model_residual``
(the calibrated model still misses by more than a calibrated robot can).

Thresholds are in campaign/tolerances.py with their reasons. This module reads arrays only: it
sits below `identify` (which calls it) and beside the CSV reader (which asks it which rotation
reading fits).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from campaign.measure.reflectors import register_measured_point, register_points, transform_points
from campaign.model.kinematics import forward
from campaign.model.priors import robot_tolerances
from campaign.model.rotations import matrix_to_rotvec
from campaign.tolerances import (CORRECTION_MAX_FRACTION_OF_SIZE, CORRECTION_MAX_RAD, CONVENTION_GAIN_MIN,
                                 FITTED_NOISE_BELOW_FLOOR_FACTOR, MODEL_RESIDUAL_MAX_FRACTION_OF_SIZE,
                                 MODEL_RESIDUAL_MAX_M, NOMINAL_RESIDUAL_MAX_FRACTION_OF_SIZE, NOMINAL_RESIDUAL_MAX_M,
                                 ORIENTATION_SPREAD_MAX_RAD, PLAUSIBILITY_MAX_POSES, POINT_REGISTRATION_MIN_TOLERANCES,
                                 READING_SPREAD_RATIO_MAX, REFLECTOR_DISTANCE_TOL_M, TRACKER_NOISE_MIN_M,
                                 TRACKER_RANGE_MAX_M, WORKSPACE_SCALE_MAX)


@dataclass(frozen=True)
class Finding:
    """One implausibility: a stable ``code`` and a one-line ``message`` (what, likely cause, fix)."""

    code: str
    message: str

    def as_json(self) -> dict:
        return {"code": self.code, "message": self.message}

    @classmethod
    def from_json(cls, d) -> "Finding":
        return cls(str(d["code"]), str(d["message"]))


def merge(*lists) -> list:
    """Warnings of several checks in order, the first of each code kept."""
    seen, out = set(), []
    for ws in lists:
        for w in ws:
            if w.code not in seen:
                seen.add(w.code)
                out.append(w)
    return out


def robot_size_m(robot) -> float:
    """The chain stretched out: the sum of the nominal transforms' translations, m."""
    return float(np.linalg.norm(robot.t_nominal, axis=1).sum())


def measured_point(robot, kind: str):
    """Where one-reflector (``kind`` "point") data were measured in the tool frame, (3,) m:
    robot.yaml's single reflector, else the tool frame's origin (None for other kinds)."""
    if kind != "point":
        return None
    return np.asarray(robot.reflector_positions_in_E[0]) if len(robot.reflectors) == 1 else np.zeros(3)


def nominal_limit_m(robot) -> float:
    """How far (rms, m) data may miss the nominal model, rigidly registered, before the miss is
    more than a real robot's geometric errors."""
    return max(NOMINAL_RESIDUAL_MAX_M, NOMINAL_RESIDUAL_MAX_FRACTION_OF_SIZE * robot_size_m(robot))


def _sample(n: int) -> np.ndarray:
    """At most PLAUSIBILITY_MAX_POSES row indices spread evenly over n rows."""
    if n <= PLAUSIBILITY_MAX_POSES:
        return np.arange(n)
    return np.unique(np.linspace(0, n - 1, PLAUSIBILITY_MAX_POSES).astype(int))


def _points(robot, q, poses_kind, marker_positions, p_e=None):
    """Nominal points (n, k, 3) where the data were measured: the tool point, or each reflector."""
    T = forward(robot, q, p_e)
    if poses_kind == "markers" and marker_positions is not None:
        return transform_points(T, np.broadcast_to(marker_positions, (len(q),) + np.shape(marker_positions)))
    return T[:, None, :3, 3]


def _registered_rms(P_nom, P_meas) -> tuple:
    """(rms (m) of the measured points about the rigidly registered nominal ones, registration T)."""
    A, B = P_nom.reshape(-1, 3), P_meas.reshape(-1, 3)
    ok = np.isfinite(A).all(axis=1) & np.isfinite(B).all(axis=1)
    if ok.sum() < 3:
        return np.nan, np.eye(4)
    T = register_points(A[ok], B[ok])
    fitted = A[ok] @ T[:3, :3].T + T[:3, 3]
    return float(np.sqrt(np.mean(np.sum((fitted - B[ok]) ** 2, axis=1)))), T


def _spread_m(P) -> float:
    """rms distance of points (m, 3) from their centroid, m."""
    P = P[np.isfinite(P).all(axis=1)]
    return float(np.sqrt(np.mean(np.sum((P - P.mean(axis=0)) ** 2, axis=1)))) if len(P) > 1 else np.nan


def _mm(v) -> str:
    v = float(v) * 1e3
    return f"{v:,.0f} mm" if abs(v) >= 100 else f"{v:.3g} mm"


def _unit_cause(robot, q, P_meas, kind, marker_positions, limit: float) -> str:
    """Which unit mistake makes the data fit the nominal model: positions scaled by 1000 either
    way (m vs mm), or the revolute joints by 180/pi either way (rad vs deg), each re-registered;
    the best under ``limit`` (m, registered rms) is named with its rms."""
    deg = np.where(robot.prismatic, 1.0, 180 / np.pi)
    trials = (("data in metres imported with --length-unit mm", 1.0, 1e3),
              ("data in mm imported as metres (--length-unit mm)", 1.0, 1e-3),
              ("joints in rad imported with --angle-unit deg", deg, 1.0),
              ("joints in degrees imported as rad (--angle-unit deg)", 1 / deg, 1.0))
    best = None
    for cause, k_q, k_p in trials:
        rms = _registered_rms(_points(robot, q * k_q, kind, marker_positions), P_meas * k_p)[0]
        if np.isfinite(rms) and rms < limit and (best is None or rms < best[1]):
            best = (cause, rms)
    if best is None:
        return "another robot, or a tool frame far from the measured one (no unit mistake fits)"
    return f"{best[0]} (read that way the nominal model fits to {_mm(best[1])} rms)"


def orientation_spread_rad(R_nom, R_meas) -> float:
    """Mean angle (rad) by which measured orientations (n, 3, 3) differ from nominal ones beyond
    one constant rotation on the tool side (R_meas ≈ R_nom X) or on the base side (R_meas ≈ X R_nom,
    a tracker's frame): the smaller of the two."""
    ok = np.isfinite(R_nom).all(axis=(1, 2)) & np.isfinite(R_meas).all(axis=(1, 2))
    if ok.sum() < 2:
        return np.nan
    A, B = R_nom[ok], R_meas[ok]
    best = np.inf
    for D in (np.swapaxes(A, 1, 2) @ B, B @ np.swapaxes(A, 1, 2)):
        U, _, Vt = np.linalg.svd(D.mean(axis=0))
        X = U @ np.diag([1, 1, np.sign(np.linalg.det(U @ Vt))]) @ Vt
        best = min(best, float(np.mean(np.linalg.norm(matrix_to_rotvec(X.T @ D), axis=1))))
    return best


def rotation_readings(robot, q, values, columns, readings, angle_scales=(1.0,)) -> list:
    """Which reading of orientation columns agrees with the nominal orientations.

    values: (n, k) the columns as written; readings: {name: (columns, values (n, k) -> R (n, 3, 3))};
    angle_scales: factors to try on angle columns (rad: 1, degrees read as rad: pi/180).
    Returns [(spread_rad, name, scale), ...] best first (:func:`orientation_spread_rad`)."""
    idx = _sample(len(q))
    R_nom = forward(robot, q[idx])[:, :3, :3]
    out = []
    for name, (cols, to_matrix, angles) in readings.items():
        if tuple(cols) != tuple(columns):
            continue
        for s in (angle_scales if angles else (1.0,)):
            with np.errstate(all="ignore"):
                R = to_matrix(values[idx] * s)
            out.append((orientation_spread_rad(R_nom, R), name, s))
    return sorted(out, key=lambda t: (np.nan_to_num(t[0], nan=np.inf), t[1] != "rotvec"))


# -- the joint conventions a controller may use ------------------------------------------------
def convention_candidates(robot) -> list:
    """The usual controller conventions as maps of the model's q: [(label, M (N, N), b (N,))],
    the model then sees q' = M q + b. Per joint a sign flip and offsets of ±90° and 180°
    (revolute joints); per pair of neighbours a coupling q_j ∓ q_(j-1) (FANUC's J3 measured
    from the horizontal: q3 of the model = q3 of the controller − q2)."""
    N = robot.n_joints
    out = []
    for j in range(N):
        M = np.eye(N)
        M[j, j] = -1
        out.append((f"joint {j + 1}'s sign is flipped (q{j + 1} -> -q{j + 1})", M, np.zeros(N)))
        if robot.prismatic[j]:
            continue
        for deg in (90, -90, 180):
            b = np.zeros(N)
            b[j] = np.deg2rad(deg)
            out.append((f"joint {j + 1} is offset by {deg:+d} deg (q{j + 1} {'+' if deg > 0 else '-'} {abs(deg)} deg)",
                        np.eye(N), b))
    for j in range(1, N):
        if robot.prismatic[j] or robot.prismatic[j - 1]:
            continue
        for s, sign in ((-1, "-"), (1, "+")):
            M = np.eye(N)
            M[j, j - 1] = s
            out.append((f"joint {j + 1} looks coupled to joint {j} (q{j + 1} {sign} q{j})", M, np.zeros(N)))
    return out


def controller_yaml(robot, M, b) -> str:
    """robot.yaml's ``controller:`` block for the convention ``q_model = M (A q_ctrl + b_c) + b``
    (A, b_c the robot's current convention)."""
    N = robot.n_joints
    A = np.eye(N) if robot.controller_matrix is None else np.asarray(robot.controller_matrix)
    b_c = np.zeros(N) if robot.controller_offset is None else np.asarray(robot.controller_offset)
    A2, b2 = M @ A, M @ b_c + b

    def num(v):
        return str(int(v)) if float(v).is_integer() else repr(float(v))

    text = "controller: {coupling: [" + ", ".join("[" + ", ".join(num(v) for v in row) + "]" for row in A2) + "]"
    if np.any(b2 != 0):
        text += ", offset: [" + ", ".join(num(v) for v in b2) + "]"
    return text + "}"


def test_conventions(robot, q, P_meas, kind, marker_positions, *, register: bool = True) -> list:
    """rms (m) of the nominal model under each candidate convention, rigidly registered to the
    data (``register``) or as it stands (data in the robot's frame): [(rms, label, M, b), ...]
    best first, the data's own convention (label None) among them."""
    N = robot.n_joints

    def rms(qq):
        P = _points(robot, qq, kind, marker_positions)
        if register:
            return _registered_rms(P, P_meas)[0]
        return float(np.sqrt(np.nanmean(np.sum((P - P_meas) ** 2, axis=-1))))

    out = [(rms(q), None, np.eye(N), np.zeros(N))]
    out += [(rms(q @ M.T + b), label, M, b) for label, M, b in convention_candidates(robot)]
    return sorted(out, key=lambda t: np.nan_to_num(t[0], nan=np.inf))


def _convention_finding(robot, ranked, rms, limit, what):
    """``joint_convention`` when the best candidate of ``ranked`` fits (under ``limit`` and
    CONVENTION_GAIN_MIN times better than ``rms``), else None."""
    best = ranked[0]
    if best[1] is None or not best[0] < limit or not best[0] * CONVENTION_GAIN_MIN < rms:
        return None
    return Finding("joint_convention",
                   f"{best[1]}: {what} {_mm(rms)} -> {_mm(best[0])} with that convention; import with the "
                   f"controller's convention in robot.yaml: {controller_yaml(robot, best[2], best[3])} "
                   "(docs/robot_yaml.md)")


# -- the checks ------------------------------------------------------------------------------
def _measured_points(poses):
    """(n, k, 3) measured points: the reflectors (raw), else the tool point."""
    if poses.kind == "markers" and poses.markers is not None:
        return poses.markers
    return poses.xyz[:, None, :]


def check_data(robot, poses, *, noise_mm: float | None = None, orientation=None, fit_rows=None) -> list:
    """Warnings on measured data (MeasuredPoses) against the nominal ``robot`` (whose tool frame is
    the measured point for one-reflector data). noise_mm: the measurement noise floor (E‖e‖, mm)
    when known, to say how far the disagreement is from it. fit_rows: the rows (indices) that place
    a measured point or a tool mounting, as calibrate places them on its training poses (default:
    every row), so that both say one value. orientation: optional
    ``(values (n, k), columns, reading, readings, angle_scales)`` of the orientation columns as
    written, to test other rotation readings (:func:`rotation_readings`). Returns a list of
    :class:`Finding`."""
    idx = _sample(len(poses))
    q = poses.q[idx]
    kind = poses.kind
    P_meas = _measured_points(poses)[idx]
    P_nom = _points(robot, q, kind, poses.marker_positions)
    out = []
    layout_bad = False
    if kind == "markers" and poses.markers is not None and poses.markers.shape[1] >= 2:
        w = _reflector_layout(poses.markers[idx], poses.marker_positions)
        if w is not None:
            out.append(w)
            layout_bad = True
    scale = _spread_m(P_meas.reshape(-1, 3)) / max(_spread_m(P_nom.reshape(-1, 3)), 1e-300)
    limit = nominal_limit_m(robot)
    if not layout_bad and np.isfinite(scale) and not 1 / WORKSPACE_SCALE_MAX <= scale <= WORKSPACE_SCALE_MAX:
        cause = _unit_cause(robot, q, P_meas, kind, poses.marker_positions, limit)
        out.append(Finding("workspace_scale",
                           f"the measured positions span {scale:.3g}× the nominal model's workspace "
                           f"({_mm(_spread_m(P_meas.reshape(-1, 3)))} vs {_mm(_spread_m(P_nom.reshape(-1, 3)))} rms "
                           f"about their centre): likely {cause}; check --length-unit, --angle-unit and the robot "
                           f"({robot.name})"))
    if out:
        return out
    rms, _ = _registered_rms(P_nom, P_meas)
    noise = "" if not noise_mm else f" ({rms * 1e3 / noise_mm:,.0f}× the noise)"
    fit_rows = np.arange(len(poses)) if fit_rows is None else np.asarray(fit_rows)
    found = (_off_point(robot, poses, q, P_meas, rms, limit, fit_rows)
             or _off_mounting(robot, poses, idx, rms, limit, fit_rows))
    if found is not None:
        out.append(found)
    elif np.isfinite(rms) and rms > limit:
        out.append(Finding("nominal_residual",
                           f"the nominal model and the measurements disagree by {_mm(rms)} rms after a rigid "
                           f"registration{noise}, more than a real {robot.name}'s geometric errors "
                           f"(≤ {_mm(limit)}): check the joint convention (coupling, signs, offsets: robot.yaml's "
                           "controller), the length and angle units, the tool frame"))
        ranked = test_conventions(robot, q, P_meas, kind, poses.marker_positions)
        found = (_convention_finding(robot, ranked, rms, limit, "registered rms")
                 or _convention_and_mounting(robot, poses, ranked[0], rms, limit, fit_rows))
        if found is not None:
            out.append(found)
    elif poses.frame == "robot" and np.isfinite(rms):  # (fewer than 3 points: no rigid move to compare)
        plain = float(np.sqrt(np.nanmean(np.sum((P_nom - P_meas) ** 2, axis=-1))))
        if np.isfinite(plain) and plain > limit:
            # one rigid move fits: a joint-1 offset or sign turns the whole arm as a set-up error does
            found = _convention_finding(robot, test_conventions(robot, q, P_meas, kind, poses.marker_positions,
                                                                register=False), plain, limit, "rms")
            out.append(found or Finding(
                "base_frame", f"the measurements sit {_mm(plain)} rms from the nominal model in the robot's base "
                              f"frame but {_mm(rms)} after one rigid move: the base frame set-up (T_LI) is off; "
                              "import with --frame tracker to identify it"))
    if kind == "pose" and orientation is not None and not out:  # orientations mean something once positions fit
        out += _orientation(robot, poses, idx, orientation)
    return out


def off_origin_point(robot, q, P_measured, frame: str):
    """Where one-reflector data were measured when robot.yaml names no reflector and the data say
    it is not the tool frame's origin: (T (4, 4), p (3,) m) of :func:`register_measured_point` on
    joint vectors q (n, N) and measured points P_measured (n, 3) (``frame`` "tracker": with the
    tracker's pose), when p lies more than POINT_REGISTRATION_MIN_TOLERANCES tool tolerances
    (robot.yaml's ``tolerances: tool_m``) from the origin; else None."""
    if len(robot.reflectors) == 1:
        return None
    T, p = register_measured_point(forward(robot, q), P_measured, tracker=frame == "tracker")
    if np.linalg.norm(p) <= POINT_REGISTRATION_MIN_TOLERANCES * robot_tolerances(robot)["tool_m"]:
        return None
    return T, p


def _convention_and_mounting(robot, poses, best, rms, limit, fit_rows):
    """``joint_convention`` when the best candidate convention ``best`` (of :func:`test_conventions`)
    makes 6-D or raw-reflector data fit the nominal model in a tool mounting (or one-reflector data
    at a measured point) within ``limit``, CONVENTION_GAIN_MIN times better than ``rms``: both at
    once (a controller's convention and a marker plate), which neither explains alone."""
    from dataclasses import replace

    _, label, M, b = best
    if label is None:
        return None
    converted = replace(poses, q=poses.q @ M.T + b)
    if poses.kind == "point":
        idx = _sample(len(poses))
        P_meas = _measured_points(poses)[idx]
        P_nom = _points(robot, converted.q[idx], "point", None)
        rms_c = _registered_rms(P_nom, P_meas)[0]
        found = _off_point(robot, converted, converted.q[idx], P_meas, rms_c, limit, fit_rows)
        if found is None:
            return None
        fit = off_origin_point(robot, converted.q[fit_rows], converted.xyz[fit_rows], poses.frame)
        T_reg, p = fit
        P_fit = transform_points(T_reg @ forward(robot, converted.q[idx]), np.broadcast_to(p, (len(idx), 1, 3)))
        rms_x = float(np.sqrt(np.nanmean(np.sum((P_fit - P_meas) ** 2, axis=-1))))
        where = f"a reflector measured at {point_text(p)} in the tool frame"
    else:
        fit = mounting_fit(robot, converted, fit_rows)
        if fit is None:
            return None
        rms_x = fit[2]
        where = mounting_text(robot, fit[0], _reflector_count(poses))
    if not rms_x < limit or not rms_x * CONVENTION_GAIN_MIN < rms:
        return None
    return Finding("joint_convention",
                   f"{label}: registered rms {_mm(rms)} -> {_mm(rms_x)} with that convention and {where}; import "
                   f"with the controller's convention in robot.yaml: {controller_yaml(robot, M, b)} "
                   "(docs/robot_yaml.md), and calibrate fits the tool where the data place it")


def _off_point(robot, poses, q, P_meas, rms, limit, fit_rows):
    """``measured_point`` when one-reflector data miss the nominal model at the tool frame's origin
    by more than ``limit`` but fit it at the point :func:`off_origin_point` finds on ``fit_rows``."""
    if poses.kind != "point" or not np.isfinite(rms) or rms <= limit:
        return None
    found = off_origin_point(robot, poses.q[fit_rows], poses.xyz[fit_rows], poses.frame)
    if found is None:
        return None
    T_reg, p = found
    P_fit = transform_points(T_reg @ forward(robot, q), np.broadcast_to(p, (len(q), 1, 3)))
    rms_p = float(np.sqrt(np.nanmean(np.sum((P_fit - P_meas) ** 2, axis=-1))))
    if rms_p > limit:
        return None
    return Finding("measured_point",
                   f"the data miss the nominal model at the tool frame's origin by {_mm(rms)} rms but fit it "
                   f"within {_mm(rms_p)} measured at {point_text(p)} in the tool frame ({robot.tool_frame}): a "
                   "reflector off the tool frame, which calibrate finds and fits at; name it in robot.yaml's "
                   "reflectors when it is known (docs/priors.md, \"The measured point\")")


def tool_mounting(robot, q, T_measured, frame: str):
    """The frame 6-D data (or raw reflectors' fitted poses) were measured in, when it is not the
    URDF's tool frame: (T (4, 4) the tracker's pose (identity for ``frame`` "robot"), X (4, 4) the
    measured frame in the tool frame) minimising the position misfit of T·FK(q)·X's origin
    (:func:`register_measured_point`) and then the orientations' (X's rotation: the mean of
    (T FK)ᵀ R_measured, projected on the rotations), on joint vectors q (n, N) and measured poses
    T_measured (n, 4, 4) (rows with a missing value left out); None when X lies within
    POINT_REGISTRATION_MIN_TOLERANCES tool tolerances and CORRECTION_MAX_RAD of the identity (the
    tool transform's own parameters fit that)."""
    T_meas = np.asarray(T_measured, dtype=float)
    ok = np.isfinite(T_meas).all(axis=(1, 2))
    if ok.sum() < 3:
        return None
    T_fk = forward(robot, np.asarray(q)[ok])
    T, p = register_measured_point(T_fk, T_meas[ok, :3, 3], tracker=frame == "tracker")
    D = np.einsum("nji,jk,nkl->nil", T_fk[:, :3, :3], T[:3, :3].T, T_meas[ok, :3, :3]).mean(axis=0)
    U, _, Vt = np.linalg.svd(D)
    X = np.eye(4)
    X[:3, :3] = U @ np.diag([1, 1, np.sign(np.linalg.det(U @ Vt))]) @ Vt
    X[:3, 3] = p
    tol = robot_tolerances(robot)
    if (np.linalg.norm(p) <= POINT_REGISTRATION_MIN_TOLERANCES * tol["tool_m"]
            and np.linalg.norm(matrix_to_rotvec(X[:3, :3])) <= CORRECTION_MAX_RAD):
        return None
    return T, X


def two_reflectors_mounting(robot, q, markers, P_nominal, frame: str):
    """The frame two raw reflectors were placed in (their nominal positions P_nominal (2, 3), m)
    when it is not the URDF's tool frame: (T (4, 4) the tracker's pose, X (4, 4) that frame in the
    tool frame), from where the reflectors sit on the tool (:func:`register_measured_points` on
    joint vectors q (n, N) and readings markers (n, 2, 3), NaN where not seen) and the rotation
    taking their nominal line onto the found one by the smallest angle (the rotation about their
    line is not observed: none); None as :func:`tool_mounting`."""
    from campaign.measure.reflectors import register_measured_points
    from campaign.model.rotations import rotvec_to_matrix

    T, p = register_measured_points(forward(robot, np.asarray(q)), markers, tracker=frame == "tracker")
    a, b = np.asarray(P_nominal, dtype=float), p
    u, v = a[1] - a[0], b[1] - b[0]
    u, v = u / np.linalg.norm(u), v / np.linalg.norm(v)
    axis = np.cross(u, v)
    angle = float(np.arctan2(np.linalg.norm(axis), np.dot(u, v)))
    X = np.eye(4)
    if np.linalg.norm(axis) > 0:
        X[:3, :3] = rotvec_to_matrix(axis / np.linalg.norm(axis) * angle)
    X[:3, 3] = b.mean(axis=0) - X[:3, :3] @ a.mean(axis=0)
    tol = robot_tolerances(robot)
    if np.linalg.norm(X[:3, 3]) <= POINT_REGISTRATION_MIN_TOLERANCES * tol["tool_m"] and angle <= CORRECTION_MAX_RAD:
        return None
    return T, X


def point_text(p) -> str:
    """``(79.1, -30.1, 60.3) mm``: a point in the tool frame as import, calibrate and the docs say it."""
    return "(" + ", ".join(f"{1e3 * v:.1f}" for v in np.asarray(p, dtype=float)) + ") mm"


def mounting_text(robot, X, reflectors: int | None = None) -> str:
    """``the tool frame is 29° and 115 mm from the URDF's (tool0)``; ``reflectors``: 2 for raw data
    of two reflectors, whose rotation about their line is not observed (said)."""
    deg = np.rad2deg(np.linalg.norm(matrix_to_rotvec(np.asarray(X)[:3, :3])))
    line = (" (two reflectors: of the frames turned about their line, which the data do not tell apart, the "
            "nearest to the URDF's)" if reflectors == 2 else "")
    return f"the tool frame is {deg:.0f}° and {_mm(np.linalg.norm(np.asarray(X)[:3, 3]))} from the URDF's " \
           f"({robot.tool_frame}){line}"


def mounting_fit(robot, poses, rows=None):
    """The tool mounting of 6-D or raw-reflector data (MeasuredPoses) on the ``rows`` (indices;
    default all, at most PLAUSIBILITY_MAX_POSES of them spread evenly): (X (4, 4), registered rms
    (m) of the nominal model in the URDF's tool frame, the same in the mounted frame X), or None
    (other kinds, or no mounting beyond the tool's tolerances: :func:`tool_mounting`)."""
    if poses.kind not in ("pose", "markers"):
        return None
    rows = np.arange(len(poses)) if rows is None else np.asarray(rows)
    idx = rows[_sample(len(rows))]
    q = poses.q[idx]
    if poses.kind == "markers" and poses.markers is not None and poses.markers.shape[1] == 2:
        found = two_reflectors_mounting(robot, q, poses.markers[idx], poses.marker_positions, poses.frame)
    else:
        found = tool_mounting(robot, q, poses.T_IE[idx], poses.frame)
    if found is None:
        return None
    P_meas = _measured_points(poses)[idx]
    rms = [_registered_rms(_points(r, q, poses.kind, poses.marker_positions), P_meas)[0]
           for r in (robot, robot.with_tool_transform(found[1]))]
    return found[1], rms[0], rms[1]


def _off_mounting(robot, poses, idx, rms, limit, fit_rows):
    """``tool_mounting`` when 6-D or raw-reflector data miss the nominal model by more than
    ``limit`` but fit it (under ``limit``, rigidly registered) in the frame :func:`tool_mounting`
    finds on ``fit_rows``."""
    if not np.isfinite(rms) or rms <= limit:
        return None
    fit = mounting_fit(robot, poses, fit_rows)
    if fit is None or not fit[2] <= limit:
        return None
    X, _, rms_x = fit
    return Finding("tool_mounting",
                   f"{mounting_text(robot, X, _reflector_count(poses))}: a tool mounting (a marker plate, a "
                   f"flange), which calibrate fits; the nominal model misses the data by {_mm(rms)} rms in the "
                   "URDF's tool frame, by "
                   f"{_mm(rms_x)} in the mounted one (the rest: the robot's own errors)")


def _reflector_count(poses) -> int | None:
    """The raw reflectors of MeasuredPoses, None for other kinds."""
    return poses.markers.shape[1] if poses.kind == "markers" and poses.markers is not None else None


def _distances(markers, P_nominal):
    """(median ratio measured / nominal, median |difference| m, median measured m, median nominal m)
    of the distances between reflectors (markers (n, k, 3) m, P_nominal (k, 3) m), or None when no
    pair is measured."""
    k = markers.shape[1]
    i, j = np.triu_indices(k, 1)
    d_meas = np.linalg.norm(markers[:, i] - markers[:, j], axis=-1)
    d_nom = np.linalg.norm(P_nominal[i] - P_nominal[j], axis=-1)
    ok = np.isfinite(d_meas) & (d_nom > 0)
    if not ok.any():
        return None
    return (float(np.median((d_meas / d_nom)[ok])), float(np.median(np.abs(d_meas - d_nom)[ok])),
            float(np.median(d_meas[ok])), float(np.median(np.broadcast_to(d_nom, d_meas.shape)[ok])))


def _reflector_layout(markers, P_nominal):
    """``reflector_layout`` when the measured reflectors' distances do not match the nominal ones."""
    found = _distances(markers, P_nominal)
    if found is None:
        return None
    ratio, diff, meas, nom = found
    if not 1 / WORKSPACE_SCALE_MAX <= ratio <= WORKSPACE_SCALE_MAX:
        cause = ("the markers file looks like mm (it must be in m)" if abs(np.log(ratio / 1e-3)) < np.log(1.3) else
                 "the data look like mm imported as metres" if abs(np.log(ratio / 1e3)) < np.log(1.3) else
                 "another tool, or the wrong file")
        return Finding("reflector_layout",
                       f"the measured reflectors are {ratio:.3g}× as far apart as their nominal positions say "
                       f"(median distance {_mm(meas)} vs {_mm(nom)}): {cause}; check --markers / robot.yaml's "
                       "reflectors (tool frame, m) and --length-unit")
    if diff > REFLECTOR_DISTANCE_TOL_M:
        return Finding("reflector_layout",
                       f"the distances between the measured reflectors differ from the nominal ones by {_mm(diff)} "
                       "(median): check the reflectors' order (m1..mk) and positions in --markers / robot.yaml")
    return None


#: lengths a tracker's software may give instead of metres: (name, how many of them make a metre)
LENGTH_UNITS = (("millimetres", 1e3), ("centimetres", 1e2), ("inches", 1 / 0.0254), ("feet", 1 / 0.3048),
                ("micrometres", 1e6))


def length_unit_named(ratio: float) -> str | None:
    """The unit whose metre is ``ratio`` of them, within 10 % (1000 -> "millimetres"), or None."""
    for name, per_metre in LENGTH_UNITS:
        if abs(np.log(ratio / per_metre)) < np.log(1.1):
            return name
    return None


def check_tracker_readings(P_L, P_E, names, geometry: str = "robot.yaml's reflectors") -> str | None:
    """Readings of one pose that no tracker measuring in metres can give, said in one sentence
    (None when plausible): the reflectors (P_L (k, 3), m in the tracker's frame) farther apart or
    closer together than the tool's reflectors (P_E (k, 3), m in the tool frame; names (k,)) by
    more than READING_SPREAD_RATIO_MAX, or a reading beyond any tracker's range
    (TRACKER_RANGE_MAX_M; P_E None: points of unknown spacing, the range alone). Each names the
    length unit the readings look like; ``geometry`` says where P_E comes from."""
    P_L = np.asarray(P_L, dtype=float)
    P_E = np.zeros((0, 3)) if P_E is None else np.asarray(P_E, dtype=float)
    fix = "the tracker adapter's measure() must return metres in the tracker's frame (docs/cell.md)"
    if len(P_E) >= 2:
        i, j = np.triu_indices(len(P_E), 1)
        d_meas = np.linalg.norm(P_L[i] - P_L[j], axis=-1)
        d_nom = np.linalg.norm(P_E[i] - P_E[j], axis=-1)
        k = int(np.argmax(d_nom))  # the widest pair: its ratio the least disturbed by noise
        ratio = float(d_meas[k] / d_nom[k]) if d_nom[k] > 0 else 1.0
        if not 1 / READING_SPREAD_RATIO_MAX <= ratio <= READING_SPREAD_RATIO_MAX:
            unit = length_unit_named(ratio)
            cause = (f"the readings look like {unit}" if unit else
                     f"the readings are in another unit than metres, or the tool's reflectors are not {geometry}")
            return (f"reflectors {names[i[k]]} and {names[j[k]]} read {d_meas[k]:,.4g} m apart, {ratio:,.4g}× the "
                    f"{d_nom[k]:.4g} m of the robot's reflector geometry ({geometry}): {cause}; {fix}")
    far = np.linalg.norm(P_L, axis=-1)
    k = int(np.argmax(far))
    if far[k] > TRACKER_RANGE_MAX_M:
        unit = (f"the readings look like millimetres ({far[k] / 1e3:.3g} m)" if far[k] / 1e3 <= TRACKER_RANGE_MAX_M
                else "the readings are in another unit than metres")
        return (f"target {names[k]} reads {far[k]:,.0f} m from the tracker, beyond any laser tracker's range "
                f"({TRACKER_RANGE_MAX_M:.0f} m): {unit}; {fix}")
    return None


def _orientation(robot, poses, idx, orientation) -> list:
    values, columns, reading, readings, scales = orientation
    ranked = rotation_readings(robot, poses.q, values, columns, readings, scales)
    here = next((t for t in ranked if t[1] == reading and t[2] == 1.0), None)
    if here is None or not np.isfinite(here[0]) or here[0] <= ORIENTATION_SPREAD_MAX_RAD:
        return []
    best = ranked[0]
    cols = ",".join(columns)
    if best[1] != reading or best[2] != 1.0:
        if best[0] <= ORIENTATION_SPREAD_MAX_RAD and best[0] * CONVENTION_GAIN_MIN < here[0]:
            if best[2] > 1.0:  # rad, read as degrees with the joints: one --angle-unit reads both
                return [Finding("rotation_reading",
                                f"columns {cols} read in degrees (--angle-unit deg, as the joints) disagree with the "
                                f"nominal orientations by {here[0] * 1e3:.0f} mrad on average; read in rad"
                                f"{'' if best[1] == reading else ' as ' + best[1]} they agree to "
                                f"{best[0] * 1e3:.1f} mrad: --angle-unit reads joints and orientations alike, write "
                                "them in one unit (docs/csv_import.md)")]
            unit = "" if best[2] == 1.0 else " (and in degrees: the columns, not the joints)"
            return [Finding("rotation_reading",
                            f"columns {cols} read as {reading} disagree with the nominal orientations by "
                            f"{here[0] * 1e3:.0f} mrad on average; read as {best[1]}{unit} they agree to "
                            f"{best[0] * 1e3:.1f} mrad: import with --rotation {best[1]} (docs/csv_import.md)")]
    return [Finding("orientation_residual",
                    f"the measured orientations disagree with the nominal ones by {here[0] * 1e3:.0f} mrad on average "
                    f"beyond one constant rotation, and no reading of {cols} (--rotation rotvec|rpy|abc|quat) fits: "
                    "check the orientation columns and the tool frame")]


def _correction_cause(robot, k: int, unit: str) -> str:
    """What a large correction of parameter k says, by the transform it belongs to: the tool's (a
    tool frame the URDF does not describe), the base's (the set-up), a joint's zero offset (the
    joint convention), else any of them."""
    N = robot.n_joints
    block = k // 6
    if block == N + 1:
        return (f"the measured tool frame is not the URDF's {robot.tool_frame} (a tool mounting calibrate could "
                "not place, or another --tool-frame)")
    if block == 0:
        return "check the base frame set-up (or --frame tracker for data in the tracker's frame)"
    if k in robot.joint_offset_index:
        return "check the joint convention (an offset or a sign: robot.yaml's controller)"
    return ("check the length unit, the joint convention and the tool frame" if unit == "m" else
            "check the joint convention (signs, offsets) and the tool frame")


def check_fit(robot, params, *, noise_sigma_m: float, heldout_mean_m: float | None = None,
              floor_sigma_m: float | None = None, floor_source: str = "stated") -> list:
    """Warnings on an identified model. params: p_e (6N + 12,) of the minimum-norm solution (m, rad);
    noise_sigma_m: the fit's own position noise estimate (σ per coordinate, m); heldout_mean_m:
    the current model's held-out mean position error, m; floor_sigma_m: the measurement noise
    from repeats or stated (σ per coordinate, m), when known; floor_source: ``"repeats"`` or
    ``"stated"`` (repeats far apart in time measure drift too)."""
    out = []
    size = robot_size_m(robot)
    p = np.asarray(params, dtype=float)
    units = np.asarray(robot.param_units)
    names = robot.param_names
    lin = units == "m"
    if lin.any():
        k = int(np.flatnonzero(lin)[np.argmax(np.abs(p[lin]))])
        if abs(p[k]) > CORRECTION_MAX_FRACTION_OF_SIZE * size:
            out.append(Finding("large_corrections",
                               f"the identified correction {names[k]} = {p[k] * 1e3:,.1f} mm is "
                               f"{abs(p[k]) / size:.0%} of the robot's stretched length ({_mm(size)}): the fit "
                               f"reshapes the robot instead of correcting it; {_correction_cause(robot, k, 'm')}"))
    rot = units == "rad"
    if rot.any() and not out:
        k = int(np.flatnonzero(rot)[np.argmax(np.abs(p[rot]))])
        if abs(p[k]) > CORRECTION_MAX_RAD:
            out.append(Finding("large_corrections",
                               f"the identified correction {names[k]} = {np.rad2deg(p[k]):.1f} deg is larger than a "
                               f"real robot's angular errors (≤ {np.rad2deg(CORRECTION_MAX_RAD):.1f} deg): "
                               f"{_correction_cause(robot, k, 'rad')}"))
    if floor_sigma_m is not None and floor_sigma_m > 0:
        if noise_sigma_m * FITTED_NOISE_BELOW_FLOOR_FACTOR < floor_sigma_m:
            where = ("from repeats: if they were measured far apart in time, they measure drift too"
                     if floor_source == "repeats" else "stated in campaign.yaml")
            out.append(Finding("noise_below_floor",
                               f"the fit leaves a noise σ of {noise_sigma_m * 1e6:.3g} µm, "
                               f"{floor_sigma_m / max(noise_sigma_m, 1e-300):,.0f}× below the measurement noise "
                               f"({floor_sigma_m * 1e6:.3g} µm, {where}): the model fits more than the measurements "
                               "carry; check the length unit (metres imported as mm)"))
    elif floor_sigma_m is None and 0 < noise_sigma_m < TRACKER_NOISE_MIN_M:
        out.append(Finding("noise_below_floor",
                           f"the fit leaves a noise σ of {noise_sigma_m * 1e6:.3g} µm, below any laser tracker's "
                           f"(≥ {TRACKER_NOISE_MIN_M * 1e6:.3g} µm): the data are scaled down or are not measurements; "
                           "check the length unit (metres imported as mm)"))
    if heldout_mean_m is not None:
        limit = max(MODEL_RESIDUAL_MAX_M, MODEL_RESIDUAL_MAX_FRACTION_OF_SIZE * size)
        if heldout_mean_m > limit:
            out.append(Finding("model_residual",
                               f"the calibrated model still misses the held-out poses by {_mm(heldout_mean_m)} on "
                               f"average, more than a calibrated robot can (≤ {_mm(limit)}): the model cannot "
                               "describe these data; check the joint convention, the units and the tool frame"))
    return out
