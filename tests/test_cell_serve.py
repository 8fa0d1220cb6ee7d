"""Issue 21: what `campaign serve` does for an adapter (docs/cell.md), with real sockets: bad
specs in one line, exceptions as error replies, idempotency while a move is in flight, the move
timeout, joint limits and conventions, the aims; and authenticated frames beyond loopback: a peer
with no token, a wrong token, or a replayed frame moves nothing."""

import socket
import sys
import struct
import threading
import time

import numpy as np
import pytest

from campaign.cell import RobotFault
from campaign.cell.server import ServedCell
from campaign.cli import main
from campaign.errors import AuthError, ConfigError, PeerError
from campaign.measure import protocol as P
from campaign.measure.auth import FrameAuth

KEY = b"k" * 32


class Recorder:
    """A controller that records what it was asked; ``delay_s`` per move; RobotFault on q1 > 1."""

    joint_convention = "model"

    def __init__(self, robot=None, options=None, delay_s=0.0):
        self.moves, self.delay_s = [], delay_s

    def move(self, q):
        if q[0] > 1.0:
            raise RobotFault("q1 beyond the fence")
        time.sleep(self.delay_s)
        self.moves.append(np.array(q))


class Echo:
    """A tracker that answers its aims (0 where none); raises once when asked for 'brr' first."""

    def __init__(self, robot=None, options=None):
        self.asked = []

    def measure(self, aims):
        self.asked.append(aims)
        if len(self.asked) == 1 and "brr" in aims:
            raise LookupError("no such reflector in the SDK list")
        return {k: (np.zeros(3) if v is None else v) for k, v in aims.items()}


@pytest.fixture
def cell(robot):
    made = []

    def make(controller=None, tracker=None, rob=None, **kw):
        c = ServedCell(controller or Recorder(), tracker or Echo(), (rob or robot).with_default_reflectors(), **kw)
        made.append(c.start())
        return c

    yield make
    for c in made:
        c.close()


def _conn(cell, role="controller", key=None):
    port = cell.controller_port if role == "controller" else cell.tracker_port
    return P.Connection.connect("127.0.0.1", port, 2.0, role, key)


def _ask(cell, msg, role="controller", key=None):
    c = _conn(cell, role, key)
    try:
        c.send(msg)
        return c.receive(5.0)
    finally:
        c.close()


ADAPTERS = '''
import numpy as np
class Controller:
    def __init__(self, robot, options): pass
    def move(self, q): pass
class Tracker:
    def __init__(self, robot, options): pass
    def measure(self, aims): return {}
class Blind:
    def __init__(self, robot, options): pass
'''


@pytest.mark.parametrize("controller, match", [
    ("nosuch", r"--controller nosuch: unknown adapter \(known: .*mujoco.*sim"),
    ("cell.py:Missing", r"cell\.py:Missing: no class 'Missing' \(defined there: Blind, Controller, Tracker\)"),
    ("cell.py:Blind", r"cell\.py:Blind: a controller adapter needs a method move\(self, q\)"),
    ("broken.py", r"broken\.py:Controller: .*broken\.py failed to load \(ModuleNotFoundError: No module named "
                  r"'vendor_sdk_that_is_not_installed'\)"),
    ("missing.py", r"missing\.py:Controller: no such file"),
])
def test_a_bad_adapter_spec_is_one_line_naming_the_file_and_the_class(controller, match, tmp_path, monkeypatch,
                                                                        capsys):
    (tmp_path / "cell.py").write_text(ADAPTERS)
    (tmp_path / "broken.py").write_text("import vendor_sdk_that_is_not_installed\n")
    monkeypatch.chdir(tmp_path)
    assert main(["serve", "--controller", controller, "--tracker", "cell.py"]) == 1
    err = capsys.readouterr().err.strip()
    assert len(err.splitlines()) == 1 and "Traceback" not in err
    assert err.startswith("campaign serve: ")
    import re

    assert re.search(match, err), err


def test_a_tracker_without_measure_is_refused(tmp_path, monkeypatch, capsys):
    (tmp_path / "cell.py").write_text(ADAPTERS)
    monkeypatch.chdir(tmp_path)
    assert main(["serve", "--controller", "cell.py", "--tracker", "cell.py:Controller"]) == 1
    assert "cell.py:Controller: a tracker adapter needs a method measure(self, aims)" in capsys.readouterr().err


