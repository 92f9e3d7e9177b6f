"""The whitened full-rate residual that diagnosis, the nuisance stage and the noise test work on.

Four full-rate channels of every sample where the model converged (of a file read from rows only, of its rows
alone, `residual_samples`): the tared force (N, biotac frame;
x, y, z) and the tared PDC (counts), each measured minus predicted, whitened by the noise estimated from
the data itself, with each trajectory's constant offset projected out (the tare sample carries one noise
draw the model cannot know; this is also where a real F/T sensor's bias goes). A real sensor's PDC gain is
unknown to about 5 %, so each sensor's PDC gain is a nuisance parameter with that prior, profiled out of
the residual and of every sensitivity. For a model that lacks nothing, the whitened residual has unit
variance.

A trajectory may be predicted by its own variant of the model (`ModelFor`): the nuisance stage
(`twin.analysis.nuisances`) gives each arm its registration offset and each sensor its skin.
"""

from __future__ import annotations

from collections.abc import Callable, Sequence
from dataclasses import dataclass, replace
from functools import cached_property

import numpy as np

from assets.indenters import get_indenter
from twin.analysis.compare import FORCE_CHANNELS, noise_estimate, rows_noise, time_in_increment
from twin.analysis.data import CampaignData, TrajectoryRecord
from twin.analysis.predict import Predictor, TwinModel, filtered, measured_force_fullrate, measured_pdc_fullrate
from twin.analysis.significance import NO_FIT, NoiseTest, OutOfFold, noise_test
from twin.processing import increment_ends

CHANNELS = (*FORCE_CHANNELS, "pdc")
"""Residual channels, in the order of the last axis of every signal array."""
PDC_GAIN_PRIOR = 0.05
"""Relative 1-sigma spread of a sensor's PDC gain about nominal (the plant's unit-to-unit prior)."""

ModelFor = Callable[[TwinModel, TrajectoryRecord], TwinModel]
"""The model that predicts one trajectory, given the campaign's model (the identity without nuisances)."""


def same_model(model: TwinModel, trajectory: TrajectoryRecord) -> TwinModel:
    """Every trajectory is predicted by the campaign's model itself."""
    return model


@dataclass(frozen=True)
class Residual:
    """Whitened, offset-projected full-rate force residual and the bookkeeping to build it."""

    values: np.ndarray  # (N,) whitened residual
    trajectory_index: np.ndarray  # (N,) index into the trajectory list
    indenter: np.ndarray  # (N,) indenter name per sample
    covariates: dict[str, np.ndarray]  # (N,) each; "axis" indexes CHANNELS
    sigma: np.ndarray  # (4,) noise per channel (N, N, N, counts)


def fullrate_prediction(
    predictor: Predictor, model: TwinModel, trajectories: list[TrajectoryRecord], model_for: ModelFor = same_model
) -> list[np.ndarray]:
    """Per trajectory (T, 4): predicted tared force x, y, z (N; low-passed like the rows for a trajectory read
    from rows only) and PDC (counts), each trajectory by model_for(model, trajectory); the missing replays
    solved as one batch first (`Predictor.prefetch_many`)."""
    models = [model_for(model, t) for t in trajectories]
    predictor.prefetch_many(model_requests([model], trajectories, model_for))
    out = []
    for m, t in zip(models, trajectories, strict=True):
        p = predictor.predict(m, t, rows=False)
        force = filtered(p.force_fullrate, t.rate_hz) if t.rows_only else p.force_fullrate  # rows are low-passed
        out.append(np.column_stack([force, p.pdc_fullrate]))
    return out


def model_requests(
    models: Sequence[TwinModel], trajectories: list[TrajectoryRecord], model_for: ModelFor = same_model
) -> list[tuple[TwinModel, list[TrajectoryRecord]]]:
    """The (model, its trajectories) requests (`Predictor.prefetch_many`) that predicting every trajectory
    under each of `models` makes, each trajectory by model_for(model, trajectory)."""
    groups: dict[str, tuple[TwinModel, list[TrajectoryRecord]]] = {}
    for model in models:
        for t in trajectories:
            m = model_for(model, t)
            groups.setdefault(m.key(), (m, []))[1].append(t)
    return list(groups.values())


