"""All simulated devices of the testbed at once, on loopback, and the config that reaches them.

`SimulatedTestbed` runs two EGM arms, the RWS server (starting RAPID starts the arms' EGM streams),
the KMS40 and a BioTac on an SPI bus behind a TCP bridge. The sensors read two plain callables:

- `wrench_source() -> (6,)`: the F/T reading (N, N·m, sensor frame, untared);
- `electrode_source() -> ((19,), pdc)`: raw electrode and PDC counts;

and the arms' joints are `testbed.arms[arm].joints` (rad, chain order). By default the sources are
constants (`rest_wrench`, `rest_electrodes`); `driven_testbed` hands them and the arms to a
`TestbedDriver` (the twin: `twin.loopback_rig.TwinSources`).
`hardware_config()` is the HardwareConfig that points `HardwareBackend` at these devices, and
tells its EGM links which ports the arms send from (the only senders they hear). On a wildcard
`host` (0.0.0.0) the devices listen on every interface, but the arms stream to, and the config
points at, this machine's loopback address.
"""

from __future__ import annotations

import socket
from collections.abc import Callable, Mapping
from typing import Protocol

import numpy as np

from assets.yumi import joint_limits, velocity_limits
from hardware.biotac.bridge import SpiBridgeServer
from hardware.biotac.protocol import SELECT_MASKS
from hardware.biotac.sim import ElectrodeSource, SimBioTac, SimBioTacBus
from hardware.config import HardwareConfig, with_changes
from hardware.egm.faults import UdpFaultProxy
from hardware.egm.sim import EGM_CYCLE_S, SimEgmArm
from hardware.kms40.sim import SimKms40, WrenchSource
from hardware.rws.protocol import MECHUNITS
from hardware.rws.sim import SimRwsServer
from twin.backend import ARMS

DEFAULT_BIOTAC_BRIDGE_PORT = 6540
WILDCARD, LOOPBACK = "0.0.0.0", "127.0.0.1"
REST_WRENCH = np.array([0.0, 0.0, -1.18, 0.0, 0.0, 0.0])  # the mounted BioTac's weight (~0.12 kg), N and N·m
REST_ELECTRODES = np.full(19, 3000.0)  # counts, mid-range of a BioTac at rest (unit-specific in reality)
REST_PDC = 2000.0  # counts


def rest_wrench() -> np.ndarray:
    """Constant F/T reading: the mount's weight only."""
    return REST_WRENCH.copy()


def rest_electrodes() -> tuple[np.ndarray, float]:
    """Constant BioTac reading at rest: (19 electrode counts, PDC counts)."""
    return REST_ELECTRODES.copy(), REST_PDC


def free_udp_port(host: str) -> int:
    """A UDP port on `host` that nothing is bound to right now."""
    with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as sock:
        sock.bind((host, 0))
        return sock.getsockname()[1]


class TestbedDriver(Protocol):
    """What drives the simulated sensors from the simulated arms (e.g. `twin.loopback_rig.TwinSources`)."""

    def wrench(self) -> np.ndarray:
        """(6,) F/T reading (N, N·m), sensor frame, untared."""
        ...

    def electrodes(self) -> tuple[np.ndarray, float]:
        """((19,) electrode counts, PDC counts)."""
        ...

    def home_joints(self) -> dict[str, np.ndarray]:
        """arm -> (7,) rad, chain order: where the arms start."""
        ...

    def follow(self, arms: Mapping[str, SimEgmArm]) -> None:
        """Start following the arms' `.joints` (rad) in a thread of its own."""
        ...

    def close(self) -> None:
        """Stop following."""
        ...


