"""RUN/program/stops.csv: the stops of a planned run in the order `campaign run` visits them."""

import numpy as np
import pytest
import yaml

from campaign.cli import main
from campaign.errors import DataError
from campaign.program.stops import KINDS, Stop, plan_stops, read_stops_csv, stops_path, write_stops_csv

#: a controller and tracker that are the simulated cell's, logging every move and measure request
LOGGING_CELL = '''
from campaign.sim.adapters import Controller as SimController, Tracker as SimTracker

def _log(options, line):
    with open(options["log"], "a") as fh:
        fh.write(line + "\\n")

class Controller(SimController):
    def __init__(self, robot, options):
        self.log_options = dict(options)
        super().__init__(robot, {})

    def move(self, q):
        _log(self.log_options, "move " + " ".join(repr(float(v)) for v in q))
        super().move(q)

class Tracker(SimTracker):
    def __init__(self, robot, options):
        self.log_options = dict(options)
        super().__init__(robot, {})

    def measure(self, aims):
        _log(self.log_options, "measure")
        return super().measure(aims)
'''


def _planned_run(tmp_path, robot, *, n=10, drift_every=3):
    """A planned run: n random poses 1000.., pose 1004 repeated as 1000001004, 1002 a validation
    pose, two vias before 1003 and one before 1007; drift checks every ``drift_every`` poses."""
    from campaign.paths import DEFAULT_SCENE
    from campaign.sim.truth import random_joint_poses

    run = tmp_path / "run"
    (run / "plan").mkdir(parents=True)
    Q = random_joint_poses(robot, n + 3, seed=4)
    ids = [1000 + i for i in range(n)]
    ids.insert(6, 1_000_001_004)
    Q_poses = np.vstack([Q[:6], Q[4:5], Q[6:n]])
    (run / "plan" / "poses.csv").write_text("pose_id,q1,q2,q3,q4,q5,q6\n" + "".join(
        f"{p}," + ",".join(repr(float(v)) for v in q) + "\n" for p, q in zip(ids, Q_poses)))
    vias = [(1003, Q[n]), (1003, Q[n + 1]), (1007, Q[n + 2])]
    (run / "plan" / "vias.csv").write_text("before_pose_id,q1,q2,q3,q4,q5,q6\n" + "".join(
        f"{p}," + ",".join(repr(float(v)) for v in q) + "\n" for p, q in vias))
    (run / "plan" / "validation.csv").write_text("pose_id\n1002\n")
    (run / "plan" / "repeats.csv").write_text("pose_id,repeat_of\n1000001004,1004\n")
    cfg = {"robot": "comau_racer5_080", "scene": str(DEFAULT_SCENE),
           "plan": {"settle_time_s": 1.5, "tracker_time_per_reflector_s": 2.0},
           "run": {"timeout_s": 5.0, "drift_check_every": drift_every}, "sim": {"seed": 3, "noise_m": 0.0}}
    (run / "campaign.yaml").write_text(yaml.safe_dump(cfg))
    return run, ids, Q_poses, vias


def test_stops_are_the_moves_campaign_run_makes_in_its_order(tmp_path, robot):
    run, ids, Q, vias = _planned_run(tmp_path, robot)
    stops = plan_stops(run)
    log = tmp_path / "cell.log"
    (tmp_path / "logcell.py").write_text(LOGGING_CELL)
    (tmp_path / "options.yaml").write_text(yaml.safe_dump({"controller": {"log": str(log)},
                                                           "tracker": {"log": str(log)}}))
    assert main(["run", str(run), "--cell", str(tmp_path / "logcell.py"), "--options",
                 str(tmp_path / "options.yaml"), "--quiet"]) == 0
    lines = log.read_text().splitlines()
    first_move = next(i for i, ln in enumerate(lines) if ln.startswith("move"))
    moves, measured = [], []
    for ln in lines[first_move:]:
        if ln.startswith("move"):
            moves.append([float(v) for v in ln.split()[1:]])
            measured.append(False)
        else:
            measured[-1] = True
    assert len(moves) == len(stops)
    np.testing.assert_array_equal(np.array(moves), np.array([s.q for s in stops]))
    assert measured == [s.measured for s in stops]
    # the kinds and ids: 11 poses, 3 vias, a drift check to pose 1000 after every 3rd pose but the last
    assert [s.kind for s in stops].count("via") == 3
    assert [s.pose_id for s in stops if s.kind == "drift"] == [1000, 1000, 1000]
    assert {s.pose_id: s.kind for s in stops if s.kind != "via"}[1002] == "validation"
    assert {s.pose_id: s.kind for s in stops}[1_000_001_004] == "repeat"
    assert [s.pose_id for s in stops if s.kind == "via"] == [1003, 1003, 1007]
    assert [s.stop for s in stops] == list(range(len(stops)))


