"""HardwareBackend: the `twin.backend.Backend` of the real testbed (YuMi EGM + RWS, KMS40, BioTac).

Opening it connects the F/T sensor that `[ft] sensor` names (through `hardware.ft_sensor`: checked,
untared, streaming; the KMS40 on the testbed), identifies and starts sampling the BioTac,
listens for EGM on one UDP port per arm, starts RAPID over RWS (whose program runs EGMRunJoint on
both tasks) and waits for every stream's first message. From then on the device threads stream on
their own; this object only steers and checks:

- `command_joints` refuses targets outside the joint limits (assets.yumi) and sets the EGM goal,
  which the arm approaches at `egm.max_speed` (rad/s).
- `advance(dt)` waits `dt` seconds in real time, checking every `safety.poll_s` that each stream is
  fresh (watchdogs), that EGM still runs on the controller, and that the F/T force has not changed by
  more than `safety.force_limit_n` since opening. A force-limit trip holds both arms, drives them
  back to their last contact-free poses, and raises BackendError; any fault holds the arms and raises
  BackendError. The message says the trajectory is incomplete, so the controller marks it so.
- `read()` returns the newest reading of every channel, or BackendError when one is stale.
"""

from __future__ import annotations

import time
from pathlib import Path

import numpy as np

from assets.yumi import joint_limits, velocity_limits
from hardware.biotac.client import BioTacError, BioTacReader
from hardware.biotac.protocol import Frame, slots
from hardware.biotac.transport import open_transport
from hardware.config import HardwareConfig, load_config
from hardware.egm.client import EgmArmLink
from hardware.ft_sensor import ForceTorqueSensor, FtSensorConfig, FtSensorError
from hardware.rws.client import RwsClient, RwsError
from hardware.stamped import Latest, StaleDataError, wait_for
from twin.backend import ARMS, BackendError, Sample, check_arm

PORT_CHECK_RAD = 0.01  # EGM and RWS joints of one arm at rest agree to better than this (rad)
ARRIVED_RAD = 1e-3  # a retract counts as done when every joint is this close (rad) to its goal
CHAIN_AXES = (1, 2, 7, 3, 4, 5, 6)  # ABB axis number of each chain index, for messages
INCOMPLETE = "arms stopped; trajectory incomplete"


