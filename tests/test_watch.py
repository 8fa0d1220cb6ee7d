"""`campaign watch` and `--watch`: the live page of a run (docs/watch.md), over real sockets, and in
a real headless Chromium while a simulated campaign runs (skipped where no Chromium is installed)."""

import http.client
import json
import math
import os
import re
import signal
import sqlite3
import subprocess
import sys
import threading
import time
from pathlib import Path

import numpy as np
import pytest

from campaign.cli import main

ROOT = Path(__file__).resolve().parents[1]
ENV = {**os.environ, "PYTHONPATH": str(ROOT)}
TOKEN = "a-shared-secret-of-the-cell-0123456789"
sys.path.insert(0, str(ROOT / "benchmarks"))
from screenshot_reports import find_browser  # noqa: E402

sys.path.pop(0)


def _reject_constant(name):
    raise ValueError(f"not strict JSON: {name}")


def get(port, path, headers=None):
    """(status, headers, body) of one GET on 127.0.0.1:port."""
    conn = http.client.HTTPConnection("127.0.0.1", port, timeout=10)
    try:
        conn.request("GET", path, headers=headers or {})
        r = conn.getresponse()
        return r.status, dict(r.getheaders()), r.read()
    finally:
        conn.close()


def get_json(port, path, headers=None):
    status, _, body = get(port, path, headers)
    assert status == 200, body
    return json.loads(body, parse_constant=_reject_constant)


def log_counts(run):
    """(measured, failed) in the run's log, read here with SQLite itself."""
    try:
        with sqlite3.connect(f"file:{run / 'measurements.sqlite'}?mode=ro", uri=True) as db:
            got = dict(db.execute("SELECT status, COUNT(*) FROM poses GROUP BY status").fetchall())
    except sqlite3.OperationalError:
        return 0, 0
    return got.get("measured", 0), got.get("failed", 0)


def url_from(stream, pattern=r"http://127\.0\.0\.1:(\d+)/", timeout_s=60.0):
    """The port in the first line of ``stream`` matching ``pattern`` (read in a thread: no hang)."""
    found = {}

    def read():
        for line in stream:
            m = re.search(pattern, line)
            if m:
                found["port"] = int(m.group(1))
                return

    t = threading.Thread(target=read, daemon=True)
    t.start()
    t.join(timeout_s)
    assert "port" in found, "the watcher never said where it serves"
    return found["port"]


# -- beyond loopback ---------------------------------------------------------------------------------
def test_beyond_loopback_without_a_token_file_the_command_refuses_in_one_line(tmp_path, capsys):
    (tmp_path / "run").mkdir()
    assert main(["watch", str(tmp_path / "run"), "--host", "0.0.0.0", "--port", "0"]) == 1
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "--host 0.0.0.0" in err[0] and "--token-file" in err[0]


def test_a_token_file_shorter_than_sixteen_characters_is_refused_naming_the_file(tmp_path, capsys):
    token = tmp_path / "token"
    token.write_text("short\n")
    assert main(["watch", str(tmp_path), "--host", "0.0.0.0", "--port", "0", "--token-file", str(token)]) == 1
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and str(token) in err[0] and "16" in err[0]


def test_the_token_is_given_once_then_kept_in_a_cookie(tmp_path):
    from campaign.measure.auth import read_token
    from campaign.watch.server import WatchServer

    token = tmp_path / "token"
    token.write_text(TOKEN + "\n")
    (tmp_path / "run").mkdir()
    server = WatchServer(tmp_path / "run", host="127.0.0.1", port=0, key=read_token(token)).start()
    try:
        for path in ("/", "/api/status", "/api/poses", "/?token=wrong-token-0123456789"):
            assert get(server.port, path)[0] == 401
        status, headers, body = get(server.port, f"/api/status?token={TOKEN}")
        assert status == 200 and json.loads(body)["state"] == "planned"
        cookie = headers["Set-Cookie"]
        assert "HttpOnly" in cookie and "SameSite=Strict" in cookie and TOKEN not in cookie
        assert "Max-Age=2592000" in cookie  # kept across browser restarts for a campaign's days
        jar = {"Cookie": cookie.split(";")[0]}
        assert get_json(server.port, "/api/status", jar)["state"] == "planned"
        assert get(server.port, "/", jar)[0] == 200
        assert get(server.port, "/api/status", {"Cookie": f"campaign_watch_{server.port}=0123abcd"})[0] == 401
    finally:
        server.stop()