def measured(trajectory: TrajectoryRecord) -> np.ndarray:
    """(T, 4) measured tared force x, y, z (N) and PDC (counts)."""
    return np.column_stack([measured_force_fullrate(trajectory), measured_pdc_fullrate(trajectory)])


class GainNuisance:
    """Profiles each sensor's PDC gain (prior `PDC_GAIN_PRIOR`) out of whitened residual vectors.

    With n the whitened base PDC prediction of a sensor's samples, a relative gain error g adds g n to
    the residual; minimising |r - g n|^2 + (g / prior)^2 over g leaves r - n (n.r) / (n.n + prior^-2).
    """

    def __init__(self, base: np.ndarray, axis: np.ndarray, sensor: np.ndarray) -> None:
        pdc = CHANNELS.index("pdc")
        self._groups = []
        for s in np.unique(sensor):
            index = np.flatnonzero((axis == pdc) & (sensor == s))
            n = np.nan_to_num(base[index])
            self._groups.append((index, n, float(n @ n) + PDC_GAIN_PRIOR**-2))

    def penalty(self, projected: np.ndarray) -> float:
        """Prior cost sum (g / prior)^2 of the gains profiled out of a projected residual (N,).

        For the projected vector v = P r, n.v = prior^-2 g, so the cost is (n.v)^2 prior^2."""
        return float(np.sum(self.penalty_rows(projected) ** 2))

    def chi2(self, projected: np.ndarray) -> float:
        """Profiled chi-square of a projected whitened residual: its squares plus the gains' prior cost."""
        return float(np.nansum(projected**2)) + self.penalty(projected)

    def penalty_rows(self, columns: np.ndarray) -> np.ndarray:
        """(G, k): the rows that `penalty` adds to a least-squares problem in columns (N, k) (NaN counted as 0):
        |v|^2 + |penalty_rows(v)|^2 is `chi2(v)`, so a fit with them is a fit in the chi-square's own metric."""
        values = np.nan_to_num(np.asarray(columns, dtype=float).reshape(len(columns), -1))
        rows = [PDC_GAIN_PRIOR * n @ values[index] for index, n, _ in self._groups]
        return np.array(rows).reshape(-1, values.shape[1])

    def project(self, values: np.ndarray) -> np.ndarray:
        """The vector (N,) or the columns of (N, k) with the gain directions profiled out."""
        out = np.array(values, dtype=float)
        for index, n, denominator in self._groups:
            part = out[index]
            gain = np.nansum(n[:, None] * part.reshape(len(index), -1), axis=0) / denominator
            out[index] = part - (n[:, None] * gain).reshape(part.shape)
        return out


def residual_samples(trajectory: TrajectoryRecord) -> np.ndarray:
    """(T,) bool: the samples of a trajectory's recording the residual uses: every one, or, for a trajectory read
    from rows only, its rows (each increment's last sample: the rest of its stand-in recording holds the row and
    carries no noise of its own, so counting it would pass copies of one row for independent samples)."""
    if not trajectory.rows_only:
        return np.ones(len(trajectory.raw.time), dtype=bool)
    rows = np.zeros(len(trajectory.raw.time), dtype=bool)
    rows[increment_ends(trajectory.raw.increment)] = True
    return rows


