"""A simulated Weiss KMS40 F/T sensor on TCP: streams the wrench of a source callable, answers commands.

Commands: L1() / L0() (stream on / off, acknowledged `L1=1` / `L0=1`, no frame after the L0 ack),
F() (one frame), TARE(1|0), LDIV(n) (rate 500/n Hz), FLT(n), VL(n), LMASK({m1,...,m6}), SN(), ID(),
V(), T(), CALDATE(), FLAGS(). Unknown commands get `ERROR(1,UNKNOWN_COMMAND)`, bad arguments
`ERROR(2,INVALID_ARGUMENT)`, lines that are not `CMD(args)` or are too long `ERROR(3,SYNTAX)`.
Simulator choices (*unverified* on the device): FLT only sets the FILTER_ENABLED flag, channels masked
off by LMASK read 0, and a reading beyond the range sets the OVERRUN flag of its axis.
"""

from __future__ import annotations

import re
import socket
import threading
import time
from collections.abc import Callable

import numpy as np

from hardware.kms40.protocol import AXES, BASE_RATE_HZ, MAX_LINE_BYTES, encode_flags, format_frame
from hardware.tcp_server import TcpServer

WrenchSource = Callable[[], np.ndarray]
"""Returns the true (6,) wrench (N, N·m) in the sensor frame; called from the sensor's threads."""

_COMMAND = re.compile(r"(\w+)\((.*)\)")


class _BadArgument(ValueError):
    pass


class SimKms40(TcpServer):
    """KMS40 simulator on `host:port` (port 0 picks one) reading `wrench_source` at every frame."""

    def __init__(
        self,
        wrench_source: WrenchSource,
        host: str = "127.0.0.1",
        port: int = 1000,
        serial: str = "KMS40-SIM-0001",
        force_range_n: float = 120.0,
        torque_range_nm: float = 3.0,
    ) -> None:
        self.wrench_source = wrench_source
        self.serial = serial
        self.range = np.array([force_range_n] * 3 + [torque_range_nm] * 3)
        self.extra_flags: set[str] = set()
        """Status bits FLAGS() reports on top of the computed ones (fault injection, e.g. {"TEMP_FAULT"})."""
        self._connections: list[_Connection] = []
        self._t0 = time.monotonic()
        super().__init__(host, port, "kms40-sim")

    def timestamp(self) -> int:
        """Device time stamp: ms since the simulator started."""
        return int((time.monotonic() - self._t0) * 1e3)

    def send_raw(self, data: bytes) -> None:
        """Write `data` as is to every client, between whole lines (fault injection: garbage, oversize)."""
        for conn in list(self._connections):
            conn.send_bytes(data)

    def disconnect_all(self) -> None:
        """Drop every client connection (as a power glitch or cable pull would); keep listening."""
        for conn in list(self._connections):
            conn.close()

    def _on_client(self, sock: socket.socket) -> None:
        self._connections = [c for c in self._connections if c.alive] + [_Connection(self, sock)]


