"""Issue 31, part 5: `campaign auto`'s limits cut the first campaign too and the stop names the
limit; a run resumed on another cell is refused unless allowed; `auto --retry-failed`."""

import json

import pytest

from campaign.cli import main
from campaign.measure.driver import read_plan
from campaign.measure.store import PoseRecord, open_run

SMALL = ["--grid-scale", "0.6", "--no-report", "--quiet"]


def _state(run):
    return json.loads((run / "auto" / "state.json").read_text())


def test_max_poses_cuts_the_first_campaign_keeps_its_repeats_and_the_stop_names_the_limit(tmp_path, capsys):
    run = tmp_path / "r"
    # --target-mm 0.002: a model the limit leaves short of it (predicted on the run's own noise, 59
    # poses give about 3 µm), so that the limit, not the model, stops the loop
    assert main(["auto", str(run), "--sim", "--max-poses", "60", "--target-mm", "0.002", *SMALL]) == 0
    out = capsys.readouterr().out
    state = _state(run)
    with open_run(run) as store:
        poses = store.load_measured()
    assert state["plan"]["poses"] <= 60 and len(poses.pose_id) <= 60
    assert all(r["planned"] <= 60 for r in state["rounds"])
    # the floor's repeats are in the cut plan, measured back to back: the floor is the repeats'
    summary = json.loads((run / "plan" / "summary.json").read_text())
    assert summary["tour"]["repeats_back_to_back"]["poses"] == 3
    assert state["rounds"][-1]["floor_mm"] is not None
    assert state["finished"]["reason"] == "max_poses" and "pose limit" in out.splitlines()[-2], out
    assert "cut to --max-poses 60" in out


def test_the_budget_cuts_the_first_campaign_and_the_clock_stays_within_it(tmp_path, capsys):
    run = tmp_path / "r"
    assert main(["auto", str(run), "--sim", "--budget", "0.25", *SMALL]) == 0
    out = capsys.readouterr().out
    state = _state(run)
    assert "is more than --budget 0.25 h" in out
    assert state["rounds"][-1]["hours"] <= 0.25 * 1.05, state["rounds"][-1]
    assert state["finished"]["reason"] == "budget" and "stopped at the budget" in out


def test_a_run_measured_on_the_simulated_cell_is_not_resumed_on_the_twin_unless_allowed(tmp_path, capsys):
    run = tmp_path / "r"
    assert main(["plan", "--run", str(run), "--grid-scale", "0.6", "--select", "30", "--quiet"]) == 0
    assert main(["run", str(run), "--sim", "--max-poses", "10", "--quiet"]) == 0
    capsys.readouterr()
    assert main(["auto", str(run), "--cell", "mujoco", *SMALL]) == 1
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "measured so far on another cell (--sim" in err[0] and "--allow-other-cell" in err[0]
    assert not (run / "auto").exists() and not (run / "cell").exists()  # nothing started, nothing written


def test_auto_retry_failed_measures_the_failed_poses_again_and_goes_on(tmp_path, capsys):
    run = tmp_path / "r"
    assert main(["plan", "--run", str(run), "--grid-scale", "0.6", "--select", "40", "--quiet"]) == 0
    assert main(["run", str(run), "--sim", "--max-poses", "20", "--quiet"]) == 0
    # two planned poses the test stores as failed in the log itself (as a cell whose beam was lost would)
    ids, Q, _ = read_plan(run)
    with open_run(run) as store:
        todo = [k for k, p in enumerate(ids) if int(p) not in store.stored_ids()][:2]
        for k in todo:
            store.add_pose(PoseRecord(int(ids[k]), "failed", tuple(map(float, Q[k])), reason="test: beam lost"))
    ids = [int(ids[k]) for k in todo]
    assert main(["auto", str(run), "--sim", "--max-poses", "100", *SMALL]) == 0
    with open_run(run) as store:
        assert store.counts().get("failed") == 2  # auto alone leaves them
    capsys.readouterr()
    assert main(["auto", str(run), "--retry-failed", *SMALL]) == 0
    out = capsys.readouterr().out
    assert "--retry-failed: 2 failed poses to measure again" in out
    with open_run(run) as store:
        assert store.counts().get("failed", 0) == 0 and set(ids) <= store.stored_ids()
        assert len(store.events("retry_failed")) == 1
    # asked again with nothing failed: said in a line, the finished loop not reopened, nothing measured
    assert main(["auto", str(run), "--retry-failed", *SMALL]) == 0
    out = capsys.readouterr().out
    assert "--retry-failed: no pose is stored as failed; nothing to measure again" in out and "continuing" not in out
    with open_run(run) as store:
        assert len(store.events("retry_failed")) == 1


def test_a_pose_limit_too_small_for_a_first_campaign_is_one_line_naming_it(tmp_path, capsys):
    run = tmp_path / "r"
    assert main(["auto", str(run), "--sim", "--max-poses", "12", *SMALL]) == 1
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "--max-poses 12 is too small for a first campaign" in err[0], err
    assert not (run / "measurements.sqlite").exists()


@pytest.mark.parametrize("flag", ["--retry-failed", "--allow-other-cell"])
def test_auto_help_names_the_flag(flag, capsys):
    try:
        main(["auto", "--help"])
    except SystemExit:
        pass
    assert flag in capsys.readouterr().out


def test_the_runs_own_plan_is_measured_only_as_far_as_the_pose_limit(tmp_path, capsys):
    run = tmp_path / "r"
    assert main(["plan", "--run", str(run), "--grid-scale", "0.6", "--select", "40", "--quiet"]) == 0
    planned = len(read_plan(run)[0])
    capsys.readouterr()
    assert main(["auto", str(run), "--sim", "--max-poses", "45", *SMALL]) == 0
    out = capsys.readouterr().out
    with open_run(run) as store:
        stored = len(store.stored_ids())
    assert planned > 45 and stored == 45, (planned, stored)
    assert "measured as far as the limits allow" in out and f"{planned - 45} planned poses left unmeasured" in out
    assert _state(run)["finished"]["reason"] == "max_poses"
