"""One driver per run, a campaign clock that never runs backwards, storage errors without loss."""

import json
import os
import re
import resource
import signal
import socket
import sqlite3
import subprocess
import sys
import threading
import time
from pathlib import Path

import pytest

from campaign.cli import main

ROOT = Path(__file__).resolve().parents[1]
ENV = {**os.environ, "PYTHONPATH": str(ROOT)}


#: a driver that waits long enough on a loaded machine and never re-measures a reference pose
RUN_OPTIONS = {"timeout_s": 2.0, "drift_check_every": 0}


def rows(run, sql):
    with sqlite3.connect(f"file:{run / 'measurements.sqlite'}?mode=ro", uri=True) as db:
        return db.execute(sql).fetchall()


def stored_count(run):
    try:
        return rows(run, "SELECT COUNT(*) FROM poses")[0][0]
    except sqlite3.OperationalError:
        return 0


def start_driver(run, *extra, **kw):
    return subprocess.Popen([sys.executable, "-m", "campaign.cli", "run", str(run), "--sim", "--quiet", *extra],
                            stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, env=ENV, **kw)


def wait_for(predicate, timeout_s=60.0):
    deadline = time.time() + timeout_s
    while time.time() < deadline:
        if predicate():
            return True
        time.sleep(0.02)
    return False


class Listener:
    """A TCP port that records whether anyone connected or sent a byte."""

    def __init__(self):
        self.sock = socket.socket()
        self.sock.bind(("127.0.0.1", 0))
        self.sock.listen(16)
        self.port = self.sock.getsockname()[1]
        self.connections = 0
        self.bytes = 0
        threading.Thread(target=self._serve, daemon=True).start()

    def _serve(self):
        while True:
            try:
                conn, _ = self.sock.accept()
            except OSError:
                return
            self.connections += 1
            conn.settimeout(0.5)
            try:
                self.bytes += len(conn.recv(65536))
            except OSError:
                pass
            conn.close()

    def close(self):
        self.sock.close()


def test_a_second_driver_is_refused_before_it_contacts_the_cell_or_the_store(capsys, runs):
    run = runs.make(n=40, sim={"time_factor": 5e-3}, run=RUN_OPTIONS)
    first = start_driver(run)
    try:
        assert wait_for(lambda: stored_count(run) >= 2)
        controller, tracker = Listener(), Listener()
        sessions_before = rows(run, "SELECT COUNT(*) FROM events WHERE kind = 'session_start'")[0][0]
        rc = main(["run", str(run), "--controller", f"127.0.0.1:{controller.port}",
                   "--tracker", f"127.0.0.1:{tracker.port}", "--quiet"])
        err = capsys.readouterr().err.strip().splitlines()
        time.sleep(0.3)
        assert rc == 1 and len(err) == 1
        assert re.search(rf"^campaign run: run {re.escape(str(run))} is busy: run pid {first.pid} since "
                         r"\d{4}-\d\d-\d\d \d\d:\d\d:\d\d;", err[0]), err[0]
        assert controller.connections == tracker.connections == 0 and controller.bytes == tracker.bytes == 0
        # a second simulated driver too: no second cell, no second session, no second set-up
        rc = main(["run", str(run), "--sim", "--quiet"])
        assert rc == 1 and f"is busy: run pid {first.pid}" in capsys.readouterr().err
        # and a calibrate while the driver stores poses
        rc = main(["calibrate", str(run), "--no-ann", "--quiet"])
        assert rc == 1 and f"is busy: run pid {first.pid}" in capsys.readouterr().err
        assert not (run / "calibration").exists()
        assert rows(run, "SELECT COUNT(*) FROM events WHERE kind = 'session_start'")[0][0] == sessions_before
        controller.close()
        tracker.close()
        assert first.wait(120) == 0
    finally:
        if first.poll() is None:
            first.kill()
            first.wait()
    assert stored_count(run) == 40
    assert rows(run, "SELECT COUNT(*) FROM events WHERE kind = 'setup'")[0][0] == 1
    assert rows(run, "SELECT COUNT(*) FROM events WHERE kind = 'session_start'")[0][0] == 1
    # the lock is released at the end: a re-run has nothing to measure and succeeds
    assert main(["run", str(run), "--sim", "--quiet"]) == 0


