"""RWS 1.0: Digest auth with sessions, RAPID control, joint targets and symbols, with clear errors."""

import urllib.error
import urllib.request
from collections.abc import Iterator

import numpy as np
import pytest

from hardware.rws.client import RwsClient, RwsError
from hardware.rws.protocol import REALM
from hardware.rws.sim import SimRwsServer

Q_LEFT = np.array([0.1, -0.2, 0.3, -0.4, 0.5, -0.6, 0.7])  # chain order: index 2 is ABB axis 7


@pytest.fixture
def server() -> Iterator[SimRwsServer]:
    events: list[str] = []
    srv = SimRwsServer(
        {"ROB_L": lambda: Q_LEFT, "ROB_R": lambda: np.zeros(7)},
        port=0,
        on_rapid_start=lambda: events.append("start"),
        on_rapid_stop=lambda: events.append("stop"),
        symbols={"T_ROB_L/depth": "0"},
    )
    srv.events = events
    yield srv
    srv.close()


def _client(server: SimRwsServer, **kwargs: str) -> RwsClient:
    return RwsClient("127.0.0.1", server.port, timeout_s=2.0, **kwargs)


def test_digest_auth_once_then_session_cookie(server: SimRwsServer) -> None:
    client = _client(server)
    assert client.ctrlstate() == "motoron"
    assert client.opmode() == "AUTO"
    assert client.rapid_running() is False
    assert server.challenges == 1
    assert len(server.sessions) == 1


def test_requests_without_credentials_get_a_digest_challenge(server: SimRwsServer) -> None:
    with pytest.raises(urllib.error.HTTPError) as info:
        urllib.request.urlopen(f"http://127.0.0.1:{server.port}/rw/panel/ctrlstate?json=1", timeout=2)
    assert info.value.code == 401
    challenge = info.value.headers["WWW-Authenticate"]
    assert challenge.startswith("Digest ") and f'realm="{REALM}"' in challenge and 'qop="auth"' in challenge


def test_wrong_password_and_too_many_sessions_are_clear_errors(server: SimRwsServer) -> None:
    with pytest.raises(RwsError, match="authentication failed") as info:
        _client(server, password="wrong").ctrlstate()
    assert info.value.status == 401
    server.max_sessions = 1
    _client(server).ctrlstate()
    with pytest.raises(RwsError, match="too many") as info:
        _client(server).ctrlstate()
    assert info.value.status == 503


def test_rapid_start_needs_motors_on_and_drives_the_callbacks(server: SimRwsServer) -> None:
    client = _client(server)
    client.set_motors(False)
    assert client.ctrlstate() == "motoroff"
    with pytest.raises(RwsError, match="cannot start RAPID") as info:
        client.start_rapid()
    assert info.value.status == 400
    client.set_motors(True)
    client.start_rapid()
    assert client.rapid_running() and server.events == ["start"]
    with pytest.raises(RwsError, match="program pointer"):
        client.reset_program_pointer()
    client.stop_rapid()
    client.reset_program_pointer()
    assert not client.rapid_running() and server.events == ["start", "stop"]


def test_joint_target_in_radians_with_axis_7_from_eax_a(server: SimRwsServer) -> None:
    np.testing.assert_allclose(_client(server).joints("left"), Q_LEFT, atol=1e-7)


def test_symbols_read_write_and_unknown(server: SimRwsServer) -> None:
    client = _client(server)
    client.write_symbol("T_ROB_L", "depth", "3")
    assert client.read_symbol("T_ROB_L", "depth") == "3"
    with pytest.raises(RwsError, match="unknown RAPID symbol"):
        client.read_symbol("T_ROB_L", "nope")


def test_unreachable_controller_is_reported(server: SimRwsServer) -> None:
    port = server.port
    server.close()
    with pytest.raises(RwsError, match="unreachable") as info:
        RwsClient("127.0.0.1", port, timeout_s=1.0).ctrlstate()
    assert info.value.status == 0
