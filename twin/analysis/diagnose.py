"""Which effect is missing? Residual signatures, score-type evidence, held-out refits, identifiability.

The residual is the full-rate tared force (N, biotac frame; x, y, z) of every sample where the model
converged, whitened by the noise estimated from the data itself, with each trajectory's constant
offset projected out (the tare sample carries one noise draw the model cannot know). For a model that
lacks nothing, the whitened residual has unit variance.

Evidence without refitting: for each candidate effect (off in the model), the sensitivity J of the
whitened prediction to the effect's parameters is taken by finite differences at the model (cheap for
measurement effects: fe replays are cached; one replay per parameter for physics effects). The
bounded linear least-squares fit of the residual on J gives the chi-square drop an effect can explain
(a score test, evaluated to second order); candidates are ranked by it minus a BIC penalty.

The top few are then refitted with chord iterations (the same J, re-predicting nonlinearly after
each step) and judged on held-out data: each indenter in turn is left out of the linearised fit and
predicted. The verdict names the effect only when it is clearly best, explains the excess residual
down to 1.3 times the noise, and is identifiable; otherwise it says "unexplained" or "nothing".
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np
from scipy.optimize import lsq_linear, minimize, minimize_scalar

from twin.analysis.compare import FORCE_CHANNELS, noise_estimate, time_in_increment
from twin.analysis.data import CampaignData, TrajectoryRecord
from twin.analysis.predict import Predictor, TwinModel, measured_force_fullrate
from twin.effects import EFFECTS, Effect

NOISE_TOLERANCE = 1.3
"""An explanation must bring the whitened residual RMS to at most this multiple of the noise."""
DOMINANCE = 1.5
"""The best candidate's evidence must exceed the runner-up's by this factor to be named."""


@dataclass(frozen=True)
class Residual:
    """Whitened, offset-projected full-rate force residual and the bookkeeping to build it."""

    values: np.ndarray  # (N,) whitened residual
    trajectory_index: np.ndarray  # (N,) index into the trajectory list
    indenter: np.ndarray  # (N,) indenter name per sample
    covariates: dict[str, np.ndarray]  # (N,) each
    sigma: np.ndarray  # (3,) noise per force axis (N)


@dataclass
class Candidate:
    """Evidence for one effect."""

    name: str
    kind: str
    parameters: dict[str, float]  # linearised best fit
    chi2_drop: float
    evidence: float  # chi2_drop - k log N
    explained_fraction: float  # of the excess chi2 over the noise
    heldout_rms: float | None = None  # whitened RMS on left-out indenters (linearised)
    refit_rms: float | None = None  # whitened RMS after the nonlinear refit on all data
    refit_parameters: dict[str, float] = field(default_factory=dict)
    correlation: list[list[float]] = field(default_factory=list)
    condition: float = float("nan")
    identifiable: bool = True


@dataclass
class Diagnosis:
    """The outcome: ranked candidates, residual signatures and a verdict."""

    base_rms: float  # whitened RMS of the base residual (1 = noise)
    signatures: dict[str, float]
    candidates: list[Candidate]
    verdict: str  # "nothing", an effect name, or "unexplained"
    reason: str

    def to_dict(self) -> dict:
        """JSON-ready form (the `twin diagnose --json` shape)."""
        return {
            "base_rms_over_noise": self.base_rms,
            "verdict": self.verdict,
            "reason": self.reason,
            "signatures": self.signatures,
            "candidates": [c.__dict__ for c in self.candidates],
        }


def _fullrate_prediction(predictor: Predictor, model: TwinModel, trajectories: list[TrajectoryRecord]) -> list:
    return [predictor.predict(model, t).force_fullrate for t in trajectories]


def build_residual(
    trajectories: list[TrajectoryRecord], predicted: list[np.ndarray], sigma: np.ndarray
) -> tuple[Residual, np.ndarray]:
    """The whitened residual and the boolean mask of samples used (valid predictions)."""
    values, index, indenter, masks = [], [], [], []
    cov: dict[str, list] = {k: [] for k in ("depth", "time_in_increment", "time", "axis", "angled")}
    for i, (t, p) in enumerate(zip(trajectories, predicted, strict=True)):
        valid = np.isfinite(p).all(axis=1)
        masks.append(valid)
        r = (measured_force_fullrate(t) - p)[valid] / sigma
        r = r - r.mean(axis=0)
        values.append(r.ravel())
        n = valid.sum()
        index.append(np.full(3 * n, i))
        indenter.append(np.full(3 * n, t.indenter, dtype=object))
        cov["depth"].append(np.repeat(t.raw.depth_command[valid], 3))
        cov["time_in_increment"].append(np.repeat(time_in_increment(t)[valid], 3))
        cov["time"].append(np.repeat(t.raw.time[valid], 3))
        cov["axis"].append(np.tile(np.arange(3), n))
        cov["angled"].append(np.full(3 * n, not t.normal))
    residual = Residual(
        np.concatenate(values),
        np.concatenate(index),
        np.concatenate(indenter),
        {k: np.concatenate(v) for k, v in cov.items()},
        sigma,
    )
    return residual, masks


def _whitened(predicted: list[np.ndarray], masks: list[np.ndarray], sigma: np.ndarray) -> np.ndarray:
    """Whitened, offset-projected predictions on the base model's sample set (for differences).

    Samples where this prediction failed (fe not converged) are NaN; fits and scores skip them.
    """
    out = []
    for p, m in zip(predicted, masks, strict=True):
        w = p[m] / sigma
        out.append((w - np.nanmean(w, axis=0)).ravel())
    return np.concatenate(out)


def _base_residual(datasets: list[CampaignData], model: TwinModel, predictor: Predictor) -> tuple:
    """Trajectories, noise sigma (3,), the base residual, its sample masks and whitened base prediction."""
    trajectories = [t for d in datasets for t in d.trajectories]
    if not trajectories:
        raise ValueError("the datasets hold no trajectories")
    noise = noise_estimate(trajectories)
    sigma = np.array([max(noise[c], 1e-9) for c in FORCE_CHANNELS])
    predicted = _fullrate_prediction(predictor, model, trajectories)
    residual, masks = build_residual(trajectories, predicted, sigma)
    return trajectories, sigma, residual, masks, _whitened(predicted, masks, sigma)


def signatures(residual: Residual) -> dict[str, float]:
    """Correlation of the whitened residual (and of its magnitude) with each covariate."""
    r = residual.values
    out = {}
    for name, values in residual.covariates.items():
        if name == "axis" or np.ptp(values.astype(float)) == 0:
            continue
        x = values.astype(float)
        out[f"corr(residual, {name})"] = float(np.corrcoef(r, x)[0, 1])
        out[f"corr(|residual|, {name})"] = float(np.corrcoef(np.abs(r), x)[0, 1])
    out["rms_over_noise"] = float(np.sqrt(np.mean(r**2)))
    return out


def sensitivity(
    effect: Effect,
    model: TwinModel,
    predictor: Predictor,
    trajectories: list[TrajectoryRecord],
    masks: list[np.ndarray],
    sigma: np.ndarray,
    base: np.ndarray,
) -> np.ndarray:
    """(N, k) finite-difference sensitivity of the whitened prediction to the effect's parameters."""
    current = effect.values(model.effects.get(effect.name))
    columns = []
    for p in effect.parameters:
        step = p.scale if current[p.name] + p.scale <= p.upper else -p.scale
        changed = model.with_effects({effect.name: {**current, p.name: current[p.name] + step}})
        shifted = _whitened(_fullrate_prediction(predictor, changed, trajectories), masks, sigma)
        columns.append((shifted - base) / step)
    return np.column_stack(columns)


