"""The F/T-sensor seam: what `HardwareBackend` needs of a force/torque sensor, whatever its make.

A sensor family lives in a folder of its own (`hardware/kms40/`: protocol, client, sim, config) and
offers a config section: a frozen dataclass whose every field has a default, with `timeout_s` and
`watchdog_s` among them, and whose `open()` returns a connected, checked, untared, streaming
`ForceTorqueSensor` (or raises `FtSensorError`). `HardwareConfig` holds one field per family, and
`[ft] sensor` names the one the backend opens (docs/hardware.md: adding an F/T sensor).
"""

from __future__ import annotations

from collections import Counter
from typing import Protocol, runtime_checkable

import numpy as np

from hardware.stamped import Latest


class FtSensorError(RuntimeError):
    """An F/T sensor cannot be opened, reports a fault, or does not answer a command."""


class ForceTorqueSensor(Protocol):
    """A streaming F/T sensor, as the backend reads it.

    wrench: the latest (6,) reading (Fx, Fy, Fz in N, Mx, My, Mz in N·m), sensor frame, untared,
    stamped with its arrival time (the watchdog reads its age). stats: counters of the link
    (frames, reconnects, dropped lines, ...). info: identity and state read when it opened
    (e.g. serial number, status flags), JSON-serialisable.
    """

    wrench: Latest[np.ndarray]
    stats: Counter[str]
    info: dict[str, object]

    def close(self) -> None:
        """Stop streaming and release the connection; safe to call twice."""
        ...


@runtime_checkable
class FtSensorConfig(Protocol):
    """A config section that opens an F/T sensor (what `[ft] sensor` may name)."""

    timeout_s: float
    """How long (s) to wait for the connection and for the first streamed reading."""
    watchdog_s: float
    """A reading older than this (s) is a fault."""

    def open(self) -> ForceTorqueSensor:
        """Connect, check, untare and start streaming; FtSensorError (or OSError) if that fails."""
        ...