def test_an_adapter_exception_is_an_error_reply_and_one_line_and_the_server_stays_up(cell, capsys):
    c = cell()
    r = _ask(c, P.Measure(11, ("brr", "rrr1")), "tracker")
    assert isinstance(r, P.ErrorReply) and r.id == 11
    assert r.message == "tracker adapter: LookupError: no such reflector in the SDK list"
    err = capsys.readouterr().err.strip().splitlines()
    assert err == ["campaign serve: tracker adapter, request 11: LookupError: no such reflector in the SDK list"]
    r = _ask(c, P.Measure(12, ("brr", "rrr1"), (("rrr1", (1.0, 2.0, 3.0)),)), "tracker")
    assert isinstance(r, P.Measurement)
    assert [(x.target, x.status, x.xyz_m) for x in r.readings] == [("brr", "ok", (0.0, 0.0, 0.0)),
                                                                    ("rrr1", "ok", (1.0, 2.0, 3.0))]


def test_robot_fault_fails_the_pose_with_its_reason_and_limits_never_reach_the_adapter(cell, robot):
    rec = Recorder()
    c = cell(controller=rec)
    q = np.array(robot.q_mid)
    r = _ask(c, P.Move(1, tuple(np.r_[1.2, q[1:]])))
    assert r == P.Fault(1, "move_rejected", "q1 beyond the fence")
    outside = q.copy()
    outside[4] = robot.q_upper[4] + 1e-6
    assert _ask(c, P.Move(2, tuple(outside))) == P.Fault(2, "joint_limit", "target outside the joint limits")
    assert _ask(c, P.Move(3, (0.0,) * 5, )).message.startswith("move: q has 5 joints")
    assert rec.moves == []
    r = _ask(c, P.Move(4, tuple(q)))
    assert isinstance(r, P.Reached) and np.allclose(r.q_encoder, q) and len(rec.moves) == 1


def test_a_retry_while_the_move_is_in_flight_moves_once(cell, robot):
    rec = Recorder(delay_s=0.4)
    c = cell(controller=rec)
    q = tuple(robot.q_mid)
    replies = []
    threads = [threading.Thread(target=lambda: replies.append(_ask(c, P.Move(77, q)))) for _ in range(3)]
    for t in threads:
        t.start()
        time.sleep(0.05)
    for t in threads:
        t.join()
    assert len(rec.moves) == 1
    assert len(replies) == 3 and all(isinstance(r, P.Reached) and r.id == 77 for r in replies)


def test_a_move_that_never_settles_is_a_move_timeout_fault(cell, robot, capsys):
    c = cell(controller=Recorder(delay_s=1.0), call_timeout_s=0.2)
    r = _ask(c, P.Move(5, tuple(robot.q_mid)))
    assert isinstance(r, P.Fault) and r.code == "move_timeout"
    assert "did not return within 0.2 s" in r.message
    assert "controller adapter, request 5" in capsys.readouterr().err


def test_the_adapter_gets_the_controllers_convention_and_its_readout_comes_back(cell, robot, tmp_path):
    from campaign.model.robot import RobotModel

    sign, offset = np.array([1, -1, 1, -1, 1, 1.0]), np.array([0.0, 0.1, -0.2, 0, 0, 0.3])
    (tmp_path / "robot.yaml").write_text(f"urdf: {robot.urdf_path}\ncontroller:\n  sign: {sign.tolist()}\n"
                                         f"  offset: {offset.tolist()}\n")
    rob = RobotModel.load(tmp_path / "robot.yaml")

    class Vendor:
        def __init__(self):
            self.got = None

        def move(self, q):
            self.got = np.array(q)

        def joints(self):
            return self.got + 1e-4  # what the encoders read: 0.1 mrad off on every joint

    v = Vendor()
    c = cell(controller=v, rob=rob)
    q = np.array(robot.q_mid) + 0.05
    r = _ask(c, P.Move(9, tuple(q)))
    # q_model = diag(sign) q_controller + offset, by hand
    assert np.allclose(v.got, sign * (q - offset), atol=1e-12)
    assert np.allclose(r.q_encoder, sign * (v.got + 1e-4) + offset, atol=1e-12)


