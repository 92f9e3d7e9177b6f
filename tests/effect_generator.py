"""An independent generator of measurement effects (an F/T calibration map, a drift, a stream delay, a clipped
range, a quantised resolution; a PDC gain and drift): applied to a campaign file's raw F/T and PDC streams.

Written apart from `twin.plant`, `twin.effects` and `twin.analysis` (it imports none of them): it reads
the file with h5py, changes each trajectory's full-rate F/T force reading (`raw/<id>/wrench`, sensor
frame, untared) and recomputes the subsampled `force` rows the way the testbed's processing documents
it (docs/dataset.md, Narang et al.): tare at the first sample, rotate into the biotac frame with the
trajectory's `sensor_in_biotac`, first-order 5 Hz zero-phase Butterworth low-pass, the last sample of
each increment. Before changing anything it checks that this recomputation reproduces the file's own
rows, so a file it writes is what the testbed would have written had the sensor carried the effect.
The PDC rows are the raw PDC at the same samples, untared.
"""

from __future__ import annotations

import shutil
from collections.abc import Callable, Iterator
from pathlib import Path

import h5py
import numpy as np
from scipy.signal import butter, filtfilt

CUTOFF_HZ = 5.0
"""The paper's force filter: first order, 5 Hz, forward and backward."""
ROWS_AGREE_N = 1e-9
"""How closely the recomputed rows must match the file's before any change (N)."""


def _rows_force(
    time: np.ndarray, wrench: np.ndarray, increment: np.ndarray, sensor_in_biotac: np.ndarray
) -> np.ndarray:
    """(R, 3) row forces (N, biotac frame) of one trajectory from its raw stream (see module docstring)."""
    force = (wrench[:, :3] - wrench[0, :3]) @ sensor_in_biotac[:3, :3].T
    rate = 1.0 / np.median(np.diff(time))
    b, a = butter(1, CUTOFF_HZ / (0.5 * rate))
    smooth = filtfilt(b, a, force, axis=0) if len(force) > 3 * max(len(a), len(b)) else force
    return smooth[_row_samples(increment)]


def _row_samples(increment: np.ndarray) -> np.ndarray:
    """The samples rows are taken at: the last of each increment >= 0 (the standoff, -1, has none)."""
    last = np.flatnonzero(np.diff(increment, append=increment[-1] + 1) != 0)
    return last[increment[last] >= 0]


def _trajectories(f: h5py.File) -> Iterator[tuple[int, h5py.Group, slice, np.ndarray]]:
    """Each trajectory of an open campaign file: its id, raw group, rows (a slice of the row datasets) and
    sensor_in_biotac (4x4)."""
    meta = f["trajectories"]
    for i, tid in enumerate(meta["trajectory_id"][()]):
        first, n = int(meta["first_row"][i]), int(meta["n_rows"][i])
        yield int(tid), f[f"raw/{int(tid)}"], slice(first, first + n), meta["sensor_in_biotac"][i]


def apply_ft_map(source: Path, out: Path, mapping: np.ndarray) -> Path:
    """Copy `source` to `out` with every trajectory's F/T force reading mapped by the 3x3 `mapping`
    (sensor frame: reading = mapping @ true force, the bias included, as a miscalibrated sensor reads)
    and its force rows recomputed. Raises when the recomputation does not reproduce the source rows."""
    mapping = np.asarray(mapping, dtype=float)

    def change(wrench: np.ndarray, time: np.ndarray) -> np.ndarray:
        wrench[:, :3] = wrench[:, :3] @ mapping.T
        return wrench

    return _apply(source, out, change)


def apply_ft_delay(source: Path, out: Path, samples: int) -> Path:
    """Copy `source` to `out` with every trajectory's F/T reading (force and torque) lagging the other
    streams by `samples` whole samples (the first reading held until then, as a stream that starts late
    reads) and its force rows recomputed."""

    def change(wrench: np.ndarray, time: np.ndarray) -> np.ndarray:
        return np.concatenate([np.repeat(wrench[:1], samples, axis=0), wrench[: len(wrench) - samples]])

    return _apply(source, out, change)


def apply_ft_drift(source: Path, out: Path, rates: np.ndarray) -> Path:
    """Copy `source` to `out` with every trajectory's F/T force reading drifting by `rates` (3,) N/s per sensor axis
    on the file's clock (a bias that creeps; taring removes its value at the first sample) and its force rows
    recomputed."""
    rates = np.asarray(rates, dtype=float)

    def change(wrench: np.ndarray, time: np.ndarray) -> np.ndarray:
        wrench[:, :3] += np.outer(time, rates)
        return wrench

    return _apply(source, out, change)


def apply_ft_clip(source: Path, out: Path, limits: np.ndarray) -> Path:
    """Copy `source` to `out` with every trajectory's F/T force reading clipped to +-`limits` (3,) N per sensor
    axis (the reading as recorded: bias and noise included, as an electronics' range clips it) and its force
    rows recomputed."""
    limits = np.asarray(limits, dtype=float)

    def change(wrench: np.ndarray, time: np.ndarray) -> np.ndarray:
        wrench[:, :3] = np.minimum(np.maximum(wrench[:, :3], -limits), limits)
        return wrench

    return _apply(source, out, change)


def apply_ft_quantise(source: Path, out: Path, step: float) -> Path:
    """Copy `source` to `out` with every trajectory's F/T force reading rounded to whole multiples of `step` (N)
    (the reading as recorded) and its force rows recomputed."""

    def change(wrench: np.ndarray, time: np.ndarray) -> np.ndarray:
        wrench[:, :3] = step * np.floor(wrench[:, :3] / step + 0.5)
        return wrench

    return _apply(source, out, change)


def apply_pdc_map(source: Path, out: Path, gain: float, rate: float) -> Path:
    """Copy `source` to `out` with every trajectory's raw PDC reading p (counts) at time t (s, the file's clock)
    replaced by gain * p + rate * t, and the PDC rows (the raw PDC at each increment's last sample) taken again."""
    shutil.copyfile(source, out)
    with h5py.File(out, "r+") as f:
        rows = f["pdc/data"]
        values = rows[()]
        for tid, raw, taken, _ in _trajectories(f):
            last = _row_samples(raw["increment"][()])
            if not np.array_equal(raw["pdc"][()][last], values[taken]):
                raise RuntimeError(f"trajectory {tid}: the PDC rows are not the raw PDC at the increment ends")
            pdc = gain * raw["pdc"][()] + rate * raw["time"][()]
            raw["pdc"][...] = pdc
            values[taken] = pdc[last]
        rows[...] = values
    return out


def _apply(source: Path, out: Path, change: Callable[[np.ndarray, np.ndarray], np.ndarray]) -> Path:
    """Copy `source` to `out`, replace each trajectory's raw wrench (T, 6) by change(wrench, time (T,) s) and recompute
    its force rows; raises when the recomputation does not reproduce the source rows first."""
    shutil.copyfile(source, out)
    with h5py.File(out, "r+") as f:
        rows = f["force/data"]
        forces = rows[()]
        for tid, raw, taken, rotation in _trajectories(f):
            time, wrench, increment = raw["time"][()], raw["wrench"][()], raw["increment"][()]
            again = _rows_force(time, wrench, increment, rotation)
            if again.shape != forces[taken].shape or np.abs(again - forces[taken]).max() > ROWS_AGREE_N:
                raise RuntimeError(f"trajectory {tid}: the recomputed rows do not match the file's")
            wrench = change(wrench, time)
            raw["wrench"][...] = wrench
            forces[taken] = _rows_force(time, wrench, increment, rotation)
        rows[...] = forces
    return out
