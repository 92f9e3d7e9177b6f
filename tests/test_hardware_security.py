"""An attacker on loopback (another socket, another port) can neither steer nor exhaust the devices.

EGM: the PC link hears only the configured robot and never answers anyone else; a simulated arm
follows only the registered link; the rehearsal's lossy proxy forwards only between those two.
RWS: a Digest header is good once, for one URI, for a while; sessions expire; bad or hostile
headers before authentication get an HTTP error, never a held thread or a traceback; what the
server keeps per stranger is bounded. `twin devices serve` warns before it exposes the factory
password beyond loopback.
"""

import hashlib
import http.client
import re
import socket
import threading
import time
from collections.abc import Iterator

import numpy as np
import pytest
from typer.testing import CliRunner

from hardware.config import HardwareConfig
from hardware.egm.client import EgmArmLink, interface_toward
from hardware.egm.faults import UdpFaultProxy
from hardware.egm.protocol import EgmRobot, EgmSensor, get_joints, set_joints
from hardware.egm.sim import SimEgmArm
from hardware.rws.client import RwsClient
from hardware.rws.protocol import REALM
from hardware.rws.sim import SimRwsServer
from hardware.stamped import wait_for
from twin.cli import app

LIMITS = np.tile([-0.15, 0.15], (7, 1))
USER, PASSWORD = "Default User", "robotics"
PATH = "/rw/panel/ctrlstate?json=1"


def _udp(host: str = "127.0.0.1") -> socket.socket:
    sock = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    sock.bind((host, 0))
    return sock


def _robot_msg(seq: int, q: np.ndarray) -> bytes:
    msg = EgmRobot()
    msg.header.seqno = seq
    set_joints(msg.feedBack, q)
    msg.motorState.state = msg.motorState.MOTORS_ON
    return msg.SerializeToString()


def _sensor_msg(seq: int, q: np.ndarray) -> bytes:
    msg = EgmSensor()
    msg.header.seqno = seq
    set_joints(msg.planned, q)
    return msg.SerializeToString()


def _silent(sock: socket.socket, wait_s: float = 0.1) -> bool:
    """Nothing arrives on `sock` within `wait_s`."""
    sock.settimeout(wait_s)
    try:
        sock.recv(4096)
    except TimeoutError:
        return True
    return False


# -- EGM ------------------------------------------------------------------------------------------
def test_factory_egm_link_never_listens_on_every_interface() -> None:
    assert HardwareConfig().egm.bind_host not in ("0.0.0.0", "")
    assert interface_toward("127.0.0.1") == "127.0.0.1"
    robot = _udp()
    link = EgmArmLink("left", "auto", 0, np.ones(7), robot=robot.getsockname())
    try:
        assert link.address[0] == "127.0.0.1"  # the interface facing the robot, here loopback
    finally:
        link.close()
        robot.close()
    with pytest.raises(OSError, match="cannot listen on 192.0.2.1:0 for the robot at 127.0.0.1"):
        EgmArmLink("left", "192.0.2.1", 0, np.ones(7), robot=("127.0.0.1", 0))  # not an address of ours


def test_link_drops_and_counts_strangers_and_never_answers_them() -> None:
    robot, stranger = _udp(), _udp()
    link = EgmArmLink("left", "127.0.0.1", 0, np.ones(7), robot=robot.getsockname())
    to_link = ("127.0.0.1", link.port)
    try:
        stranger.sendto(_robot_msg(100, np.full(7, 0.3)), to_link)  # forged joints, far-ahead seqno
        assert wait_for(lambda: link.stats["foreign"] == 1, 10.0)
        assert _silent(stranger)
        assert link.state.count == 0  # nothing forged reached the state the safety logic reads
        robot.sendto(_robot_msg(1, np.full(7, 0.1)), to_link)  # seqno 1 is still new: no takeover
        robot.settimeout(1.0)
        reply = EgmSensor()
        reply.ParseFromString(robot.recv(4096))
        np.testing.assert_allclose(get_joints(reply.planned), 0.1)
        assert link.stats["received"] == 1 and link.stats["malformed"] == 0
    finally:
        link.close()
        robot.close()
        stranger.close()


def test_link_with_any_robot_port_still_checks_the_robot_address() -> None:
    robot, stranger = _udp("127.0.0.1"), _udp("127.0.0.2")  # 127.0.0.0/8 is loopback: another host
    link = EgmArmLink("right", "127.0.0.1", 0, np.ones(7), robot=("127.0.0.1", 0))
    try:
        stranger.sendto(_robot_msg(1, np.zeros(7)), ("127.0.0.1", link.port))
        assert wait_for(lambda: link.stats["foreign"] == 1, 10.0)
        assert _silent(stranger)
        robot.sendto(_robot_msg(1, np.zeros(7)), ("127.0.0.1", link.port))
        robot.settimeout(1.0)
        assert robot.recv(4096)
    finally:
        link.close()
        robot.close()
        stranger.close()