def test_on_every_interface_the_command_says_what_to_open_not_0_0_0_0(tmp_path):
    (tmp_path / "token").write_text(TOKEN)
    (tmp_path / "run" / "plan").mkdir(parents=True)
    (tmp_path / "run" / "plan" / "poses.csv").write_text("pose_id,q1,q2,q3,q4,q5,q6\n")
    proc = subprocess.Popen([sys.executable, "-m", "campaign.cli", "watch", str(tmp_path / "run"), "--host", "0.0.0.0",
                             "--port", "0", "--token-file", str(tmp_path / "token")], stdout=subprocess.PIPE,
                            stderr=subprocess.PIPE, text=True, env=ENV)
    try:
        port = url_from(proc.stdout, r"http://<this machine's name or address>:(\d+)/ \(every interface\)")
        assert get(port, "/api/status")[0] == 401  # and it serves, with the token required
    finally:
        proc.send_signal(signal.SIGINT)
        assert proc.wait(timeout=10) == 0 and "Traceback" not in proc.stderr.read()


def test_two_watchers_on_one_machine_keep_a_cookie_each(tmp_path):
    """A browser keeps one cookie per host whatever the port: the second watcher's cookie replaced
    the first's, which then refused the page (401)."""
    from campaign.measure.auth import read_token
    from campaign.watch.server import WatchServer

    servers, jar = [], {}
    try:
        for k in range(2):
            (tmp_path / f"token{k}").write_text(f"{TOKEN}-{k}")
            (tmp_path / f"run{k}").mkdir()
            servers.append(WatchServer(tmp_path / f"run{k}", port=0, key=read_token(tmp_path / f"token{k}")).start())
        for k, server in enumerate(servers):  # each opened once with its token, as a browser would in turn
            name, _, value = get(server.port, f"/?token={TOKEN}-{k}")[1]["Set-Cookie"].split(";")[0].partition("=")
            jar[name] = value  # the browser's jar for this host: a cookie of the same name is replaced
        cookie = {"Cookie": "; ".join(f"{n}={v}" for n, v in jar.items())}
        assert len(jar) == 2 and [get(s.port, "/api/status", cookie)[0] for s in servers] == [200, 200]
    finally:
        for server in servers:
            server.stop()


def test_a_base64_token_is_taken_as_typed_in_the_address_bar_and_as_a_form_encodes_it(tmp_path):
    from campaign.measure.auth import read_token
    from campaign.watch.server import WatchServer

    token = "Ab+cd/ef+0123456789xyz=="  # `openssl rand -base64`: '+' is a space to a form's decoding
    (tmp_path / "token").write_text(token + "\n")
    (tmp_path / "run").mkdir()
    server = WatchServer(tmp_path / "run", port=0, key=read_token(tmp_path / "token")).start()
    try:
        for given in (token, token.replace("+", "%2B").replace("/", "%2F").replace("=", "%3D")):
            assert get(server.port, f"/api/status?token={given}")[0] == 200, given
        for wrong in (token.replace("+", " "), token.replace("+", "-"), token[:-1]):
            assert get(server.port, f"/api/status?token={wrong.replace(' ', '%20')}")[0] == 401, wrong
    finally:
        server.stop()


