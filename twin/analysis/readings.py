"""What the raw F/T readings show of the sensor's electronics (sensor frame, untared, bias included):

- a clipped range: a reading that clips stays at its limit, so an axis whose largest |reading| over the campaign
  is held by `PLATEAU_SAMPLES` samples or more (to `PLATEAU_TOLERANCE_N`) clips there (`plateaus`);
- a resolution: a quantised reading takes values on a lattice, so the distinct values of an axis lie a whole
  number of steps apart; the step is the smallest gap between them, kept when it is at least `MIN_STEP_N` and
  nearly every gap (`LATTICE_SHARE`) is a whole multiple of it (to `LATTICE_TOLERANCE`; `lattice_step`).

A continuous noisy reading shows neither (no plateau; gaps far below a ten-thousandth of a newton). The noise
estimate leaves clipped samples out and never goes below a resolution's rounding noise
(`twin.analysis.compare.noise_estimate`); a range is also where `ft_saturation`'s fit starts
(`twin.analysis.reading_starts`).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from twin.analysis.data import TrajectoryRecord

PLATEAU_SAMPLES = 5
"""Samples at an axis's largest |reading| that make it a clipped range (a clipped press holds it for many)."""
PLATEAU_TOLERANCE_N = 1e-9
"""How close to the largest |reading| a sample must be to count as held there (N)."""
MIN_STEP_N = 1e-4
"""Smallest quantisation step taken from the data (N): finer gaps are those of a continuous noisy reading."""
LATTICE_TOLERANCE = 1e-3
"""How close to a whole number of steps a gap must be (fraction of a step)."""
LATTICE_SHARE = 0.99
"""Share of the gaps that must be whole multiples of the step."""


def force_readings(trajectories: list[TrajectoryRecord]) -> np.ndarray:
    """(T, 3) every raw force reading of the trajectories that have raw streams (N, sensor frame, untared)."""
    parts = [np.asarray(t.raw.wrench, dtype=float)[:, :3] for t in trajectories if not t.rows_only]
    return np.concatenate(parts) if parts else np.zeros((0, 3))


@dataclass(frozen=True)
class Plateaus:
    """Per force axis: the largest |reading| over the campaign (N) and how many samples hold it."""

    largest: np.ndarray  # (3,) N
    held: np.ndarray  # (3,) samples

    @property
    def clipped(self) -> np.ndarray:
        """(3,) bool: the axes whose largest reading is a plateau (`PLATEAU_SAMPLES`)."""
        return self.held >= PLATEAU_SAMPLES

    def at_limit(self, readings: np.ndarray) -> np.ndarray:
        """(T,) bool: the samples of `readings` (T, 3) held at a clipped axis's plateau."""
        limit = np.where(self.clipped, self.largest - PLATEAU_TOLERANCE_N, np.inf)
        return (np.abs(readings) >= limit).any(axis=1)


def plateaus(readings: np.ndarray) -> Plateaus:
    """The largest |reading| per axis of `readings` (T, 3) (a campaign's, `force_readings`) and how many samples
    hold it."""
    magnitude = np.abs(readings)
    if magnitude.size == 0:
        return Plateaus(np.zeros(3), np.zeros(3, dtype=int))
    largest = magnitude.max(axis=0)
    return Plateaus(largest, (magnitude >= largest - PLATEAU_TOLERANCE_N).sum(axis=0))


def lattice_step(values: np.ndarray) -> float:
    """The step (N) of the lattice `values` (N,) lie on (see the module docstring), or NaN."""
    gaps = np.diff(np.unique(values))
    gaps = gaps[gaps > 0.0]
    if gaps.size == 0 or gaps.min() < MIN_STEP_N:
        return float("nan")
    multiples = gaps / gaps.min()
    if (np.abs(multiples - np.round(multiples)) <= LATTICE_TOLERANCE).mean() < LATTICE_SHARE:
        return float("nan")
    return float(np.median(gaps[np.round(multiples) == 1.0]))


def resolution(readings: np.ndarray) -> np.ndarray:
    """(3,) the lattice step of each axis of `readings` (T, 3) (a campaign's, `force_readings`; N; NaN: not
    quantised)."""
    return np.array([lattice_step(readings[:, axis]) if len(readings) else np.nan for axis in range(3)])