def test_sim_arm_follows_only_its_registered_link() -> None:
    sensor, stranger = _udp(), _udp()
    arm = SimEgmArm("left", sensor.getsockname(), np.zeros(7), LIMITS, np.full(7, 10.0))
    arm.start_streaming()
    try:
        sensor.settimeout(1.0)
        _, arm_addr = sensor.recvfrom(4096)
        sensor.sendto(_sensor_msg(5, np.full(7, 0.01)), arm_addr)
        assert wait_for(lambda: arm.stats["accepted"] == 1, 10.0)
        stranger.sendto(_sensor_msg(1000, np.full(7, 0.1)), arm_addr)  # another port, newer seqno
        assert wait_for(lambda: arm.stats["foreign"] == 1, 10.0)
        sensor.sendto(_sensor_msg(6, np.full(7, -0.01)), arm_addr)  # the link keeps control
        assert wait_for(lambda: arm.stats["accepted"] == 2, 10.0)
        assert wait_for(lambda: np.allclose(arm.joints, -0.01), 10.0)
        assert arm.stats["out_of_order"] == 0
    finally:
        arm.close()
        sensor.close()
        stranger.close()


def test_fault_proxy_forwards_only_between_its_two_ends() -> None:
    robot, link, stranger = _udp(), _udp(), _udp()
    proxy = UdpFaultProxy(link.getsockname())
    proxy.client = robot.getsockname()
    try:
        stranger.sendto(b"forged feedback", ("127.0.0.1", proxy.port))  # would reach the link as the robot
        robot.sendto(b"feedback", ("127.0.0.1", proxy.port))
        link.settimeout(1.0)
        assert link.recvfrom(64) == (b"feedback", ("127.0.0.1", proxy.source_port))
        assert _silent(link)
        stranger.sendto(b"forged setpoint", ("127.0.0.1", proxy.source_port))  # would reach the robot
        link.sendto(b"setpoint", ("127.0.0.1", proxy.source_port))
        robot.settimeout(1.0)
        assert robot.recv(64) == b"setpoint"
        assert _silent(robot) and _silent(stranger)
        assert proxy.foreign == 2
    finally:
        proxy.close()
        for sock in (robot, link, stranger):
            sock.close()


# -- RWS: Digest --------------------------------------------------------------------------------
def _md5(text: str) -> str:
    return hashlib.md5(text.encode()).hexdigest()


def _digest(method: str, uri: str, nonce: str, nc: int, password: str = PASSWORD) -> str:
    """An RFC 2617 Digest Authorization header (MD5, qop=auth), written independently of the server."""
    cnonce = "0a4f113b"
    ha1 = _md5(f"{USER}:{REALM}:{password}")
    ha2 = _md5(f"{method}:{uri}")
    response = _md5(f"{ha1}:{nonce}:{nc:08x}:{cnonce}:auth:{ha2}")
    return (
        f'Digest username="{USER}", realm="{REALM}", nonce="{nonce}", uri="{uri}", qop=auth, '
        f'nc={nc:08x}, cnonce="{cnonce}", response="{response}", algorithm=MD5'
    )


def _request(server: SimRwsServer, path: str = PATH, **headers: str) -> http.client.HTTPResponse:
    conn = http.client.HTTPConnection("127.0.0.1", server.port, timeout=3.0)
    conn.request("GET", path, headers=headers)
    reply = conn.getresponse()
    reply.read()
    conn.close()
    return reply


def _nonce(server: SimRwsServer) -> str:
    reply = _request(server)
    assert reply.status == 401
    return re.search(r'nonce="([^"]+)"', reply.headers["WWW-Authenticate"])[1]


@pytest.fixture
def rws() -> Iterator[SimRwsServer]:
    srv = SimRwsServer(
        {"ROB_L": lambda: np.zeros(7)},
        port=0,
        max_sessions=3,
        session_idle_s=0.4,
        nonce_ttl_s=0.4,
        max_nonces=16,
        max_connections=6,
        request_timeout_s=0.5,
    )
    yield srv
    srv.close()


def test_digest_header_is_good_once_for_one_uri_while_fresh(rws: SimRwsServer) -> None:
    nonce = _nonce(rws)
    header = _digest("GET", PATH, nonce, 1)
    assert _request(rws, Authorization=header).status == 200
    assert _request(rws, Authorization=header).status == 401  # replayed: same nonce, same nc
    assert _request(rws, Authorization=_digest("GET", PATH, nonce, 2)).status == 200  # nc counts up
    assert _request(rws, Authorization=_digest("GET", PATH, nonce, 2)).status == 401
    other = "/rw/panel/opmode?json=1"
    assert _request(rws, other, Authorization=_digest("GET", PATH, _nonce(rws), 1)).status == 401  # uri
    assert _request(rws, Authorization=_digest("GET", PATH, "f" * 32, 1)).status == 401  # not our nonce
    assert _request(rws, Authorization=_digest("GET", PATH, _nonce(rws), 1, "wrong")).status == 401
    unicode = _digest("GET", PATH, _nonce(rws), 1).replace('response="', 'response="\u00e9')
    assert _request(rws, Authorization=unicode.encode().decode("latin-1")).status == 401
    assert len(rws.sessions) == 2
    late = _nonce(rws)
    time.sleep(0.5)  # past nonce_ttl_s
    assert _request(rws, Authorization=_digest("GET", PATH, late, 1)).status == 401