class HardwareBackend:
    """The real testbed behind the Backend interface; open with a HardwareConfig (or `from_file`)."""

    def __init__(self, config: HardwareConfig) -> None:
        self.config = config
        self.tools: dict[str, str | None] = dict.fromkeys(ARMS)
        self._links: dict[str, EgmArmLink] = {}
        self._ft: ForceTorqueSensor | None = None
        self._biotac: BioTacReader | None = None
        self._rws: RwsClient | None = None
        self._rapid_started = False
        self._closed = False
        try:
            self._open()
        except (FtSensorError, BioTacError, RwsError, StaleDataError, OSError) as exc:
            self.close()
            raise BackendError(f"cannot open the hardware backend: {exc}") from exc
        except BaseException:
            self.close()
            raise

    @classmethod
    def from_file(cls, path: str | Path) -> HardwareBackend:
        """Open the backend described by a TOML/JSON config file."""
        return cls(load_config(path))

    def _open(self) -> None:
        c = self.config
        self._ft = self._ft_config.open()
        self._biotac = BioTacReader(
            lambda: open_transport(c.biotac.transport, c.biotac.bitrate_khz),
            c.biotac.select_mask,
            c.biotac.bitrate_khz,
            c.biotac.reconnect_s,
        )
        ports = {"left": c.egm.left_port, "right": c.egm.right_port}
        robot_ports = {"left": c.egm.left_robot_port, "right": c.egm.right_robot_port}
        for arm in ARMS:
            speed = np.minimum(c.egm.max_speed, velocity_limits(arm))
            robot = (c.egm.robot_host, robot_ports[arm])
            self._links[arm] = EgmArmLink(arm, c.egm.bind_host, ports[arm], speed, robot)
        self._rws = RwsClient(c.rws.host, c.rws.port, c.rws.user, c.rws.password, c.rws.timeout_s)
        if c.rws.start_rapid and not self._rws.rapid_running():
            if self._rws.ctrlstate() != "motoron":
                self._rws.set_motors(True)
            self._rws.start_rapid()
            self._rapid_started = True
        for arm, link in self._links.items():
            try:
                link.state.wait(c.egm.startup_timeout_s)
            except StaleDataError as exc:
                foreign = link.stats["foreign"]
                dropped = f" ({foreign} datagrams from senders other than egm.robot_host and its port dropped)"
                raise StaleDataError(
                    f"{exc}: no EgmRobot on UDP port {link.port} of {link.address[0]} - is RAPID running "
                    f"EGMRunJoint for {arm}, and does the controller's EGM (UDPUC) device point at this PC and "
                    f"port?{dropped if foreign else ''}"
                ) from exc
        self._check_arm_ports()
        self._ft.wrench.wait(self._ft_config.timeout_s)
        self._frames().wait(1.0)
        self._baseline = self._ft.wrench.get(self._ft_config.watchdog_s)[:3].copy()
        self._safe = {arm: self._measured(arm) for arm in ARMS}

    def _check_arm_ports(self) -> None:
        """EGM feedback must match RWS's joint target per arm: catches swapped or foreign EGM ports."""
        for arm in ARMS:
            egm, rws = self._measured(arm), self._rws.joints(arm)
            if np.max(np.abs(egm - rws)) > PORT_CHECK_RAD:
                raise StaleDataError(
                    f"EGM on port {self._links[arm].port} does not carry the {arm} arm: its joints "
                    f"{np.degrees(egm).round(2)} deg differ from RWS's {np.degrees(rws).round(2)} deg "
                    "(check egm.left_port / egm.right_port against the controller's UDPUC devices)"
                )

    # -- Backend ---------------------------------------------------------------------------------
    def attach_tool(self, arm: str, tool: str | None) -> None:
        """Record what is mounted on `arm` (the operator mounts it; nothing is sent to the robot)."""
        self.tools[check_arm(arm)] = tool

    def command_joints(self, arm: str, joints: np.ndarray) -> None:
        """Steer `arm` toward `joints` (rad, chain order); BackendError outside the limits or without EGM."""
        check_arm(arm)
        self._check_open()
        q = np.asarray(joints, dtype=float)
        if q.shape != (7,) or not np.all(np.isfinite(q)):
            raise BackendError(f"joint target for {arm} must be 7 finite numbers (rad), got {q!r}")
        limits = joint_limits(arm)
        outside = np.flatnonzero((q < limits[:, 0]) | (q > limits[:, 1]))
        if outside.size:
            i = outside[0]
            raise BackendError(
                f"joint target for {arm} refused: joint {i + 1} (ABB axis {CHAIN_AXES[i]}) = {q[i]:.4f} rad is "
                f"outside its limits [{limits[i, 0]:.4f}, {limits[i, 1]:.4f}]"
            )
        here = self._measured(arm)
        if self._force_change() < self.config.safety.free_force_n:
            self._safe[arm] = here
        self._links[arm].set_goal(q)

    def advance(self, dt: float) -> None:
        """Wait `dt` s in real time while the devices stream, checking force and watchdogs throughout."""
        if dt < 0:
            raise ValueError(f"dt must be >= 0, got {dt!r}")
        self._check_open()
        deadline = time.monotonic() + dt
        while True:
            self._check_safety()
            remaining = deadline - time.monotonic()
            if remaining <= 0:
                return
            time.sleep(min(self.config.safety.poll_s, remaining))

    def read(self) -> Sample:
        """The newest joints (both arms), wrench (untared) and BioTac frame; BackendError when one is stale."""
        self._check_open()
        c = self.config
        try:
            joints = {arm: self._measured(arm) for arm in ARMS}
            wrench = self._ft.wrench.get(self._ft_config.watchdog_s).copy()
            frame = self._frames().get(c.biotac.watchdog_s)
        except StaleDataError as exc:
            self._halt()
            raise BackendError(f"{exc}; {INCOMPLETE}") from exc
        return Sample(time.monotonic(), joints, wrench, frame.electrodes.astype(float), float(frame.pdc))

    def close(self) -> None:
        """Hold the arms, stop RAPID if this backend started it, and release every device; safe twice."""
        if self._closed:
            return
        self._closed = True
        self._halt()
        if self._rws is not None and self._rapid_started and self.config.rws.stop_rapid_on_close:
            try:
                self._rws.stop_rapid()
            except RwsError:
                pass
        if self._ft is not None:
            self._ft.close()
        if self._biotac is not None:
            self._biotac.close()
        for link in self._links.values():
            link.close()

    # -- diagnostics -----------------------------------------------------------------------------
    def status(self) -> dict:
        """Counters and identities of every device link (for `twin devices check` and logs).

        The F/T sensor's entries are named after its section: "kms40" and "kms40_info" on the testbed.
        """
        ft = self.config.ft.sensor
        return {
            "egm": {arm: dict(link.stats) for arm, link in self._links.items()},
            ft: dict(self._ft.stats) if self._ft else {},
            f"{ft}_info": dict(self._ft.info) if self._ft else {},
            "biotac": dict(self._biotac.stats) if self._biotac else {},
            "biotac_info": {slot: vars(info) for slot, info in self._biotac.info.items()} if self._biotac else {},
            "tools": dict(self.tools),
        }

    # -- internals -------------------------------------------------------------------------------
    def _check_open(self) -> None:
        if self._closed:
            raise BackendError("the hardware backend is closed")

    @property
    def _ft_config(self) -> FtSensorConfig:
        return self.config.ft_sensor

    def _frames(self) -> Latest[Frame]:
        return self._biotac.frames[slots(self.config.biotac.select_mask)[0]]

    def _measured(self, arm: str) -> np.ndarray:
        try:
            return self._links[arm].state.get(self.config.egm.watchdog_s).joints.copy()
        except StaleDataError as exc:
            self._halt()
            raise BackendError(f"{exc}; {INCOMPLETE}") from exc

    def _force_change(self) -> float:
        """|F - F_open| (N): how far the force moved from its value when the backend opened."""
        try:
            wrench = self._ft.wrench.get(self._ft_config.watchdog_s)
        except StaleDataError as exc:
            self._halt()
            raise BackendError(f"{exc}; {INCOMPLETE}") from exc
        return float(np.linalg.norm(wrench[:3] - self._baseline))

    def _halt(self) -> None:
        for link in self._links.values():
            link.hold()

    def _check_safety(self) -> None:
        sample = self.read()  # watchdogs on every stream
        for arm, link in self._links.items():
            state = link.state.get(float("inf"))
            if not (state.motors_on and state.mci_running and state.rapid_running):
                self._halt()
                raise BackendError(
                    f"EGM on the {arm} arm reports motors_on={state.motors_on}, mci_running={state.mci_running}, "
                    f"rapid_running={state.rapid_running}; {INCOMPLETE}"
                )
        force = float(np.linalg.norm(sample.wrench[:3] - self._baseline))
        if force > self.config.safety.force_limit_n:
            self._retract(force)

    def _retract(self, force: float) -> None:
        """Hold, go back to the last contact-free poses, and raise BackendError saying how it went."""
        self._halt()
        for arm, link in self._links.items():
            link.set_goal(self._safe[arm])
        arrived = wait_for(
            lambda: all(np.max(np.abs(self._measured(arm) - self._safe[arm])) < ARRIVED_RAD for arm in ARMS),
            self.config.safety.retract_timeout_s,
            self.config.safety.poll_s,
        )
        outcome = "retracted to the last contact-free pose" if arrived else "retract did NOT finish in time"
        raise BackendError(
            f"force limit {self.config.safety.force_limit_n:g} N exceeded (|dF| = {force:.2f} N): arms stopped and "
            f"{outcome} (|dF| now {self._force_change():.2f} N); trajectory incomplete"
        )
