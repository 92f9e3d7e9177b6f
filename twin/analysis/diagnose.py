"""Which effect is missing? Residual signatures, score-type evidence, held-out refits, identifiability.

The residual is built in `twin.analysis.residual`; with `nuisances`, the standard unknowns of a real
campaign are fitted first (`twin.analysis.nuisances`) and candidates are ranked on what remains.

The residual holds four full-rate channels of every sample where the model converged: the tared
force (N, biotac frame; x, y, z) and the tared PDC (counts), each whitened by the noise estimated from
the data itself, with each trajectory's constant offset projected out (the tare sample carries one
noise draw the model cannot know). A real sensor's PDC gain is unknown to about 5 %, so each sensor's
PDC gain is a nuisance parameter with that prior, profiled out of the residual and of every
sensitivity. The PDC channel separates effects that scale the force alike (a stiffer skin raises the
fluid pressure; an F/T gain error does not). Electrodes are left out: their read-out is nonlinear with
per-sensor parameters the model does not know. For a model that lacks nothing, the whitened residual
has unit variance.

Evidence without refitting: for each candidate effect (off in the model), the sensitivity J of the
whitened prediction to the effect's parameters is taken by finite differences at the model (cheap for
measurement effects: fe replays are cached; one replay per parameter for physics effects). An effect
that declares starts across its range (a registration offset of a millimetre, a long delay) is
linearised again at the start that predicts the data best, so a large effect is not judged by its
slope at zero. The bounded linear least-squares fit of the residual on J gives the chi-square drop an
effect can explain (a score test, evaluated to second order); candidates are ranked by it minus a BIC
penalty.

The top few are then refitted with chord iterations (the same J, re-predicting nonlinearly after
each step) and judged held out about their refit: each indenter in turn is left out of the fit
(linearised at the refitted values) and predicted. The verdict (`twin.analysis.verdict`) names an
effect only when that held-out residual passes the noise test (`twin.analysis.significance`, a
chi-square test whose threshold shrinks as the data grow), its parameters are identifiable and no
other comes close; "nothing" when the base residual passes the test; "unexplained" otherwise.
"""

from __future__ import annotations

import json
from collections.abc import Callable
from dataclasses import dataclass, field, replace

import numpy as np

from twin.analysis.data import CampaignData
from twin.analysis.fit import GaussNewtonHooks, GaussNewtonSettings, Parameters, gauss_newton, linear_step, polish
from twin.analysis.fit import uncertainty as fit_uncertainty
from twin.analysis.nuisances import NUISANCE_EFFECTS, fit_nuisances
from twin.analysis.predict import Predictor, TwinModel
from twin.analysis.residual import CHANNELS, Base, Residual, base_residual
from twin.analysis.significance import out_of_fold_excess
from twin.analysis.verdict import Candidate, order_candidates, parameters_at_bound, verdict
from twin.effects import EFFECTS, Effect

NOISE_TOLERANCE = 1.3
"""Screen before refits: candidates whose linearised held-out RMS is within this multiple of the noise
rank ahead of those that are not. Naming uses the noise test (`twin.analysis.significance`) instead."""
BACKTRACKS = 2
"""Halvings of a refit step that does not lower the misfit before the refit stops there."""
STEP_TOLERANCE = 0.05
"""A refit stops once a step moves every parameter by less than this fraction of its scale (its
finite-difference step): smaller steps change the fit by far less than the noise, at an fe replay set each."""


@dataclass
class Diagnosis:
    """The outcome: ranked candidates, residual signatures and a verdict."""

    base_rms: float  # whitened RMS of the base residual (1 = noise)
    signatures: dict[str, float]
    candidates: list[Candidate]
    verdict: str  # "nothing", "nothing beyond the nuisances", an effect name, "ambiguous" or "unexplained"
    reason: str
    tied: list[str] = field(default_factory=list)  # with "ambiguous": the effects that explain it equally
    rms_threshold: float = float("nan")  # the noise test's whitened RMS threshold on these data
    nuisances: dict | None = None  # the nuisance stage's summary (`NuisanceFit.to_dict`) when it ran

    def to_dict(self) -> dict:
        """JSON-ready form (the `twin diagnose --json` shape)."""
        return {
            "base_rms_over_noise": self.base_rms,
            "noise_rms_threshold": self.rms_threshold,
            "verdict": self.verdict,
            "reason": self.reason,
            "tied": self.tied,
            "signatures": self.signatures,
            "candidates": [dict(c.__dict__) for c in self.candidates],
            "nuisances": self.nuisances,
        }

    def to_json(self) -> str:
        """Strict JSON text of `to_dict` (a NaN or infinite number becomes null)."""
        return json.dumps(strict_json(self.to_dict()), allow_nan=False)


