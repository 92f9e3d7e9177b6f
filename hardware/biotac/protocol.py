"""The BioTac SPI protocol: command bytes, 12-bit words, the 44-sample frame, error words, properties.

Pure functions and data, shared by the driver (`hardware.biotac.client`) and the simulator (`hardware.biotac.sim`).
A transport executes a batch of `SpiOp`s (slave-select changes, byte transfers, delays) and returns
the MISO bytes of every transfer, in order; that batch is the seam between the protocol and the
USB-SPI adapter.

- Every byte sent to the sensor carries odd parity in its LSB. A sample command is
  0x80 | channel << 1 | parity; a sample reply word is (b0, b1) with value = (b0 >> 1) * 32 + (b1 >> 3)
  (12 bits) and odd parity in each byte.
- Error words (0xA5xx) fail the first byte's parity check by construction, so they cannot be
  mistaken for data.
- One frame = 44 samples at 4400 samples/s: E1, PAC, E2, PAC, ..., E19, PAC, PDC, PAC, TAC, PAC, TDC, PAC.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass
from enum import IntEnum
from typing import Protocol

import numpy as np

SAMPLE_RATE_HZ = 4400.0  # samples per second (frame rate = SAMPLE_RATE_HZ / FRAME_LENGTH = 100 Hz)
DEFAULT_BITRATE_KHZ = 4400
COMMAND_DELAY_NS = 50_000  # wait between a sample command and clocking out its reply
READ_DELAY_NS = 10_000  # wait after clocking out the replies
SELECT_MASKS = {1: 0x01, 2: 0x02, 3: 0x04}  # sensor slot -> slave select line


class Channel(IntEnum):
    """Channel ids of the sample command (electrodes E1..E19 are 17..35)."""

    PAC = 0
    PDC = 1
    TAC = 2
    TDC = 3
    HAL = 15


ELECTRODE_CHANNELS = tuple(range(17, 36))
KNOWN_CHANNELS = frozenset([*map(int, Channel), *ELECTRODE_CHANNELS])
FRAME_CHANNELS = tuple(
    ch
    for pair in [(e, Channel.PAC) for e in ELECTRODE_CHANNELS]
    + [(Channel.PDC, Channel.PAC), (Channel.TAC, Channel.PAC), (Channel.TDC, Channel.PAC)]
    for ch in pair
)
FRAME_LENGTH = len(FRAME_CHANNELS)  # 44


class ErrorWord(IntEnum):
    """Words the BioTac answers instead of data when something went wrong."""

    PARITY = 0xA545
    UNKNOWN_COMMAND = 0xA53F
    INSUFFICIENT_DELAY = 0xA52E
    INSUFFICIENT_SAMPLING_DELAY = 0xA52D
    CHANNEL_NOT_RECOGNISED = 0xA558
    NO_DATA_TO_RESEND = 0xA55F
    READ_ONLY = 0xA552
    WRITE_ERROR = 0xA557


READ_COMMAND = 0x61


class Property(IntEnum):
    """Property ids for the read command 0x61 (each already carries odd parity)."""

    FLEX_VERSION = 0x10
    FIRMWARE_VERSION = 0x13
    SERIAL_NUMBER = 0x15
    CPU_SPEED = 0x61
    SAMPLING_FREQUENCY = 0x70
    SAMPLING_PATTERN = 0x73


PROPERTY_LENGTHS = {
    Property.FLEX_VERSION: 2,
    Property.FIRMWARE_VERSION: 4,
    Property.SERIAL_NUMBER: 16,
    Property.CPU_SPEED: 2,
    Property.SAMPLING_FREQUENCY: 2,
    Property.SAMPLING_PATTERN: 44,
}
PROPERTY_END = (0x00, 0xFF)  # a property's bytes end at the first of these


@dataclass(frozen=True)
class Select:
    """Drive the slave-select lines: bit k set selects sensor slot k+1; 0 deselects all."""

    mask: int


@dataclass(frozen=True)
class Transfer:
    """Clock `data` out on MOSI; the same number of bytes comes back on MISO."""

    data: bytes


@dataclass(frozen=True)
class Delay:
    """Idle for `ns` nanoseconds."""

    ns: int


SpiOp = Select | Transfer | Delay


class TransportError(RuntimeError):
    """The SPI adapter or the link to it failed; a reader closes the transport and opens a new one."""


class SpiTransport(Protocol):
    """Runs SPI batches: the seam between the BioTac protocol and an adapter (Cheetah, TCP bridge, simulator)."""

    def batch(self, ops: Sequence[SpiOp]) -> bytes:
        """Execute `ops` in order (blocking for their duration); the MISO bytes of every Transfer, concatenated."""

    def close(self) -> None:
        """Release the adapter; safe to call twice."""


class WordError(ValueError):
    """A reply word is not data: `error` is the BioTac's error word, or None for a parity failure."""

    def __init__(self, word: int, error: ErrorWord | None) -> None:
        super().__init__(f"BioTac {error.name} (0x{word:04X})" if error else f"parity error in word 0x{word:04X}")
        self.word = word
        self.error = error


def odd_parity_ok(byte: int) -> bool:
    """Whether `byte` has an odd number of set bits."""
    return bin(byte & 0xFF).count("1") % 2 == 1


def with_parity(byte7: int) -> int:
    """`byte7` (bits 7..1 carry data, bit 0 ignored) with bit 0 set so the byte has odd parity."""
    byte = byte7 & 0xFE
    return byte if odd_parity_ok(byte) else byte | 1


