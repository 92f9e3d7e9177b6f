"""Opening an SPI transport for the BioTac: the Total Phase Cheetah adapter, or the TCP bridge.

The Cheetah's vendor Python module (`cheetah_py`, wrapping the native `cheetah.so` / `cheetah.dll`)
is on no package registry; it is loaded when present and otherwise the error says how to get it.
"""

from __future__ import annotations

import importlib
import os
import sys
from array import array
from collections.abc import Sequence
from types import ModuleType

from hardware.biotac.bridge import TcpSpiTransport
from hardware.biotac.protocol import DEFAULT_BITRATE_KHZ, Delay, Select, SpiOp, SpiTransport, Transfer, TransportError

CHEETAH_PATH_ENV = "BIOTAC_CHEETAH_PATH"
CHEETAH_HELP = (
    "The Total Phase Cheetah API (Python module `cheetah_py`) is not installed. Download the "
    "'Cheetah Software API' for your OS from https://www.totalphase.com/products/cheetah-spi/ "
    "(free for adapter owners), unpack it, and put `cheetah_py.py` and the native library next to it "
    "(`cheetah.so` on Linux/macOS, `cheetah.dll` on Windows) in a folder on PYTHONPATH or in the folder "
    f"named by the environment variable {CHEETAH_PATH_ENV}. To rehearse without the adapter, run "
    '`twin devices serve` and set biotac.transport = "tcp://127.0.0.1:PORT" in the hardware config.'
)
POWER_UP_MS = 100  # wait after powering the target before the first command


def load_cheetah() -> ModuleType:
    """Import the vendor's `cheetah_py` (also from $BIOTAC_CHEETAH_PATH); TransportError with help if absent."""
    folder = os.environ.get(CHEETAH_PATH_ENV)
    if folder and folder not in sys.path:
        sys.path.insert(0, folder)
    try:
        return importlib.import_module("cheetah_py")
    except ImportError as exc:  # the module, or the native library it wraps, is missing
        raise TransportError(f"{CHEETAH_HELP} ({exc})") from exc


class CheetahTransport:
    """SPI batches on a Total Phase Cheetah (mode 0, MSB first, slave selects active low), target powered."""

    def __init__(self, port: int = 0, bitrate_khz: int = DEFAULT_BITRATE_KHZ) -> None:
        self.ch = load_cheetah()
        handle = self.ch.ch_open(port)
        if handle <= 0:
            raise TransportError(
                f"cannot open the Cheetah on port {port} (code {handle}): is it plugged in and not in use?"
            )
        self.handle = handle
        ch = self.ch
        ch.ch_spi_configure(
            handle, ch.CH_SPI_POL_RISING_FALLING, ch.CH_SPI_PHASE_SAMPLE_SETUP, ch.CH_SPI_BITORDER_MSB, 0x0
        )
        self.bitrate_khz = ch.ch_spi_bitrate(handle, bitrate_khz)
        ch.ch_target_power(handle, ch.CH_TARGET_POWER_ON)
        ch.ch_sleep_ms(POWER_UP_MS)

    def batch(self, ops: Sequence[SpiOp]) -> bytes:
        """Queue `ops`, shift the batch (blocks for its duration) and return the MISO bytes."""
        ch, h = self.ch, self.handle
        ch.ch_spi_queue_clear(h)
        ch.ch_spi_queue_oe(h, 1)
        n = 0
        for op in ops:
            if isinstance(op, Select):
                ch.ch_spi_queue_ss(h, op.mask)
            elif isinstance(op, Transfer):
                ch.ch_spi_queue_array(h, array("B", op.data))
                n += len(op.data)
            elif isinstance(op, Delay):
                ch.ch_spi_queue_delay_ns(h, op.ns)
        count, data = ch.ch_spi_batch_shift(h, n)
        if count != n:
            raise TransportError(f"Cheetah batch shifted {count} of {n} bytes")
        return bytes(data[:n])

    def close(self) -> None:
        """Power the target down and close the adapter; safe to call twice."""
        if self.handle > 0:
            self.ch.ch_target_power(self.handle, self.ch.CH_TARGET_POWER_OFF)
            self.ch.ch_close(self.handle)
            self.handle = 0


def open_transport(spec: str, bitrate_khz: int = DEFAULT_BITRATE_KHZ, timeout_s: float = 2.0) -> SpiTransport:
    """Open the transport `spec` names: "cheetah" or "cheetah:PORT", or "tcp://HOST:PORT" (an SPI bridge)."""
    kind, _, rest = spec.partition(":")
    if kind == "cheetah":
        return CheetahTransport(int(rest or 0), bitrate_khz)
    if kind == "tcp" and rest.startswith("//"):
        host, _, port = rest[2:].rpartition(":")
        return TcpSpiTransport(host, int(port), timeout_s)
    raise ValueError(f"unknown BioTac transport {spec!r}: use 'cheetah', 'cheetah:PORT' or 'tcp://HOST:PORT'")