def test_plan_is_refused_while_a_driver_holds_the_run(capsys, runs):
    run = runs.make(n=30, sim={"time_factor": 5e-3}, run=RUN_OPTIONS)
    first = start_driver(run)
    try:
        assert wait_for(lambda: (run / ".lock").is_file() and (run / ".lock").read_text().strip() != "")
        plan_before = (run / "plan" / "poses.csv").read_bytes()
        rc = main(["plan", "--run", str(run), "--grid-scale", "0.2", "--quiet"])
        err = capsys.readouterr().err.strip().splitlines()
        assert rc == 1 and len(err) == 1
        assert f"is busy: run pid {first.pid}" in err[0] or "measured poses" in err[0]
        assert (run / "plan" / "poses.csv").read_bytes() == plan_before
    finally:
        first.kill()
        first.wait()


def test_kill_9_and_resume_keep_the_campaign_clock_monotone(runs):
    sim = {"time_factor": 1e-3}
    reference = runs.make(n=60, name="reference", sim=sim, run=RUN_OPTIONS)
    assert main(["run", str(reference), "--sim", "--quiet"]) == 0
    clock_reference = rows(reference, "SELECT value FROM meta WHERE key = 'campaign_clock_s'")[0][0]

    run = runs.make(n=60, name="killed", sim=sim, run=RUN_OPTIONS)
    proc = start_driver(run)
    assert wait_for(lambda: stored_count(run) >= 20)
    os.kill(proc.pid, signal.SIGKILL)
    proc.wait()
    before = rows(run, "SELECT seq, time_s FROM poses ORDER BY seq")
    t_kill = max(t for _, t in before)
    assert 20 <= len(before) < 60 and t_kill > 0
    assert main(["run", str(run), "--sim", "--quiet"]) == 0  # the killed driver's lock is gone with it
    after = rows(run, "SELECT seq, time_s FROM poses ORDER BY seq")
    assert after[: len(before)] == before and len(after) == 60
    times = [t for _, t in after]
    assert all(b >= a for a, b in zip(times, times[1:])), "the campaign clock ran backwards"
    assert min(times[len(before):]) > t_kill
    clock = float(rows(run, "SELECT value FROM meta WHERE key = 'campaign_clock_s'")[0][0])
    # the same poses (plus the one repeated after the kill) take at least as long as without a kill
    assert clock >= 0.98 * float(clock_reference)
    sessions = rows(run, "SELECT time_s FROM events WHERE kind = 'session_end'")
    assert sessions and sessions[-1][0] == pytest.approx(clock)


def _limit_file_size(limit_bytes):
    def set_limit():
        signal.signal(signal.SIGXFSZ, signal.SIG_IGN)  # a write past the limit fails with EFBIG instead
        resource.setrlimit(resource.RLIMIT_FSIZE, (limit_bytes, limit_bytes))
    return set_limit


def test_a_full_disk_is_one_line_and_loses_nothing(runs):
    run = runs.make(n=300, run=RUN_OPTIONS)
    proc = subprocess.run([sys.executable, "-m", "campaign.cli", "run", str(run), "--sim", "--quiet"],
                          capture_output=True, text=True, env=ENV, timeout=300,
                          preexec_fn=_limit_file_size(96 * 1024))
    err = proc.stderr.strip().splitlines()
    assert proc.returncode == 1, proc.stderr
    assert len(err) == 1 and "Traceback" not in proc.stderr, proc.stderr
    assert "measurements.sqlite" in err[0] and "full" in err[0] and "everything stored before is kept" in err[0]
    stored = rows(run, "SELECT pose_id FROM poses ORDER BY pose_id")
    assert 0 < len(stored) < 300
    # with room again, a re-run measures the rest, each pose once
    assert main(["run", str(run), "--sim", "--quiet"]) == 0
    assert [r[0] for r in rows(run, "SELECT pose_id FROM poses ORDER BY pose_id")] == list(range(1000, 1300))