# -- the API against a log written here ------------------------------------------------------------------
def _write_log(run, robot, ids, q, failed, offsets_m, times_s):
    from campaign.measure.store import MeasurementStore, PoseRecord
    from campaign.model.kinematics import forward

    T = forward(robot, q)
    with MeasurementStore(run / "measurements.sqlite") as store:
        store.use_wal()
        store.add_event("session_start", {"planned": 10})
        for k, pid in enumerate(ids):
            if pid in failed:
                store.add_pose(PoseRecord(int(pid), "failed", tuple(q[k]), seq=k, reason="tracker: brr: beam_lost",
                                          time_s=times_s[k], wall_time_unix_s=time.time()))
            else:
                xyz = T[k, :3, 3] + offsets_m[k]
                store.add_pose(PoseRecord(int(pid), "measured", tuple(q[k]), seq=k, time_s=times_s[k],
                                          wall_time_unix_s=time.time(), xyz=tuple(xyz), rotvec=(0.0, 0.0, 0.0)))
            if k == 3:
                store.add_event("drift_check", {"drift_mm": 0.031, "over_threshold": False}, pose_id=int(pid),
                                time_s=times_s[k] + 1.0)


def test_status_and_poses_agree_with_a_log_written_here_and_the_state_follows_the_lock(tmp_path, robot):
    from campaign.measure.store import MeasurementStore
    from campaign.run import RunFolder
    from campaign.sim.truth import random_joint_poses
    from campaign.watch.server import WatchServer
    from campaign.watch.view import RunView, strict_json

    run = tmp_path / "run"
    (run / "plan").mkdir(parents=True)
    q = random_joint_poses(robot, 10, seed=3)
    ids = np.arange(500, 510)
    (run / "plan" / "poses.csv").write_text("pose_id,q1,q2,q3,q4,q5,q6\n" + "".join(
        f"{i}," + ",".join(repr(float(v)) for v in row) + "\n" for i, row in zip(ids, q)))
    server = WatchServer(run, port=0).start()
    try:
        st = get_json(server.port, "/api/status")
        assert st["state"] == "planned" and (st["measured"], st["failed"], st["planned"]) == (0, 0, 10)
        assert get_json(server.port, "/api/poses") == []

        rng = np.random.default_rng(7)
        offsets = rng.normal(size=(10, 3)) * 1e-3  # known position errors against the nominal model
        times = np.arange(10) * 36.0 + 100.0
        _write_log(run, robot, ids[:8], q[:8], {502, 506}, offsets, times)
        time.sleep(0.3)  # the view reads the log at most every 0.25 s
        st = get_json(server.port, "/api/status")
        assert set(st) == {"measured", "failed", "planned", "eta_s", "state", "campaign_h", "last_pose", "drift"}
        assert (st["measured"], st["failed"], st["planned"]) == (6, 2, 10)
        assert st["state"] == "interrupted"  # no command holds the run, two planned poses have no outcome
        assert st["last_pose"] == 507 and math.isclose(st["campaign_h"], times[7] / 3600)
        assert math.isclose(st["eta_s"], 2 * 36.0)  # two poses to go at 36 s each on the campaign clock
        assert math.isclose(st["drift"]["last_mm"], 0.031) and st["drift"]["checks"] == 1
        poses = get_json(server.port, "/api/poses")
        assert [p["pose_id"] for p in poses] == list(range(500, 508))
        assert [p["reason"] for p in poses if p["status"] == "failed"] == ["tracker: brr: beam_lost"] * 2
        for p, off in zip(poses, offsets):
            if p["status"] == "measured":
                assert math.isclose(p["error_nominal_mm"], 1e3 * np.linalg.norm(off), rel_tol=1e-9)
            else:  # where in the workspace it failed: the nominal position of its joints
                assert p["error_nominal_mm"] is None and len(p["nominal_xyz_m"]) == 3
        assert [p["pose_id"] for p in get_json(server.port, "/api/poses?from=6")] == [506, 507]

        with RunFolder(run).lock("run"):  # a driver holds the run (here: this process)
            time.sleep(0.3)  # the view looks again at most every 0.25 s
            assert get_json(server.port, "/api/status")["state"] == "running"
        _write_remaining(run, robot, ids, q, offsets, times)
        time.sleep(0.3)
        st = get_json(server.port, "/api/status")
        assert (st["measured"], st["failed"], st["state"], st["eta_s"]) == (8, 2, "finished", 0.0)
        # what was read piece by piece is what a watcher opened now reads whole
        assert server.view.reads["appended"] >= 1
        assert get_json(server.port, "/api/poses") == json.loads(strict_json(RunView(run).poses()))
        with MeasurementStore(run / "measurements.sqlite") as store:  # `campaign run --retry-failed` forgets them
            store.forget_failed()
        time.sleep(0.3)
        st = get_json(server.port, "/api/status")
        assert (st["measured"], st["failed"], st["state"]) == (8, 0, "interrupted")
        assert [p["pose_id"] for p in get_json(server.port, "/api/poses")] == [500, 501, 503, 504, 505, 507, 508, 509]

        # only the reports' folders are served, never the simulator's truth nor anything outside
        (run / "sim").mkdir()
        (run / "sim" / "truth.yaml").write_text("secret: 1\n")
        (run / "plan" / "tour.png").write_bytes(b"\x89PNG")
        assert get(server.port, "/run/plan/tour.png")[0] == 200
        for path in ("/run/sim/truth.yaml", "/run/../run/sim/truth.yaml", "/run/plan/../sim/truth.yaml",
                     "/run/campaign.yaml", "/run/measurements.sqlite", "/api/poses?from=-1"):
            assert get(server.port, path)[0] in (400, 404), path
    finally:
        server.stop()


