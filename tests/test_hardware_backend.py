"""HardwareBackend over simulated devices on loopback: reading, moving, limits, force stop and retract,
watchdogs, reconnects, lossy EGM, clean open failures, the config file, and the controller unchanged."""

import json
import socket
import time
from collections.abc import Callable, Iterator

import numpy as np
import pytest

from hardware.backend import HardwareBackend
from hardware.config import HardwareConfig, config_to_toml, load_config, with_changes
from hardware.rws.client import RwsClient
from hardware.stamped import wait_for
from hardware.testbed import REST_ELECTRODES, REST_PDC, REST_WRENCH, SimulatedTestbed
from twin.backend import Backend, BackendError

STIFFNESS = 200.0  # N per rad of left joint 1 past CONTACT: a stand-in for the BioTac under an indenter
CONTACT = 0.02  # rad


def contact_wrench(q_left: np.ndarray) -> np.ndarray:
    """The F/T reading of the toy contact: the mount's weight plus a push along -z past CONTACT."""
    return REST_WRENCH - np.array([0, 0, STIFFNESS * max(0.0, q_left[0] - CONTACT), 0, 0, 0])


def _testbed(**kwargs: object) -> SimulatedTestbed:
    box: dict[str, SimulatedTestbed] = {}
    testbed = SimulatedTestbed(
        wrench_source=lambda: contact_wrench(box["tb"].arms["left"].joints),
        rws_port=0,
        kms40_port=0,
        egm_ports=(0, 0),
        biotac_port=0,
        **kwargs,
    )
    box["tb"] = testbed
    return testbed


def _config(testbed: SimulatedTestbed, **sections: dict) -> HardwareConfig:
    fast = {  # watchdogs wider than on the bench: tests share two busy cores with other work
        "egm": {"startup_timeout_s": 2.0, "watchdog_s": 0.5},
        "kms40": {"reconnect_s": 0.05, "watchdog_s": 0.5},
        "biotac": {"reconnect_s": 0.05, "watchdog_s": 0.5},
        "safety": {"force_limit_n": 3.0, "retract_timeout_s": 3.0},
    }
    for name, values in sections.items():
        fast[name] = {**fast.get(name, {}), **values}
    return with_changes(testbed.hardware_config(), **fast)


@pytest.fixture
def testbed() -> Iterator[SimulatedTestbed]:
    tb = _testbed()
    yield tb
    tb.close()


@pytest.fixture
def backend(testbed: SimulatedTestbed) -> Iterator[HardwareBackend]:
    hw = HardwareBackend(_config(testbed))
    yield hw
    hw.close()


def _move(backend: HardwareBackend, arm: str, q: np.ndarray, timeout_s: float = 3.0) -> float:
    """Command q and advance until the arm is there; returns the time it took (s)."""
    t0 = time.monotonic()
    backend.command_joints(arm, q)
    while np.max(np.abs(backend.read().joints[arm] - q)) > 1e-6:
        assert time.monotonic() - t0 < timeout_s, "arm did not arrive"
        backend.advance(0.01)
    return time.monotonic() - t0


def _reads_ok(backend: HardwareBackend) -> Callable[[], bool]:
    def ok() -> bool:
        try:
            backend.read()
        except BackendError:
            return False
        return True

    return ok


def test_reads_every_channel_from_the_devices(backend: HardwareBackend) -> None:
    assert isinstance(backend, Backend)
    first = backend.read()
    backend.advance(0.02)
    second = backend.read()
    assert second.time_s >= first.time_s + 0.02
    assert set(second.joints) == {"left", "right"}
    np.testing.assert_array_equal(second.joints["right"], np.zeros(7))
    np.testing.assert_allclose(second.wrench, REST_WRENCH)
    np.testing.assert_array_equal(second.electrodes, REST_ELECTRODES)
    assert second.pdc == REST_PDC
    assert backend.status()["biotac_info"][1]["serial"].startswith("BT")


def test_moves_at_the_configured_speed_and_refuses_bad_targets(backend: HardwareBackend) -> None:
    q = np.array([0.01, -0.05, 0.05, 0.05, -0.05, 0.05, -0.05])
    took = _move(backend, "right", q)
    assert took >= 0.05 / backend.config.egm.max_speed * 0.9
    with pytest.raises(BackendError, match=r"joint 2 \(ABB axis 2\) = 1.0000 rad is outside its limits \[-2.5046"):
        backend.command_joints("left", np.array([0, 1.0, 0, 0, 0, 0, 0]))
    with pytest.raises(BackendError, match="7 finite numbers"):
        backend.command_joints("left", np.array([0, np.nan, 0, 0, 0, 0, 0]))
    with pytest.raises(BackendError, match="7 finite numbers"):
        backend.command_joints("left", np.zeros(6))
    with pytest.raises(ValueError, match="unknown arm"):
        backend.command_joints("middle", np.zeros(7))
    backend.advance(0.05)
    np.testing.assert_allclose(backend.read().joints["right"], q)  # refused targets changed nothing


