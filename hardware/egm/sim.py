"""A simulated YuMi arm on the controller side of EGM: streams `EgmRobot` every 4 ms, follows `EgmSensor`.

While streaming (RAPID running), each cycle the arm moves toward the last valid joint target by at
most `velocity_limits * cycle_s` per joint, clamps to the position limits, and sends its feedback
(degrees, axis 7 in externalJoints[0]) to the sensor address. Only that address (host and port) is
the registered peer: datagrams from any other sender are counted (`foreign`) and ignored, whatever
their sequence number. Replies that are garbage, oversized, carry no joints, or are not newer than
the last accepted one are counted and ignored. `joints` is the arm's current configuration (rad,
chain order) for whoever drives a twin from it.
"""

from __future__ import annotations

import socket
import threading
import time
from collections import Counter

import numpy as np

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

EGM_CYCLE_S = 0.004


class SimEgmArm:
    """One arm's EGM stream from a simulated controller, sending to `sensor_addr` from an ephemeral port."""

    def __init__(
        self,
        arm: str,
        sensor_addr: tuple[str, int],
        joints0: np.ndarray,
        position_limits: np.ndarray,
        velocity_limits: np.ndarray,
        cycle_s: float = EGM_CYCLE_S,
    ) -> None:
        self.arm = arm
        self.sensor_addr = sensor_addr
        self._peer = (socket.gethostbyname(sensor_addr[0]), sensor_addr[1])
        self.cycle_s = cycle_s
        self.limits = np.asarray(position_limits, dtype=float)
        self.max_step = np.asarray(velocity_limits, dtype=float) * cycle_s
        self.stats: Counter[str] = Counter()
        self._joints = np.clip(np.asarray(joints0, dtype=float), self.limits[:, 0], self.limits[:, 1])
        self._target = self._joints.copy()
        self._lock = threading.Lock()
        self._streaming = threading.Event()
        self._stop = threading.Event()
        self._seq = 0
        self._last_reply_seq: int | None = None
        self._t0 = time.monotonic()
        self._sock = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
        self._sock.bind((sensor_addr[0], 0))
        self._thread = threading.Thread(target=self._run, name=f"egm-sim-{arm}", daemon=True)
        self._thread.start()

    @property
    def port(self) -> int:
        """The UDP port the arm sends from (what the sensor sees as the robot's port)."""
        return self._sock.getsockname()[1]

    @property
    def joints(self) -> np.ndarray:
        """Current joints (rad, chain order 1-2-7-3-4-5-6)."""
        with self._lock:
            return self._joints.copy()

    def start_streaming(self) -> None:
        """Begin sending EgmRobot every cycle (what EGMRunJoint does when RAPID starts)."""
        with self._lock:
            self._target = self._joints.copy()
            self._last_reply_seq = None
        self._streaming.set()

    def stop_streaming(self) -> None:
        """Stop sending; the arm stays where it is."""
        self._streaming.clear()

    def close(self) -> None:
        """Stop the stream thread and release the socket; safe to call twice."""
        self._stop.set()
        self._thread.join(timeout=1.0)
        self._sock.close()

    def _run(self) -> None:
        next_tick = time.monotonic()
        while not self._stop.is_set():
            if not self._streaming.wait(timeout=0.02):
                next_tick = time.monotonic()
                continue
            self._step()
            self._send()
            next_tick += self.cycle_s
            self._receive_until(next_tick)
            if time.monotonic() - next_tick > 10 * self.cycle_s:  # fell far behind (paused process)
                next_tick = time.monotonic()

    def _step(self) -> None:
        with self._lock:
            move = np.clip(self._target - self._joints, -self.max_step, self.max_step)
            self._joints = np.clip(self._joints + move, self.limits[:, 0], self.limits[:, 1])

    def _send(self) -> None:
        self._seq = (self._seq + 1) & 0xFFFFFFFF
        msg = EgmRobot()
        msg.header.seqno = self._seq
        msg.header.tm = int((time.monotonic() - self._t0) * 1e3) & 0xFFFFFFFF
        msg.header.mtype = EgmHeader.MSGTYPE_DATA
        with self._lock:
            set_joints(msg.feedBack, self._joints)
            set_joints(msg.planned, self._target)
        msg.motorState.state = msg.motorState.MOTORS_ON
        msg.mciState.state = msg.mciState.MCI_RUNNING
        msg.rapidExecState.state = msg.rapidExecState.RAPID_RUNNING
        msg.mciConvergenceMet = True
        try:
            self._sock.sendto(msg.SerializeToString(), self.sensor_addr)
            self.stats["sent"] += 1
        except OSError:  # e.g. ICMP port unreachable while no sensor listens yet
            self.stats["send_errors"] += 1

    def _receive_until(self, deadline: float) -> None:
        while (remaining := deadline - time.monotonic()) > 0:
            self._sock.settimeout(remaining)
            try:
                data, sender = self._sock.recvfrom(MAX_DATAGRAM_BYTES + 1)
            except TimeoutError:
                return
            except OSError:
                self.stats["receive_errors"] += 1
                continue
            if sender != self._peer:
                self.stats["foreign"] += 1
                continue
            try:
                self._accept(parse_datagram(EgmSensor, data))
            except EgmMessageError:
                self.stats["malformed"] += 1

    def _accept(self, msg: EgmSensor) -> None:
        target = get_joints(msg.planned)
        seq = msg.header.seqno
        if self._last_reply_seq is not None and seq_newer(seq, self._last_reply_seq) <= 0:
            self.stats["out_of_order"] += 1
            return
        self._last_reply_seq = seq
        with self._lock:
            self._target = np.clip(target, self.limits[:, 0], self.limits[:, 1])
        self.stats["accepted"] += 1
