"""Refitting one effect to the data (damped Gauss-Newton through `twin.analysis.fit`, re-predicted nonlinearly),
and `fit_effect`: one effect fitted and judged held out; `fit_jointly`, what `twin improve` runs: one added, then
every effect of the model refitted in turn."""

from __future__ import annotations

from collections.abc import Callable, Sequence
from dataclasses import dataclass, field, replace
from functools import partial
from itertools import product

import numpy as np

from twin.analysis.data import CampaignData
from twin.analysis.fit import Fit, GaussNewtonHooks, GaussNewtonSettings, Parameters, gauss_newton, polish
from twin.analysis.heldout import judge_heldout, whitened_rms
from twin.analysis.predict import Predictor, TwinModel
from twin.analysis.residual import Base, base_residual
from twin.analysis.sensitivity import (
    Linearisation,
    effect_parameters,
    linearisation_models,
    linearise,
    point_models,
    sensitivity,
)
from twin.analysis.verdict import Candidate
from twin.effects import EFFECTS, Effect, EffectParameter

BACKTRACKS = 2
"""Halvings of a refit step that does not lower the misfit before the refit stops there."""
EXTRA_ITERATIONS = 3
"""Gauss-Newton steps a refit takes beyond its `iterations` while each lowers its whitened RMS by a tenth or more
(`GaussNewtonSettings.extra_iterations`): a registration offset of 0.3 mm on 2 mm presses needed a fourth."""
STEP_TOLERANCE = 0.05
"""A refit stops once a step moves every parameter by less than this fraction of its scale (its
finite-difference step): smaller steps change the fit by far less than the noise, at an fe replay set each."""
STARTS_ALONE = 5
"""Starts across its range for an effect of one parameter (`starts_across`); 3 a parameter for more."""
FINISH_STEPS = 2
"""Gauss-Newton steps a refit made on a coarser fe mesh takes on the model's own mesh (`finish_on_model_mesh`)."""
FINISH_OWN_COLUMNS = 0.5
"""A finish's steps take the model mesh's own columns (one replay a parameter there) once a step with the coarse ones
leaves more than this fraction of the whitened RMS it started from: biased columns converge slowly (a 0.41 mm
registration offset finished from 4.76x with 2 mm columns on a 1 mm campaign: 3.13x, 2.60x, 2.00x, 1.73x, 1.44x in
its five steps; docs/analysis.md)."""
FINISH_REACH = 5.0
"""A finish's step is worth its wave when its linearisation predicts a residual within this factor of the noise test's
RMS threshold (or one that keeps at most `FINISH_PROMISE` of the RMS it starts from)."""
FINISH_PROMISE = 0.5
"""A finish takes a step only when the residual its linearisation predicts is within `FINISH_REACH` times the noise
test's RMS threshold or at most `FINISH_PROMISE` times the whitened RMS it starts from: a fit that its own
linearisation leaves far above the noise, and barely lower, cannot be named, and each step costs a wave of the
model's mesh (the paper diagnose on an H200: four such waves, 260 s, for fits that ended at 48-56x the noise;
docs/scale.md, session 26); a step from far off that promises to halve the misfit is taken (a backlash's linearisation
at zero lag predicts 12.6x from 30.8x; the steps from there reach the noise)."""
DECADE_SPACED = 10.0
"""A positive range whose bounds differ by this factor or more is spaced geometrically (a relaxation time of
0.05-10 s), otherwise evenly."""


def _misfit(base: Base, predictor: Predictor, model: TwinModel, name: str) -> Callable[[dict], np.ndarray]:
    """The whitened residual `base` leaves about `model` with effect `name` at given values."""
    return lambda values: base.residual.values - base.shifted(predictor, model.with_effects({name: values}))


def _controls(
    base: Base, jacobian: Callable[[Parameters], np.ndarray] | None, iterations: int
) -> tuple[GaussNewtonHooks, GaussNewtonSettings]:
    """A refit's Gauss-Newton hooks (its whitened RMS the cost, stopping at `base`'s noise test before a new
    `jacobian`) and settings (`iterations`, then `EXTRA_ITERATIONS` while converging fast)."""
    hooks = GaussNewtonHooks(
        jacobian=jacobian, at_noise=lambda r: base.noise_test(r).is_noise, cost=lambda r, _: whitened_rms(r)
    )
    return hooks, GaussNewtonSettings(iterations, BACKTRACKS, STEP_TOLERANCE, extra_iterations=EXTRA_ITERATIONS)


