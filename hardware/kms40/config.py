"""The `[kms40]` section of the hardware config: where the KMS40 is and how it streams; opens it."""

from __future__ import annotations

from dataclasses import dataclass

from hardware.kms40.client import Kms40Client


@dataclass(frozen=True)
class Kms40Config:
    """Weiss KMS40 F/T sensor on TCP (a `hardware.ft_sensor.FtSensorConfig`). Times in s."""

    host: str = "192.168.1.30"
    port: int = 1000
    rate_divider: int = 2
    """Stream at 500 / rate_divider Hz (2 -> 250 Hz, above the protocol's 100 Hz)."""
    filter_id: int = 0
    timeout_s: float = 1.0
    reconnect_s: float = 0.5
    watchdog_s: float = 0.1

    def __post_init__(self) -> None:
        if not 0 <= self.port <= 65535:
            raise ValueError(f"kms40.port must be a port number 0..65535, got {self.port}")
        if not 1 <= self.rate_divider <= 1000:
            raise ValueError(f"kms40.rate_divider must be 1..1000, got {self.rate_divider}")

    def open(self) -> Kms40Client:
        """Connect, check the flags, untare, set rate divider and filter, stream; Kms40Error if that fails."""
        client = Kms40Client(self.host, self.port, self.timeout_s, self.reconnect_s)
        try:
            client.start(self.rate_divider, self.filter_id)
        except BaseException:
            client.close()
            raise
        return client