class _Connection:
    """One client: a command thread and a streaming thread sharing the socket's write side."""

    def __init__(self, device: SimKms40, sock: socket.socket) -> None:
        self.device = device
        self.sock = sock
        self.alive = True
        self.streaming = False
        self.ldiv = 1
        self.filter_id = 0
        self.verbosity = 0
        self.mask = np.ones(6)
        self.tare = np.zeros(6)
        self.tared = False
        self._write_lock = threading.RLock()  # re-entered by the stream thread
        threading.Thread(target=self._commands, name="kms40-sim-cmd", daemon=True).start()
        threading.Thread(target=self._stream, name="kms40-sim-stream", daemon=True).start()

    def close(self) -> None:
        self.alive = False
        try:
            self.sock.shutdown(socket.SHUT_RDWR)
        except OSError:
            pass
        self.sock.close()

    def send_bytes(self, data: bytes) -> None:
        with self._write_lock:
            if self.alive:
                try:
                    self.sock.sendall(data)
                except OSError:
                    self.alive = False

    def _send(self, line: str) -> None:
        self.send_bytes(line.encode() + b"\n")

    def _raw(self) -> np.ndarray:
        return np.asarray(self.device.wrench_source(), dtype=float).reshape(6)

    def _frame(self) -> str:
        return format_frame((self._raw() - self.tare) * self.mask, self.device.timestamp())

    def _stream(self) -> None:
        next_t = time.monotonic()
        while self.alive:
            next_t += self.ldiv / BASE_RATE_HZ
            time.sleep(max(0.0, next_t - time.monotonic()))
            with self._write_lock:  # decide and write atomically, so no frame follows an L0 ack
                if self.streaming:
                    self.send_bytes(self._frame().encode() + b"\n")
            if time.monotonic() - next_t > 0.1:
                next_t = time.monotonic()

    def _commands(self) -> None:
        buffer = b""
        while self.alive:
            try:
                chunk = self.sock.recv(4096)
            except OSError:
                break
            if not chunk:
                break
            buffer += chunk
            *lines, buffer = buffer.split(b"\n")
            if len(buffer) > MAX_LINE_BYTES:
                buffer = b""
                self._send("ERROR(3,SYNTAX)")
            for raw in lines:
                self._send(self._answer(raw.decode(errors="replace").strip()))
        self.close()

    def _answer(self, line: str) -> str:
        m = _COMMAND.fullmatch(line)
        if m is None or len(line) > MAX_LINE_BYTES:
            return "ERROR(3,SYNTAX)"
        name, arg = m[1], m[2].strip()
        handler = getattr(self, f"_cmd_{name}", None)
        if handler is None:
            return "ERROR(1,UNKNOWN_COMMAND)"
        try:
            return f"{name}={handler(arg)}"
        except _BadArgument:
            return "ERROR(2,INVALID_ARGUMENT)"

    @staticmethod
    def _int(arg: str, lo: int, hi: int) -> int:
        try:
            value = int(arg)
        except ValueError as exc:
            raise _BadArgument(arg) from exc
        if not lo <= value <= hi:
            raise _BadArgument(arg)
        return value

    def _cmd_L1(self, arg: str) -> str:  # noqa: N802 (device command names)
        with self._write_lock:
            self.streaming = True
        return "1"

    def _cmd_L0(self, arg: str) -> str:  # noqa: N802
        with self._write_lock:
            self.streaming = False
        return "1"

    def _cmd_F(self, arg: str) -> str:  # noqa: N802
        return self._frame()[2:]

    def _cmd_TARE(self, arg: str) -> str:  # noqa: N802
        self.tared = bool(self._int(arg, 0, 1))
        self.tare = self._raw() if self.tared else np.zeros(6)
        return arg

    def _cmd_LDIV(self, arg: str) -> str:  # noqa: N802
        self.ldiv = self._int(arg, 1, 1000)
        return str(self.ldiv)

    def _cmd_FLT(self, arg: str) -> str:  # noqa: N802
        self.filter_id = self._int(arg, 0, 9)
        return str(self.filter_id)

    def _cmd_VL(self, arg: str) -> str:  # noqa: N802
        self.verbosity = self._int(arg, 0, 9)
        return str(self.verbosity)

    def _cmd_LMASK(self, arg: str) -> str:  # noqa: N802
        m = re.fullmatch(r"\{([01]),([01]),([01]),([01]),([01]),([01])\}", arg.replace(" ", ""))
        if m is None:
            raise _BadArgument(arg)
        self.mask = np.array([float(v) for v in m.groups()])
        return "{" + ",".join(m.groups()) + "}"

    def _cmd_SN(self, arg: str) -> str:  # noqa: N802
        return self.device.serial

    def _cmd_ID(self, arg: str) -> str:  # noqa: N802
        return "KMS40"

    def _cmd_V(self, arg: str) -> str:  # noqa: N802
        return "1.0.0-sim"

    def _cmd_T(self, arg: str) -> str:  # noqa: N802
        return "25.0"

    def _cmd_CALDATE(self, arg: str) -> str:  # noqa: N802
        return "2019-01-01"

    def _cmd_FLAGS(self, arg: str) -> str:  # noqa: N802
        flags = {"CALIB_VALID", "STABLE"} | self.device.extra_flags
        flags |= {"TARA"} if self.tared else set()
        flags |= {"FILTER_ENABLED"} if self.filter_id else set()
        flags |= {"DAQ_RUNNING"} if self.streaming else set()
        overrun = np.abs(self._raw()) > self.device.range
        flags |= {f"OVERRUN_{axis}" for axis, hit in zip(AXES, overrun, strict=True) if hit}
        return str(encode_flags(flags))