def refit(
    candidate: Candidate, model: TwinModel, predictor: Predictor, base: Base, lin: Linearisation, iterations: int = 3
) -> None:
    """Damped Gauss-Newton (`twin.analysis.fit.gauss_newton`): linear steps re-predicted nonlinearly each
    time, the first with the given J; a step that does not lower the misfit is halved (up to `BACKTRACKS`
    times, one prediction each) and the iterations stop when none does or when a step is below
    `STEP_TOLERANCE`; a physics effect stops once its residual passes the noise test, and otherwise is
    linearised again where it stands (one fe replay per parameter); a measurement effect keeps J (its
    predictions reuse cached fe replays) and, unless linear in its parameters, ends with a nonlinear
    least-squares polish (`twin.analysis.fit.polish`). A physics effect whose fit still fails the noise test is
    tried again from starts across its range (`_from_starts`: a cost can have several basins). When the result
    fits worse than the model's own values of the effect (the starting point), those are kept, unless their
    replay loses samples `base` reaches (a refit on the samples a fit reaches, `refit_on_reached`)."""
    effect = EFFECTS[candidate.name]
    misfit = _misfit(base, predictor, model, candidate.name)
    ahead = effect.kind == "physics" and predictor.solve_ahead

    def stepped(trial: dict[str, float]) -> np.ndarray:  # a step's misfit; ahead, its linearisation's replays too
        base.prefetch(predictor, point_models(effect, model, trial, ahead))
        return misfit(trial)

    def relinearised(at: Parameters) -> np.ndarray:
        return linearise(effect, model, at.as_dict(), predictor, base).jac

    start = effect.values(model.effects.get(candidate.name))
    at_start = misfit(start)
    lost = np.isnan(at_start) & np.isfinite(base.residual.values)  # no fallback that drops samples
    best = (float("inf") if lost.any() else whitened_rms(at_start), start)
    hooks, settings = _controls(base, relinearised if effect.kind == "physics" else None, iterations)
    fitted = gauss_newton(
        lambda at: stepped(at.as_dict()),
        effect_parameters(effect, lin.point),
        hooks,
        settings,
        start_residual=base.residual.values - lin.offset,
        start_jacobian=lin.jac,
    )
    if effect.kind == "physics" and not base.noise_test(fitted.residual).is_noise:
        fitted = _from_starts(
            effect, fitted, misfit, stepped, lambda models: base.prefetch(predictor, models), model, hooks, settings
        )
    values, rms = fitted.parameters, fitted.cost
    if effect.kind == "measurement" and not effect.linear:
        names = values.names

        def mean_square(x: np.ndarray) -> float:
            return float(np.nanmean(misfit(dict(zip(names, map(float, x), strict=True))) ** 2))

        values = polish(mean_square, values).parameters
        rms = whitened_rms(misfit(values.as_dict()))
    # Never end above the starting point (the model as given): a step the linearisation misjudged is undone.
    candidate.refit_rms, candidate.refit_parameters = min(best, (rms, values.as_dict()), key=lambda b: b[0])


def refit_on_reached(candidate: Candidate, model: TwinModel, predictor: Predictor, base: Base) -> None:
    """When the candidate's refit values reach samples `base` (the residual it was fitted on) does not, as when the
    model without the effect pressed deeper than the data and its fe stopped converging part of the way, refit it on
    the residual at those values, over every sample they reach (linearised there: one fe replay per parameter), so
    that no sample its model predicts is left out of its fit. A fit on the samples the model
    without the effect reached left a hidden 0.6 mm registration offset at 1.006x there and 1.30x on the whole of a
    paper-depth press (docs/analysis.md)."""
    if not candidate.refit_parameters:
        return
    reach = base.reaching(predictor, model.with_effects({candidate.name: candidate.refit_parameters}))
    if reach.reached > base.reached:
        lin = linearise(EFFECTS[candidate.name], model, candidate.refit_parameters, predictor, reach)
        refit(candidate, model, predictor, reach, lin)


