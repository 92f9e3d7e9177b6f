"""Measured vs predicted, channel by channel, as flat tables that can be broken down any way.

Two tables per comparison, both long-form (one entry per sample, equal-length arrays):
- `rows`: the subsampled rows (the paper's comparison points: end of each 0.1 mm increment);
- `fullrate`: every full-rate sample, labelled loading / pause / unloading, for effects that live in
  the settle pauses and the moves.
Channels: force x, y, z (N, biotac frame, tared; rows filtered as in the paper, full rate unfiltered),
pdc (counts, raw). Electrodes are compared on rows only, after a per-sensor least-squares gain and
offset per electrode (the model does not know a real sensor's read-out).
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass, field

import numpy as np

from twin.analysis.data import CampaignData, TrajectoryRecord
from twin.analysis.predict import Prediction, Predictor, TwinModel, measured_force_fullrate
from twin.analysis.readings import force_readings, plateaus, resolution

FORCE_CHANNELS = ("force_x", "force_y", "force_z")
PHASES = ("loading", "pause", "unloading")


@dataclass
class SampleTable:
    """Long-form table: `labels` (per-sample covariates) and `measured` / `predicted` per channel."""

    labels: dict[str, np.ndarray] = field(default_factory=dict)
    measured: dict[str, np.ndarray] = field(default_factory=dict)
    predicted: dict[str, np.ndarray] = field(default_factory=dict)

    def residual(self, channel: str) -> np.ndarray:
        """measured - predicted of one channel."""
        return self.measured[channel] - self.predicted[channel]

    def __len__(self) -> int:
        return len(next(iter(self.labels.values()), ()))


@dataclass
class Comparison:
    """Both tables plus the model and data they came from; `noise` is the estimated per-channel noise."""

    model: TwinModel
    datasets: list[str]
    rows: SampleTable
    fullrate: SampleTable
    noise: dict[str, float]
    predictions: dict[tuple[int, int], Prediction]  # (sensor, trajectory) -> prediction


def _append(table: SampleTable, labels: dict, measured: dict, predicted: dict) -> None:
    for target, source in ((table.labels, labels), (table.measured, measured), (table.predicted, predicted)):
        for key, value in source.items():
            target.setdefault(key, []).append(np.asarray(value))


def _concatenate(table: SampleTable) -> SampleTable:
    return SampleTable(
        *({k: np.concatenate(v) for k, v in part.items()} for part in (table.labels, table.measured, table.predicted))
    )


def sample_phase(trajectory: TrajectoryRecord, move_s: float) -> np.ndarray:
    """Per full-rate sample: 0 loading move, 1 settle pause, 2 unloading move (standoff samples: pause)."""
    raw = trajectory.raw
    in_move = time_in_increment(trajectory) < move_s
    deepest = int(np.argmax(raw.depth_command))
    unloading = np.arange(len(raw.time)) > deepest
    phase = np.where(in_move, np.where(unloading, 2, 0), 1)
    phase[raw.increment < 0] = 1
    return phase


def time_in_increment(trajectory: TrajectoryRecord) -> np.ndarray:
    """Seconds since the current increment's command, per full-rate sample."""
    raw = trajectory.raw
    starts = np.r_[0, np.flatnonzero(np.diff(raw.increment)) + 1]
    start_time = np.repeat(raw.time[starts], np.diff(np.r_[starts, len(raw.time)]))
    return raw.time - start_time


LATTICE_REACH = 4.0
"""Scales within which a quantised reading's differences count as noise (`noise_estimate`)."""


def _robust_sigma(values: np.ndarray) -> float:
    """1.4826 MAD: the standard deviation of the normal part of `values` (NaN when none is finite)."""
    values = values[np.isfinite(values)]
    return float(1.4826 * np.median(np.abs(values - np.median(values)))) if values.size else float("nan")


