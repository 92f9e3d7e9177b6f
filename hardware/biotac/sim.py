"""Simulated BioTacs on an SPI bus: an `SpiTransport` that answers like the sensors behind the adapter.

`SimBioTacBus.batch` plays the SPI ops on a virtual clock (transfers take 8 bits / bitrate, delays
their length), lets each selected sensor shift bytes in and out, and then sleeps until that much
real time has passed, as a USB-SPI adapter blocks for its batch. Each `SimBioTac` checks what a real
one checks and answers with the same error words: command parity (0xA545), unknown commands
(0xA53F), unknown channels (0xA558), a reply clocked out sooner than 50 us after its command
(0xA52E), and samples closer together than 90 % of the 4400 samples/s period (0xA52D).
Electrodes and PDC come from `electrode_source`, read once per frame (at each E1 command).
"""

from __future__ import annotations

import threading
import time
from collections.abc import Callable, Sequence

import numpy as np

from hardware.biotac.protocol import (
    COMMAND_DELAY_NS,
    DEFAULT_BITRATE_KHZ,
    ELECTRODE_CHANNELS,
    FRAME_CHANNELS,
    KNOWN_CHANNELS,
    PROPERTY_LENGTHS,
    READ_COMMAND,
    SAMPLE_RATE_HZ,
    SELECT_MASKS,
    Channel,
    Delay,
    ErrorWord,
    Property,
    Select,
    SpiOp,
    Transfer,
    command_channel,
    encode_error,
    encode_word,
    odd_parity_ok,
)

ElectrodeSource = Callable[[], tuple[np.ndarray, float]]
"""Returns ((19,) electrode counts E1..E19, PDC counts), raw 12-bit; called from the bus thread."""

IDLE_BYTE = 0xFF  # what MISO reads when a sensor has nothing to say (fails the parity check)
MIN_SAMPLE_INTERVAL_NS = 0.9e9 / SAMPLE_RATE_HZ


class SimBioTac:
    """One simulated BioTac: a byte-level SPI slave with the sampling and property commands."""

    def __init__(
        self,
        electrode_source: ElectrodeSource,
        serial: str = "BT-SIM-0000001",
        pac: int = 2048,
        tac: int = 2000,
        tdc: int = 2300,
    ) -> None:
        if not serial.startswith("BT") or len(serial) > PROPERTY_LENGTHS[Property.SERIAL_NUMBER]:
            raise ValueError(f"BioTac serials start with 'BT' and have at most 16 characters: {serial!r}")
        self.electrode_source = electrode_source
        self.properties = {
            Property.SERIAL_NUMBER: serial.encode() + bytes([0x00]),
            Property.FIRMWARE_VERSION: bytes([2, 1, 0, 7]),
            Property.FLEX_VERSION: bytes([3, 1]),
            Property.CPU_SPEED: (32).to_bytes(2, "big"),
            Property.SAMPLING_FREQUENCY: int(SAMPLE_RATE_HZ).to_bytes(2, "big"),
            Property.SAMPLING_PATTERN: bytes(int(ch) for ch in FRAME_CHANNELS),
        }
        self.fixed = {Channel.PAC: pac, Channel.TAC: tac, Channel.TDC: tdc, Channel.HAL: 0}
        self._values: dict[int, int] = {}
        self._rx = bytearray()
        self._tx = bytearray()
        self._pending = b""
        self._command_end_ns = float("-inf")
        self._last_sample_ns = float("-inf")

    def begin(self, t_ns: float) -> None:
        """Slave select asserted at virtual time `t_ns`: prepare the reply to clock out."""
        self._rx.clear()
        reply, self._pending = self._pending, b""
        if reply and t_ns - self._command_end_ns < COMMAND_DELAY_NS:
            reply = encode_error(ErrorWord.INSUFFICIENT_DELAY)
        self._tx = bytearray(reply)

    def shift(self, data: bytes) -> bytes:
        """Clock `data` in; the same number of bytes out (reply bytes, then IDLE_BYTE)."""
        self._rx += data
        out = bytes(self._tx[: len(data)]).ljust(len(data), bytes([IDLE_BYTE]))
        del self._tx[: len(data)]
        return out

    def end(self, t_ns: float) -> None:
        """Slave select released at `t_ns`: act on the command received, if it was one."""
        if not self._rx or self._rx[0] == 0x00:  # a read: the reply has been clocked out
            return
        cmd = self._rx[0]
        self._command_end_ns = t_ns
        if not odd_parity_ok(cmd):
            self._pending = encode_error(ErrorWord.PARITY)
        elif cmd & 0x80:
            self._pending = self._sample(command_channel(cmd), t_ns)
        elif cmd == READ_COMMAND and len(self._rx) >= 2 and self._rx[1] in Property._value2member_map_:
            self._pending = self.properties[Property(self._rx[1])]
        else:
            self._pending = encode_error(ErrorWord.UNKNOWN_COMMAND)

    def _sample(self, channel: int, t_ns: float) -> bytes:
        if channel not in KNOWN_CHANNELS:
            return encode_error(ErrorWord.CHANNEL_NOT_RECOGNISED)
        if t_ns - self._last_sample_ns < MIN_SAMPLE_INTERVAL_NS:
            return encode_error(ErrorWord.INSUFFICIENT_SAMPLING_DELAY)
        self._last_sample_ns = t_ns
        if channel == ELECTRODE_CHANNELS[0] or not self._values:
            self._refresh()
        return encode_word(self._values[channel])

    def _refresh(self) -> None:
        electrodes, pdc = self.electrode_source()
        counts = np.clip(np.rint(np.asarray(electrodes, dtype=float).reshape(19)), 0, 4095).astype(int)
        self._values = {int(ch): int(v) for ch, v in self.fixed.items()}
        self._values |= {ch: int(c) for ch, c in zip(ELECTRODE_CHANNELS, counts, strict=True)}
        self._values[Channel.PDC] = int(np.clip(round(float(pdc)), 0, 4095))