def finish_on_model_mesh(
    candidate: Candidate,
    model: TwinModel,
    predictor: Predictor,
    base: Base,
    coarse: TwinModel,
    columns: Base,
    starts: Sequence[dict[str, float]] = (),
    steps: int = FINISH_STEPS,
) -> None:
    """A physics refit made on the coarser fe mesh of `coarse` continued on `model`'s own: damped Gauss-Newton of
    `model`'s residual (`base`) from the refitted values or from whichever of `starts` (an effect's data-driven start)
    and the model's own values of the effect leaves less of that residual (all tried in one batch; the model's own
    values are its base replays), its Jacobian the differences of `coarse`'s replays (`columns`: the coarse base,
    residual `base`'s) until a step with them converges slowly, then of `model`'s own (`FINISH_OWN_COLUMNS`); `steps`
    steps (up to `EXTRA_ITERATIONS` more while each lowers that residual by a tenth), none once it passes the noise
    test, none that its linearisation leaves far above the noise and barely lower (`FINISH_REACH`, `FINISH_PROMISE`);
    a step is kept only when it lowers that residual (so never worse than the coarse fit on `model`'s mesh). A coarse
    mesh's facets put the skin's contact elsewhere, so a fit of the indenter's path there is biased by more than the
    noise allows, or in another basin (docs/analysis.md: a 0.3 mm registration offset on a 1 mm campaign fitted 0.04
    mm off on a 2 mm mesh, 1.46x the noise; a 0.5 mm one at the 3 mm bound). Ahead (`Predictor.solve_ahead`), each
    step's columns with its replays, and the coarse fit's with the first batch."""
    effect = EFFECTS[candidate.name]
    if effect.kind != "physics" or coarse == model or candidate.refit_parameters is None:
        return
    ahead = predictor.solve_ahead

    def on_model(values: dict[str, float]) -> TwinModel:
        return model.with_effects({candidate.name: values})

    own = False  # the model mesh's own columns from now on (`FINISH_OWN_COLUMNS`)
    last_rms = np.inf

    def solved(points: list[dict[str, float]]) -> None:  # ahead, with the first point's columns
        columns_ahead = linearisation_models(effect, model if own else coarse, points[0]) if ahead else []
        base.prefetch(predictor, [*map(on_model, points), *columns_ahead])

    def watched(_: int, residual: np.ndarray) -> None:  # each iteration's start: was the last step slow?
        nonlocal own, last_rms
        rms = whitened_rms(residual)
        own = own or rms > FINISH_OWN_COLUMNS * last_rms
        last_rms = rms

    def jacobian(at: Parameters) -> np.ndarray:
        mesh_model, about = (model, base) if own else (coarse, columns)
        return linearise(effect, mesh_model, at.as_dict(), predictor, about).jac

    misfit = _misfit(base, predictor, model, candidate.name)
    tried = [candidate.refit_parameters]
    for values in [*starts, effect.values(model.effects.get(candidate.name))]:
        if values not in tried:
            tried.append(values)
    solved(tried)
    begin = min(tried, key=lambda values: whitened_rms(misfit(values)))
    hooks, settings = _controls(base, jacobian, steps)
    hooks = replace(hooks, promising=partial(_promising, base), on_iteration=watched)

    def stepped(at: Parameters) -> np.ndarray:
        solved([at.as_dict()])
        return misfit(at.as_dict())

    fitted = gauss_newton(stepped, effect_parameters(effect, begin), hooks, settings, start_residual=misfit(begin))
    candidate.refit_rms, candidate.refit_parameters = fitted.cost, fitted.parameters.as_dict()


def _promising(base: Base, residual: np.ndarray, predicted: np.ndarray) -> bool:
    """Whether a finish's step is worth its wave (`FINISH_REACH`, `FINISH_PROMISE`)."""
    rms, reach = whitened_rms(predicted), FINISH_REACH * base.noise_test(predicted).rms_threshold
    return rms <= reach or rms <= FINISH_PROMISE * whitened_rms(residual)


def starts_across(effect: Effect, at: dict[str, float]) -> list[dict[str, float]]:
    """Values of the effect across its parameters' bounds (`_across`): `STARTS_ALONE` of its one parameter; for two,
    every pair of 3 each; for more, each parameter through its 3 with the others at `at`; then the effect's own
    declared starts (over `at`)."""
    names = [p.name for p in effect.parameters]
    count = STARTS_ALONE if len(names) == 1 else 3
    grids = [_across(p, count) for p in effect.parameters]
    if len(names) <= 2:
        points = [dict(zip(names, map(float, values), strict=True)) for values in product(*grids)]
    else:
        points = [{**at, name: float(v)} for name, grid in zip(names, grids, strict=True) for v in grid]
    return points + [effect.values({**at, **start}) for start in effect.starts]


def _across(parameter: EffectParameter, count: int) -> np.ndarray:
    """`count` values inside the parameter's bounds, at the centres of equal parts (geometric parts for a positive
    range of `DECADE_SPACED` or more)."""
    lower, upper = parameter.lower, parameter.upper
    if lower > 0 and upper >= DECADE_SPACED * lower:
        return np.geomspace(lower, upper, 2 * count + 1)[1::2]
    return np.linspace(lower, upper, 2 * count + 1)[1::2]