def noise_estimate(trajectories: list[TrajectoryRecord]) -> dict[str, float]:
    """Per-channel full-rate white-noise standard deviation (N for forces, counts for pdc), robust (MAD).

    From the full-rate recordings: during the settle pauses the signal is (nearly) constant, so successive
    differences are noise: sigma = 1.4826 MAD(diff) / sqrt(2). Differences that touch a sample held at a
    clipped F/T range (`twin.analysis.readings.plateaus`: noise-free there) are left out. When the F/T reading
    is quantised (`twin.analysis.readings.resolution`, the coarsest axis's step q) a force channel's differences
    take a few values only, so its MAD can be 0 or a whole step: sigma is then their root mean square within
    `LATTICE_REACH` scales (max(sqrt(2) MAD sigma, q)), and never below the rounding noise q / sqrt(12). When no
    trajectory has raw streams (row-only files), `rows_noise_estimate` instead.
    """
    recorded = [t for t in trajectories if not t.rows_only]
    if not recorded:
        return rows_noise_estimate(trajectories)
    readings = force_readings(recorded)
    clipped = plateaus(readings)
    diffs: dict[str, list[np.ndarray]] = {c: [] for c in (*FORCE_CHANNELS, "pdc")}
    for t in recorded:
        force = measured_force_fullrate(t)
        held = clipped.at_limit(np.asarray(t.raw.wrench, dtype=float)[:, :3])
        free = ~(held[1:] | held[:-1])
        for i, c in enumerate(FORCE_CHANNELS):
            diffs[c].append(np.diff(force[:, i])[free])
        diffs["pdc"].append(np.diff(t.raw.pdc))
    steps = resolution(readings)
    step = float(np.nanmax(steps)) if np.isfinite(steps).any() else None
    noise = {}
    for c, parts in diffs.items():
        d = np.concatenate(parts)
        noise[c] = float(_robust_sigma(d) / np.sqrt(2.0))
        if step is not None and c in FORCE_CHANNELS:
            reach = LATTICE_REACH * max(np.sqrt(2.0) * noise[c], step)
            noise[c] = max(float(np.sqrt(np.mean(d[np.abs(d) <= reach] ** 2) / 2.0)), step / np.sqrt(12.0))
    return noise


def rows_noise(trajectories: list[TrajectoryRecord]) -> dict[str, float]:
    """Per-channel noise of the rows themselves (N for forces, low-passed as the rows are; counts for pdc).

    Rows are increment ends a settle pause apart, so their noise is independent from row to row; second
    differences along each press remove a force that changes linearly with depth: rows sigma = 1.4826
    MAD(second differences) / sqrt(6) (an upper bound where the force curves within three rows).
    """
    second: dict[str, list[np.ndarray]] = {c: [] for c in (*FORCE_CHANNELS, "pdc")}
    for t in trajectories:
        for i, c in enumerate(FORCE_CHANNELS):
            second[c].append(np.diff(t.rows["force"][:, i], n=2))
        second["pdc"].append(np.diff(np.asarray(t.rows["pdc"], dtype=float), n=2))
    return {c: float(_robust_sigma(np.concatenate(parts)) / np.sqrt(6.0)) for c, parts in second.items()}


def rows_noise_estimate(trajectories: list[TrajectoryRecord]) -> dict[str, float]:
    """Per-channel noise from rows alone, as the full-rate sigma `noise_estimate` gives: forces in rows are
    low-passed, so the full-rate sigma is the rows sigma (`rows_noise`) over the filter's noise gain at the
    trajectories' (stand-in) sample rate."""
    from twin.analysis.report.stats import filtered_noise_gain

    rates = [t.rate_hz for t in trajectories if len(t.raw.time) > 1]  # a press refused at once has one sample
    gain = filtered_noise_gain(float(np.median(rates)))
    return {c: v / gain if c in FORCE_CHANNELS else v for c, v in rows_noise(trajectories).items()}