def test_aims_are_the_nominal_model_through_the_setup_or_a_fit_of_what_was_measured(robot):
    import pinocchio as pin

    from campaign.measure.aims import AimPredictor

    rob = robot.with_default_reflectors()
    names = [r.name for r in rob.reflectors]
    c, s = np.cos(0.4), np.sin(0.4)
    T_LI = np.array([[c, -s, 0, 2.0], [s, c, 0, -0.7], [0, 0, 1, 0.2], [0, 0, 0, 1]])
    model = rob.pinocchio_model
    data = model.createData()

    def reference(q):  # Pinocchio, not our kinematics
        pin.framesForwardKinematics(model, data, q)
        T = T_LI @ data.oMf[model.getFrameId(rob.tool_frame)].homogeneous
        return np.array([T[:3, :3] @ r.position_in_E + T[:3, 3] for r in rob.reflectors])

    rng = np.random.default_rng(3)
    Q = rob.q_lower + (rob.q_upper - rob.q_lower) * rng.random((4, 6))
    fixed = AimPredictor(rob, names, rob.reflector_positions_in_E, T_LI)
    assert [n for n, _ in fixed(Q[0])] == names
    assert np.allclose([a for _, a in fixed(Q[0])], reference(Q[0]), atol=1e-9)
    learned = AimPredictor(rob, names, rob.reflector_positions_in_E)
    assert all(a is None for _, a in learned(Q[0]))
    learned.learn(Q[0], reference(Q[0]))  # one pose's three reflectors span 7-10 cm
    assert np.allclose([a for _, a in learned(Q[1])], reference(Q[1]), atol=1e-6)


# -- authentication ------------------------------------------------------------------------------

def _raw_frame(body: bytes) -> bytes:
    return struct.pack(">I", len(body)) + body


def _closed(sock) -> bool:
    sock.settimeout(3.0)
    try:
        return sock.recv(1) == b""
    except ConnectionResetError:
        return True


def test_beyond_loopback_serve_refuses_to_start_without_a_token(tmp_path, monkeypatch, capsys):
    (tmp_path / "cell.py").write_text(ADAPTERS)
    monkeypatch.chdir(tmp_path)
    assert main(["serve", "--controller", "cell.py", "--tracker", "cell.py", "--host", "0.0.0.0"]) == 1
    err = capsys.readouterr().err.strip()
    assert len(err.splitlines()) == 1 and "--host 0.0.0.0" in err and "--token-file" in err
    (tmp_path / "short.token").write_text("secret\n")
    assert main(["serve", "--controller", "cell.py", "--tracker", "cell.py", "--token-file", "short.token"]) == 1
    assert "at least 16 characters" in capsys.readouterr().err


def test_a_peer_without_the_token_moves_nothing(cell, robot, capsys):
    rec = Recorder()
    c = cell(controller=rec, key=KEY)
    s = socket.create_connection(("127.0.0.1", c.controller_port), timeout=3)
    conn = P.Connection(s, "raw")
    hello = conn.receive(3.0)
    assert isinstance(hello, P.Hello) and len(hello.nonce) == 32
    s.sendall(P.encode(P.Move(1, tuple(robot.q_mid))))  # a plain frame, as a driver without a token sends
    assert _closed(s)
    s.close()
    assert rec.moves == []
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "refused a frame from 127.0.0.1:" in err[0] and "nothing done" in err[0]


def test_a_peer_with_a_wrong_token_moves_nothing(cell, robot, capsys):
    rec = Recorder()
    c = cell(controller=rec, key=KEY)
    conn = _conn(c, key=b"x" * 32)
    conn.send(P.Move(1, tuple(robot.q_mid)))
    with pytest.raises(PeerError, match="closed by the peer|connection lost"):
        conn.receive(3.0)
    conn.close()
    assert rec.moves == []
    assert "failed authentication" in capsys.readouterr().err


