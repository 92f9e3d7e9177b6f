"""The paper's signal processing (Methods C): from a full-rate recording to dataset rows.

Forward kinematics gives the indenter tip in the robot frame, the estimated registration takes it
to the biotac frame; electrodes and F/T are tared at the trajectory's first sample; forces are
low-passed by a first-order 5 Hz Butterworth filter run forward and backward; rows are the last
sample of each 0.1 mm increment. The F/T reading is turned into the force the indenter applies to
the BioTac through the mount's (CAD-known) sensor-to-biotac rotation.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy.signal import butter, filtfilt

from twin.controller import Recording
from twin.kinematics import forward

FILTER_CUTOFF_HZ = 5.0
FILTER_ORDER = 1


@dataclass(frozen=True)
class ProcessedRows:
    """Subsampled rows of one trajectory (R rows; SI units; biotac frame unless named otherwise)."""

    sample_index: np.ndarray  # (R,) index into the full-rate recording
    electrode_vals: np.ndarray  # (R, 19) tared counts
    electrode_tare: np.ndarray  # (R, 19) counts at the first sample
    pdc: np.ndarray  # (R,) raw counts
    force: np.ndarray  # (R, 3) N, indenter on BioTac, tared, filtered
    contact_loc: np.ndarray  # (R, 3) m, tip position in the biotac frame (estimated registration)
    tip_pos: np.ndarray  # (R, 3) m, tip position in the robot frame
    depth: np.ndarray  # (R,) m
    phase: np.ndarray  # (R,) 0 loading, 1 unloading
    joint_angles: np.ndarray  # (R, 7) rad
    time: np.ndarray  # (R,) s


def lowpass(signal: np.ndarray, rate_hz: float, cutoff_hz: float = FILTER_CUTOFF_HZ) -> np.ndarray:
    """Zero-phase first-order Butterworth low-pass along axis 0 (forward-backward, as in the paper)."""
    if len(signal) <= 3 * (FILTER_ORDER + 1):  # too short to pad: left as it is (its rate may be undefined)
        return np.asarray(signal, dtype=float).copy()
    if not cutoff_hz < 0.5 * rate_hz:
        raise ValueError(f"cutoff {cutoff_hz} Hz must be below the Nyquist frequency {0.5 * rate_hz} Hz")
    b, a = butter(FILTER_ORDER, cutoff_hz, fs=rate_hz)
    return filtfilt(b, a, signal, axis=0)


def increment_ends(increment: np.ndarray) -> np.ndarray:
    """Index of the last sample of each increment >= 0, in recording order."""
    increment = np.asarray(increment)
    last = np.flatnonzero(np.diff(increment, append=increment[-1] + 1) != 0)
    return last[increment[last] >= 0]


def loading_phase(depth: np.ndarray) -> np.ndarray:
    """0 while the commanded depth has not yet passed its maximum, 1 afterwards (unloading); no rows, none."""
    if len(depth) == 0:  # a press stopped before its first row (the FE refused its first step)
        return np.zeros(0, dtype=np.int64)
    deepest = int(np.argmax(depth))
    phase = np.zeros(len(depth), dtype=np.int64)
    phase[deepest + 1 :] = 1
    return phase


def process(
    recording: Recording,
    arm: str,
    tool_tip: np.ndarray,
    robot_to_biotac: np.ndarray,
    sensor_to_biotac: np.ndarray,
    rate_hz: float,
) -> ProcessedRows:
    """Rows of `recording` made with `arm` and flange->tip transform `tool_tip`.

    robot_to_biotac: 4x4 map of robot-frame points into the biotac frame (the estimated registration).
    sensor_to_biotac: 4x4 pose of the F/T sensor frame in the biotac frame (mount CAD).
    """
    if len(recording.time) == 0:
        raise ValueError("empty recording")
    tared_wrench = recording.wrench - recording.wrench[0]
    force_biotac = tared_wrench[:, :3] @ sensor_to_biotac[:3, :3].T
    filtered = lowpass(force_biotac, rate_hz)
    rows = increment_ends(recording.increment)
    tips = np.array([forward(arm, recording.joints[i], tool_tip)[:3, 3] for i in rows]).reshape(-1, 3)
    contact = tips @ robot_to_biotac[:3, :3].T + robot_to_biotac[:3, 3]
    depth = recording.depth_command[rows]
    return ProcessedRows(
        sample_index=rows,
        electrode_vals=recording.electrodes[rows] - recording.electrodes[0],
        electrode_tare=np.repeat(recording.electrodes[:1], len(rows), axis=0),
        pdc=recording.pdc[rows],
        force=filtered[rows],
        contact_loc=contact,
        tip_pos=tips,
        depth=depth,
        phase=loading_phase(depth),
        joint_angles=recording.joints[rows],
        time=recording.time[rows],
    )