def _write_remaining(run, robot, ids, q, offsets, times):
    from campaign.measure.store import MeasurementStore, PoseRecord
    from campaign.model.kinematics import forward

    T = forward(robot, q)
    with MeasurementStore(run / "measurements.sqlite") as store:
        for k in (8, 9):
            store.add_pose(PoseRecord(int(ids[k]), "measured", tuple(q[k]), seq=k, time_s=times[k],
                                      xyz=tuple(T[k, :3, 3] + offsets[k]), rotvec=(0.0, 0.0, 0.0)))


def test_a_watcher_polling_as_fast_as_it_can_never_makes_a_command_find_the_run_busy(tmp_path):
    from campaign.watch.view import RunView

    run = tmp_path / "run"
    run.mkdir()
    (run / ".lock").write_text("{}")
    # another process takes and releases the run's lock 400 times, as commands starting would
    script = ("import sys; from campaign.run import RunFolder; from campaign.errors import RunBusy\n"
              "busy = 0\n"
              "for _ in range(400):\n"
              "    try:\n"
              "        with RunFolder(sys.argv[1]).lock('run'): pass\n"
              "    except RunBusy: busy += 1\n"
              "print(busy)\n")
    proc = subprocess.Popen([sys.executable, "-c", script, str(run)], stdout=subprocess.PIPE, text=True, env=ENV)
    view, looks, states = RunView(run), 0, set()
    while proc.poll() is None:
        view.refresh(force=True)  # who holds the lock, looked up every time
        states.add(view.status()["state"])
        looks += 1
    assert proc.communicate()[0].strip() == "0" and looks > 20, looks
    assert states <= {"planned", "running"}