def strict_json(value: object) -> object:
    """`value` (nested dicts, lists, numbers) with every NaN or infinite float replaced by None and numpy
    scalars (numpy.bool_ included) as Python ones."""
    if isinstance(value, np.generic):
        return strict_json(value.item())
    if isinstance(value, dict):
        return {k: strict_json(v) for k, v in value.items()}
    if isinstance(value, list | tuple):
        return [strict_json(v) for v in value]
    if isinstance(value, float | np.floating):
        return float(value) if np.isfinite(value) else None
    return value


def signatures(residual: Residual) -> dict[str, float]:
    """Per channel, the correlation of the whitened residual (and of its magnitude) with each covariate;
    and each channel's whitened RMS."""
    out = {}
    axis = residual.covariates["axis"]
    for c, channel in enumerate(CHANNELS):
        mine = axis == c
        r = residual.values[mine]
        if r.size < 3:
            continue
        for name, values in residual.covariates.items():
            x = values[mine].astype(float)
            if name == "axis" or np.ptp(x) == 0:
                continue
            out[f"corr({channel} residual, {name})"] = float(np.corrcoef(r, x)[0, 1])
            out[f"corr(|{channel} residual|, {name})"] = float(np.corrcoef(np.abs(r), x)[0, 1])
        out[f"{channel} rms_over_noise"] = float(np.sqrt(np.mean(r**2)))
    out["rms_over_noise"] = float(np.sqrt(np.mean(residual.values**2)))
    return out


@dataclass(frozen=True)
class Linearisation:
    """An effect's prediction change to first order about `point` (its parameter values):
    shifted(values) ~ offset + jac (values - point), in profiled whitened units."""

    point: dict[str, float]
    offset: np.ndarray  # (N,) profiled change of the prediction from the base model to `point`
    jac: np.ndarray  # (N, k) finite-difference sensitivity at `point`


def linearise(
    effect: Effect, model: TwinModel, point: dict[str, float], predictor: Predictor, base: Base
) -> Linearisation:
    """Linearise the profiled whitened prediction change from the base to `model` with the effect at
    `point`, by forward differences of each parameter's scale (backward at its upper bound; see
    `_column_steps`). The replays of the point and of every column are solved as one batch."""
    steps = _column_steps(effect, model, point)
    at_point = model.with_effects({effect.name: point})
    base.prefetch(predictor, [at_point, *(changed for _, changed in steps)])
    offset = base.shifted(predictor, at_point)
    columns = [(base.shifted(predictor, changed) - offset) / step for step, changed in steps]
    return Linearisation(point, offset, np.column_stack(columns))


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


def _linearisation_models(effect: Effect, model: TwinModel, point: dict[str, float]) -> list[TwinModel]:
    """The models `linearise` predicts: the effect at `point`, then each column's step."""
    return [model.with_effects({effect.name: point}), *(changed for _, changed in _column_steps(effect, model, point))]


def sensitivity(effect: Effect, model: TwinModel, predictor: Predictor, base: Base) -> Linearisation:
    """Linearise the effect where its fit is best begun (`sensitivities` of this one effect)."""
    return sensitivities([effect], model, predictor, base)[0]