def test_force_limit_stops_and_retracts_to_the_last_contact_free_pose(backend: HardwareBackend) -> None:
    free = np.array([0.01, 0, 0, 0, 0, 0, 0])
    _move(backend, "left", free)
    backend.command_joints("left", np.array([0.2, 0, 0, 0, 0, 0, 0]))  # would press 36 N
    with pytest.raises(BackendError, match="force limit 3 N exceeded.*retracted.*trajectory incomplete"):
        for _ in range(200):
            backend.advance(0.01)
    sample = backend.read()
    np.testing.assert_allclose(sample.joints["left"], free, atol=1e-3)
    np.testing.assert_allclose(sample.wrench, REST_WRENCH)
    peak = STIFFNESS * (0.2 - CONTACT)
    assert peak > 10 * backend.config.safety.force_limit_n  # the arm was stopped long before the target
    backend.advance(0.05)  # after the retract the backend works normally


def test_watchdog_flags_a_dead_force_sensor(testbed: SimulatedTestbed, backend: HardwareBackend) -> None:
    testbed.kms40.close()
    with pytest.raises(BackendError, match="KMS40 F/T data is stale.*trajectory incomplete"):
        backend.advance(2.0)
    with pytest.raises(BackendError, match="stale"):
        backend.read()


def test_egm_stopping_cuts_the_trajectory(testbed: SimulatedTestbed, backend: HardwareBackend) -> None:
    backend.command_joints("left", np.array([0.01, 0, 0, 0, 0, 0, 0]))
    RwsClient("127.0.0.1", testbed.rws.port, timeout_s=2.0).stop_rapid()
    with pytest.raises(BackendError, match="EGM (left|right) data is stale.*trajectory incomplete"):
        backend.advance(2.0)


def test_recovers_when_sensors_disconnect_mid_stream(testbed: SimulatedTestbed, backend: HardwareBackend) -> None:
    testbed.kms40.disconnect_all()
    testbed.biotac_bridge.disconnect_all()
    assert wait_for(lambda: backend.status()["kms40"].get("reconnects") == 1, 10.0)
    assert wait_for(lambda: backend.status()["biotac"].get("reconnects") == 1, 10.0)
    assert wait_for(_reads_ok(backend), 10.0)
    np.testing.assert_allclose(backend.read().wrench, REST_WRENCH)


def test_lossy_slow_egm_and_garbage_datagrams_are_survived() -> None:
    with _testbed(egm_loss=0.2, egm_delay_s=0.003) as testbed:
        backend = HardwareBackend(_config(testbed))
        try:
            port = testbed.egm_ports["right"]
            with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as rogue:
                for junk in (b"\x00" * 10, b"\xff" * 3000, b"\x0a\x05\x08"):
                    rogue.sendto(junk, ("127.0.0.1", port))
            _move(backend, "right", np.full(7, 0.02))
            stats = backend.status()["egm"]["right"]
            assert stats["lost"] > 0 and stats["foreign"] == 3 and "malformed" not in stats  # dropped unread
            assert sum(p.dropped for p in testbed.proxies.values()) > 0
        finally:
            backend.close()


def _port_free(port: int) -> bool:
    with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as sock:
        try:
            sock.bind(("127.0.0.1", port))
        except OSError:
            return False
        return True


def test_open_failures_are_clear_and_release_everything(testbed: SimulatedTestbed) -> None:
    testbed.rws.opmode = "MANR"
    testbed.rws.ctrlstate = "motoroff"
    with pytest.raises(BackendError, match="RWS 403"):
        HardwareBackend(_config(testbed))
    testbed.rws.opmode = "AUTO"
    with pytest.raises(BackendError, match="no EgmRobot on UDP port"):
        HardwareBackend(_config(testbed, rws={"start_rapid": False}, egm={"startup_timeout_s": 0.2}))
    with pytest.raises(BackendError, match="no BioTac answers on slot 2"):
        HardwareBackend(_config(testbed, biotac={"select_mask": 0x02}))
    testbed.kms40.extra_flags = {"TEMP_FAULT"}
    with pytest.raises(BackendError, match="KMS40: the sensor reports TEMP_FAULT"):
        HardwareBackend(_config(testbed))
    assert all(_port_free(p) for p in testbed.egm_ports.values())


