"""Weiss KMS40 driver: TCP ASCII commands, frame streaming, and automatic reconnection.

One I/O thread owns the socket's read side. Stream frames (`F=...`) update `wrench`, a stamped
latest-value slot the backend's watchdog reads. Replies are matched to requests in order (the sensor
answers one line per command); `ERROR(code,text)` raises `Kms40Error` in the caller. Lines that are
garbage, too long or answer nothing are counted in `stats` and dropped. When the connection drops the
thread reconnects every `reconnect_s` and re-sends the settings made so far (tare, rate divider,
filter, ...) and L1 if streaming was on.
"""

from __future__ import annotations

import socket
import threading
from collections import Counter, deque
from dataclasses import dataclass, field

import numpy as np

from hardware.kms40.protocol import (
    FAULT_FLAGS,
    MAX_LINE_BYTES,
    Kms40Error,
    decode_flags,
    parse_error,
    parse_frame,
)
from hardware.stamped import Latest

_RESTORED = ("TARE", "LDIV", "FLT", "VL", "LMASK")  # settings re-sent after a reconnect, in this order


@dataclass
class _Pending:
    name: str
    done: threading.Event = field(default_factory=threading.Event)
    value: str = ""
    error: Kms40Error | None = None

    def resolve(self, value: str = "", error: Kms40Error | None = None) -> None:
        self.value, self.error = value, error
        self.done.set()