def build_residual(
    trajectories: list[TrajectoryRecord], predicted: list[np.ndarray], sigma: np.ndarray
) -> tuple[Residual, list[np.ndarray]]:
    """The whitened residual (channel gains not yet profiled) and each trajectory's mask of samples
    used (valid predictions)."""
    values, index, indenter, masks = [], [], [], []
    names = (
        "depth",
        "time_in_increment",
        "time",
        "axis",
        "angled",
        "sensor",
        "indenter_size",
        "location_x",
        "location_y",
        "predicted_pdc",
    )
    cov: dict[str, list] = {k: [] for k in names}
    k = len(CHANNELS)
    for i, (t, p) in enumerate(zip(trajectories, predicted, strict=True)):
        valid = np.isfinite(p).all(axis=1) & residual_samples(t)
        masks.append(valid)
        r = (measured(t) - p)[valid] / sigma
        r = r - r.mean(axis=0)
        values.append(r.ravel())
        n = valid.sum()
        index.append(np.full(k * n, i))
        indenter.append(np.full(k * n, t.indenter, dtype=object))
        cov["depth"].append(np.repeat(t.raw.depth_command[valid], k))
        cov["time_in_increment"].append(np.repeat(time_in_increment(t)[valid], k))
        cov["time"].append(np.repeat(t.raw.time[valid], k))
        cov["axis"].append(np.tile(np.arange(k), n))
        cov["angled"].append(np.full(k * n, not t.normal))
        cov["sensor"].append(np.full(k * n, t.sensor_id))
        cov["indenter_size"].append(np.full(k * n, get_indenter(t.indenter).dims[0]))
        cov["location_x"].append(np.full(k * n, t.touch_point[0]))
        cov["location_y"].append(np.full(k * n, t.touch_point[1]))
        cov["predicted_pdc"].append(np.repeat(p[valid, CHANNELS.index("pdc")], k))
    residual = Residual(
        np.concatenate(values),
        np.concatenate(index),
        np.concatenate(indenter),
        {k: np.concatenate(v) for k, v in cov.items()},
        sigma,
    )
    return residual, masks


def recentred(values: np.ndarray, group: np.ndarray) -> np.ndarray:
    """`values` (N,) less, in each group (non-negative integer labels, N,), the mean of its finite entries; NaN
    entries stay NaN (a no-op, to round-off, on groups whose finite entries already have zero mean)."""
    finite = np.isfinite(values)
    keep = slice(None) if finite.all() else finite  # views when every entry is finite, else copies of those only
    kept = group[keep]
    sums = np.bincount(kept, weights=values[keep], minlength=int(group.max()) + 1)
    counts = np.bincount(kept, minlength=len(sums))
    return values - np.divide(sums, counts, out=np.zeros_like(sums), where=counts > 0)[group]


def whitened(predicted: list[np.ndarray], masks: list[np.ndarray], sigma: np.ndarray) -> np.ndarray:
    """Whitened, offset-projected predictions on the base model's sample set (for differences).

    Samples where this prediction failed (fe not converged) are NaN; fits and scores skip them (a channel of a
    trajectory with none left stays NaN).
    """
    out = []
    for p, m in zip(predicted, masks, strict=True):
        w = p[m] / sigma
        finite = np.isfinite(w)
        count = finite.sum(axis=0)
        mean = np.divide(np.where(finite, w, 0.0).sum(axis=0), count, out=np.full(w.shape[1:], np.nan), where=count > 0)
        out.append((w - mean).ravel())
    return np.concatenate(out)