def test_auto_rounds_and_the_reports_present_are_shown_and_auto_decides_finished(tmp_path, capsys):
    from campaign.auto.state import Decision, Round, load_state, save_state
    from campaign.cli import build_parser
    from campaign.run import RunFolder
    from campaign.watch.server import WatchServer

    run = RunFolder(tmp_path / "run")
    (run.path / "calibration").mkdir(parents=True)
    (run.path / "calibration" / "report.html").write_text("<html>the report</html>")
    state = load_state(run)
    rnd = Round(1, 120, 120, 0.61, "geometric", (), 0.0213, 0.0100, "ground_compliance", False, (), None,
                Decision("add_effect", "add ground_compliance", effect="ground_compliance"))
    state["rounds"].append(rnd.as_json())
    state["pending"] = rnd.decision.as_json()
    save_state(run, state)
    server = WatchServer(run.path, port=0).start()
    try:
        d = get_json(server.port, "/api/details")
        assert d["auto"]["rounds"][0]["decision"] == "add ground_compliance"
        assert math.isclose(d["auto"]["rounds"][0]["heldout_mm"], 0.0213) and d["auto"]["pending"]
        assert get_json(server.port, "/api/status")["state"] == "interrupted"  # no auto holds the run, not done
        [report] = d["reports"]
        assert report["label"] == "calibration report"
        assert get(server.port, "/" + report["href"])[2] == b"<html>the report</html>"
        state["finished"] = {"reason": "at the noise floor", "time_unix_s": time.time()}
        save_state(run, state)
        time.sleep(0.3)
        assert get_json(server.port, "/api/status")["state"] == "finished"
    finally:
        server.stop()
    parser = build_parser()
    taken = WatchServer(run.path, port=0)  # a port another watcher serves: refused in one line, nothing measured
    try:
        assert main(["run", str(run.path), "--sim", "--watch", str(taken.port)]) == 1
    finally:
        taken.stop()
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and f"--watch {taken.port} on 127.0.0.1: cannot bind" in err[0]
    assert not (run.path / "measurements.sqlite").exists()
    assert parser.parse_args(["auto", "r", "--sim", "--watch"]).watch == 8765
    assert parser.parse_args(["run", "r", "--sim", "--watch", "9000"]).watch == 9000
    assert parser.parse_args(["run", "r", "--sim"]).watch is None


def test_the_nominal_residuals_follow_pinocchio_and_the_calibrated_ones_calibrates_own_metrics(measured, robot):
    import pinocchio as pin

    from campaign.watch.view import RunView

    run, _, _ = measured.make(n=40, seed=4)
    view = RunView(run)
    before = view.poses()
    assert all(p["error_calibrated_mm"] is None for p in before)  # no calibration yet
    assert main(["calibrate", str(run), "--no-ann", "--no-report", "--quiet"]) == 0
    time.sleep(0.3)
    rows = view.poses()
    model = robot.pinocchio_model
    data = model.createData()
    frame = model.getFrameId(robot.tool_frame)
    with sqlite3.connect(f"file:{run / 'measurements.sqlite'}?mode=ro", uri=True) as db:
        q = {p: r for p, *r in db.execute("SELECT pose_id, q1, q2, q3, q4, q5, q6 FROM poses")}
    for p in rows:  # the nominal point by Pinocchio, not by the package's kinematics
        pin.framesForwardKinematics(model, data, robot.pinocchio_q(np.array([q[p["pose_id"]]]))[0])
        T_IE = np.linalg.inv(robot.T_root_base) @ data.oMf[frame].homogeneous
        assert np.allclose(p["nominal_xyz_m"], T_IE[:3, 3], atol=1e-9)
        assert math.isclose(p["error_nominal_mm"], 1e3 * np.linalg.norm(T_IE[:3, 3] - p["xyz_m"]), rel_tol=1e-6)
    # the calibrated residuals average to what calibrate reported for its train and test sets
    metrics = json.loads((run / "calibration" / "metrics.json").read_text())
    stage = metrics["stages"][metrics["order"][-1]]
    n = {k: stage[k]["n_poses"] for k in ("train", "test")}
    expected = sum(n[k] * stage[k]["position_mm"]["mean"] for k in n) / sum(n.values())
    got = [p["error_calibrated_mm"] for p in rows]
    assert len(got) == sum(n.values()) and math.isclose(np.mean(got), expected, rel_tol=1e-6)
    assert np.median(got) < 0.2 * np.median([p["error_nominal_mm"] for p in rows])
    assert view.details()["calibration_stage"] == metrics["order"][-1]


# -- live, in a real browser ---------------------------------------------------------------------------
def chromium(**kw):
    """benchmarks/browser.py's headless Chromium."""
    sys.path.insert(0, str(ROOT / "benchmarks"))
    try:
        from browser import Chromium
    finally:
        sys.path.pop(0)
    return Chromium(**kw)


