"""KMS40: protocol parsing, commands, streaming and draining, tare, garbage, disconnects, timeouts."""

import socket
import time
from collections.abc import Iterator

import numpy as np
import pytest

from hardware.kms40.client import Kms40Client
from hardware.kms40.protocol import (
    FLAG_BITS,
    Kms40Error,
    decode_flags,
    encode_flags,
    format_frame,
    parse_error,
    parse_frame,
)
from hardware.kms40.sim import SimKms40
from hardware.stamped import wait_for

WRENCH = np.array([0.5, -1.25, -3.0, 0.01, -0.02, 0.03])


@pytest.fixture
def sensor() -> Iterator[SimKms40]:
    sim = SimKms40(lambda: WRENCH, port=0)
    yield sim
    sim.close()


@pytest.fixture
def client(sensor: SimKms40) -> Iterator[Kms40Client]:
    c = Kms40Client("127.0.0.1", sensor.port, timeout_s=1.0, reconnect_s=0.05)
    yield c
    c.close()


def test_frame_flags_and_error_parsing() -> None:
    wrench, stamp = parse_frame(format_frame(WRENCH, 1234))
    np.testing.assert_allclose(wrench, WRENCH)
    assert stamp == 1234
    for bad in ("F={1,2,3}", "F={1,2,3,4,5,nan},1", "F={a,b,c,d,e,f},1", "X={1,2,3,4,5,6},1", "F={1,2,3,4,5,6}"):
        with pytest.raises(ValueError):
            parse_frame(bad)
    assert decode_flags(encode_flags({"CALIB_VALID", "OVERRUN_FZ", "CMD_FAILURE"})) == {
        "CALIB_VALID",
        "OVERRUN_FZ",
        "CMD_FAILURE",
    }
    assert FLAG_BITS["OVERRUN_FX"] == 20 and FLAG_BITS["CMD_FAILURE"] == 29
    assert decode_flags(1 << 5 | 1) == {"CALIB_VALID", "BIT5"}
    error = parse_error("ERROR(2,INVALID_ARGUMENT)")
    assert error is not None and error.code == 2 and "INVALID_ARGUMENT" in str(error)
    assert parse_error("LDIV=5") is None


def test_commands_and_error_replies(client: Kms40Client) -> None:
    assert client.serial() == "KMS40-SIM-0001"
    assert client.temperature() == 25.0
    np.testing.assert_allclose(client.frame(), WRENCH)
    assert {"CALIB_VALID", "STABLE"} <= client.flags()
    client.set_filter(2)
    assert "FILTER_ENABLED" in client.flags()
    with pytest.raises(Kms40Error) as info:
        client.command("BOGUS")
    assert info.value.code == 1
    with pytest.raises(Kms40Error) as info:
        client.set_rate_divider(0)
    assert info.value.code == 2
    assert client.command("LMASK", "{1,1,1,1,1,1}") == "{1,1,1,1,1,1}"
    assert client.stats["errors"] == 2


def test_streaming_rate_and_draining_stop(client: Kms40Client) -> None:
    assert client.set_rate_divider(5) == 100.0
    client.start_stream()
    assert "DAQ_RUNNING" in client.flags()
    n0, t0 = client.stats["frames"], time.monotonic()
    time.sleep(0.3)
    rate = (client.stats["frames"] - n0) / (time.monotonic() - t0)
    assert 50 < rate < 115  # 500 / 5 Hz; an ignored divider would give 500
    np.testing.assert_allclose(client.wrench.get(0.1), WRENCH)
    client.stop_stream()
    n = client.stats["frames"]
    time.sleep(0.05)
    assert client.stats["frames"] == n  # nothing after the L0 acknowledgement
    assert "DAQ_RUNNING" not in client.flags()


def test_tare_zeroes_and_untare_restores(client: Kms40Client) -> None:
    client.tare(True)
    np.testing.assert_allclose(client.frame(), 0.0)
    assert "TARA" in client.flags()
    client.tare(False)
    np.testing.assert_allclose(client.frame(), WRENCH)


def test_garbage_from_the_sensor_is_counted_not_fatal(sensor: SimKms40, client: Kms40Client) -> None:
    client.start_stream()
    client.wrench.wait(1.0)
    sensor.send_raw(b"\x00\xff\xfe junk\nF={1,2}\nF={1,2,3,4,5,6},7,8\n" + b"x" * 3000 + b"\nSN=surprise\n")
    assert wait_for(lambda: client.stats["oversized"] >= 1 and client.stats["malformed"] >= 2, 10.0)
    assert client.stats["unknown_replies"] >= 2  # the junk line and the unsolicited SN reply
    n = client.wrench.count
    assert wait_for(lambda: client.wrench.count > n + 5, 10.0)
    np.testing.assert_allclose(client.wrench.get(0.1), WRENCH)
    assert client.serial() == "KMS40-SIM-0001"


def test_reconnects_and_restores_settings_after_a_disconnect(sensor: SimKms40, client: Kms40Client) -> None:
    client.set_rate_divider(10)
    client.tare(True)
    client.start_stream()
    client.wrench.wait(1.0)
    sensor.disconnect_all()
    assert wait_for(lambda: client.stats["reconnects"] == 1, 10.0)
    n = client.wrench.count
    assert wait_for(lambda: client.wrench.count > n + 3, 10.0)  # streaming resumed by itself
    np.testing.assert_allclose(client.wrench.get(0.1), 0.0)  # tare restored
    assert client.stats["restore_failures"] == 0


def test_unreachable_and_silent_sensors_raise_in_time() -> None:
    with socket.create_server(("127.0.0.1", 0)) as silent:
        port = silent.getsockname()[1]
        t0 = time.monotonic()
        client = Kms40Client("127.0.0.1", port, timeout_s=0.2)
        try:
            with pytest.raises(Kms40Error, match="no reply"):
                client.serial()
        finally:
            client.close()
        assert time.monotonic() - t0 < 1.5
    with pytest.raises(Kms40Error, match="cannot connect"):
        Kms40Client("127.0.0.1", port, timeout_s=0.2)
