"""Residual statistics of a comparison: per-channel RMS / mean / count, their breakdowns, noise levels.

Errors are residuals measured - predicted. Channels are those of `twin.analysis.compare` plus two
derived per-sample magnitudes: `force` (N, Euclidean norm of the force residual vector, biotac frame)
and `electrodes` (counts, RMS over the 19 electrodes). The RMS of `force` over samples is
sqrt(sum of the per-axis mean squares); the RMS of `electrodes` is the pooled electrode RMS; their
`mean` is the mean magnitude, not a bias. Samples whose prediction did not converge are NaN and are
left out of every statistic (`n` counts what was used). Depths are m inside, mm in group names.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass

import numpy as np

from twin.analysis.compare import FORCE_CHANNELS, PHASES, Comparison, SampleTable
from twin.processing import lowpass

ROW_CHANNELS = (*FORCE_CHANNELS, "force", "pdc", "electrodes")
"""Channels of the per-covariate breakdowns of the rows table."""
FULLRATE_CHANNELS = (*FORCE_CHANNELS, "force")
"""Channels of the per-phase breakdown of the full-rate table."""
DEPTH_STEPS_MM = (0.1, 0.2, 0.25, 0.5, 1.0, 2.0, 5.0)
MAX_DEPTH_BINS = 6


@dataclass(frozen=True)
class ErrorStats:
    """Residual statistics of one channel over a set of samples (units of the channel)."""

    rms: float
    mean: float
    n: int

    def to_json(self) -> dict:
        """JSON-ready dict; NaN (no samples) becomes null."""
        return {"rms": _json_float(self.rms), "mean": _json_float(self.mean), "n": self.n}


def _json_float(value: float) -> float | None:
    return float(value) if np.isfinite(value) else None


def residuals(table: SampleTable) -> dict[str, np.ndarray]:
    """measured - predicted of every channel of `table`, plus the derived `force` and `electrodes`."""
    out = {c: table.residual(c) for c in table.measured}
    if all(c in out for c in FORCE_CHANNELS):
        out["force"] = np.linalg.norm(np.column_stack([out[c] for c in FORCE_CHANNELS]), axis=1)
    electrodes = [c for c in out if c.startswith("electrode_")]
    if electrodes:
        out["electrodes"] = np.sqrt(np.mean(np.column_stack([out[c] for c in electrodes]) ** 2, axis=1))
    return out


def trajectories(table: SampleTable) -> list[np.ndarray]:
    """Sample indices of each (sensor, trajectory), in table order."""
    keys = np.column_stack([table.labels["sensor"], table.labels["trajectory"]])
    _, inverse = np.unique(keys, axis=0, return_inverse=True)
    return [np.flatnonzero(inverse.ravel() == k) for k in range(inverse.max() + 1)] if len(keys) else []


def error_stats(residual: np.ndarray) -> ErrorStats:
    """RMS, mean and count of the finite entries of `residual` (NaN statistics when none)."""
    finite = residual[np.isfinite(residual)]
    if not len(finite):
        return ErrorStats(float("nan"), float("nan"), 0)
    return ErrorStats(float(np.sqrt(np.mean(finite**2))), float(np.mean(finite)), len(finite))


def grouped_stats(residual: np.ndarray, groups: np.ndarray, name: Callable = str) -> dict[str, ErrorStats]:
    """`error_stats` per distinct value of `groups` (sorted), keyed by `name(value)`."""
    return {name(g): error_stats(residual[groups == g]) for g in np.unique(groups)}


def depth_step_mm(max_depth: float) -> float:
    """Bin width (mm) for depths up to `max_depth` (m): the finest step giving at most MAX_DEPTH_BINS bins."""
    needed = max(max_depth * 1e3, DEPTH_STEPS_MM[0]) / MAX_DEPTH_BINS
    return next((s for s in DEPTH_STEPS_MM if s >= needed - 1e-9), DEPTH_STEPS_MM[-1])


def depth_bins(depth: np.ndarray) -> tuple[np.ndarray, Callable[[int], str]]:
    """Bin index of each depth (m) and the bins' names (mm).

    Bin k >= 0 holds depths in (k w, (k+1) w] mm, named "lo-hi"; bin -1, named "<=0", holds the samples
    with no commanded indentation (first contact and the retract). w is `depth_step_mm` of the deepest sample.
    """
    finite = depth[np.isfinite(depth)]
    step = depth_step_mm(float(finite.max()) if len(finite) else 0.0)
    index = np.maximum(np.ceil(np.round(depth * 1e3 / step, 6)) - 1, -1).astype(int)
    return index, lambda k: "<=0" if k < 0 else f"{k * step:g}-{(k + 1) * step:g}"


def row_groupings(rows: SampleTable) -> dict[str, tuple[np.ndarray, Callable]]:
    """The covariates the rows table is broken down by: (group of each sample, group naming)."""
    labels = rows.labels
    return {
        "indenter": (labels["indenter"], str),
        "sensor": (labels["sensor"], str),
        "normal": (labels["normal"], lambda normal: "normal" if normal else "angled"),
        "depth_mm": depth_bins(labels["depth"]),
    }


def breakdowns(comparison: Comparison) -> dict[str, dict[str, dict[str, ErrorStats]]]:
    """{covariate: {channel: {group: stats}}}: rows by `row_groupings`, the full-rate table by phase."""
    rows_res, full_res = residuals(comparison.rows), residuals(comparison.fullrate)
    out = {
        by: {c: grouped_stats(rows_res[c], groups, name) for c in ROW_CHANNELS if c in rows_res}
        for by, (groups, name) in row_groupings(comparison.rows).items()
    }
    phase = comparison.fullrate.labels["phase"]
    out["phase"] = {c: grouped_stats(full_res[c], phase, PHASES.__getitem__) for c in FULLRATE_CHANNELS}
    return out


def filtered_noise_gain(rate_hz: float) -> float:
    """Standard deviation of unit white noise after the rows' force filter (exact: impulse response norm)."""
    impulse = np.zeros(int(20 * rate_hz) + 1)
    impulse[len(impulse) // 2] = 1.0
    return float(np.linalg.norm(lowpass(impulse, rate_hz)))


def noise_levels(comparison: Comparison) -> dict[str, dict[str, float]]:
    """Per channel, the noise sigma of full-rate samples and of rows (forces in rows are low-passed)."""
    time = comparison.fullrate.labels["time"]
    gain = filtered_noise_gain(float(1.0 / np.median(np.diff(time))))
    return {
        c: {"fullrate": sigma, "rows": sigma * gain if c in FORCE_CHANNELS else sigma}
        for c, sigma in comparison.noise.items()
    }
