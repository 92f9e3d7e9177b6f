"""The PC side of EGM for one arm: receive `EgmRobot`, answer `EgmSensor` with a joint target.

The robot controller sends one `EgmRobot` datagram every 4 ms to this link's port; each valid one is
answered at once, to its sender, with the current joint setpoint. The setpoint walks toward the goal
set by `set_goal` at no more than `max_speed` (rad/s per joint), so a far goal becomes a smooth
speed-limited motion. Before the first goal the link holds the robot where it is.

Only the configured robot may speak: a datagram from any other address (or, when the robot's port
is given, any other port) is dropped unread, counted in `stats["foreign"]` and never answered, so a
stranger can neither feed forged joints or motor states to the safety logic nor learn the
setpoints. The link listens on one interface: the configured one, or with "auto" the one that
routes to the robot.

Bad datagrams (garbage, truncated, oversized, missing joints) and old or repeated sequence numbers
are counted in `stats` and never answered; a sequence number far behind the last one, or any older
one after a pause in traffic, is taken as a restart of EGM on the controller.
"""

from __future__ import annotations

import socket
import threading
import time
from collections import Counter
from dataclasses import dataclass

import numpy as np

from hardware.config import AUTO_BIND
from hardware.egm.protocol import (
    MAX_DATAGRAM_BYTES,
    EgmHeader,
    EgmMessageError,
    EgmRobot,
    EgmSensor,
    get_joints,
    parse_datagram,
    seq_newer,
    set_joints,
)
from hardware.stamped import Latest

RESTART_WINDOW = 1000  # a seqno this far behind the last one means EGM restarted on the controller
RESTART_GAP_S = 0.2  # so does any older seqno after this long without a message (UDP reorders within ms)
_MAX_STEP_S = 0.012  # setpoint advance is capped at 3 cycles, so a gap in traffic never makes a jump


@dataclass(frozen=True)
class RobotState:
    """One valid `EgmRobot` message, in SI: measured joints (rad, chain order) and controller states."""

    seqno: int
    joints: np.ndarray
    motors_on: bool
    mci_running: bool
    rapid_running: bool


def interface_toward(host: str) -> str:
    """This machine's IPv4 address on the interface that routes to `host` (nothing is sent)."""
    with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as probe:
        probe.connect((host, 9))  # UDP connect only picks the route
        return probe.getsockname()[0]


class EgmArmLink:
    """EGM sensor endpoint for one arm, bound to `host:port` (port 0 picks a free one; host "auto":
    the interface facing the robot), hearing only `robot` = (address, port; port 0 = any of its ports)."""

    def __init__(self, arm: str, host: str, port: int, max_speed: np.ndarray, robot: tuple[str, int]) -> None:
        self.arm = arm
        self.max_speed = np.asarray(max_speed, dtype=float)
        self.state: Latest[RobotState] = Latest(f"EGM {arm}")
        self.stats: Counter[str] = Counter()
        self._sock = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
        try:
            self.robot = (socket.gethostbyname(robot[0]), robot[1])
            self._sock.bind((interface_toward(self.robot[0]) if host == AUTO_BIND else host, port))
        except OSError as exc:
            self._sock.close()
            raise OSError(f"EGM {arm}: cannot listen on {host}:{port} for the robot at {robot[0]}: {exc}") from exc
        self._sock.settimeout(0.02)  # how soon close() is noticed
        self._lock = threading.Lock()
        self._goal: np.ndarray | None = None
        self._setpoint: np.ndarray | None = None
        self._last_reply = 0.0
        self._last_seq: int | None = None
        self._tx_seq = 0
        self._t0 = time.monotonic()
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._run, name=f"egm-link-{arm}", daemon=True)
        self._thread.start()

    @property
    def address(self) -> tuple[str, int]:
        """The (address, UDP port) this link listens on."""
        return self._sock.getsockname()

    @property
    def port(self) -> int:
        """The UDP port this link listens on."""
        return self.address[1]

    def set_goal(self, q: np.ndarray) -> None:
        """Move toward joints `q` (rad, chain order) at no more than `max_speed`; no limit checks here."""
        with self._lock:
            self._goal = np.array(q, dtype=float)

    def hold(self) -> None:
        """Stop: make the last measured joints the goal and the setpoint (no further motion)."""
        with self._lock:
            if self.state.count:
                here = self.state.get(float("inf")).joints
                self._goal, self._setpoint = here.copy(), here.copy()

    def close(self) -> None:
        """Stop answering and release the port; safe to call twice."""
        self._stop.set()
        self._thread.join(timeout=1.0)
        self._sock.close()

    def _run(self) -> None:
        while not self._stop.is_set():
            try:
                data, _, flags, sender = self._sock.recvmsg(MAX_DATAGRAM_BYTES + 1)
            except TimeoutError:
                continue
            except OSError:
                self.stats["socket_errors"] += 1
                continue
            if not self._from_robot(sender):
                self.stats["foreign"] += 1
                continue
            try:
                if flags & socket.MSG_TRUNC:
                    raise EgmMessageError("oversized EGM datagram")
                robot = self._accept(parse_datagram(EgmRobot, data))
            except EgmMessageError:
                self.stats["malformed"] += 1
                continue
            if robot is not None:
                self._reply(robot, sender)

    def _from_robot(self, sender: tuple[str, int]) -> bool:
        host, port = self.robot
        return sender[0] == host and port in (0, sender[1])

    def _accept(self, msg: EgmRobot) -> RobotState | None:
        """Validate one message (joints, then sequence number); None for an old or repeated one."""
        if not msg.HasField("header") or not msg.header.HasField("seqno"):
            raise EgmMessageError("EgmRobot without header.seqno")
        seq = msg.header.seqno
        joints = get_joints(msg.feedBack)
        if self._last_seq is not None:
            ahead = seq_newer(seq, self._last_seq)
            restarted = -ahead >= RESTART_WINDOW or self.state.age() > RESTART_GAP_S
            if ahead <= 0 and not restarted:
                self.stats["out_of_order"] += 1
                return None
            if ahead <= 0:
                self.stats["restarts"] += 1
            elif ahead > 1:
                self.stats["lost"] += ahead - 1
        robot = RobotState(
            seqno=seq,
            joints=joints,
            motors_on=msg.motorState.state == msg.motorState.MOTORS_ON,
            mci_running=msg.mciState.state == msg.mciState.MCI_RUNNING,
            rapid_running=msg.rapidExecState.state == msg.rapidExecState.RAPID_RUNNING,
        )
        self._last_seq = seq
        self.stats["received"] += 1
        self.state.put(robot)
        return robot

    def _reply(self, robot: RobotState, sender: tuple[str, int]) -> None:
        now = time.monotonic()
        with self._lock:
            if self._goal is None:
                self._goal = robot.joints.copy()
            if self._setpoint is None:
                self._setpoint = robot.joints.copy()
            dt = min(now - self._last_reply, _MAX_STEP_S)
            step = np.clip(self._goal - self._setpoint, -self.max_speed * dt, self.max_speed * dt)
            self._setpoint = self._setpoint + step
            setpoint = self._setpoint.copy()
            self._last_reply = now
        self._tx_seq += 1
        msg = EgmSensor()
        msg.header.seqno = self._tx_seq
        msg.header.tm = int((now - self._t0) * 1e3) & 0xFFFFFFFF
        msg.header.mtype = EgmHeader.MSGTYPE_CORRECTION
        set_joints(msg.planned, setpoint)
        try:
            self._sock.sendto(msg.SerializeToString(), sender)
            self.stats["replied"] += 1
        except OSError:
            self.stats["socket_errors"] += 1