def test_dwell_is_settle_plus_each_reflector_and_zero_at_a_via(tmp_path, robot):
    run, *_ = _planned_run(tmp_path, robot)
    stops = plan_stops(run)
    assert {s.dwell_s for s in stops if s.measured} == {1.5 + 3 * 2.0}  # 3 reflectors of the default tool
    assert {s.dwell_s for s in stops if s.kind == "via"} == {0.0}


def test_stops_csv_round_trips_exactly(tmp_path):
    rng = np.random.default_rng(1)
    stops = [Stop(k, 1000 + k, KINDS[k % 5], float(rng.uniform(0, 20)), tuple(rng.normal(size=6))) for k in range(12)]
    path = write_stops_csv(tmp_path / "stops.csv", stops)
    assert path.read_text().splitlines()[0] == "stop,pose_id,kind,dwell_s,q1,q2,q3,q4,q5,q6"
    assert read_stops_csv(path) == stops


@pytest.mark.parametrize("text, match", [
    ("stop,pose_id,kind,dwell,q1\n", "header must be stop,pose_id,kind,dwell_s,q1..qN"),
    ("stop,pose_id,kind,dwell_s,q1\n0,5,home,1,0.1\n", "line 2: kind 'home' is not one of"),
    ("stop,pose_id,kind,dwell_s,q1\n1,5,pose,1,0.1\n", "line 2: stop 1, expected 0"),
    ("stop,pose_id,kind,dwell_s,q1\n0,5,pose,-1,0.1\n", "line 2: dwell_s must be"),
    ("stop,pose_id,kind,dwell_s,q1\n0,5,pose,1\n", "line 2 has 4 fields, expected 5"),
    ("stop,pose_id,kind,dwell_s,q1\n", "no stops"),
])
def test_a_bad_stops_file_is_named_with_its_line(tmp_path, text, match):
    (tmp_path / "s.csv").write_text(text)
    with pytest.raises(DataError, match=match):
        read_stops_csv(tmp_path / "s.csv")


def test_program_csv_writes_stops_csv_and_the_controller_table(tmp_path, robot, capsys):
    run, *_ = _planned_run(tmp_path, robot)
    assert main(["program", str(run), "--format", "csv"]) == 0
    stops = read_stops_csv(stops_path(run))
    assert stops == plan_stops(run)
    from campaign.program import csvprog

    prog = (run / "program" / "cal_run.csv").read_text()
    np.testing.assert_array_equal(csvprog.read_joints(prog), robot.to_controller_q(np.array([s.q for s in stops])))


@pytest.mark.parametrize("args, match", [
    (["program", "{tmp}/nowhere", "--format", "csv"], "nowhere: no such run folder"),
    (["program", "{tmp}", "--format", "csv"], "no plan/poses.csv"),
    (["program", "{run}", "--format", "gcode"], "--format 'gcode': unknown format"),
    (["program", "{run}", "--format", "csv", "--speed", "0"], "--speed must be a fraction in"),
    (["program", "{run}", "--format", "csv", "--trigger-output", "0"], "--trigger-output must be"),
])
def test_bad_program_input_is_one_line(tmp_path, robot, capsys, args, match):
    run, *_ = _planned_run(tmp_path, robot)
    assert main([a.format(tmp=tmp_path, run=run) for a in args]) == 1
    err = capsys.readouterr().err.strip()
    assert match in err and len(err.splitlines()) == 1
    assert not (run / "program").exists()