def _linear_fit(effect: Effect, current: dict[str, float], jac: np.ndarray, r: np.ndarray) -> np.ndarray:
    finite = np.isfinite(jac).all(axis=1) & np.isfinite(r)
    jac, r = jac[finite], r[finite]
    lower = np.array([p.lower - current[p.name] for p in effect.parameters])
    upper = np.array([p.upper - current[p.name] for p in effect.parameters])
    scale = np.array([p.scale for p in effect.parameters])
    fit = lsq_linear(jac * scale, r, bounds=(lower / scale, upper / scale))
    return fit.x * scale


def diagnose(
    datasets: list[CampaignData],
    model: TwinModel,
    predictor: Predictor | None = None,
    candidates: list[str] | None = None,
    top: int = 3,
) -> Diagnosis:
    """Rank the library's effects (off in `model`) by how well each explains the residual."""
    predictor = predictor or Predictor()
    trajectories, sigma, residual, masks, base = _base_residual(datasets, model, predictor)
    r = residual.values
    n = len(r)
    chi2 = float(r @ r)
    excess = chi2 - n
    base_rms = float(np.sqrt(chi2 / n))
    names = candidates if candidates is not None else [k for k in EFFECTS if k not in model.effects]
    ranked: list[tuple[Candidate, np.ndarray]] = []
    for name in names:
        effect = EFFECTS[name]
        jac = sensitivity(effect, model, predictor, trajectories, masks, sigma, base)
        current = effect.values(model.effects.get(name))
        delta = _linear_fit(effect, current, jac, r)
        drop = chi2 - float(np.nansum((r - jac @ delta) ** 2))
        candidate = Candidate(
            name=name,
            kind=effect.kind,
            parameters={p.name: current[p.name] + d for p, d in zip(effect.parameters, delta, strict=True)},
            chi2_drop=drop,
            evidence=drop - len(delta) * np.log(n),
            explained_fraction=drop / excess if excess > 0 else 0.0,
        )
        ranked.append((candidate, jac))
    ranked.sort(key=lambda item: -item[0].evidence)
    for candidate, jac in ranked[:top]:
        _heldout(
            candidate, jac, r, residual.indenter, EFFECTS[candidate.name].values(model.effects.get(candidate.name))
        )
        _identifiability(candidate, jac)
        _refit(candidate, model, predictor, trajectories, masks, sigma, jac, r, base)
    ordered = [c for c, _ in ranked]
    verdict, reason = _verdict(base_rms, ordered)
    return Diagnosis(base_rms, signatures(residual), ordered, verdict, reason)


