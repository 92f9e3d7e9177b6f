"""SPI batches over TCP: reach simulated (or remote) BioTacs from another process.

`SpiBridgeServer` exposes any `SpiTransport` (e.g. `SimBioTacBus`) on a TCP port; `TcpSpiTransport`
is the matching client transport, so `HardwareBackend` in one process can read the BioTac simulator
that `twin devices serve` runs in another, through exactly the same protocol code as on a Cheetah.

Wire format (ours, big-endian): each message is b"BTSP", a u32 payload length, then the payload.
Request payload: ops, each b"S" u8 mask | b"T" u16 length + bytes | b"D" u32 ns.
Reply payload: u8 status (0 ok, 1 error) then the MISO bytes or a UTF-8 error message.
A malformed request gets an error reply and the connection is closed (there is no way to resync).
"""

from __future__ import annotations

import socket
import struct
import threading
from collections.abc import Sequence

from hardware.biotac.protocol import Delay, Select, SpiOp, SpiTransport, Transfer, TransportError
from hardware.tcp_server import TcpServer

MAGIC = b"BTSP"
MAX_PAYLOAD = 1 << 16


def encode_ops(ops: Sequence[SpiOp]) -> bytes:
    """Serialize a batch of SPI ops."""
    out = bytearray()
    for op in ops:
        if isinstance(op, Select):
            out += b"S" + struct.pack(">B", op.mask)
        elif isinstance(op, Transfer):
            out += b"T" + struct.pack(">H", len(op.data)) + op.data
        elif isinstance(op, Delay):
            out += b"D" + struct.pack(">I", op.ns)
        else:
            raise TypeError(f"not an SPI op: {op!r}")
    return bytes(out)


def decode_ops(payload: bytes) -> list[SpiOp]:
    """Parse a serialized batch; ValueError when truncated or unknown."""
    ops: list[SpiOp] = []
    i = 0
    try:
        while i < len(payload):
            kind, i = payload[i : i + 1], i + 1
            if kind == b"S":
                ops.append(Select(payload[i]))
                i += 1
            elif kind == b"T":
                (n,) = struct.unpack_from(">H", payload, i)
                if i + 2 + n > len(payload):
                    raise ValueError("truncated transfer")
                ops.append(Transfer(payload[i + 2 : i + 2 + n]))
                i += 2 + n
            elif kind == b"D":
                ops.append(Delay(struct.unpack_from(">I", payload, i)[0]))
                i += 4
            else:
                raise ValueError(f"unknown op {kind!r} at byte {i - 1}")
    except (IndexError, struct.error) as exc:
        raise ValueError(f"truncated op at byte {i}") from exc
    return ops


def _send(sock: socket.socket, payload: bytes) -> None:
    sock.sendall(MAGIC + struct.pack(">I", len(payload)) + payload)


def _recv_exact(sock: socket.socket, n: int) -> bytes:
    data = bytearray()
    while len(data) < n:
        chunk = sock.recv(n - len(data))
        if not chunk:
            raise ConnectionError("connection closed")
        data += chunk
    return bytes(data)


def _recv(sock: socket.socket) -> bytes:
    header = _recv_exact(sock, 8)
    (length,) = struct.unpack(">I", header[4:])
    if header[:4] != MAGIC or length > MAX_PAYLOAD:
        raise ValueError(f"bad message header {header!r}")
    return _recv_exact(sock, length)


class TcpSpiTransport:
    """An SpiTransport whose batches run on a `SpiBridgeServer` at `host:port`."""

    def __init__(self, host: str, port: int, timeout_s: float = 2.0) -> None:
        try:
            self._sock = socket.create_connection((host, port), timeout=timeout_s)
        except OSError as exc:
            raise TransportError(f"cannot reach the SPI bridge at {host}:{port}: {exc}") from exc

    def batch(self, ops: Sequence[SpiOp]) -> bytes:
        """Run `ops` remotely; TransportError on a broken link or an error reply."""
        try:
            _send(self._sock, encode_ops(ops))
            reply = _recv(self._sock)
        except (OSError, ValueError) as exc:
            raise TransportError(f"SPI bridge: {exc}") from exc
        if not reply or reply[0] != 0:
            raise TransportError(f"SPI bridge refused the batch: {reply[1:].decode(errors='replace')}")
        return reply[1:]

    def close(self) -> None:
        """Close the connection; safe to call twice."""
        self._sock.close()


class SpiBridgeServer(TcpServer):
    """Serve `transport` (e.g. a SimBioTacBus) to TcpSpiTransport clients on `host:port` (0 picks one)."""

    def __init__(self, transport: SpiTransport, host: str = "127.0.0.1", port: int = 0) -> None:
        self.transport = transport
        self._clients: set[socket.socket] = set()
        super().__init__(host, port, "spi-bridge")

    def disconnect_all(self) -> None:
        """Drop every client connection (keeps listening)."""
        for sock in list(self._clients):
            try:
                sock.shutdown(socket.SHUT_RDWR)
            except OSError:
                pass

    def _on_client(self, sock: socket.socket) -> None:
        self._clients.add(sock)
        threading.Thread(target=self._serve, args=(sock,), name="spi-bridge-client", daemon=True).start()

    def _serve(self, sock: socket.socket) -> None:
        try:
            while not self.closing:
                try:
                    ops = decode_ops(_recv(sock))
                except ValueError as exc:
                    _send(sock, b"\x01" + str(exc).encode())
                    return
                try:
                    miso = self.transport.batch(ops)
                except (TransportError, ValueError) as exc:
                    _send(sock, b"\x01" + str(exc).encode())
                    continue
                _send(sock, b"\x00" + miso)
        except OSError:  # includes ConnectionError: the client went away
            pass
        finally:
            self._clients.discard(sock)
            sock.close()