def test_swapped_egm_ports_are_caught_by_comparing_with_rws() -> None:
    with _testbed(joints0={"right": np.full(7, 0.1)}) as testbed:
        ports = testbed.egm_ports
        swapped = {"left_port": ports["right"], "right_port": ports["left"]}
        with pytest.raises(BackendError, match="EGM on port .* does not carry the left arm"):  # any robot port
            HardwareBackend(_config(testbed, egm={**swapped, "left_robot_port": 0, "right_robot_port": 0}))
        with pytest.raises(BackendError, match="datagrams from senders other than egm.robot_host"):  # its port
            HardwareBackend(_config(testbed, egm={**swapped, "startup_timeout_s": 0.3}))


def test_close_is_idempotent_and_stops_what_it_started(testbed: SimulatedTestbed, backend: HardwareBackend) -> None:
    assert testbed.rws.rapid_running
    backend.close()
    backend.close()
    assert not testbed.rws.rapid_running
    with pytest.raises(BackendError, match="closed"):
        backend.command_joints("left", np.zeros(7))


def test_config_files_round_trip_and_typos_are_errors(tmp_path) -> None:
    config = with_changes(HardwareConfig(), kms40={"port": 1001}, safety={"force_limit_n": 12.5})
    toml = tmp_path / "hw.toml"
    toml.write_text(config_to_toml(config))
    assert load_config(toml) == config
    js = tmp_path / "hw.json"
    js.write_text(json.dumps({"egm": {"left_port": 7000, "watchdog_s": 1}, "biotac": {"transport": "cheetah:1"}}))
    loaded = load_config(js)
    assert loaded.egm.left_port == 7000 and loaded.egm.watchdog_s == 1.0 and loaded.biotac.transport == "cheetah:1"
    assert loaded.rws == HardwareConfig().rws
    for bad, message in [
        ({"egm": {"left_prot": 1}}, "unknown key.*left_prot"),
        ({"robot": {}}, "unknown section.*robot"),
        ({"kms40": {"port": "1000"}}, "port must be int"),
        ({"rws": {"start_rapid": 1}}, "start_rapid must be bool"),
        ({"biotac": {"select_mask": 3}}, "select_mask must be 0x01, 0x02 or 0x04"),
        ({"biotac": {"transport": "usb"}}, "transport must be cheetah"),
        ({"safety": {"free_force_n": 50.0}}, "free_force_n < safety.force_limit_n"),
    ]:
        js.write_text(json.dumps(bad))
        with pytest.raises(ValueError, match=message):
            load_config(js)
    with pytest.raises(ValueError, match=".toml or .json"):
        load_config(tmp_path / "hw.yaml")


def test_the_campaign_controller_runs_unchanged_over_the_wire_protocols(backend: HardwareBackend) -> None:
    from twin.controller import execute
    from twin.protocol import ProtocolSettings, TrajectorySpec

    depths = np.array([-1e-3, 0.0, 1e-4, 2e-4])
    spec = TrajectorySpec(
        trajectory_id=0,
        indenter="sphere_small",
        point=np.zeros(3),
        angle=0.0,
        azimuth=0.0,
        touch_point=np.zeros(3),
        direction=np.array([0.0, 0.0, 1.0]),
        rotation=np.eye(3),
        depths=depths,
        increment=np.array([-1, 0, 1, 2]),
    )
    path = np.zeros((4, 7))
    path[:, 0] = CONTACT + 20.0 * depths  # 20 rad per m of depth: 2e-4 m -> 4 mrad past contact
    settings = ProtocolSettings(pause_s=0.05, speed=1e-2, sample_rate_hz=100.0)
    recording = execute(backend, spec, "left", path, settings)
    assert recording.complete, recording.message
    assert backend.tools["left"] == "sphere_small"
    last = [np.flatnonzero(recording.increment == k)[-1] for k in (0, 1, 2)]  # end of each settle pause
    np.testing.assert_allclose(recording.joints[last], path[1:], atol=1e-6)
    expected = np.array([contact_wrench(q) for q in recording.joints[last]])
    np.testing.assert_allclose(recording.wrench[last], expected, atol=1e-4)
    assert recording.wrench[last[-1], 2] == pytest.approx(REST_WRENCH[2] - STIFFNESS * 4e-3)
    assert np.all(np.diff(recording.time) > 0) and recording.electrodes.shape[1] == 19
