"""A lossy, slow UDP link for rehearsing EGM under bad network conditions.

`UdpFaultProxy` sits between a robot (EGM sender) and the PC's EGM port: datagrams in both directions
are dropped with probability `loss` and delivered `delay_s` late. Point the simulated robot at the
proxy's port and the proxy at the PC's, then name the robot's address as `client`: the proxy
forwards only what the client sends to its front and what the target sends to its back, and counts
the rest as `foreign`, so it gives a stranger no way around either end's peer check.
"""

from __future__ import annotations

import heapq
import select
import socket
import threading
import time

import numpy as np


class UdpFaultProxy:
    """Forward UDP between `client` and `target`, dropping (`loss`, 0..1) and delaying (`delay_s`, s).

    Nothing is forwarded until `client` (address, port) is set.
    """

    def __init__(
        self, target: tuple[str, int], loss: float = 0.0, delay_s: float = 0.0, seed: int = 0, host: str = "127.0.0.1"
    ) -> None:
        if not 0.0 <= loss <= 1.0 or delay_s < 0:
            raise ValueError(f"need 0 <= loss <= 1 and delay_s >= 0, got {loss}, {delay_s}")
        self.target = (socket.gethostbyname(target[0]), target[1])
        self.loss, self.delay_s = loss, delay_s
        self.dropped = 0
        self.foreign = 0
        self.client: tuple[str, int] | None = None
        self._rng = np.random.default_rng(seed)
        self._front = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)  # faces the client
        self._front.bind((host, 0))
        self._back = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)  # faces the target
        self._back.bind((host, 0))
        self._queue: list[tuple[float, int, socket.socket, bytes, tuple[str, int]]] = []
        self._n = 0
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._run, name="udp-fault-proxy", daemon=True)
        self._thread.start()

    @property
    def port(self) -> int:
        """The port clients send to."""
        return self._front.getsockname()[1]

    @property
    def source_port(self) -> int:
        """The port the proxy forwards from: the sender's port that the target sees."""
        return self._back.getsockname()[1]

    def close(self) -> None:
        """Stop forwarding; safe to call twice."""
        self._stop.set()
        self._thread.join(timeout=1.0)
        self._front.close()
        self._back.close()

    def _run(self) -> None:
        while not self._stop.is_set():
            wait = 0.05 if not self._queue else max(0.0, self._queue[0][0] - time.monotonic())
            readable, _, _ = select.select([self._front, self._back], [], [], wait)
            for sock in readable:
                try:
                    data, sender = sock.recvfrom(65536)
                except OSError:  # ICMP errors from an earlier send surface here
                    continue
                if sock is self._front and sender == self.client:
                    self._schedule(self._back, data, self.target)
                elif sock is self._back and sender == self.target and self.client is not None:
                    self._schedule(self._front, data, self.client)
                else:
                    self.foreign += 1
            now = time.monotonic()
            while self._queue and self._queue[0][0] <= now:
                _, _, sock, data, dest = heapq.heappop(self._queue)
                try:
                    sock.sendto(data, dest)
                except OSError:
                    pass

    def _schedule(self, sock: socket.socket, data: bytes, dest: tuple[str, int]) -> None:
        if self._rng.random() < self.loss:
            self.dropped += 1
            return
        self._n += 1
        heapq.heappush(self._queue, (time.monotonic() + self.delay_s, self._n, sock, data, dest))