def test_a_frame_replayed_on_another_connection_or_the_same_moves_nothing(cell, robot, capsys):
    rec = Recorder()
    c = cell(controller=rec, key=KEY)
    a = _conn(c, key=KEY)
    sent = []
    send_raw = a.send_raw
    a.send_raw = lambda data: (sent.append(data), send_raw(data))
    a.send(P.Move(1, tuple(robot.q_mid)))
    assert isinstance(a.receive(3.0), P.Reached) and len(rec.moves) == 1
    b = _conn(c, key=KEY)  # another nonce
    b.send_raw(sent[0])
    with pytest.raises(PeerError):
        b.receive(3.0)
    a.send_raw(sent[0])  # the same connection, the counter has moved on
    with pytest.raises(PeerError):
        a.receive(3.0)
    assert len(rec.moves) == 1
    assert capsys.readouterr().err.count("failed authentication") == 2


def test_the_driver_with_the_token_works_and_without_it_stops_in_one_line(cell, robot):
    from campaign.measure.driver import AuthFailed, Peer, RunOptions

    opts = RunOptions(timeout_s=1.0, retries=1, reconnect_attempts=1, backoff_s=0.01)
    locked = cell(key=KEY)
    ok = Peer("127.0.0.1", locked.tracker_port, "tracker", opts, print, KEY)
    assert ok.heartbeat().peer == "tracker"
    m = ok.request(P.Measure(3, ("rrr1",), (("rrr1", (0.5, 0.5, 0.5)),)), 2.0)
    assert m.readings[0].xyz_m == (0.5, 0.5, 0.5)
    ok.close()
    with pytest.raises(AuthFailed, match="authenticates its frames; give its shared secret"):
        Peer("127.0.0.1", locked.tracker_port, "tracker", opts, print).heartbeat()
    plain = cell()
    with pytest.raises(AuthFailed, match="sent no hello within 1 s"):
        Peer("127.0.0.1", plain.tracker_port, "tracker", opts, print, KEY).heartbeat()


def test_frame_tags_bind_nonce_direction_and_order():
    nonce = bytes(range(16))
    driver, peer = FrameAuth(KEY, nonce, "driver"), FrameAuth(KEY, nonce, "peer")
    f1, f2 = driver.seal(b'{"a":1}'), driver.seal(b'{"a":2}')
    assert peer.open(f1) == b'{"a":1}'
    assert peer.open(f2) == b'{"a":2}'
    with pytest.raises(AuthError, match="failed authentication"):
        FrameAuth(KEY, nonce, "peer").open(f2)  # out of order (a replay)
    with pytest.raises(AuthError, match="failed authentication"):
        FrameAuth(KEY, nonce, "driver").open(FrameAuth(KEY, nonce, "driver").seal(b"x"))  # reflected
    with pytest.raises(AuthError, match="failed authentication"):
        FrameAuth(KEY, bytes(16), "peer").open(f1)  # another connection
    with pytest.raises(AuthError, match="failed authentication"):
        FrameAuth(b"y" * 32, nonce, "peer").open(f1)  # another key
    tampered = f1[:-2] + b"2}"
    with pytest.raises(AuthError, match="failed authentication"):
        FrameAuth(KEY, nonce, "peer").open(tampered)


def test_an_installed_package_names_its_cell_by_an_entry_point(tmp_path, monkeypatch, robot):
    from campaign.cell import load_adapters

    (tmp_path / "acme_cell.py").write_text(ADAPTERS)
    dist = tmp_path / "acme_cell-1.0.dist-info"
    dist.mkdir()
    (dist / "METADATA").write_text("Metadata-Version: 2.1\nName: acme-cell\nVersion: 1.0\n")
    (dist / "entry_points.txt").write_text("[campaign.cell]\nacme = acme_cell\nacme-blind = acme_cell:Blind\n")
    monkeypatch.syspath_prepend(str(tmp_path))
    monkeypatch.delitem(sys.modules, "acme_cell", raising=False)
    ctrl, trk = load_adapters("acme", "acme", robot, None, None)
    assert (type(ctrl).__name__, type(trk).__name__) == ("Controller", "Tracker")
    assert type(ctrl).__module__ == type(trk).__module__ == "acme_cell"
    with pytest.raises(ConfigError, match=r"--controller acme-blind: a controller adapter needs a method move"):
        load_adapters("acme-blind", "acme", robot, None, None)
