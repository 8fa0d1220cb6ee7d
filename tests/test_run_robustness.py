"""`campaign run` when things go wrong: bad peers, Ctrl-C, the cell alone, drift.

Real sockets throughout; the misbehaving peers below are small socket servers, the
simulated cell is a real separate process.
"""

import json
import os
import re
import signal
import socket
import sqlite3
import struct
import subprocess
import sys
import threading
import time

import numpy as np
import pytest

from campaign.cli import main
from campaign.errors import ConfigError
from campaign.measure import protocol as P
from campaign.measure.driver import RunOptions, run_campaign
from campaign.measure.store import open_run
from campaign.sim.cell import parse_faults

#: replies a broken peer may send instead of a valid one
BAD_REPLIES = {
    "garbage": b"HTTP/1.1 400 Bad Request\r\n\r\n",
    "oversized": struct.pack(">I", P.MAX_FRAME + 1) + b"{" * 64,
    "half_sent": struct.pack(">I", 200) + b'{"type": "reached", "id": ',
    "not_utf8": struct.pack(">I", 8) + b"\xff\xfe\xfd\xfc\xfb\xfa\xf9\xf8",
    "wrong_schema": struct.pack(">I", 30) + b'{"type":"reached","id":1,"q":1}',
    "trickled": None,  # a valid reply, one byte every 20 ms: complete only long after the timeout
}


class BadPeer:
    """A peer that answers heartbeats and the base-frame set-up properly and every other
    request with ``BAD_REPLIES[kind]`` (then hangs up, or stays silent after a half-sent frame)."""

    def __init__(self, name, kind):
        self.name, self.kind = name, kind
        self.sock = socket.create_server(("127.0.0.1", 0))
        self.port = self.sock.getsockname()[1]
        self.bad_sent = 0
        threading.Thread(target=self._serve, daemon=True).start()

    def _serve(self):
        while True:
            try:
                conn, _ = self.sock.accept()
            except OSError:
                return
            threading.Thread(target=self._handle, args=(conn,), daemon=True).start()

    def _handle(self, conn):
        c = P.Connection(conn, "driver")
        try:
            while True:
                msg = c.receive(30.0)
                if isinstance(msg, P.Heartbeat):
                    c.send(P.HeartbeatAck(msg.id, 0.0, self.name))
                elif isinstance(msg, P.Measure) and msg.targets == P.SETUP_TARGETS:
                    pts = {"setup_origin": (1.0, 0.0, 0.0), "setup_x": (1.3, 0.0, 0.0), "setup_y": (1.0, 0.3, 0.0)}
                    c.send(P.Measurement(msg.id, 0.0, tuple(P.Reading(t, "ok", pts[t]) for t in msg.targets)))
                elif isinstance(msg, P.Move) and self.name == "controller" and self.kind is None:
                    c.send(P.Reached(msg.id, msg.q, 0.0))
                elif self.kind == "trickled":
                    self.bad_sent += 1
                    reply = (P.Reached(msg.id, msg.q, 0.0) if isinstance(msg, P.Move) else
                             P.Measurement(msg.id, 0.0, tuple(P.Reading(t, "ok", (1.0, 1.0, 1.0)) for t in msg.targets)))
                    for byte in P.encode(reply):
                        c.send_raw(bytes([byte]))
                        time.sleep(0.02)
                else:
                    self.bad_sent += 1
                    c.send_raw(BAD_REPLIES[self.kind])
                    if self.kind == "half_sent":
                        time.sleep(5.0)
                    return
        except Exception:
            return
        finally:
            c.close()

    def close(self):
        self.sock.close()


@pytest.mark.parametrize("port", ["controller", "tracker"])
@pytest.mark.parametrize("kind", sorted(BAD_REPLIES))
def test_bad_replies_on_either_port_mark_poses_failed_and_never_crash_the_driver(tmp_path, robot, kind, port, runs):
    run = runs.make(n=2)
    ctrl = BadPeer("controller", kind if port == "controller" else None)
    trk = BadPeer("tracker", kind)  # the tracker is only asked when the controller behaves
    try:
        res = run_campaign(run, robot, ("127.0.0.1", ctrl.port), ("127.0.0.1", trk.port),
                           RunOptions(timeout_s=0.2, move_timeout_s=0.2, retries=1, backoff_s=0.0,
                                      drift_check_every=0))
    finally:
        ctrl.close()
        trk.close()
    assert (res.measured, res.failed, res.stopped) == (0, 2, None)
    assert (ctrl if port == "controller" else trk).bad_sent >= 2
    rows = runs.stored(run)
    assert [r[1] for r in rows] == ["failed", "failed"]
    assert all(f"{port} 127.0.0.1:" in r[2] and "no valid reply after 2 attempts" in r[2] for r in rows)


def test_a_peer_that_is_not_the_expected_one_is_named(tmp_path, robot, capsys, runs):
    run = runs.make(n=2)
    a, b = BadPeer("controller", None), BadPeer("tracker", None)
    try:
        rc = main(["run", str(run), "--controller", f"127.0.0.1:{b.port}", "--tracker", f"127.0.0.1:{a.port}"])
    finally:
        a.close()
        b.close()
    err = capsys.readouterr().err.strip().splitlines()
    assert rc == 1 and len(err) == 1
    assert f"controller 127.0.0.1:{b.port}: the peer there is a 'tracker'" in err[0] and "swapped" in err[0]


