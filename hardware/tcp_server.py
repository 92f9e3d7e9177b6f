"""The TCP side of a simulated device: listen on a port, accept clients on a daemon thread, hand each over.

`TcpServer` is the base of the BioTac SPI bridge (`hardware.biotac.bridge`) and the KMS40 simulator
(`hardware.kms40.sim`): a subclass says what serving one client is (`_on_client`, called on the accept
thread, so it must return at once: start a thread for a long conversation) and how to drop them all
(`disconnect_all`). The listener binds loopback unless told otherwise; `close()` is noticed within
ACCEPT_POLL_S.
"""

from __future__ import annotations

import socket
import threading
from abc import ABC, abstractmethod

ACCEPT_POLL_S = 0.02
"""How often (s) the accept thread looks whether `close()` was called."""


class TcpServer(ABC):
    """Accepts TCP clients on `host:port` (port 0 picks a free one) until `close()`.

    The accept thread starts in `__init__`: a subclass sets whatever `_on_client` reads before it calls
    `super().__init__`.
    """

    def __init__(self, host: str, port: int, thread_name: str) -> None:
        self._server = socket.create_server((host, port))
        self._server.settimeout(ACCEPT_POLL_S)
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._accept, name=thread_name, daemon=True)
        self._thread.start()

    @property
    def port(self) -> int:
        """The TCP port the server listens on."""
        return self._server.getsockname()[1]

    @property
    def closing(self) -> bool:
        """`close()` was called: client conversations should end."""
        return self._stop.is_set()

    @abstractmethod
    def disconnect_all(self) -> None:
        """Drop every client connection; keep listening."""

    @abstractmethod
    def _on_client(self, sock: socket.socket) -> None:
        """Take over a newly accepted connection (on the accept thread: return at once)."""

    def close(self) -> None:
        """Stop listening and drop every client; safe to call twice."""
        self._stop.set()
        self._thread.join(timeout=1.0)
        self._server.close()
        self.disconnect_all()

    def _accept(self) -> None:
        while not self._stop.is_set():
            try:
                sock, _ = self._server.accept()
            except TimeoutError:
                continue
            except OSError:
                return
            self._on_client(sock)
