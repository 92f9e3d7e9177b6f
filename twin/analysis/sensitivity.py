"""Effects linearised about where their fits are best begun: finite-difference sensitivities of the profiled,
whitened prediction (`twin.analysis.residual`), their replays solved as batches, and the bounded linear fit
of a residual on them (`twin.analysis.fit`)."""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass, replace
from functools import partial
from typing import Protocol

import numpy as np

from twin.analysis.fit import Parameters, linear_step
from twin.analysis.onset import onset_start
from twin.analysis.predict import Predictor, TwinModel
from twin.analysis.reading_starts import range_start
from twin.analysis.residual import Base
from twin.analysis.surrogate import RELAXATION, RELAXATION_SURROGATE, Surrogate
from twin.effects import REGISTRATION, Effect
from twin.lanes import thread_map


class StartEstimate(Protocol):
    """What an effect's data-driven start (`DATA_STARTS`) found in the data."""

    def start(self, current: dict[str, float]) -> dict[str, float] | None:
        """The effect's values to try, about its `current` values (None: nothing worth trying)."""
        ...

    def estimate(self, current: dict[str, float]) -> dict[str, float] | None:
        """The effect's values the data give about its `current` values whatever their size (None: none): where a fit
        made on a coarser fe mesh is also finished from (`twin.analysis.refit.finish_on_model_mesh`)."""
        ...

    def to_dict(self) -> dict:
        """A JSON-ready summary (what diagnosis reports beside the candidate)."""
        ...


DataStart = Callable[[Predictor, TwinModel, Base], StartEstimate]
"""An effect's start estimated from the data (predictor, the model, the base residual): no linearisation."""
DATA_STARTS: dict[str, DataStart] = {
    REGISTRATION: onset_start,
    "ft_saturation": range_start,
}
"""Effect name -> its start from the data, tried first among the effect's declared starts while it is off (a
registration offset from the contact onsets, `twin.analysis.onset`; an F/T range from the readings' plateaus,
`twin.analysis.reading_starts`); effects not listed have the declared starts only.
Kept here, not in the effect library: the library knows nothing of the analysis."""
SURROGATES: dict[str, Surrogate] = {RELAXATION: RELAXATION_SURROGATE}
"""Effect name -> what stands in for its own replays in its first linearisation while it is off in the model, when
`sensitivities` is asked to rank on surrogates (a relaxing skin's probe from the skin modulus's elastic replays,
`twin.analysis.surrogate`: no timed replay); a refit linearises it again on its own replays."""


@dataclass(frozen=True)
class Linearisation:
    """An effect's prediction change to first order about `point` (its parameter values):
    shifted(values) ~ offset + jac (values - point), in profiled whitened units."""

    point: dict[str, float]
    offset: np.ndarray  # (N,) profiled change of the prediction from the base model to `point`
    jac: np.ndarray  # (N, k) finite-difference sensitivity at `point`
    data_start: StartEstimate | None = None  # the effect's start from the data (`DATA_STARTS`), if any
    surrogate: bool = False  # from its `SURROGATES` stand-in, not its own replays: for ranking only


def linearise(
    effect: Effect,
    model: TwinModel,
    point: dict[str, float],
    predictor: Predictor,
    base: Base,
    surrogate: Surrogate | None = None,
) -> Linearisation:
    """Linearise the profiled whitened prediction change from the base to `model` with the effect at
    `point`, by forward differences of each parameter's scale (backward at its upper bound; see
    `_column_steps`). The replays of the point and of every column are solved as one batch; with a `surrogate`
    (`SURROGATES`, the effect off in `model`), the changes are its stand-ins instead (its replays already solved)."""
    steps = _column_steps(effect, model, point)
    at_point = model.with_effects({effect.name: point})
    if surrogate is None:
        base.prefetch(predictor, [at_point, *(changed for _, changed in steps)])
        shifted = partial(base.shifted, predictor)
    else:
        shifted = surrogate.shift(model, predictor, base)
    offset = shifted(at_point)
    columns = [(shifted(changed) - offset) / step for step, changed in steps]
    return Linearisation(point, offset, np.column_stack(columns), surrogate=surrogate is not None)


def _column_steps(effect: Effect, model: TwinModel, point: dict[str, float]) -> list[tuple[float, TwinModel]]:
    """Per parameter, the finite-difference step (its scale; backward at its upper bound) and the model
    with the effect at `point` so stepped. A probed parameter at its probe value, where stepping it back
    to its off value turns the effect off, differs back to that off point instead: the model as given,
    whose replays the base already holds (a relaxing fraction's column costs no fe replay)."""
    steps = []
    for p in effect.parameters:
        step = p.scale if point[p.name] + p.scale <= p.upper else -p.scale
        probed = effect.probe.get(p.name) == point[p.name] != p.off
        if probed and effect.is_off({**point, p.name: p.off}) and effect.is_off(model.effects.get(effect.name)):
            step = p.off - point[p.name]
        steps.append((step, model.with_effects({effect.name: {**point, p.name: point[p.name] + step}})))
    return steps


