"""The Weiss KMS40 ASCII protocol shared by driver and simulator: frames, flags, error replies.

Requests are `CMD(args)\\n`, replies `CMD=value\\n`, failures `ERROR(<code>,<text>)\\n`; a frame is
`F={fx,fy,fz,mx,my,mz},<timestamp>` with forces in N and torques in N·m in the sensor frame.
The timestamp's unit is *unverified* (the simulator sends milliseconds since power-up).
"""

from __future__ import annotations

import re

import numpy as np

from hardware.ft_sensor import FtSensorError

AXES = ("FX", "FY", "FZ", "MX", "MY", "MZ")
FLAG_BITS = {
    "CALIB_VALID": 0,
    "STABLE": 1,
    "TARA": 2,
    "FILTER_ENABLED": 3,
    "DAQ_RUNNING": 4,
    "CALIB_EXPIRED": 10,
    "TEMP_WARNING": 11,
    **{f"OVERRUN_{axis}": 20 + i for i, axis in enumerate(AXES)},
    "CALIB_FAULT": 26,
    "TEMP_FAULT": 27,
    "POWER_FAULT": 28,
    "CMD_FAILURE": 29,
}
FAULT_FLAGS = frozenset({"CALIB_FAULT", "TEMP_FAULT", "POWER_FAULT", "CMD_FAILURE"})
"""Flags that make the sensor unusable (it must also report CALIB_VALID)."""
BASE_RATE_HZ = 500.0  # streaming rate = BASE_RATE_HZ / LDIV
MAX_LINE_BYTES = 1024  # longer lines are garbage by definition
_FRAME = re.compile(r"F=\{([^{}]*)\},\s*([-+0-9.eE]+)")
_ERROR = re.compile(r"ERROR\((-?\d+)(?:,(.*))?\)")


class Kms40Error(FtSensorError):
    """The sensor answered ERROR(code, text), or did not answer in time (code None)."""

    def __init__(self, code: int | None, message: str) -> None:
        super().__init__(f"KMS40 error {code}: {message}" if code is not None else f"KMS40: {message}")
        self.code = code


def format_frame(wrench: np.ndarray, timestamp: int) -> str:
    """One `F={...},ts` line (no newline) for a (6,) wrench in N and N·m."""
    return "F={" + ",".join(f"{v:.5f}" for v in wrench) + f"}},{timestamp}"


def parse_frame(line: str) -> tuple[np.ndarray, float]:
    """(wrench (6,) N/N·m, device timestamp) of an `F=` line; ValueError when malformed or non-finite."""
    m = _FRAME.fullmatch(line.strip())
    if m is None:
        raise ValueError(f"not a KMS40 frame: {line[:80]!r}")
    values = np.array([float(v) for v in m[1].split(",")])
    if values.shape != (6,) or not np.all(np.isfinite(values)):
        raise ValueError(f"KMS40 frame needs 6 finite values: {line[:80]!r}")
    return values, float(m[2])


def parse_error(line: str) -> Kms40Error | None:
    """The Kms40Error an `ERROR(code,text)` line stands for, else None."""
    m = _ERROR.fullmatch(line.strip())
    return Kms40Error(int(m[1]), m[2] or "") if m else None


def decode_flags(value: int) -> set[str]:
    """Names of the FLAGS() bits set in `value` (unknown bits are reported as BIT<n>)."""
    named = {name for name, bit in FLAG_BITS.items() if value >> bit & 1}
    known = {bit for bit in FLAG_BITS.values()}
    return named | {f"BIT{b}" for b in range(32) if value >> b & 1 and b not in known}


def encode_flags(names: set[str]) -> int:
    """The FLAGS() integer with the bits in `names` set."""
    return sum(1 << FLAG_BITS[n] for n in names)