@pytest.mark.skipif(find_browser() is None, reason="no Chromium on this machine (apt-get install chromium)")
def test_a_headless_browser_follows_a_simulated_campaign_live_until_finished(runs):
    run = runs.make(n=24, sim={"time_factor": 0.015}, run={"timeout_s": 2.0})  # ~0.4 s per pose in real time
    proc = subprocess.Popen([sys.executable, "-m", "campaign.cli", "run", str(run), "--sim", "--quiet", "--watch", "0"],
                            stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, text=True, env=ENV,
                            start_new_session=True)
    try:
        port = url_from(proc.stderr)
        with chromium(width=1200, height=900) as browser:
            browser.goto(f"http://127.0.0.1:{port}/")
            seen, samples = [], 0
            while proc.poll() is None:
                before = log_counts(run)[0]
                shown = browser.evaluate("document.getElementById('measured').textContent")
                try:
                    status = get_json(port, "/api/status")
                except ConnectionError:  # the run ended and its watcher with it, between poll() and here
                    assert proc.wait(timeout=30) == 0
                    break
                after = log_counts(run)[0]
                if shown.isdigit():
                    assert before - 5 <= int(shown) <= after, (before, shown, after)
                    seen.append(int(shown))
                if status["state"] == "running":  # read within 0.25 s of the log (RunView's refresh)
                    assert before - 5 <= status["measured"] <= after
                samples += 1
                time.sleep(0.3)
            # the command keeps serving a moment after the run while a page polls: the page ends "finished"
            browser.wait_for("document.getElementById('state').textContent === 'finished'", timeout_s=10)
            final = int(browser.evaluate("document.getElementById('measured').textContent"))
        assert proc.wait(timeout=30) == 0
        measured, failed = log_counts(run)
        assert final == measured and measured + failed == 24
        from campaign.watch.server import WatchServer

        server = WatchServer(run, port=0).start()  # a watcher opened on the finished run
        try:
            st = get_json(server.port, "/api/status")
        finally:
            server.stop()
        assert (st["state"], st["measured"], st["failed"], st["planned"]) == ("finished", measured, failed, 24)
        assert len(set(seen)) >= 3 and seen == sorted(seen) and seen[-1] > seen[0], seen  # it grew, live
    finally:
        if proc.poll() is None:
            os.killpg(proc.pid, signal.SIGKILL)
        proc.wait()


def test_a_watcher_on_a_killed_run_shows_it_interrupted(runs):
    run = runs.make(n=200, sim={"time_factor": 5e-4})
    watcher = subprocess.Popen([sys.executable, "-m", "campaign.cli", "watch", str(run), "--port", "0"],
                               stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, env=ENV)
    driver = subprocess.Popen([sys.executable, "-m", "campaign.cli", "run", str(run), "--sim", "--quiet"],
                              stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL, env=ENV, start_new_session=True)
    try:
        port = url_from(watcher.stdout)
        deadline = time.time() + 60
        while time.time() < deadline and log_counts(run)[0] < 10:
            time.sleep(0.05)
        assert get_json(port, "/api/status")["state"] == "running"
        os.killpg(driver.pid, signal.SIGKILL)  # no goodbye: the lock file still names the dead driver
        driver.wait()
        time.sleep(0.3)
        st = get_json(port, "/api/status")
        assert st["state"] == "interrupted" and st["measured"] == log_counts(run)[0] < 200
        assert json.loads((run / ".lock").read_text())["command"] == "run"
    finally:
        if driver.poll() is None:
            os.killpg(driver.pid, signal.SIGKILL)
        watcher.send_signal(signal.SIGINT)
        watcher.wait(timeout=10)
        for pid in runs.cell_pids(run):
            os.kill(pid, signal.SIGKILL)


def test_a_folder_that_is_no_run_is_refused_in_one_line_naming_it(tmp_path, capsys):
    (tmp_path / "empty").mkdir()
    (tmp_path / "file").write_text("x")
    for name, said in (("empty", "not a run folder"), ("file", "not a folder"), ("missing", "no such run folder")):
        assert main(["watch", str(tmp_path / name), "--port", "0"]) == 1
        err = capsys.readouterr().err.strip().splitlines()
        assert len(err) == 1 and f"{tmp_path / name}: {said}" in err[0], err


