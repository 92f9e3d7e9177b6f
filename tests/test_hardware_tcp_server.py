"""The simulated devices' TCP listener: every client reaches the subclass, close() really stops listening."""

from __future__ import annotations

import socket
import threading

import pytest

from hardware.tcp_server import TcpServer


class _Greeter(TcpServer):
    """Writes its client number to each client, then hangs up."""

    def __init__(self) -> None:
        self.served = 0
        self.dropped = threading.Event()
        super().__init__("127.0.0.1", 0, "greeter")

    def disconnect_all(self) -> None:
        self.dropped.set()

    def _on_client(self, sock: socket.socket) -> None:
        self.served += 1
        sock.sendall(str(self.served).encode())
        sock.close()


def _greeting(port: int) -> bytes:
    with socket.create_connection(("127.0.0.1", port), timeout=1.0) as sock:
        return sock.recv(16)


def test_each_client_is_handed_over_in_turn_and_close_stops_listening() -> None:
    server = _Greeter()
    port = server.port
    try:
        assert port > 0 and not server.closing
        assert [_greeting(port) for _ in range(3)] == [b"1", b"2", b"3"]
    finally:
        server.close()
    assert server.closing and server.dropped.is_set()
    with pytest.raises(ConnectionRefusedError):
        _greeting(port)
    server.close()  # twice is fine