def test_ctrl_c_stops_after_the_current_pose_with_everything_stored(tmp_path, robot, runs):
    run = runs.make(n=120, sim={"time_factor": 5e-4})  # ~10 ms per pose
    proc = subprocess.Popen([sys.executable, "-m", "campaign.cli", "run", str(run), "--sim", "--quiet"],
                            stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, start_new_session=True)
    deadline = time.time() + 60
    while time.time() < deadline:
        try:
            if len(runs.stored(run)) >= 20:
                break
        except sqlite3.OperationalError:
            pass
        time.sleep(0.05)
    os.killpg(proc.pid, signal.SIGINT)  # what a terminal does: the whole foreground group
    out, err = proc.communicate(timeout=60)
    assert proc.returncode == 130
    assert "Ctrl-C" in err.strip().splitlines()[-1] and "re-run to resume" in err
    rows = runs.stored(run)
    assert 20 <= len(rows) < 120 and all(r[1] == "measured" for r in rows)  # no pose failed by the stop
    assert runs.cell_pids(run) == []
    assert main(["run", str(run), "--sim", "--quiet"]) == 0
    assert [r[0] for r in runs.stored(run)] == list(range(1000, 1120))


def test_the_cell_alone_serves_a_driver_given_its_ports(tmp_path, robot, runs):
    run = runs.make(n=15)
    cell = subprocess.Popen([sys.executable, "-m", "campaign.cli", "sim", "--config", str(run / "campaign.yaml"),
                             "--run", str(tmp_path / "cell")],
                            stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    try:
        line = cell.stdout.readline()  # "simulated cell: controller 127.0.0.1:P, tracker 127.0.0.1:P ..."
        ports = {name: int(port) for name, port in re.findall(r"(controller|tracker) 127\.0\.0\.1:(\d+)", line)}
        assert main(["run", str(run), "--controller", f"127.0.0.1:{ports['controller']}",
                     "--tracker", f"127.0.0.1:{ports['tracker']}", "--quiet"]) == 0
    finally:
        cell.send_signal(signal.SIGINT)
        cell.wait(timeout=10)
    assert cell.returncode == 0
    assert [r[1] for r in runs.stored(run)] == ["measured"] * 15
    assert (tmp_path / "cell" / "sim" / "truth.yaml").is_file() and not (run / "sim").exists()


@pytest.mark.parametrize("hidden, warned", [(["drift"], True), ([], False)])
def test_the_drift_check_warns_when_the_reference_pose_moves(tmp_path, robot, hidden, warned, runs):
    run = runs.make(n=40, sim={"noise_m": 0.0, "hidden_effects": hidden},
                   run={"drift_check_every": 10, "drift_threshold_mm": 1e-4})
    assert main(["run", str(run), "--sim", "--quiet"]) == 0
    with open_run(run) as store:
        checks = store.events("drift_check")
        warnings = store.events("warning")
    assert len(checks) == 3  # after 10, 20 and 30 poses
    drifts = np.array([c[3]["drift_mm"] for c in checks])
    if warned:
        assert np.all(np.diff(drifts) > 0) and len(warnings) >= 1  # it grows with time
    else:
        assert np.all(drifts < 1e-9) and warnings == []


def test_fault_rates_are_validated():
    assert parse_faults({"drop": 0.1, "late_delay_s": 2}) == ({"drop": 0.1}, 2.0)
    with pytest.raises(ConfigError, match="unknown fault 'sim.faults.meteor'"):
        parse_faults({"meteor": 0.1})
    with pytest.raises(ConfigError, match=r"sim.faults.drop must be a rate in 0..1, got 5"):
        parse_faults({"drop": 5})


def test_a_measurement_carries_the_tracker_temperature_into_the_export(tmp_path, robot, runs):
    run = runs.make(n=5)
    assert main(["run", str(run), "--sim", "--quiet"]) == 0
    out = tmp_path / "out.csv"
    assert main(["export", str(run), "--csv", str(out)]) == 0
    header = out.read_text().splitlines()[0].split(",")
    assert header[:14] == "pose_id,time_s,q1,q2,q3,q4,q5,q6,x,y,z,rx,ry,rz".split(",")
    assert "temperature_c" in header
    with pytest.raises(P.ProtocolError, match="temperature_c"):
        P.decode(json.dumps({"type": "measurement", "id": 1, "time_s": 0, "readings": [],
                             "temperature_c": 400}).encode())


def test_the_protocol_document_names_every_message_status_target_and_fault():
    import dataclasses
    from pathlib import Path

    from campaign.measure.driver import POSE_FAULT_CODES, REFLECTORS
    from campaign.sim.cell import FAULT_KINDS

    doc = (Path(__file__).parents[1] / "docs" / "protocol.md").read_text()
    types = [f.default for cls in vars(P).values() if dataclasses.is_dataclass(cls)
             for f in dataclasses.fields(cls) if f.name == "type"]
    assert len(types) == 9  # hello (authenticated frames) joined the eight
    for name in (*types, *P.TARGET_STATUS, *P.SETUP_TARGETS, *REFLECTORS, *FAULT_KINDS, *POSE_FAULT_CODES):
        assert f"`{name}`" in doc, name
    assert f"{P.MAX_FRAME:,}" in doc