class SimBioTacBus:
    """Up to three simulated BioTacs on one adapter's select lines (slot 1..3 -> mask 0x01, 0x02, 0x04)."""

    def __init__(self, sensors: dict[int, SimBioTac], bitrate_khz: int = DEFAULT_BITRATE_KHZ) -> None:
        if not set(sensors) <= set(SELECT_MASKS):
            raise ValueError(f"sensor slots are 1..3, got {sorted(sensors)}")
        self.sensors = sensors
        self.ns_per_byte = 8e6 / bitrate_khz
        self._lock = threading.Lock()
        self._selected = 0
        self._t_ns = 0

    def batch(self, ops: Sequence[SpiOp]) -> bytes:
        """Play `ops` (see SpiTransport.batch); sleeps for the batch's duration on the bus."""
        start = time.monotonic()
        with self._lock:
            t0 = self._t_ns
            miso = bytearray()
            for op in ops:
                if isinstance(op, Select):
                    self._select(op.mask)
                elif isinstance(op, Transfer):
                    miso += self._transfer(op.data)
                elif isinstance(op, Delay):
                    self._t_ns += op.ns
            duration_s = (self._t_ns - t0) * 1e-9
        time.sleep(max(0.0, duration_s - (time.monotonic() - start)))
        return bytes(miso)

    def close(self) -> None:
        """Nothing to release."""

    def _select(self, mask: int) -> None:
        for slot, sensor in self.sensors.items():
            bit = SELECT_MASKS[slot]
            if mask & bit and not self._selected & bit:
                sensor.begin(self._t_ns)
            elif self._selected & bit and not mask & bit:
                sensor.end(self._t_ns)
        self._selected = mask

    def _transfer(self, data: bytes) -> bytes:
        selected = [s for slot, s in self.sensors.items() if self._selected & SELECT_MASKS[slot]]
        replies = [s.shift(data) for s in selected]
        self._t_ns += round(len(data) * self.ns_per_byte)  # integer ns: delay checks stay exact
        if len(replies) == 1:
            return replies[0]
        return bytes(data) if replies else bytes([IDLE_BYTE]) * len(data)  # several drivers: read back the echo