def test_a_locked_database_is_one_line_and_loses_nothing(capsys, monkeypatch, runs):
    from campaign.measure import store as store_module

    run = runs.make(n=10, run=RUN_OPTIONS)
    assert main(["run", str(run), "--sim", "--quiet", "--max-poses", "4"]) == 0
    capsys.readouterr()
    before = rows(run, "SELECT pose_id, time_s, x, y, z FROM poses ORDER BY pose_id")
    monkeypatch.setattr(store_module, "BUSY_TIMEOUT_S", 0.2)
    other = sqlite3.connect(run / "measurements.sqlite", timeout=0.2)
    other.execute("BEGIN EXCLUSIVE")
    try:
        rc = main(["run", str(run), "--sim", "--quiet"])
    finally:
        other.rollback()
        other.close()
    err = capsys.readouterr().err.strip().splitlines()
    assert rc == 1 and len(err) == 1 and "database is locked" in err[0]
    assert rows(run, "SELECT pose_id, time_s, x, y, z FROM poses ORDER BY pose_id") == before
    assert main(["run", str(run), "--sim", "--quiet"]) == 0
    assert len(rows(run, "SELECT pose_id FROM poses")) == 10


# -- every command that writes a run holds its lock ------------------------------------------------

BUSY_LINE = r"^campaign {cmd}: run {run} is busy: {holder} pid {pid} since \d{{4}}-\d\d-\d\d \d\d:\d\d:\d\d; "


def folder_state(path) -> dict:
    """{relative path: bytes} of every file under ``path``."""
    return {str(p.relative_to(path)): p.read_bytes() for p in sorted(Path(path).rglob("*")) if p.is_file()}


def start_calibrate(run):
    return subprocess.Popen([sys.executable, "-m", "campaign.cli", "calibrate", str(run), "--no-ann", "--quiet"],
                            stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, env=ENV)


def holds_lock(run, proc, command):
    from campaign.run import RunFolder

    holder = RunFolder(run).lock_holder()
    return holder is not None and holder.get("pid") == proc.pid and holder.get("command") == command


def test_two_calibrates_at_once_the_second_is_refused_before_it_writes_anything(capsys, measured):
    run, _, _ = measured.make(n=60)
    first = start_calibrate(run)
    try:
        assert wait_for(lambda: holds_lock(run, first, "calibrate"), 120)
        os.kill(first.pid, signal.SIGSTOP)  # frozen while it holds the lock: nothing of its own changes now
        before = folder_state(run)
        second = subprocess.run([sys.executable, "-m", "campaign.cli", "calibrate", str(run), "--no-ann", "--quiet"],
                                capture_output=True, text=True, env=ENV, timeout=120)
        err = second.stderr.strip().splitlines()
        assert second.returncode == 1 and len(err) == 1, second.stderr
        assert re.search(BUSY_LINE.format(cmd="calibrate", run=re.escape(str(run)), holder="calibrate",
                                          pid=first.pid), err[0]), err[0]
        # diagnose too (it writes diagnose/ and reads calibration/), the folder untouched
        assert main(["diagnose", str(run), "--folds", "2", "--no-report"]) == 1
        lines = capsys.readouterr().err.strip().splitlines()
        assert len(lines) == 1 and re.search(BUSY_LINE.format(cmd="diagnose", run=re.escape(str(run)),
                                                              holder="calibrate", pid=first.pid), lines[0]), lines
        assert folder_state(run) == before
        os.kill(first.pid, signal.SIGCONT)
        assert first.wait(300) == 0, first.stderr.read().decode()
    finally:
        if first.poll() is None:
            os.kill(first.pid, signal.SIGCONT)
            first.kill()
            first.wait()
    history = json.loads((run / "calibration" / "history.json").read_text())["runs"]
    assert len(history) == 1  # the first calibrate's entry alone