def sample_command(channel: int) -> int:
    """The sample command byte for `channel` (e.g. PDC -> 0x83, E1 -> 0xA2)."""
    return with_parity(0x80 | (int(channel) & 0x3F) << 1)


def command_channel(command: int) -> int:
    """The channel a sample command byte asks for."""
    return (command & 0x7E) >> 1


def encode_word(value: int) -> bytes:
    """A 12-bit value as the two reply bytes (7 + 5 data bits, odd parity in each LSB)."""
    if not 0 <= value < 4096:
        raise ValueError(f"BioTac words are 12-bit, got {value}")
    return bytes([with_parity((value >> 5) << 1), with_parity((value & 0x1F) << 3)])


def encode_error(error: ErrorWord) -> bytes:
    """The two bytes of an error word."""
    return int(error).to_bytes(2, "big")


def decode_word(b0: int, b1: int) -> int:
    """The 12-bit value of reply bytes (b0, b1); WordError for error words and parity failures."""
    word = b0 << 8 | b1
    if word in ErrorWord._value2member_map_:
        raise WordError(word, ErrorWord(word))
    if not (odd_parity_ok(b0) and odd_parity_ok(b1)):
        raise WordError(word, None)
    return (b0 >> 1) * 32 + (b1 >> 3)


def slots(select_mask: int) -> list[int]:
    """Sensor slots (1..3) in a select mask, e.g. 0x05 -> [1, 3]."""
    if not 0 < select_mask <= 0x07:
        raise ValueError(f"select mask must be in 0x01..0x07, got 0x{select_mask:02X}")
    return [slot for slot, bit in SELECT_MASKS.items() if select_mask & bit]


def sample_ops(command: int, select_mask: int, bitrate_khz: int = DEFAULT_BITRATE_KHZ) -> list[SpiOp]:
    """One sample of every sensor in `select_mask`, padded to the 4400 samples/s period.

    Reply layout: 2 echo bytes, then 2 bytes per selected sensor in slot order.
    """
    sensors = slots(select_mask)
    ops: list[SpiOp] = [Select(select_mask), Transfer(bytes([command, 0x00])), Select(0), Delay(COMMAND_DELAY_NS)]
    for slot in sensors:
        ops += [Select(SELECT_MASKS[slot]), Transfer(b"\x00\x00"), Select(0)]
    ops.append(Delay(READ_DELAY_NS))
    busy_ns = COMMAND_DELAY_NS + READ_DELAY_NS + (2 + 2 * len(sensors)) * 8e6 / bitrate_khz
    pad_ns = int(1e9 / SAMPLE_RATE_HZ - busy_ns)
    if pad_ns > 0:
        ops.append(Delay(pad_ns))
    return ops


def frame_ops(select_mask: int, bitrate_khz: int = DEFAULT_BITRATE_KHZ) -> list[SpiOp]:
    """The batch for one 44-sample frame of every sensor in `select_mask`."""
    return [op for ch in FRAME_CHANNELS for op in sample_ops(sample_command(ch), select_mask, bitrate_khz)]


@dataclass(frozen=True)
class Frame:
    """One decoded frame of one sensor (raw 12-bit counts)."""

    electrodes: np.ndarray  # (19,) E1..E19
    pdc: int
    pac: np.ndarray  # (22,) at 2200 Hz
    tac: int
    tdc: int


def decode_frame(miso: bytes, select_mask: int) -> dict[int, Frame | WordError]:
    """Split a frame batch's MISO bytes per sensor slot; a slot with any bad word maps to its first WordError."""
    sensors = slots(select_mask)
    stride = 2 + 2 * len(sensors)
    if len(miso) != stride * FRAME_LENGTH:
        raise ValueError(f"frame reply has {len(miso)} bytes, expected {stride * FRAME_LENGTH}")
    out: dict[int, Frame | WordError] = {}
    for k, slot in enumerate(sensors):
        try:
            values = [
                decode_word(miso[i * stride + 2 + 2 * k], miso[i * stride + 3 + 2 * k]) for i in range(FRAME_LENGTH)
            ]
        except WordError as exc:
            out[slot] = exc
            continue
        by_channel = dict(zip(FRAME_CHANNELS[::2], values[::2], strict=True))
        out[slot] = Frame(
            electrodes=np.array([by_channel[ch] for ch in ELECTRODE_CHANNELS]),
            pdc=by_channel[Channel.PDC],
            pac=np.array(values[1::2]),
            tac=by_channel[Channel.TAC],
            tdc=by_channel[Channel.TDC],
        )
    return out


def property_ops(prop: Property, slot: int) -> list[SpiOp]:
    """Ask sensor `slot` for property `prop`, then clock out its bytes plus one for the end marker."""
    mask = SELECT_MASKS[slot]
    n = PROPERTY_LENGTHS[prop] + 1
    return [
        Select(mask),
        Transfer(bytes([READ_COMMAND, int(prop)])),
        Select(0),
        Delay(COMMAND_DELAY_NS),
        Select(mask),
        Transfer(bytes(n)),
        Select(0),
        Delay(READ_DELAY_NS),
    ]


def property_bytes(miso: bytes, prop: Property) -> bytes:
    """The property value from a `property_ops` reply: fixed-length numbers, text up to its end marker."""
    data = miso[2 : 2 + PROPERTY_LENGTHS[prop]]
    if prop == Property.SERIAL_NUMBER:
        for end in PROPERTY_END:
            data = data.split(bytes([end]))[0]
    return data