def test_replays_cannot_fill_the_sessions_and_idle_sessions_expire(rws: SimRwsServer) -> None:
    captured = _digest("GET", PATH, _nonce(rws), 1)
    assert _request(rws, Authorization=captured).status == 200
    assert all(_request(rws, Authorization=captured).status == 401 for _ in range(2 * rws.max_sessions))
    assert len(rws.sessions) == 1
    clients = [RwsClient("127.0.0.1", rws.port, timeout_s=2.0) for _ in range(2)]
    for client in clients:
        assert client.ctrlstate() == "motoron"  # a valid login after the flood
    challenges = rws.challenges
    time.sleep(0.5)  # past session_idle_s: every session is gone
    assert clients[0].ctrlstate() == "motoron"  # logs in again by itself
    assert rws.challenges == challenges + 1 and len(rws.sessions) == 1


# -- RWS: before authentication -------------------------------------------------------------------
def _raw(server: SimRwsServer, head: bytes, wait_s: float = 3.0) -> bytes:
    """Send `head` on a fresh connection; what the server sends back before closing (b"" if nothing)."""
    with socket.create_connection(("127.0.0.1", server.port), timeout=wait_s) as sock:
        sock.sendall(head)
        chunks = []
        while chunk := sock.recv(4096):
            chunks.append(chunk)
        return b"".join(chunks)


@pytest.mark.parametrize(("length", "status"), [("-1", b"400"), ("abc", b"400"), ("99999999999", b"413")])
def test_bad_content_length_is_an_http_error_at_once(
    rws: SimRwsServer, length: str, status: bytes, capfd: pytest.CaptureFixture[str]
) -> None:
    head = f"POST /rw/panel/ctrlstate HTTP/1.1\r\nHost: x\r\nContent-Length: {length}\r\n\r\n".encode()
    start = time.monotonic()
    reply = _raw(rws, head)
    assert reply.split(b" ")[1] == status
    assert time.monotonic() - start < rws.request_timeout_s  # answered, not timed out
    assert "Traceback" not in capfd.readouterr().err


def _handler_threads() -> int:
    return sum("process_request_thread" in t.name for t in threading.enumerate())


def test_idle_connections_hold_bounded_threads_for_bounded_time(rws: SimRwsServer) -> None:
    before = _handler_threads()
    idle = []
    for _ in range(3 * rws.max_connections):
        idle.append(socket.create_connection(("127.0.0.1", rws.port), timeout=2.0))
        time.sleep(0.01)  # let the server accept: a full listen backlog makes the client wait 1 s
    try:
        time.sleep(0.2)
        assert _handler_threads() - before <= rws.max_connections
        assert all(sock.recv(1) == b"" for sock in idle)  # every one closed by the server, none held
    finally:
        for sock in idle:
            sock.close()
    assert wait_for(lambda: _handler_threads() == before, 10.0)
    assert RwsClient("127.0.0.1", rws.port, timeout_s=2.0).ctrlstate() == "motoron"


def test_nonces_of_strangers_are_pruned(rws: SimRwsServer) -> None:
    for _ in range(3 * rws.max_nonces):
        _nonce(rws)
    assert rws.pending_nonces == rws.max_nonces
    time.sleep(0.5)  # past nonce_ttl_s
    nonce = _nonce(rws)
    assert rws.pending_nonces == 1
    assert _request(rws, Authorization=_digest("GET", PATH, nonce, 1)).status == 200


# -- twin devices serve -----------------------------------------------------------------------------
def test_serving_beyond_loopback_warns_about_the_factory_password() -> None:
    ports = ["--rws-port", "0", "--kms40-port", "0", "--egm-ports", "0,0", "--biotac-port", "0"]
    result = CliRunner().invoke(app, ["devices", "serve", *ports, "--host", "0.0.0.0", "--duration-s", "0.1"])
    assert result.exit_code == 0, result.output
    text = " ".join(result.output.split())
    assert "WARNING" in text and "all interfaces" in text and "factory password" in text
    quiet = CliRunner().invoke(app, ["devices", "serve", *ports, "--duration-s", "0.1"])
    assert quiet.exit_code == 0 and "WARNING" not in quiet.output