def linearisation_models(effect: Effect, model: TwinModel, point: dict[str, float]) -> list[TwinModel]:
    """The models `linearise` predicts: the effect at `point`, then each column's step."""
    return [model.with_effects({effect.name: point}), *(changed for _, changed in _column_steps(effect, model, point))]


def point_models(effect: Effect, model: TwinModel, point: dict[str, float], ahead: bool) -> list[TwinModel]:
    """The models to solve for `model` with the effect at `point`: that one, and with `ahead`
    (`Predictor.solve_ahead`) every model of a linearisation there (`linearisation_models`), so that linearising
    at the point, should its result call for it, needs no batch of its own."""
    return linearisation_models(effect, model, point) if ahead else [model.with_effects({effect.name: point})]


def sensitivity(effect: Effect, model: TwinModel, predictor: Predictor, base: Base) -> Linearisation:
    """Linearise the effect where its fit is best begun (`sensitivities` of this one effect)."""
    return sensitivities([effect], model, predictor, base)[0]


def sensitivities(
    effects: list[Effect], model: TwinModel, predictor: Predictor, base: Base, surrogates: bool = False
) -> list[Linearisation]:
    """Linearise each effect where its fit is best begun: at the model's values, or, when the effect is
    off there and declares a probe (parameters that act only once it is on), at the probe; and when it is
    off and declares starts (values across its range, or one from the data), at the start or the first
    linearisation's fit, whichever leaves the least profiled chi-square when predicted nonlinearly (one
    prediction each), so an effect far from its off value is fitted about a point near it; an effect with a
    data-driven start (`DATA_STARTS`: a registration offset's contact onsets, `twin.analysis.onset`, no fe
    replay) tries what that gives (when it gives one) before its declared starts; its Linearisation keeps
    the estimate either way. Each stage's replays, over all the effects (the first linearisations, the
    trials, the second linearisations), are solved as one batch; with `Predictor.solve_ahead` the declared starts
    come first (a diagnosis solves them with its first batch) and the linearisations at the data-driven start and at
    the best declared start with the trials, so that no batch follows them. With `surrogates`, an effect off in the
    model that has a `SURROGATES` stand-in is first linearised on it (for ranking: no replay of its own)."""
    points = first_points(effects, model)
    base.prefetch(predictor, first_models(effects, model, points, surrogates))
    lins = thread_map(  # their replays solved: each linearisation is numpy over the residual's samples
        lambda at: linearise(at[0], model, at[1], predictor, base, _surrogate(at[0], model) if surrogates else None),
        list(zip(effects, points, strict=True)),
    )
    r = base.residual.values
    costs: dict[tuple, float] = {}

    def cost(effect: Effect, values: dict[str, float]) -> float:  # profiled chi-square, predicted nonlinearly
        key = (effect.name, tuple(sorted(values.items())))
        if key not in costs:
            costs[key] = base.nuisance.chi2(r - base.shifted(predictor, model.with_effects({effect.name: values})))
        return costs[key]

    def costed(trials: list[tuple[Effect, dict[str, float]]]) -> None:  # each trial's `cost`, on threads, memoised
        thread_map(lambda trial: cost(*trial), trials)

    def tries_starts(effect: Effect) -> bool:  # off in the model, with starts declared or from the data
        return effect.is_off(effect.values(model.effects.get(effect.name))) and bool(
            effect.starts or effect.name in DATA_STARTS
        )

    ahead = predictor.solve_ahead
    if ahead:  # the declared starts first (a diagnosis solved them with its first batch): the best one's columns ahead
        base.prefetch(predictor, start_models(effects, model))
        starts = [
            (e, t)
            for e, lin in zip(effects, lins, strict=True)
            if tries_starts(e)
            for t in declared_starts(e, lin.point)
        ]
        costed(starts)
    trials: list[list[dict[str, float]]] = []
    columns_ahead: list[TwinModel] = []
    for i, (effect, lin) in enumerate(zip(effects, lins, strict=True)):
        data_start = DATA_STARTS.get(effect.name)
        if not tries_starts(effect):
            trials.append([])
            continue
        at = effect_parameters(effect, lin.point)
        fitted = at.moved(linear_step(lin.jac, r - lin.offset, at)).as_dict()
        first = []
        if data_start is not None:
            lins[i] = replace(lin, data_start=data_start(predictor, model, base))
            first = [start] if (start := lins[i].data_start.start(lin.point)) is not None else []
        declared = declared_starts(effect, lin.point)
        trials.append([fitted, *first, *declared])
        # ahead, the linearisations at the data-driven start and at the best declared start, the trials that may win
        # (where the fitted step wins the first linearisation stands)
        best_declared = [min(declared, key=partial(cost, effect))] if ahead and declared else []
        columns_ahead += [m for t in [*first, *best_declared] for m in point_models(effect, model, t, ahead)]
    tried = [model.with_effects({e.name: t}) for e, ts in zip(effects, trials, strict=True) for t in ts]
    base.prefetch(predictor, [*tried, *columns_ahead])
    costed([(e, t) for e, ts in zip(effects, trials, strict=True) for t in ts])
    again: dict[int, dict[str, float]] = {}
    for i, (effect, ts) in enumerate(zip(effects, trials, strict=True)):
        if ts and (best := int(np.nanargmin([cost(effect, t) for t in ts]))) > 0:
            again[i] = ts[best]
    base.prefetch(predictor, [m for i, p in again.items() for m in linearisation_models(effects[i], model, p)])
    at_best = thread_map(lambda i: linearise(effects[i], model, again[i], predictor, base), list(again))
    for i, lin in zip(again, at_best, strict=True):
        lins[i] = replace(lin, data_start=lins[i].data_start)
    return lins