def _heldout(
    candidate: Candidate, jac: np.ndarray, r: np.ndarray, indenter: np.ndarray, current: dict[str, float]
) -> None:
    """Leave-one-indenter-out: fit the linearised effect on the rest, score the whitened RMS on the left-out."""
    effect = EFFECTS[candidate.name]
    groups = np.unique(indenter)
    if len(groups) < 2:
        candidate.heldout_rms = None
        return
    squared, count = 0.0, 0
    for g in groups:
        train, test = indenter != g, indenter == g
        delta = _linear_fit(effect, current, jac[train], r[train])
        misfit = (r[test] - jac[test] @ delta) ** 2
        squared += float(np.nansum(misfit))
        count += int(np.isfinite(misfit).sum())
    candidate.heldout_rms = float(np.sqrt(squared / count))


def _identifiability(candidate: Candidate, jac: np.ndarray) -> None:
    """Parameter correlations and the condition of J^T J (scaled); flag non-identifiable fits."""
    scale = np.array([p.scale for p in EFFECTS[candidate.name].parameters])
    scaled = (jac * scale)[np.isfinite(jac).all(axis=1)]
    info = scaled.T @ scaled
    eig = np.linalg.eigvalsh(info)
    candidate.condition = float(eig[-1] / max(eig[0], 1e-300))
    cov = np.linalg.pinv(info)
    d = np.sqrt(np.clip(np.diag(cov), 1e-300, None))
    corr = cov / np.outer(d, d)
    candidate.correlation = corr.round(4).tolist()
    off_diagonal = np.abs(corr - np.diag(np.diag(corr)))
    candidate.identifiable = bool(candidate.condition < 1e8 and (off_diagonal.max(initial=0.0) < 0.98))


def _refit(
    candidate: Candidate,
    model: TwinModel,
    predictor: Predictor,
    trajectories: list[TrajectoryRecord],
    masks: list[np.ndarray],
    sigma: np.ndarray,
    jac: np.ndarray,
    r: np.ndarray,
    base: np.ndarray,
    iterations: int = 2,
) -> None:
    """Chord iterations (linear steps with the base J, re-predicted nonlinearly each time), then, for
    measurement effects whose predictions reuse cached fe replays, a nonlinear least-squares polish."""
    effect = EFFECTS[candidate.name]
    values = effect.values(model.effects.get(candidate.name))

    def misfit(trial_values: dict[str, float]) -> np.ndarray:
        trial = model.with_effects({candidate.name: trial_values})
        predicted = _whitened(_fullrate_prediction(predictor, trial, trajectories), masks, sigma)
        return r - (predicted - base)

    residual = r
    for _ in range(iterations):
        delta = _linear_fit(effect, values, jac, residual)
        values = {
            p.name: float(np.clip(values[p.name] + d, p.lower, p.upper))
            for p, d in zip(effect.parameters, delta, strict=True)
        }
        residual = misfit(values)
    if effect.kind == "measurement":
        values, residual = _polish(effect, values, misfit)
    candidate.refit_parameters = values
    candidate.refit_rms = float(np.sqrt(np.nanmean(residual**2)))


