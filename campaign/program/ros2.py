"""ROS 2: the campaign as a ``trajectory_msgs/JointTrajectory`` (YAML, or JSON for ``--out X.json``),
the ``trajectory`` of a ``control_msgs/action/FollowJointTrajectory`` goal for a
joint_trajectory_controller.

Joints in radians (m for a prismatic joint), named as the URDF names them, in the controller's
convention. Each move is the plan's Ruckig trajectory (time-optimal, jerk-limited, within
robot.yaml's limits, slowed by ``--speed`` through time scaling) sampled every SAMPLE_S with
positions, velocities and accelerations, so that the controller's spline between samples stays
on it; at each stop the trajectory holds still for the dwell (a point at arrival and one at the
end of the dwell, both at rest). A YAML comment before each stop's arrival point names it. A
JointTrajectory carries no outputs: ``--trigger-output`` is refused (a tracker on a trigger is
then driven by the stop times of RUN/program/stops.csv). No size limit: one file.
"""

from __future__ import annotations

import json
import re

import numpy as np

from campaign.errors import ConfigError

EXTENSION = ".yaml"
UNITS = "rad"
DECIMALS = 9
#: samples of a move (s): the controller's spline between them follows Ruckig's profile closely
SAMPLE_S = 0.1


def _time(t: float) -> dict:
    ns = int(round(t * 1e9))
    return {"sec": ns // 1_000_000_000, "nanosec": ns % 1_000_000_000}


def _points(inp):
    """[(stop or None, t_s, positions, velocities, accelerations)] of the whole program."""
    t = 0.0
    N = inp.q_controller.shape[1]
    zero = np.zeros(N)
    for k, s in enumerate(inp.stops):
        if k and inp.move_s[k] > 0 and inp.sampler is not None:
            times, P, V, A = inp.sampler(k, SAMPLE_S)
            for tt, p, v, a in zip(times, P, V, A):
                yield None, t + tt, p, v, a
        t += inp.move_s[k]
        yield s, t, inp.q_controller[k], zero, zero
        if s.dwell_s > 0:
            t += s.dwell_s
            yield "dwell", t, inp.q_controller[k], zero, zero


def _num(v) -> str:
    s = f"{float(v):.{DECIMALS}f}".rstrip("0").rstrip(".")
    return "0.0" if s in ("-0", "0", "") else (s if "." in s else s + ".0")


def render(inp) -> list:
    if inp.trigger_output is not None:
        raise ConfigError("--trigger-output: a ROS 2 JointTrajectory carries no digital outputs")
    name = inp.name.lower()
    if inp.out_suffix.lower() == ".json":
        pts = [{"positions": [float(x) for x in p], "velocities": [float(x) for x in v],
                "accelerations": [float(x) for x in a], "time_from_start": _time(t)} for _, t, p, v, a in _points(inp)]
        doc = {"joint_names": list(inp.joint_names), "points": pts}
        return [(name + ".json", json.dumps(doc, indent=1) + "\n")]
    out = [f"# {inp.robot_name}: {len(inp.stops)} stops, joints in rad (controller convention); the trajectory of a",
           "# control_msgs/action/FollowJointTrajectory goal; written by `campaign program --format ros2-trajectory`",
           "joint_names: [" + ", ".join(inp.joint_names) + "]", "points:"]
    for s, t, p, v, a in _points(inp):
        if s is not None and s != "dwell":
            out.append(f"  # stop {s.stop} {s.kind} {s.pose_id}")
        tf = _time(t)
        out += ["  - positions: [" + ", ".join(_num(x) for x in p) + "]",
                "    velocities: [" + ", ".join(_num(x) for x in v) + "]",
                "    accelerations: [" + ", ".join(_num(x) for x in a) + "]",
                f"    time_from_start: {{sec: {tf['sec']}, nanosec: {tf['nanosec']}}}"]
    return [(name + EXTENSION, "\n".join(out) + "\n")]


def read_joints(files, n_joints: int | None = None) -> np.ndarray:
    """The stops' positions (n, N), rad/m (controller convention): in YAML the point after each
    ``# stop`` comment; in JSON the points at rest that end a motion or a dwell (a stop is one
    point at rest, or two at one posture for a dwell)."""
    name, text = files[0]
    if name.lower().endswith(".json"):
        doc = json.loads(text)
        rows, prev_rest = [], None
        for p in doc["points"]:
            rest = not any(p["velocities"])
            if rest and not (prev_rest is not None and prev_rest == p["positions"]):
                rows.append(p["positions"])
            prev_rest = p["positions"] if rest else None
        return np.array(rows, dtype=float)
    rows, want = [], False
    for line in text.splitlines():
        if re.match(r"^\s*# stop \d+", line):
            want = True
        elif want:
            m = re.match(r"^\s*- positions: \[([^\]]*)\]", line)
            if m:
                rows.append([float(x) for x in m.group(1).split(",")])
                want = False
    return np.array(rows, dtype=float)


def check(files, robot) -> list:
    """Structure: a mapping with joint_names (the robot's) and points whose times rise, whose
    vectors have one value a joint, whose velocities and accelerations stay within the limits."""
    import yaml

    from campaign.program import common as C

    name, text = files[0]
    try:
        doc = json.loads(text) if name.lower().endswith(".json") else yaml.safe_load(text)
    except (ValueError, yaml.YAMLError) as exc:
        return [f"{name}: not valid YAML/JSON ({exc.__class__.__name__})"]
    if not isinstance(doc, dict) or set(doc) != {"joint_names", "points"}:
        return [f"{name}: must be a mapping of joint_names and points"]
    out = []
    if list(doc["joint_names"]) != list(robot.joint_names):
        out.append(f"{name}: joint_names {doc['joint_names']} are not {list(robot.joint_names)}")
    N = robot.n_joints
    vmax, amax = np.asarray(robot.max_velocity), np.asarray(robot.max_acceleration)
    A = robot.controller_matrix if robot.controller_matrix is not None else np.eye(N)
    last = -1.0
    for i, p in enumerate(doc["points"]):
        if set(p) != {"positions", "velocities", "accelerations", "time_from_start"}:
            out.append(f"{name}: point {i}: fields must be positions, velocities, accelerations, time_from_start")
            break
        if any(len(p[f]) != N for f in ("positions", "velocities", "accelerations")):
            out.append(f"{name}: point {i}: vectors must have {N} values")
            break
        tf = p["time_from_start"]
        t = tf["sec"] + tf["nanosec"] * 1e-9
        if not 0 <= tf["nanosec"] < 1_000_000_000 or t <= last:
            out.append(f"{name}: point {i}: time_from_start must rise (nanosec < 1e9)")
            break
        last = t
        v_model, a_model = A @ np.asarray(p["velocities"]), A @ np.asarray(p["accelerations"])
        if np.any(np.abs(v_model) > vmax * (1 + 1e-6)) or np.any(np.abs(a_model) > amax * (1 + 1e-6)):
            out.append(f"{name}: point {i}: velocity or acceleration beyond the robot's limits")
            break
    if not out:
        out += C.limit_problems(np.array([p["positions"] for p in doc["points"]]), robot, UNITS, name, DECIMALS)
    return out