def data_estimate(effect: Effect, lin: Linearisation, model: TwinModel) -> list[dict[str, float]]:
    """What the data give of the effect (its `DATA_STARTS` estimate about `model`'s values of it, whatever its size),
    as a list of one, when `lin` has such an estimate: where a refit on a coarse mesh is also finished from
    (`twin.analysis.refit.finish_on_model_mesh`)."""
    values = effect.values(model.effects.get(effect.name))
    estimate = lin.data_start.estimate(values) if lin.data_start is not None else None
    return [] if estimate is None else [estimate]


def declared_starts(effect: Effect, point: dict[str, float]) -> list[dict[str, float]]:
    """The effect's declared starts (values across its range) about its first linearisation's `point`."""
    return [effect.values({**point, **start}) for start in effect.starts]


def start_models(effects: list[Effect], model: TwinModel) -> list[TwinModel]:
    """The models of the declared starts `sensitivities` tries for each effect off in `model`: known before any
    residual (unlike the fitted and data-driven starts), so they may be solved with the first batch."""
    models = []
    for effect, point in zip(effects, first_points(effects, model), strict=True):
        if effect.is_off(effect.values(model.effects.get(effect.name))):
            models += [model.with_effects({effect.name: start}) for start in declared_starts(effect, point)]
    return models


def first_points(effects: list[Effect], model: TwinModel) -> list[dict[str, float]]:
    """Where `sensitivities` first linearises each effect: at the model's values, or at the effect's probe when it
    is off there and declares one."""
    points = []
    for effect in effects:
        point = effect.values(model.effects.get(effect.name))
        points.append({**point, **effect.probe} if effect.probe and effect.is_off(point) else point)
    return points


def first_models(
    effects: list[Effect], model: TwinModel, points: list[dict[str, float]] | None = None, surrogates: bool = False
) -> list[TwinModel]:
    """The models whose replays the effects' first linearisations at `points` (default `first_points`) need, with
    `surrogates` those of the effects' stand-ins where they have one (`sensitivities`): known before any residual,
    so they may be solved with the base model's replays."""
    points = first_points(effects, model) if points is None else points
    models: list[TwinModel] = []
    for effect, point in zip(effects, points, strict=True):
        surrogate = _surrogate(effect, model) if surrogates else None
        models += surrogate.models(model) if surrogate is not None else linearisation_models(effect, model, point)
    return models


def _surrogate(effect: Effect, model: TwinModel) -> Surrogate | None:
    """The effect's `SURROGATES` stand-in while it is off in `model`; None when it has none or is on."""
    return SURROGATES.get(effect.name) if effect.is_off(model.effects.get(effect.name)) else None


def effect_parameters(effect: Effect, point: dict[str, float]) -> Parameters:
    """The effect's parameters at `point`, with their bounds and scales, for `twin.analysis.fit`."""
    ps = effect.parameters
    return Parameters(
        tuple(p.name for p in ps),
        np.array([point[p.name] for p in ps]),
        np.array([p.lower for p in ps]),
        np.array([p.upper for p in ps]),
        np.array([p.scale for p in ps]),
    )


def linear_fit(effect: Effect, current: dict[str, float], jac: np.ndarray, r: np.ndarray) -> np.ndarray:
    """The bounded linear least-squares step (parameter units) of `r` on `jac` from `current`."""
    return linear_step(jac, r, effect_parameters(effect, current))