def sensitivities(effects: list[Effect], model: TwinModel, predictor: Predictor, base: Base) -> list[Linearisation]:
    """Linearise each effect where its fit is best begun: at the model's values, or, when the effect is
    off there and declares a probe (parameters that act only once it is on), at the probe; and when it is
    off and declares starts (values across its range), at the start or the first linearisation's fit,
    whichever leaves the least profiled chi-square when predicted nonlinearly (one prediction each), so
    an effect far from its off value is fitted about a point near it. Each stage's replays, over all the
    effects (the first linearisations, the trials, the second linearisations), are solved as one batch."""
    points = []
    for effect in effects:
        point = effect.values(model.effects.get(effect.name))
        points.append({**point, **effect.probe} if effect.probe and effect.is_off(point) else point)
    base.prefetch(
        predictor, [m for e, p in zip(effects, points, strict=True) for m in _linearisation_models(e, model, p)]
    )
    lins = [linearise(e, model, p, predictor, base) for e, p in zip(effects, points, strict=True)]
    r = base.residual.values
    trials: list[list[dict[str, float]]] = []
    for effect, lin in zip(effects, lins, strict=True):
        if not (effect.is_off(effect.values(model.effects.get(effect.name))) and effect.starts):
            trials.append([])
            continue
        at = _parameters(effect, lin.point)
        fitted = at.moved(linear_step(lin.jac, r - lin.offset, at)).as_dict()
        trials.append([fitted, *(effect.values({**lin.point, **start}) for start in effect.starts)])
    tried = [model.with_effects({e.name: t}) for e, ts in zip(effects, trials, strict=True) for t in ts]
    base.prefetch(predictor, tried)
    again: dict[int, dict[str, float]] = {}
    for i, (effect, ts) in enumerate(zip(effects, trials, strict=True)):
        if not ts:
            continue
        shifted = [base.shifted(predictor, model.with_effects({effect.name: t})) for t in ts]
        best = int(np.nanargmin([base.nuisance.chi2(r - s) for s in shifted]))
        if best > 0:
            again[i] = ts[best]
    base.prefetch(predictor, [m for i, p in again.items() for m in _linearisation_models(effects[i], model, p)])
    for i, point in again.items():
        lins[i] = linearise(effects[i], model, point, predictor, base)
    return lins


def _parameters(effect: Effect, point: dict[str, float]) -> Parameters:
    """The effect's parameters at `point`, with their bounds and scales, for `twin.analysis.fit`."""
    ps = effect.parameters
    return Parameters(
        tuple(p.name for p in ps),
        np.array([point[p.name] for p in ps]),
        np.array([p.lower for p in ps]),
        np.array([p.upper for p in ps]),
        np.array([p.scale for p in ps]),
    )


def _linear_fit(effect: Effect, current: dict[str, float], jac: np.ndarray, r: np.ndarray) -> np.ndarray:
    """The bounded linear least-squares step (parameter units) of `r` on `jac` from `current`."""
    return linear_step(jac, r, _parameters(effect, current))


