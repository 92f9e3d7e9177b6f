"""Validate a model like the paper: the model on every trajectory, mean RMS force error per indenter.

Per trajectory (Narang et al., Eq. 1's force term): the sum over the three axes of the RMS error (N)
between predicted and measured row forces (filtered, increment-end samples, biotac frame), using only
rows whose measured force magnitude exceeds 0.5 N (the F/T noise floor) and that the model reached
before it stopped converging. Per indenter: the mean over its trajectories, and that mean normalised by
the indenter's measured force-magnitude range.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import asdict, dataclass
from pathlib import Path

import numpy as np

from twin.analysis.data import CampaignData, TrajectoryRecord
from twin.analysis.predict import Prediction, Predictor, TwinModel

FORCE_THRESHOLD = 0.5
"""Only measured forces above this magnitude (N) are compared (the paper's threshold)."""


@dataclass(frozen=True)
class TrajectoryError:
    """One trajectory's validation error."""

    sensor: int
    trajectory: int
    indenter: str
    normal: bool
    rms_n: float  # sum of per-axis RMS errors (N); NaN when no row qualifies
    rows_used: int
    rows_reached: int  # rows before non-convergence
    rows_total: int
    force_max_n: float  # largest measured force magnitude (N)


@dataclass(frozen=True)
class IndenterError:
    """Mean and spread of the trajectory errors of one indenter."""

    indenter: str
    trajectories: int
    mean_rms_n: float
    median_rms_n: float
    force_range_n: float  # measured force-magnitude range over its qualifying rows (N)
    normalised: float  # mean_rms_n / force_range_n


@dataclass(frozen=True)
class Validation:
    """Per-trajectory and per-indenter errors, and the predictions behind them (for plots)."""

    trajectories: list[TrajectoryError]
    indenters: list[IndenterError]
    predictions: dict[tuple[int, int], Prediction]

    def to_dict(self) -> dict:
        """JSON-ready form (the `twin validate --json` shape)."""
        means = [i.mean_rms_n for i in self.indenters if np.isfinite(i.mean_rms_n)]
        return {
            "force_threshold_n": FORCE_THRESHOLD,
            "indenters": {i.indenter: asdict(i) for i in self.indenters},
            "median_of_indenter_means_n": float(np.median(means)) if means else None,
            "trajectories": [asdict(t) for t in self.trajectories],
        }


def trajectory_error(trajectory: TrajectoryRecord, prediction: Prediction) -> TrajectoryError:
    """The paper's per-trajectory error (see the module docstring)."""
    measured = trajectory.rows["force"]
    predicted = prediction.rows.force
    reached = np.isfinite(predicted).all(axis=1)
    if not reached.all():
        reached[np.argmin(reached) :] = False  # only before the first failure
    magnitude = np.linalg.norm(measured, axis=1)
    used = reached & (magnitude > FORCE_THRESHOLD)
    rms = float(np.sum(np.sqrt(np.mean((predicted[used] - measured[used]) ** 2, axis=0)))) if used.any() else np.nan
    return TrajectoryError(
        trajectory.sensor_id,
        trajectory.trajectory_id,
        trajectory.indenter,
        bool(trajectory.normal),
        rms,
        int(used.sum()),
        int(reached.sum()),
        len(reached),
        float(magnitude.max(initial=0.0)),
    )


def validate(
    datasets: list[CampaignData],
    model: TwinModel,
    predictor: Predictor | None = None,
    progress: Callable[[int, int], None] | None = None,
) -> Validation:
    """Predict every trajectory (the replays solved as one batch, `Predictor.prefetch`) and tabulate the
    errors; progress(done, total) as the replays are solved and after each prediction."""
    predictor = predictor or Predictor()
    trajectories = [t for d in datasets for t in d.trajectories]
    if not trajectories:
        raise ValueError("the datasets hold no trajectories")
    predictor.prefetch(model, trajectories, progress)
    errors, predictions = [], {}
    for i, t in enumerate(trajectories):
        prediction = predictor.predict(model, t)
        predictions[(t.sensor_id, t.trajectory_id)] = prediction
        errors.append(trajectory_error(t, prediction))
        if progress is not None:
            progress(i + 1, len(trajectories))
    indenters = []
    for name in sorted({e.indenter for e in errors}):
        mine = [e for e in errors if e.indenter == name and np.isfinite(e.rms_n)]
        rms = np.array([e.rms_n for e in mine])
        magnitudes = [np.linalg.norm(t.rows["force"], axis=1) for t in trajectories if t.indenter == name]
        qualifying = np.concatenate([m[m > FORCE_THRESHOLD] for m in magnitudes])
        force_range = float(np.ptp(qualifying)) if qualifying.size else np.nan
        mean = float(rms.mean()) if rms.size else np.nan
        indenters.append(
            IndenterError(
                name,
                len(mine),
                mean,
                float(np.median(rms)) if rms.size else np.nan,
                force_range,
                mean / force_range if force_range and np.isfinite(force_range) and force_range > 0 else np.nan,
            )
        )
    return Validation(errors, indenters, predictions)


def plot_validation(validation: Validation, datasets: list[CampaignData], out_dir: Path) -> list[Path]:
    """Bar chart of per-indenter mean RMS error and, per indenter, measured vs predicted force of its
    deepest trajectory (PNG files in `out_dir`)."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    out_dir = Path(out_dir)
    out_dir.mkdir(parents=True, exist_ok=True)
    paths = []
    fig, ax = plt.subplots(figsize=(7, 3.5))
    names = [i.indenter for i in validation.indenters]
    ax.bar(names, [i.mean_rms_n for i in validation.indenters], color="tab:blue")
    ax.set_ylabel("mean RMS force error (N)")
    ax.set_title(f"validation: measured |F| > {FORCE_THRESHOLD} N, before non-convergence")
    ax.tick_params(axis="x", rotation=45)
    fig.tight_layout()
    paths.append(out_dir / "validation_by_indenter.png")
    fig.savefig(paths[-1], dpi=120)
    plt.close(fig)
    by_key = {(t.sensor_id, t.trajectory_id): t for d in datasets for t in d.trajectories}
    for name in names:
        mine = [e for e in validation.trajectories if e.indenter == name]
        deepest = max(mine, key=lambda e: e.force_max_n)
        t = by_key[(deepest.sensor, deepest.trajectory)]
        p = validation.predictions[(deepest.sensor, deepest.trajectory)]
        fig, ax = plt.subplots(figsize=(6, 3.2))
        for i, (axis, colour) in enumerate(zip("xyz", ("tab:red", "tab:green", "tab:blue"), strict=True)):
            ax.plot(t.rows["force"][:, i], color=colour, label=f"F{axis} measured")
            ax.plot(p.rows.force[:, i], color=colour, linestyle="--", label=f"F{axis} model")
        ax.set_xlabel("row (increment end)")
        ax.set_ylabel("force (N, biotac frame)")
        ax.set_title(f"{name}: sensor {deepest.sensor}, trajectory {deepest.trajectory}, RMS {deepest.rms_n:.3f} N")
        ax.legend(fontsize=7, ncol=2)
        fig.tight_layout()
        paths.append(out_dir / f"validation_{name}.png")
        fig.savefig(paths[-1], dpi=120)
        plt.close(fig)
    return paths