@pytest.mark.skipif(find_browser() is None, reason="no Chromium on this machine (apt-get install chromium)")
def test_the_page_asks_only_its_server_shows_no_error_and_follows_each_new_calibration(measured):
    from campaign.auto.state import Decision, Round, load_state, save_state
    from campaign.run import RunFolder
    from campaign.watch.server import WatchServer

    run, _, _ = measured.make(n=40, seed=5)
    server = WatchServer(run, port=0).start()
    page_errors = "S.poses.map((p) => p.error_calibrated_mm)"
    try:
        with chromium(width=1200, height=900) as browser:
            for domain in ("Network", "Runtime", "Log"):
                browser.call(f"{domain}.enable")
            browser.goto(f"http://127.0.0.1:{server.port}/")
            browser.wait_for("document.getElementById('measured').textContent === '40'", timeout_s=15)
            assert browser.evaluate(page_errors) == [None] * 40
            answers = []
            for extra in ([], ["--fix", "joint3"]):  # a calibration, then another of the same stage's name
                assert main(["calibrate", str(run), "--no-ann", "--no-report", "--quiet", *extra]) == 0
                time.sleep(0.3)  # the view reads the run again at most every 0.25 s
                api = [p["error_calibrated_mm"] for p in get_json(server.port, "/api/poses")]
                assert None not in api and api not in answers
                answers.append(api)
                browser.wait_for(f"JSON.stringify({page_errors}) === '{json.dumps(api, separators=(',', ':'))}'",
                                 timeout_s=15)
                # calibrated errors a decade below the nominal ones or more: the residual plot's axis is
                # logarithmic (the first calibration's are a hundredth, the one with joint 3 fixed not)
                nominal = [p["error_nominal_mm"] for p in get_json(server.port, "/api/poses")]
                scale = "log" if np.median(nominal) > 10 * np.median(api) else "linear"
                assert scale == ("log", "linear")[len(answers) - 1]
                assert browser.evaluate("document.getElementById('residuals').dataset.yscale") == scale
            # auto between rounds (round 1 decided, its decision applied, nothing pending): says so
            state = load_state(RunFolder(run))
            state["rounds"].append(Round(1, 40, 40, 0.2, "geometric", (), 0.02, 0.01, "ground_compliance", False, (),
                                         None, Decision("add_effect", "add ground_compliance")).as_json())
            save_state(RunFolder(run), state)
            note = browser.wait_for("document.getElementById('auto-note').textContent", timeout_s=10)
            assert note.startswith("round 2 under way"), note
            # then it stops: the page says why in the stop decision's words (it said 'finished: at_floor')
            stop = Decision("stop", "stop: at the measurement noise", reason="at_floor")
            state["rounds"].append(Round(2, 40, 40, 0.2, "geometric+ground_compliance+joint_compliance", (), 0.011,
                                         0.01, "at the noise", False, (), None, stop).as_json())
            state["finished"] = {"reason": "at_floor", "time_unix_s": time.time()}
            save_state(RunFolder(run), state)
            browser.wait_for("document.getElementById('auto-note').textContent === "
                             "'finished; stop: at the measurement noise'", timeout_s=10)
            # on a phone the page stays within the screen's width (a long model name ran it off the right)
            browser.call("Emulation.setDeviceMetricsOverride", width=560, height=900, deviceScaleFactor=1, mobile=False)
            browser.wait_for("document.documentElement.scrollWidth <= 560", timeout_s=5)
            # a failure's numbers are folded, its names kept (the reflector 'm1' was shown as 'm#')
            assert browser.evaluate("reasonKey('tracker after 4 attempts: m1: beam_lost at 0.31 m, q3 -1.2e-3')") == \
                "tracker after # attempts: m1: beam_lost at # m, q3 #"
            # a report page opened from the page asks for /favicon.ico: no 404 in the console
            assert get(server.port, "/favicon.ico")[0] == 204
            origin = f"http://127.0.0.1:{server.port}/"
            assert [u for u in browser.requested() if not u.startswith(origin)] == []
            assert browser.problems() == []
    finally:
        server.stop()