class Kms40Client:
    """Connected KMS40 at `host:port`; raises Kms40Error if no connection within `timeout_s` (s).

    A `hardware.ft_sensor.ForceTorqueSensor` once `start` has run (`wrench`, `stats`, `info`, `close`).
    """

    def __init__(self, host: str, port: int = 1000, timeout_s: float = 1.0, reconnect_s: float = 0.5) -> None:
        self.address = (host, port)
        self.timeout_s = timeout_s
        self.reconnect_s = reconnect_s
        self.wrench: Latest[np.ndarray] = Latest("KMS40 F/T")
        self.stats: Counter[str] = Counter()
        self.info: dict[str, object] = {}
        """Serial number and status flags, read by `start`."""
        self._sock: socket.socket | None = None
        self._pending: deque[_Pending] = deque()
        self._lock = threading.Lock()
        self._settings: dict[str, str] = {}
        self._streaming = False
        self._connected = threading.Event()
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._run, name="kms40-client", daemon=True)
        self._thread.start()
        if not self._connected.wait(timeout_s):
            self.close()
            raise Kms40Error(None, f"cannot connect to {host}:{port} within {timeout_s:g} s")

    def start(self, rate_divider: int, filter_id: int) -> None:
        """Check the sensor (CALIB_VALID, no fault flag), untare, set rate and filter, start streaming.

        Records serial number and flags in `info`; Kms40Error naming the problems if the flags forbid use.
        """
        flags = self.flags()
        self.info = {"serial": self.serial(), "flags": sorted(flags)}
        problems = sorted(flags & FAULT_FLAGS) + ([] if "CALIB_VALID" in flags else ["no CALIB_VALID"])
        if problems:
            raise Kms40Error(None, f"the sensor reports {', '.join(problems)} (flags: {sorted(flags)})")
        self.tare(False)
        self.set_rate_divider(rate_divider)
        self.set_filter(filter_id)
        self.start_stream()

    # -- commands --------------------------------------------------------------------------------
    def command(self, name: str, arg: str = "") -> str:
        """Send `name(arg)` and return the value of its `name=value` reply; Kms40Error on ERROR/timeout."""
        pending = self._send(name, arg)
        if not pending.done.wait(self.timeout_s):
            raise Kms40Error(None, f"no reply to {name}({arg}) within {self.timeout_s:g} s")
        if pending.error is not None:
            raise pending.error
        return pending.value

    def _send(self, name: str, arg: str, track: bool = True) -> _Pending:
        pending = _Pending(name)
        with self._lock:
            if self._sock is None:
                raise Kms40Error(None, f"not connected to {self.address[0]}:{self.address[1]}")
            self._pending.append(pending)
            try:
                self._sock.sendall(f"{name}({arg})\n".encode())
            except OSError as exc:
                self._pending.remove(pending)
                raise Kms40Error(None, f"send failed: {exc}") from exc
            if track and name in _RESTORED:
                self._settings[name] = arg
        return pending

    def start_stream(self) -> None:
        """Start streaming frames into `wrench` (L1)."""
        self.command("L1")
        self._streaming = True

    def stop_stream(self) -> None:
        """Stop streaming (L0); frames still in flight are drained until the acknowledgement."""
        self._streaming = False
        self.command("L0")

    def frame(self) -> np.ndarray:
        """One wrench (6,) in N and N·m (F()); while streaming, the latest streamed frame instead."""
        if self._streaming:
            return self.wrench.get(self.timeout_s)
        return parse_frame("F=" + self.command("F"))[0]

    def tare(self, on: bool) -> None:
        """Zero the readings at the current load (TARE(1)) or go back to untared values (TARE(0))."""
        self.command("TARE", "1" if on else "0")

    def set_rate_divider(self, n: int) -> float:
        """Stream at 500/n Hz (LDIV(n)); returns the rate in Hz."""
        return 500.0 / int(self.command("LDIV", str(int(n))))

    def set_filter(self, filter_id: int) -> None:
        """Select the sensor's internal filter (FLT(n); 0 = off)."""
        self.command("FLT", str(int(filter_id)))

    def serial(self) -> str:
        """The sensor's serial number (SN())."""
        return self.command("SN")

    def temperature(self) -> float:
        """Sensor temperature (°C) (T())."""
        return float(self.command("T"))

    def flags(self) -> set[str]:
        """Names of the status bits set (FLAGS()), e.g. {"CALIB_VALID", "STABLE", "DAQ_RUNNING"}."""
        return decode_flags(int(self.command("FLAGS")))

    def close(self) -> None:
        """Stop streaming if connected, close the socket and stop reconnecting; safe to call twice."""
        if self._streaming and self._connected.is_set():
            try:
                self.stop_stream()
            except Kms40Error:
                pass
        self._stop.set()
        self._drop_socket()
        self._thread.join(timeout=2.0)

    # -- I/O thread ------------------------------------------------------------------------------
    def _run(self) -> None:
        first = True
        while not self._stop.is_set():
            try:
                sock = socket.create_connection(self.address, timeout=self.timeout_s)
            except OSError:
                self._stop.wait(self.reconnect_s)
                continue
            sock.settimeout(0.2)
            with self._lock:
                self._sock = sock
            if not first:
                self.stats["reconnects"] += 1
                self._restore()
            first = False
            self._connected.set()
            self._read(sock)
            self._connected.clear()
            self._drop_socket()
            if not self._stop.is_set():
                self._stop.wait(self.reconnect_s)

    def _restore(self) -> None:
        """Re-send the settings and streaming state after a reconnect (replies are checked by _line)."""
        try:
            for name in _RESTORED:
                if name in self._settings:
                    self._send(name, self._settings[name], track=False)
            if self._streaming:
                self._send("L1", "", track=False)
        except Kms40Error:
            self.stats["restore_failures"] += 1

    def _drop_socket(self) -> None:
        with self._lock:
            sock, self._sock = self._sock, None
            pending, self._pending = list(self._pending), deque()
        if sock is not None:
            try:
                sock.shutdown(socket.SHUT_RDWR)
            except OSError:
                pass
            sock.close()
        for p in pending:
            p.resolve(error=Kms40Error(None, f"connection lost while waiting for {p.name}()"))

    def _read(self, sock: socket.socket) -> None:
        buffer = b""
        while not self._stop.is_set():
            try:
                chunk = sock.recv(4096)
            except TimeoutError:
                continue
            except OSError:
                return
            if not chunk:
                return
            *lines, buffer = (buffer + chunk).split(b"\n")
            if len(buffer) > MAX_LINE_BYTES:
                self.stats["oversized"] += 1
                buffer = b""
            for raw in lines:
                if len(raw) > MAX_LINE_BYTES:
                    self.stats["oversized"] += 1
                else:
                    self._line(raw.decode("ascii", errors="replace").strip())

    def _line(self, line: str) -> None:
        with self._lock:
            head = self._pending[0] if self._pending else None
        if line.startswith("F=") and (head is None or head.name != "F"):
            try:
                self.wrench.put(parse_frame(line)[0])
                self.stats["frames"] += 1
            except ValueError:
                self.stats["malformed"] += 1
            return
        error = parse_error(line)
        if head is None or (error is None and not line.startswith(head.name + "=")):
            self.stats["unknown_replies"] += 1
            return
        with self._lock:
            self._pending.popleft()
        if error is not None:
            self.stats["errors"] += 1
        head.resolve(line[len(head.name) + 1 :], error)