def _polish(effect: Effect, start: dict[str, float], misfit) -> tuple[dict[str, float], np.ndarray]:
    """Bounded nonlinear least squares on the effect's parameters from `start` (derivative-free steps of
    each parameter's scale, robust to signals that move in whole samples, like a delay)."""
    names = [p.name for p in effect.parameters]

    def as_values(x: np.ndarray) -> dict[str, float]:
        return dict(zip(names, (float(v) for v in x), strict=True))

    def cost(x: np.ndarray) -> float:
        return float(np.nanmean(misfit(as_values(x)) ** 2))

    x0 = np.array([start[n] for n in names])
    bounds = [(p.lower, p.upper) for p in effect.parameters]
    if len(names) == 1:
        p = effect.parameters[0]
        lo, hi = max(p.lower, x0[0] - 5 * p.scale), min(p.upper, x0[0] + 5 * p.scale)
        best = minimize_scalar(lambda v: cost(np.array([v])), bounds=(lo, hi), method="bounded")
        x = np.array([best.x]) if best.fun < cost(x0) else x0
    else:
        best = minimize(cost, x0, method="Powell", bounds=bounds, options={"maxfev": 60 * len(names), "xtol": 1e-3})
        x = best.x if best.fun < cost(x0) else x0
    values = as_values(x)
    return values, misfit(values)


def _verdict(base_rms: float, candidates: list[Candidate]) -> tuple[str, str]:
    if base_rms <= NOISE_TOLERANCE:
        return "nothing", f"the residual is already within {NOISE_TOLERANCE}x the noise ({base_rms:.2f}x)"
    if not candidates or candidates[0].evidence <= 0:
        return "unexplained", "no candidate effect explains a significant part of the residual"
    best = candidates[0]
    runner = candidates[1].evidence if len(candidates) > 1 else 0.0
    if best.refit_rms is None or best.refit_rms > NOISE_TOLERANCE:
        return "unexplained", (
            f"the best candidate ({best.name}) leaves {best.refit_rms:.2f}x the noise after refitting"
        )
    if runner > 0 and best.evidence < DOMINANCE * runner:
        return "unexplained", f"{best.name} and {candidates[1].name} explain the residual about equally well"
    if not best.identifiable:
        return "unexplained", f"{best.name} fits, but its parameters are not identifiable from these data"
    return best.name, (
        f"{best.name} explains {best.explained_fraction:.0%} of the excess residual; "
        f"refitted RMS {best.refit_rms:.2f}x noise (held-out {best.heldout_rms or float('nan'):.2f}x)"
    )


@dataclass(frozen=True)
class EffectFit:
    """An effect fitted to data: its values, and whitened RMS (1 = noise) before, after and held out."""

    name: str
    values: dict[str, float]
    rms_before: float
    rms_after: float
    heldout_rms: float | None
    model: TwinModel


def fit_effect(
    datasets: list[CampaignData], model: TwinModel, name: str, predictor: Predictor | None = None
) -> EffectFit:
    """Fit one library effect's parameters (chord iterations on the whitened full-rate residual)."""
    predictor = predictor or Predictor()
    effect = EFFECTS.get(name)
    if effect is None:
        raise ValueError(f"unknown effect {name!r}; the library has {sorted(EFFECTS)}")
    trajectories, sigma, residual, masks, base = _base_residual(datasets, model, predictor)
    jac = sensitivity(effect, model, predictor, trajectories, masks, sigma, base)
    candidate = Candidate(name, effect.kind, {}, 0.0, 0.0, 0.0)
    _heldout(candidate, jac, residual.values, residual.indenter, effect.values(model.effects.get(name)))
    _refit(candidate, model, predictor, trajectories, masks, sigma, jac, residual.values, base, iterations=3)
    rms_before = float(np.sqrt(np.mean(residual.values**2)))
    improved = model.with_effects({name: candidate.refit_parameters})
    return EffectFit(name, candidate.refit_parameters, rms_before, candidate.refit_rms, candidate.heldout_rms, improved)