@pytest.mark.parametrize("kind, frame", [("point", "tracker"), ("markers", "robot")])
def test_one_reflector_and_raw_reflector_data_get_the_residuals_calibrate_gets(tmp_path, robot, kind, frame):
    """One reflector in the tracker's frame (residuals once calibrate found the tracker), raw
    reflectors in the robot's (the log holds the pose they were fitted to)."""
    import pinocchio as pin

    from campaign.watch.view import RunView

    csv, run = tmp_path / "data.csv", tmp_path / "run"
    assert main(["synth", "--csv", str(csv), "--poses", "60", "--seed", "3", "--kind", kind, "--frame", frame]) == 0
    assert main(["import", str(csv), "--run", str(run), "--frame", frame]) == 0
    view = RunView(run)
    if frame == "tracker":  # where the tracker stands is unknown before a calibration
        assert [p["error_nominal_mm"] for p in view.poses()] == [None] * 60
    assert main(["calibrate", str(run), "--no-ann", "--no-report", "--quiet"]) == 0
    time.sleep(0.3)
    rows = view.poses()
    metrics = json.loads((run / "calibration" / "metrics.json").read_text())
    T_L_I = np.array(metrics["tracker"]["T_L_I"]) if frame == "tracker" else np.eye(4)
    model = robot.pinocchio_model
    data = model.createData()
    frame = model.getFrameId(robot.tool_frame)
    with sqlite3.connect(f"file:{run / 'measurements.sqlite'}?mode=ro", uri=True) as db:
        q = {p: r for p, *r in db.execute("SELECT pose_id, q1, q2, q3, q4, q5, q6 FROM poses")}
    for p in rows:  # the nominal point (the tool frame's origin, where synth measures) by Pinocchio, in L or I
        pin.framesForwardKinematics(model, data, robot.pinocchio_q(np.array([q[p["pose_id"]]]))[0])
        T_LE = T_L_I @ np.linalg.inv(robot.T_root_base) @ data.oMf[frame].homogeneous
        assert math.isclose(p["error_nominal_mm"], 1e3 * np.linalg.norm(T_LE[:3, 3] - p["xyz_m"]), rel_tol=1e-6)
    # the calibrated residuals average to calibrate's own train and test means (they were 70 mm off:
    # the first of the robot's three reflectors taken for the measured point, for both kinds)
    stage = metrics["stages"][metrics["order"][-1]]
    n = {k: stage[k]["n_poses"] for k in ("train", "test")}
    expected = sum(n[k] * stage[k]["position_mm"]["mean"] for k in n) / sum(n.values())
    assert math.isclose(np.mean([p["error_calibrated_mm"] for p in rows]), expected, rel_tol=1e-6)


@pytest.mark.skipif(find_browser() is None, reason="no Chromium on this machine (apt-get install chromium)")
def test_a_page_whose_watcher_restarted_with_another_token_says_to_open_it_again_with_the_token(tmp_path):
    from campaign.measure.auth import read_token
    from campaign.watch.server import WatchServer

    (tmp_path / "run").mkdir()
    for k in range(2):
        (tmp_path / f"token{k}").write_text(f"{TOKEN}-{k}\n")
    server = WatchServer(tmp_path / "run", port=0, key=read_token(tmp_path / "token0")).start()
    port = server.port
    try:
        with chromium(width=1000, height=700) as browser:
            browser.goto(f"http://127.0.0.1:{port}/?token={TOKEN}-0")
            browser.wait_for("document.getElementById('state').textContent === 'planned'", timeout_s=10)
            assert browser.evaluate("location.search") == ""  # the token left the address bar
            server.stop()
            server = WatchServer(tmp_path / "run", port=port, key=read_token(tmp_path / "token1")).start()
            # said as such, not as 'no answer from the watcher (HTTP 401)' (the moment it was down, it was)
            browser.wait_for("document.getElementById('conn').textContent.includes('refuses')", timeout_s=10)
            assert "?token=" in browser.evaluate("document.getElementById('conn').textContent")
    finally:
        server.stop()