@dataclass(frozen=True)
class Base:
    """Everything the base model's residual needs: trajectories, noise, residual, masks, whitened base
    prediction, the PDC-gain nuisance projector, the whitened data, the model of each trajectory and how many
    nuisance parameters were fitted to reach it (they reduce the noise test's degrees of freedom)."""

    trajectories: list[TrajectoryRecord]
    sigma: np.ndarray
    residual: Residual
    masks: list[np.ndarray]
    prediction: np.ndarray
    nuisance: GainNuisance
    data: np.ndarray  # (N,) the measurements, whitened and offset-projected like `prediction`
    model_for: ModelFor = same_model
    fitted: int = 0

    @property
    def reached(self) -> int:
        """Samples (of every trajectory) this residual's model reached."""
        return sum(int(mask.sum()) for mask in self.masks)

    @property
    def samples(self) -> int:
        """Residual samples the data hold (`residual_samples`, every trajectory), reached by its model or not."""
        return sum(int(residual_samples(t).sum()) for t in self.trajectories)

    def reaching(self, predictor: Predictor, model: TwinModel) -> Base:
        """The residual of `model` (each trajectory by `model_for`) on every sample it reaches, this residual's noise
        and fitted count kept (`about` keeps this residual's samples)."""
        predicted = fullrate_prediction(predictor, model, self.trajectories, self.model_for)
        return residual_about(self.trajectories, predicted, self.sigma, self.model_for, self.fitted)

    def with_prediction(self, prediction: np.ndarray) -> Base:
        """This residual about another model whose whitened, offset-projected prediction on these samples is
        `prediction` (N,; NaN where its replay failed): the data less it, each sensor's PDC gain profiled about
        that model's own PDC. A read-out gain error scales the pressure the sensor reads, which is the model's
        with its effects, not the base's: profiled about the base's PDC, a gain of a few per cent leaves that
        fraction of a large effect's PDC change in the residual, along the effect's own signature (measured on
        the hidden registration offsets, docs/analysis.md)."""
        nuisance = GainNuisance(prediction, self.residual.covariates["axis"], self.residual.covariates["sensor"])
        residual = replace(self.residual, values=nuisance.project(self.misfit(prediction)))
        return replace(self, residual=residual, prediction=prediction, nuisance=nuisance)

    def misfit(self, prediction: np.ndarray) -> np.ndarray:
        """The whitened data less a whitened, offset-projected `prediction` (N,) on these samples, each trajectory's
        channel offsets projected again over the samples the prediction reached (`recentred`): a replay that failed
        part of the way (its later samples NaN) centred its prediction over the samples it reached and the data
        over all of them, and the difference of those two means, one constant over the rest of the trajectory,
        passed for misfit (measured on a skin modulus of 0.709, docs/analysis.md, session 17)."""
        group = self.residual.trajectory_index * len(CHANNELS) + self.residual.covariates["axis"]
        return recentred(self.data - prediction, group)

    def about(self, predictor: Predictor, model: TwinModel) -> Base:
        """This residual about `model` (each trajectory by `model_for`) on the same samples (`with_prediction`)."""
        predicted = fullrate_prediction(predictor, model, self.trajectories, self.model_for)
        return self.with_prediction(whitened(predicted, self.masks, self.sigma))

    def shifted(self, predictor: Predictor, model: TwinModel) -> np.ndarray:
        """Profiled change of the whitened prediction from the base to `model` (NaN where it failed): the residual
        less `model`'s `misfit`, so each trajectory's offsets are projected over the samples `model` reached."""
        return self.nuisance.project(self.unprofiled_shift(predictor, model))

    def shift_of(self, predicted: list[np.ndarray]) -> np.ndarray:
        """Profiled change of the whitened prediction from the base to the per-trajectory full-rate predictions
        `predicted` ((T, 4) each, `fullrate_prediction`'s form: N and counts; NaN where there is none), as
        `shifted` makes it of a model's."""
        return self.nuisance.project(self.unprofiled_shift_of(predicted))

    def unprofiled_shift(self, predictor: Predictor, model: TwinModel) -> np.ndarray:
        """`shifted` before the PDC gains are profiled out (`GainNuisance.project`, linear): each trajectory's rows
        depend on its own replay only (the gain's profile couples a sensor's trajectories)."""
        return self.unprofiled_shift_of(fullrate_prediction(predictor, model, self.trajectories, self.model_for))

    def unprofiled_shift_of(self, predicted: list[np.ndarray]) -> np.ndarray:
        """`shift_of` before the PDC gains are profiled out."""
        return self._own_misfit - self.misfit(whitened(predicted, self.masks, self.sigma))

    @cached_property
    def _own_misfit(self) -> np.ndarray:
        """`misfit` of this base's own prediction (every shift is taken from it)."""
        return self.misfit(self.prediction)

    def prefetch(self, predictor: Predictor, models: Sequence[TwinModel]) -> int:
        """Solve the replays that `shifted` needs for every model of `models` as one batch (those not cached
        yet; `Predictor.prefetch_many`); returns how many were solved."""
        return predictor.prefetch_many(model_requests(models, self.trajectories, self.model_for))

    def noise_test(self, values: np.ndarray, fitted: int | None = None, out_of_fold: OutOfFold = NO_FIT) -> NoiseTest:
        """The noise test (`twin.analysis.significance`) of a whitened residual on this residual's samples
        (NaN skipped): the nuisances are each trajectory's channel offsets, each sensor's PDC gain and the
        `fitted` parameters (default: those fitted to reach this base), and each channel's noise was
        estimated from every trajectory's successive differences; `out_of_fold` for a held-out residual
        (what the fits on the other folds add, `significance.out_of_fold_excess`)."""
        axis = self.residual.covariates["axis"]
        finite = np.isfinite(values)
        channels = range(len(CHANNELS))
        squares = [float(np.sum(values[finite & (axis == c)] ** 2)) for c in channels]
        counts = [int(np.sum(finite & (axis == c))) for c in channels]
        differences = sum(len(t.raw.time) - 1 for t in self.trajectories)
        sensors = len(np.unique(self.residual.covariates["sensor"]))
        nuisances = len(CHANNELS) * len(self.trajectories) + sensors + (self.fitted if fitted is None else fitted)
        return noise_test(squares, counts, [differences] * len(CHANNELS), nuisances, out_of_fold=out_of_fold)