def _from_starts(
    effect: Effect,
    fitted: Fit,
    misfit: Callable[[dict[str, float]], np.ndarray],
    stepped: Callable[[dict[str, float]], np.ndarray],
    prefetch: Callable[[list[TwinModel]], int],
    model: TwinModel,
    hooks: GaussNewtonHooks,
    settings: GaussNewtonSettings,
) -> Fit:
    """A refit that ended above the noise, tried again from across the effect's range (a cost can have several
    basins): the misfit at each of `starts_across` (their replays solved as one batch; not their linearisations,
    even ahead: many, and far), then damped Gauss-Newton from the best of them when it fits better than `fitted`;
    whichever of the two fits better. `misfit` of values; `stepped`, the misfit of a Gauss-Newton step's values
    (`refit`: ahead, with the step's linearisation's replays)."""
    starts = starts_across(effect, fitted.parameters.as_dict())
    prefetch([model.with_effects({effect.name: start}) for start in starts])
    costs = np.array([hooks.cost(misfit(start), None) for start in starts])
    if not np.isfinite(costs).any():  # no start's replays reached a sample
        return fitted
    best = int(np.nanargmin(costs))
    if not costs[best] < fitted.cost:
        return fitted
    again = gauss_newton(lambda at: stepped(at.as_dict()), effect_parameters(effect, starts[best]), hooks, settings)
    return again if again.cost < fitted.cost else fitted


@dataclass(frozen=True)
class EffectFit:
    """An effect fitted to data: its values, and whitened RMS (1 = noise) before, after and held out, with
    the held-out test's figures as diagnosis reports them (`twin.analysis.heldout.record_heldout`)."""

    name: str
    values: dict[str, float]
    rms_before: float
    rms_after: float
    heldout_rms: float | None
    model: TwinModel
    heldout_is_noise: bool | None = None  # the held-out residual passes the noise test
    at_bound: list[str] = field(default_factory=list)  # fitted parameters at a bound of their range
    heldout_rms_threshold: float | None = None  # the held-out RMS that test allows
    heldout_base_rms: float | None = None  # the residual without the effect on the same left-out samples
    heldout_has_power: bool | None = None  # that base residual fails the same test (the power rule)


def fit_effect(
    datasets: list[CampaignData], model: TwinModel, name: str, predictor: Predictor | None = None
) -> EffectFit:
    """Fit one library effect's parameters (chord iterations on the whitened full-rate residual)."""
    predictor = predictor or Predictor()
    effect = EFFECTS.get(name)
    if effect is None:
        raise ValueError(f"unknown effect {name!r}; the library has {sorted(EFFECTS)}")
    base = base_residual(datasets, model, predictor)
    residual = base.residual
    lin = sensitivity(effect, model, predictor, base)
    candidate = Candidate(name, effect.kind, {}, 0.0, 0.0, 0.0)
    refit(candidate, model, predictor, base, lin, iterations=4)
    refit_on_reached(candidate, model, predictor, base)
    rms_before = float(np.sqrt(np.mean(residual.values**2)))
    improved = model.with_effects({name: candidate.refit_parameters})
    judge_heldout(candidate, model, predictor, base)
    return EffectFit(
        name,
        candidate.refit_parameters,
        rms_before,
        candidate.refit_rms,
        candidate.heldout_rms,
        improved,
        candidate.heldout_is_noise,
        candidate.at_bound,
        candidate.heldout_rms_threshold,
        candidate.heldout_base_rms,
        candidate.heldout_has_power,
    )


JOINT_SWEEPS = 1
"""Sweeps of `fit_jointly` over the model's effects after one is added."""


def fit_jointly(
    datasets: list[CampaignData],
    model: TwinModel,
    name: str,
    predictor: Predictor | None = None,
    sweeps: int = JOINT_SWEEPS,
) -> EffectFit:
    """Add effect `name` (`fit_effect`), then refit every effect of the model in turn, the others fixed at their
    latest values (the earlier ones first, `name` last), `sweeps` times: a coordinate descent by which an earlier
    effect's fit, biased by the one missing then, is corrected once that one is in. The fit returned is `name`'s last,
    on the model with every effect refitted (`EffectFit.model`), with the RMS before the first; without earlier
    effects it is `fit_effect`'s."""
    predictor = predictor or Predictor()
    first = fit_effect(datasets, model, name, predictor)
    earlier = [other for other in model.effects if other != name]
    if not earlier:
        return first
    last = first
    for _ in range(sweeps):
        for other in [*earlier, name]:
            last = fit_effect(datasets, last.model, other, predictor)
    return replace(last, rms_before=first.rms_before)