def test_a_killed_holders_lock_is_stale_and_taken_over(measured):
    from campaign.run import RunFolder

    run, _, _ = measured.make(n=60)
    first = start_calibrate(run)
    try:
        assert wait_for(lambda: holds_lock(run, first, "calibrate"), 120)
        os.kill(first.pid, signal.SIGKILL)
        first.wait()
    finally:
        if first.poll() is None:
            first.kill()
            first.wait()
    assert json.loads((run / ".lock").read_text())["pid"] == first.pid  # its record is still there ...
    assert RunFolder(run).lock_holder() is None  # ... but nobody holds the lock
    assert main(["calibrate", str(run), "--no-ann", "--quiet", "--no-report"]) == 0
    assert json.loads((run / ".lock").read_text())["pid"] == os.getpid()
    assert (run / "calibration" / "metrics.json").is_file()


def test_one_simulated_cell_per_run_and_a_driver_beside_it(tmp_path, runs):
    run = runs.make(n=10)
    cell = subprocess.Popen([sys.executable, "-m", "campaign.cli", "sim", "--config", str(run / "campaign.yaml"),
                             "--run", str(run)], stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, env=ENV)
    try:
        line = cell.stdout.readline()
        ports = dict(re.findall(r"(controller|tracker) 127\.0\.0\.1:(\d+)", line))
        assert set(ports) == {"controller", "tracker"}, line + cell.stderr.read()
        sim_line = rf"^campaign {{cmd}}: the simulated cell of run {re.escape(str(run))} is busy: sim pid {cell.pid} "
        second = subprocess.run([sys.executable, "-m", "campaign.cli", "sim", "--run", str(run)],
                                capture_output=True, text=True, env=ENV, timeout=60)
        err = second.stderr.strip().splitlines()
        assert second.returncode == 1 and len(err) == 1 and re.search(sim_line.format(cmd="sim"), err[0]), err
        # a driver with its own simulated cell would start a second cell on the run: refused
        proc = subprocess.run([sys.executable, "-m", "campaign.cli", "run", str(run), "--sim", "--quiet"],
                              capture_output=True, text=True, env=ENV, timeout=60)
        err = proc.stderr.strip().splitlines()
        assert proc.returncode == 1 and len(err) == 1 and "the simulated cell of run" in err[0] \
            and f"is busy: sim pid {cell.pid}" in err[0], err
        assert not (run / "measurements.sqlite").exists()
        # the cell holds RUN/sim only: a driver measures into the same run beside it
        assert main(["run", str(run), "--controller", f"127.0.0.1:{ports['controller']}",
                     "--tracker", f"127.0.0.1:{ports['tracker']}", "--quiet"]) == 0
    finally:
        cell.send_signal(signal.SIGINT)
        cell.wait(timeout=30)
    assert cell.returncode == 0
    assert stored_count(run) == 10


def test_the_driver_skips_a_drift_check_whose_return_the_plan_found_not_clear(tmp_path, runs):
    """summary.json's drift_monitor lists the poses after which the direct motions to the reference
    pose and back are not clear; the driver skips those checks (an event says why), the others run."""
    import json
    import sqlite3

    from campaign.cli import main

    run = runs.make(n=30, run={"drift_check_every": 10})
    ids = [int(line.split(",")[0]) for line in (run / "plan" / "poses.csv").read_text().splitlines()[1:]]
    (run / "plan" / "summary.json").write_text(json.dumps({"drift_monitor": {"not_clear_after_pose_ids": [ids[9]]}}))
    assert main(["run", str(run), "--sim", "--quiet"]) == 0
    with sqlite3.connect(run / "measurements.sqlite") as db:
        kinds = [k for (k,) in db.execute("SELECT kind FROM events WHERE kind LIKE 'drift_check%' ORDER BY rowid")]
        skipped = [json.loads(d) for (d,) in db.execute("SELECT detail FROM events WHERE kind = 'drift_check_skipped'")]
    assert kinds == ["drift_check_skipped", "drift_check"]  # after poses 10 and 20 (not after the last)
    assert skipped[0]["after_pose_id"] == ids[9] and "not clear" in skipped[0]["why"]