class SimulatedTestbed:
    """Simulated YuMi (EGM + RWS), KMS40 and BioTac on `host`; a port of 0 picks a free one.

    `egm_ports` are where the arms send EgmRobot, i.e. the ports `HardwareBackend` listens on. With
    `egm_loss` / `egm_delay_s` each arm's datagrams pass a UdpFaultProxy (both directions).
    """

    def __init__(
        self,
        wrench_source: WrenchSource = rest_wrench,
        electrode_source: ElectrodeSource = rest_electrodes,
        host: str = "127.0.0.1",
        rws_port: int = 80,
        kms40_port: int = 1000,
        egm_ports: tuple[int, int] = (6511, 6512),
        biotac_port: int = DEFAULT_BIOTAC_BRIDGE_PORT,
        joints0: dict[str, np.ndarray] | None = None,
        biotac_slot: int = 1,
        egm_loss: float = 0.0,
        egm_delay_s: float = 0.0,
        egm_cycle_s: float = EGM_CYCLE_S,
    ) -> None:
        self.host = host
        self.local_host = LOOPBACK if host == WILDCARD else host
        """Where a backend on this machine reaches the devices (loopback when `host` is the wildcard)."""
        self.biotac_slot = biotac_slot
        self.egm_ports = dict(zip(ARMS, (p or free_udp_port(self.local_host) for p in egm_ports), strict=True))
        self.proxies: dict[str, UdpFaultProxy] = {}
        self.arms: dict[str, SimEgmArm] = {}
        self._closers: list[Callable[[], None]] = []
        try:
            for arm in ARMS:
                dest = self.egm_ports[arm]
                if egm_loss or egm_delay_s:
                    proxy = UdpFaultProxy(
                        (self.local_host, dest), egm_loss, egm_delay_s, seed=ARMS.index(arm), host=self.local_host
                    )
                    self._closers.append(proxy.close)
                    self.proxies[arm], dest = proxy, proxy.port
                q0 = (joints0 or {}).get(arm, np.zeros(7))
                self.arms[arm] = SimEgmArm(
                    arm, (self.local_host, dest), q0, joint_limits(arm), velocity_limits(arm), cycle_s=egm_cycle_s
                )
                self._closers.append(self.arms[arm].close)
                if arm in self.proxies:
                    self.proxies[arm].client = (self.local_host, self.arms[arm].port)
            self.rws = SimRwsServer(
                {MECHUNITS[arm]: self._joints_of(arm) for arm in ARMS},
                host,
                rws_port,
                on_rapid_start=self._start_egm,
                on_rapid_stop=self._stop_egm,
            )
            self._closers.append(self.rws.close)
            self.kms40 = SimKms40(wrench_source, host, kms40_port)
            self._closers.append(self.kms40.close)
            self.biotac = SimBioTac(electrode_source)
            self.biotac_bus = SimBioTacBus({biotac_slot: self.biotac})
            self.biotac_bridge = SpiBridgeServer(self.biotac_bus, host, biotac_port)
            self._closers.append(self.biotac_bridge.close)
        except BaseException:
            self.close()
            raise

    def _joints_of(self, arm: str) -> Callable[[], np.ndarray]:
        return lambda: self.arms[arm].joints

    def _start_egm(self) -> None:
        for arm in self.arms.values():
            arm.start_streaming()

    def _stop_egm(self) -> None:
        for arm in self.arms.values():
            arm.stop_streaming()

    def hardware_config(self, base: HardwareConfig | None = None, watchdog_s: float | None = None) -> HardwareConfig:
        """`base` (default: the real testbed's config) with every address and port pointing here.

        watchdog_s: if given, the stale-data limit (s) of every stream (EGM, F/T, BioTac).
        """
        host = self.local_host
        config = base or HardwareConfig()
        if watchdog_s is not None:
            wide = {"watchdog_s": watchdog_s}
            config = with_changes(config, egm=wide, kms40=wide, biotac=wide)
        return with_changes(
            config,
            rws={"host": host, "port": self.rws.port},
            egm={
                "bind_host": host,
                "left_port": self.egm_ports["left"],
                "right_port": self.egm_ports["right"],
                "robot_host": host,
                "left_robot_port": self.robot_port("left"),
                "right_robot_port": self.robot_port("right"),
            },
            kms40={"host": host, "port": self.kms40.port},
            biotac={
                "transport": f"tcp://{host}:{self.biotac_bridge.port}",
                "select_mask": SELECT_MASKS[self.biotac_slot],
            },
        )

    def robot_port(self, arm: str) -> int:
        """The UDP port `arm`'s EGM reaches the backend from: the arm's own, or its fault proxy's."""
        return self.proxies[arm].source_port if arm in self.proxies else self.arms[arm].port

    def add_closer(self, close: Callable[[], None]) -> None:
        """Also call `close` when the testbed closes, before the devices stop (e.g. a twin driving them)."""
        self._closers.append(close)

    def close(self) -> None:
        """Stop every device; safe to call twice."""
        while self._closers:
            self._closers.pop()()

    def __enter__(self) -> SimulatedTestbed:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()


def driven_testbed(driver: TestbedDriver, **testbed_options: object) -> SimulatedTestbed:
    """A `SimulatedTestbed` whose arms start at `driver.home_joints()` and whose sensors stream `driver`'s readings.

    The driver follows the arms at once; closing the testbed stops it too. `testbed_options` are
    `SimulatedTestbed`'s (host, ports, EGM faults).
    """
    testbed = SimulatedTestbed(driver.wrench, driver.electrodes, joints0=driver.home_joints(), **testbed_options)
    testbed.add_closer(driver.close)
    try:
        driver.follow(testbed.arms)
    except BaseException:
        testbed.close()
        raise
    return testbed