def diagnose(
    datasets: list[CampaignData],
    model: TwinModel,
    predictor: Predictor | None = None,
    candidates: list[str] | None = None,
    top: int = 3,
    on_progress: Callable[[str, str], None] | None = None,
    nuisances: bool = False,
) -> Diagnosis:
    """Rank the library's effects (off in `model`) by how well each explains the residual; the first
    `top` of the ranking are refitted and judged held out about their refit (`twin.analysis.verdict`).
    With `nuisances`, the standard unknowns of a real campaign (`twin.analysis.nuisances`: registration
    per arm, skin per sensor) are fitted first, candidates are ranked on what remains (their signatures
    less what the nuisances can absorb) and are never the nuisance effects themselves.
    on_progress(stage, effect) is called before each candidate is scored ("evidence"; every candidate's
    sensitivity is solved first, their replays batched, `sensitivities`) and refitted
    ("refit"), and with ("nuisances", what) during the nuisance fit."""
    if top < 0:
        raise ValueError(f"the number of candidates to refit must be >= 0, got {top}")
    if nuisances and set(candidates or ()) & set(NUISANCE_EFFECTS):
        raise ValueError(f"with the nuisances fitted, {sorted(NUISANCE_EFFECTS)} cannot be candidates")
    report = on_progress or (lambda stage, name: None)
    predictor = predictor or Predictor()
    fitted = fit_nuisances(datasets, model, predictor, lambda text: report("nuisances", text)) if nuisances else None
    base = fitted.base if fitted is not None else base_residual(datasets, model, predictor)
    residual = base.residual
    r = residual.values
    n = len(r)
    chi2 = base.nuisance.chi2(r)
    excess = chi2 - n
    base_rms = float(np.sqrt(chi2 / n))
    excluded = set(model.effects) | (set(NUISANCE_EFFECTS) if fitted is not None else set())
    names = candidates if candidates is not None else [k for k in EFFECTS if k not in excluded]
    ranked: list[tuple[Candidate, Linearisation]] = []
    lins = sensitivities([EFFECTS[name] for name in names], model, predictor, base)
    for name, lin in zip(names, lins, strict=True):
        effect = EFFECTS[name]
        report("evidence", name)
        scored = lin
        if fitted is not None:  # what a joint refit with the nuisances would leave of the effect's signature
            fitted.confounding(name, lin.jac)
            scored = replace(lin, offset=fitted.project(lin.offset), jac=fitted.project(lin.jac))
        delta = _linear_fit(effect, scored.point, scored.jac, r - scored.offset)
        drop = chi2 - base.nuisance.chi2(r - scored.offset - scored.jac @ delta)
        candidate = Candidate(
            name=name,
            kind=effect.kind,
            parameters={p.name: lin.point[p.name] + d for p, d in zip(effect.parameters, delta, strict=True)},
            chi2_drop=drop,
            evidence=drop - len(delta) * np.log(n),
            explained_fraction=drop / excess if excess > 0 else 0.0,
        )
        candidate.heldout_rms = _heldout(effect, scored, r, residual.indenter)[0]
        ranked.append((candidate, lin))
    # Evidence can be fooled by a flexible effect that fits every indenter its own way: those that
    # also predict left-out indenters to within the tolerance rank ahead of those that do not.
    ranked.sort(key=lambda item: (not generalises(item[0]), -item[0].evidence))
    for candidate, lin in ranked[:top]:
        report("refit", candidate.name)
        _identifiability(candidate, lin.jac)
        if fitted is not None and candidate.name in fitted.cannot_tell_apart():
            candidate.identifiable = False  # never named: the nuisances could be what it fits
        _refit(candidate, model, predictor, base, lin)
    refitted = [candidate for candidate, _ in ranked[:top]]
    at_fits = [_linearisation_models(EFFECTS[c.name], model, c.refit_parameters) for c in refitted]
    base.prefetch(predictor, [m for models in at_fits for m in models])  # every held-out judgement in one batch
    for candidate in refitted:
        _judge_heldout(candidate, model, predictor, base)
    ordered = order_candidates([c for c, _ in ranked])
    base_test = base.noise_test(r)
    threshold = base_test.rms_threshold
    is_noise = base_test.is_noise and (fitted is None or fitted.heldout_is_noise)
    outcome, reason, tied = verdict(base_rms, is_noise, threshold, ordered, fitted is not None)
    if fitted is not None and fitted.cannot_tell_apart():
        reason += f"; these data cannot tell {', '.join(fitted.cannot_tell_apart())} from the nuisances"
    summary = fitted.to_dict() if fitted is not None else None
    return Diagnosis(base_rms, signatures(residual), ordered, outcome, reason, tied, threshold, summary)


def generalises(candidate: Candidate) -> bool:
    """Whether the candidate's held-out RMS (when there is one) is within the screening tolerance."""
    return candidate.heldout_rms is None or candidate.heldout_rms <= NOISE_TOLERANCE


def _heldout(
    effect: Effect, lin: Linearisation, r: np.ndarray, indenter: np.ndarray
) -> tuple[float | None, np.ndarray]:
    """Leave-one-indenter-out about `lin`: the effect fitted (linearised) on the other indenters predicts
    each left-out one. (whitened RMS of the left-out residuals, those residuals (N,), NaN where no
    prediction); (None, r - offset) with fewer than two indenters."""
    target = r - lin.offset
    groups = np.unique(indenter)
    if len(groups) < 2:
        return None, target
    left_out = np.full_like(target, np.nan)
    for g in groups:
        train, test = indenter != g, indenter == g
        delta = _linear_fit(effect, lin.point, lin.jac[train], target[train])
        left_out[test] = target[test] - lin.jac[test] @ delta
    return _rms(left_out), left_out


def _judge_heldout(candidate: Candidate, model: TwinModel, predictor: Predictor, base: Base) -> None:
    """Held-out RMS about the refitted values (the effect linearised again there: one fe replay per
    parameter for a physics effect) and whether that held-out residual passes the noise test, which
    allows for the error the fits on the other indenters carry into it (`significance.out_of_fold_excess`;
    the parameter bounds of the fits are not modelled); and which refitted parameters sit at a bound."""
    effect = EFFECTS[candidate.name]
    at_fit = linearise(effect, model, candidate.refit_parameters, predictor, base)
    rms, left_out = _heldout(effect, at_fit, base.residual.values, base.residual.indenter)
    test = base.noise_test(left_out, out_of_fold=out_of_fold_excess(at_fit.jac, base.residual.indenter))
    candidate.heldout_rms = rms
    candidate.heldout_is_noise = test.is_noise
    candidate.heldout_rms_threshold = test.rms_threshold
    candidate.at_bound = parameters_at_bound(candidate.name, candidate.refit_parameters)


