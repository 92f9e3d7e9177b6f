"""BioTac driver: identify the sensors, then sample 44-sample frames at 100 Hz in a background thread.

At start the reader asks each selected sensor for its serial number (which must start with "BT"),
firmware and flex versions. The sampling thread then runs one batch per frame and publishes each
sensor's decoded `Frame` in `frames[slot]` (a stamped latest-value slot for watchdogs). A frame with
any bad word (parity failure or error word) is dropped and counted in `stats` under the error's name;
a transport failure is counted and the transport reopened every `reconnect_s` until it works again.
"""

from __future__ import annotations

import threading
from collections import Counter
from collections.abc import Callable
from dataclasses import dataclass

from hardware.biotac.protocol import (
    DEFAULT_BITRATE_KHZ,
    Frame,
    Property,
    SpiTransport,
    TransportError,
    decode_frame,
    frame_ops,
    property_bytes,
    property_ops,
    slots,
)
from hardware.stamped import Latest


class BioTacError(RuntimeError):
    """A BioTac could not be found or read."""


@dataclass(frozen=True)
class BioTacInfo:
    """What a sensor says about itself."""

    serial: str
    firmware: tuple[int, ...]
    flex_version: tuple[int, ...]


def read_info(transport: SpiTransport, slot: int) -> BioTacInfo:
    """Read serial number, firmware and flex versions of the sensor in `slot`; BioTacError if none answers."""

    def prop(p: Property) -> bytes:
        return property_bytes(transport.batch(property_ops(p, slot)), p)

    serial = prop(Property.SERIAL_NUMBER).decode("ascii", errors="replace")
    if not serial.startswith("BT"):
        raise BioTacError(f"no BioTac answers on slot {slot} (serial number read as {serial!r})")
    return BioTacInfo(serial, tuple(prop(Property.FIRMWARE_VERSION)), tuple(prop(Property.FLEX_VERSION)))


class BioTacReader:
    """Sample every sensor in `select_mask` (0x01, 0x02, 0x04 or a combination) through `open_transport`."""

    def __init__(
        self,
        open_transport: Callable[[], SpiTransport],
        select_mask: int,
        bitrate_khz: int = DEFAULT_BITRATE_KHZ,
        reconnect_s: float = 0.5,
    ) -> None:
        self.slots = slots(select_mask)
        self.select_mask = select_mask
        self.reconnect_s = reconnect_s
        self.frames = {slot: Latest[Frame](f"BioTac {slot}") for slot in self.slots}
        self.stats: Counter[str] = Counter()
        self._open = open_transport
        self._ops = frame_ops(select_mask, bitrate_khz)
        try:
            self._transport: SpiTransport | None = open_transport()
        except TransportError as exc:
            raise BioTacError(f"cannot open the BioTac adapter: {exc}") from exc
        try:
            self.info = {slot: read_info(self._transport, slot) for slot in self.slots}
        except (TransportError, BioTacError) as exc:
            self._transport.close()
            raise BioTacError(str(exc)) from exc
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._run, name="biotac-reader", daemon=True)
        self._thread.start()

    def close(self) -> None:
        """Stop sampling and close the transport; safe to call twice."""
        self._stop.set()
        self._thread.join(timeout=2.0)
        if self._transport is not None:
            self._transport.close()
            self._transport = None

    def _run(self) -> None:
        while not self._stop.is_set():
            if self._transport is None and not self._reopen():
                continue
            try:
                miso = self._transport.batch(self._ops)
                decoded = decode_frame(miso, self.select_mask)
            except (TransportError, ValueError):
                self.stats["transport_errors"] += 1
                self._transport.close()
                self._transport = None
                continue
            for slot, frame in decoded.items():
                if isinstance(frame, Frame):
                    self.frames[slot].put(frame)
                    self.stats["frames"] += 1
                else:
                    self.stats[frame.error.name.lower() if frame.error else "parity_errors"] += 1

    def _reopen(self) -> bool:
        if self._stop.wait(self.reconnect_s):
            return False
        try:
            self._transport = self._open()
        except TransportError:
            return False
        self.stats["reconnects"] += 1
        return True