def base_residual(
    datasets: list[CampaignData],
    model: TwinModel,
    predictor: Predictor,
    model_for: ModelFor = same_model,
    fitted: int = 0,
    sigma: np.ndarray | None = None,
) -> Base:
    """The residual of `model` (each trajectory by model_for(model, trajectory)) on every trajectory of
    `datasets`; the noise estimated from the data unless `sigma` (4,) is given."""
    trajectories = [t for d in datasets for t in d.trajectories]
    if not trajectories:
        raise ValueError("the datasets hold no trajectories")
    if sigma is None:
        sigma = noise_sigma(trajectories)
    predicted = fullrate_prediction(predictor, model, trajectories, model_for)
    return residual_about(trajectories, predicted, sigma, model_for, fitted)


def residual_about(
    trajectories: list[TrajectoryRecord],
    predicted: list[np.ndarray],
    sigma: np.ndarray,
    model_for: ModelFor,
    fitted: int,
) -> Base:
    """The `Base` of these trajectories about the full-rate predictions `predicted` (`fullrate_prediction`'s form),
    on every sample a prediction reached."""
    residual, masks = build_residual(trajectories, predicted, sigma)
    base = whitened(predicted, masks, sigma)
    nuisance = GainNuisance(base, residual.covariates["axis"], residual.covariates["sensor"])
    residual = replace(residual, values=nuisance.project(residual.values))
    data = whitened([measured(t) for t in trajectories], masks, sigma)
    return Base(trajectories, sigma, residual, masks, base, nuisance, data, model_for, fitted)


def noise_sigma(trajectories: list[TrajectoryRecord]) -> np.ndarray:
    """(4,) noise sigma of force x, y, z (N) and PDC (counts) of the residual's samples, never below the rounding
    noise of integer PDC counts: from successive differences (`noise_estimate`), or, when every trajectory is
    read from rows only (whose rows alone are residual samples, `residual_samples`), the rows' own
    (`rows_noise`: their forces low-passed)."""
    rows_only = all(t.rows_only for t in trajectories)
    noise = rows_noise(trajectories) if rows_only else noise_estimate(trajectories)
    quantum = 1.0 / np.sqrt(12.0)
    return np.array([max(noise[c], 1e-9) for c in FORCE_CHANNELS] + [max(noise["pdc"], quantum)])