def compare(
    datasets: list[CampaignData],
    model: TwinModel,
    predictor: Predictor,
    move_s: float = 0.1,
    progress: Callable[[int, int], None] | None = None,
) -> Comparison:
    """Predict every trajectory of every dataset (incomplete ones up to their cut; the replays solved as one
    batch, `Predictor.prefetch`) and tabulate both. progress(done, total) as the replays are solved."""
    rows, full = SampleTable(), SampleTable()
    predictions = {}
    predictor.prefetch(model, [t for d in datasets for t in d.trajectories], progress)
    for data in datasets:
        for t in data.trajectories:
            prediction = predictor.predict(model, t)
            predictions[(t.sensor_id, t.trajectory_id)] = prediction
            _append_rows(rows, t, prediction, data.indenter_names)
            _append_fullrate(full, t, prediction, move_s)
    noise = noise_estimate([t for d in datasets for t in d.trajectories])
    rows, full = _concatenate(rows), _concatenate(full)
    _fit_electrodes(rows)
    return Comparison(model, [str(d.path) for d in datasets], rows, full, noise, predictions)


def _trajectory_labels(t: TrajectoryRecord, n: int) -> dict[str, np.ndarray]:
    return {
        "sensor": np.full(n, t.sensor_id),
        "trajectory": np.full(n, t.trajectory_id),
        "indenter": np.full(n, t.indenter, dtype=object),
        "normal": np.full(n, t.normal),
    }


def _append_rows(table: SampleTable, t: TrajectoryRecord, p: Prediction, names: list[str]) -> None:
    n = len(t.rows["depth"])
    valid = np.isfinite(p.rows.force).all(axis=1)
    labels = {
        **_trajectory_labels(t, n),
        "depth": t.rows["depth"],
        "phase": np.where(t.rows["phase"] == 1, 2, 0),
        "time": t.rows["time"],
        "contact_x": t.rows["contact_loc"][:, 0],
        "contact_y": t.rows["contact_loc"][:, 1],
        "contact_z": t.rows["contact_loc"][:, 2],
        "converged": valid,
    }
    measured = {c: t.rows["force"][:, i] for i, c in enumerate(FORCE_CHANNELS)}
    predicted = {c: p.rows.force[:, i] for i, c in enumerate(FORCE_CHANNELS)}
    measured["pdc"], predicted["pdc"] = t.rows["pdc"], p.rows.pdc
    for e in range(19):
        measured[f"electrode_{e + 1}"] = t.rows["electrode_vals"][:, e]
        predicted[f"electrode_{e + 1}"] = p.rows.electrode_vals[:, e]
    _append(table, labels, measured, predicted)


def _append_fullrate(table: SampleTable, t: TrajectoryRecord, p: Prediction, move_s: float) -> None:
    raw = t.raw
    n = len(raw.time)
    force = measured_force_fullrate(t)
    labels = {
        **_trajectory_labels(t, n),
        "depth": raw.depth_command,
        "phase": sample_phase(t, move_s),
        "time": raw.time,
        "time_in_increment": time_in_increment(t),
        "converged": np.isfinite(p.force_fullrate).all(axis=1),
    }
    measured = {c: force[:, i] for i, c in enumerate(FORCE_CHANNELS)}
    predicted = {c: p.force_fullrate[:, i] for i, c in enumerate(FORCE_CHANNELS)}
    _append(table, labels, measured, predicted)


def _fit_electrodes(rows: SampleTable) -> None:
    """Replace each predicted electrode channel by its per-sensor least-squares affine fit to the measurement."""
    for e in range(1, 20):
        key = f"electrode_{e}"
        fitted = np.array(rows.predicted[key], dtype=float)
        for sensor in np.unique(rows.labels["sensor"]):
            mask = (rows.labels["sensor"] == sensor) & np.isfinite(fitted)
            if mask.sum() < 2 or np.ptp(fitted[mask]) == 0:
                continue
            design = np.column_stack([fitted[mask], np.ones(mask.sum())])
            coef, *_ = np.linalg.lstsq(design, rows.measured[key][mask], rcond=None)
            fitted[mask] = design @ coef
        rows.predicted[key] = fitted