def _identifiability(candidate: Candidate, jac: np.ndarray) -> None:
    """Parameter correlations and the condition of J^T J (scaled, `twin.analysis.fit.uncertainty`); flag
    non-identifiable fits."""
    spread = fit_uncertainty(jac, np.array([p.scale for p in EFFECTS[candidate.name].parameters]))
    candidate.condition = spread.condition
    candidate.correlation = spread.correlation.round(4).tolist()
    off_diagonal = np.abs(spread.correlation - np.diag(np.diag(spread.correlation)))
    candidate.identifiable = bool(candidate.condition < 1e8 and (off_diagonal.max(initial=0.0) < 0.98))


def _refit(
    candidate: Candidate, model: TwinModel, predictor: Predictor, base: Base, lin: Linearisation, iterations: int = 3
) -> None:
    """Damped Gauss-Newton (`twin.analysis.fit.gauss_newton`): linear steps re-predicted nonlinearly each
    time, the first with the given J; a step that does not lower the misfit is halved (up to `BACKTRACKS`
    times, one prediction each) and the iterations stop when none does or when a step is below
    `STEP_TOLERANCE`; a physics effect stops once its residual passes the noise test, and otherwise is
    linearised again where it stands (one fe replay per parameter); a measurement effect keeps J (its
    predictions reuse cached fe replays) and, unless linear in its parameters, ends with a nonlinear
    least-squares polish (`twin.analysis.fit.polish`). When the result fits worse than the model's own
    values of the effect (the starting point), those are kept."""
    effect = EFFECTS[candidate.name]

    def misfit(trial: dict[str, float]) -> np.ndarray:
        return base.residual.values - base.shifted(predictor, model.with_effects({candidate.name: trial}))

    def relinearised(at: Parameters) -> np.ndarray:
        return linearise(effect, model, at.as_dict(), predictor, base).jac

    start = effect.values(model.effects.get(candidate.name))
    best = (_rms(misfit(start)), start)
    hooks = GaussNewtonHooks(
        jacobian=relinearised if effect.kind == "physics" else None,
        at_noise=lambda r: base.noise_test(r).is_noise,
        cost=lambda r, _: _rms(r),
    )
    fitted = gauss_newton(
        lambda at: misfit(at.as_dict()),
        _parameters(effect, lin.point),
        hooks,
        GaussNewtonSettings(iterations, BACKTRACKS, STEP_TOLERANCE),
        start_residual=base.residual.values - lin.offset,
        start_jacobian=lin.jac,
    )
    values, rms = fitted.parameters, fitted.cost
    if effect.kind == "measurement" and not effect.linear:
        names = values.names

        def mean_square(x: np.ndarray) -> float:
            return float(np.nanmean(misfit(dict(zip(names, map(float, x), strict=True))) ** 2))

        values = polish(mean_square, values).parameters
        rms = _rms(misfit(values.as_dict()))
    # Never end above the starting point (the model as given): a step the linearisation misjudged is undone.
    candidate.refit_rms, candidate.refit_parameters = min(best, (rms, values.as_dict()), key=lambda b: b[0])


def _rms(residual: np.ndarray) -> float:
    """Whitened RMS of a residual, skipping samples without a prediction (NaN)."""
    return float(np.sqrt(np.nanmean(residual**2)))


@dataclass(frozen=True)
class EffectFit:
    """An effect fitted to data: its values, and whitened RMS (1 = noise) before, after and held out."""

    name: str
    values: dict[str, float]
    rms_before: float
    rms_after: float
    heldout_rms: float | None
    model: TwinModel
    heldout_is_noise: bool | None = None  # the held-out residual passes the noise test
    at_bound: list[str] = field(default_factory=list)  # fitted parameters at a bound of their range


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
    _refit(candidate, model, predictor, base, lin, iterations=4)
    rms_before = float(np.sqrt(np.mean(residual.values**2)))
    improved = model.with_effects({name: candidate.refit_parameters})
    _judge_heldout(candidate, model, predictor, base)
    return EffectFit(
        name,
        candidate.refit_parameters,
        rms_before,
        candidate.refit_rms,
        candidate.heldout_rms,
        improved,
        candidate.heldout_is_noise,
        candidate.at_bound,
    )
