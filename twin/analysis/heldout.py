"""Whether a candidate's fit generalises: leave-one-indenter-out predictions about a fit, the noise test of what
they leave (`twin.analysis.significance`), and whether the fit's parameters are identifiable."""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import replace

import numpy as np

from twin.analysis.fit import reduced
from twin.analysis.fit import uncertainty as fit_uncertainty
from twin.analysis.predict import Predictor, TwinModel
from twin.analysis.residual import Base, Residual
from twin.analysis.sensitivity import Linearisation, linear_fit, linearisation_models, linearise
from twin.analysis.significance import NoiseTest, out_of_fold_excess
from twin.analysis.verdict import Candidate, parameters_at_bound
from twin.effects import EFFECTS, Effect

NOISE_TOLERANCE = 1.3
"""Screen before refits: candidates whose linearised held-out RMS is within this multiple of the noise
rank ahead of those that are not. Naming uses the noise test (`twin.analysis.significance`) instead."""


def generalises(candidate: Candidate) -> bool:
    """Whether the candidate's held-out RMS (when there is one) is within the screening tolerance."""
    return candidate.heldout_rms is None or candidate.heldout_rms <= NOISE_TOLERANCE


def heldout_folds(residual: Residual) -> np.ndarray:
    """(N,) the fold each residual sample is held out with: its indenter when the residual has two or more, else
    its trajectory (a campaign of one indenter holds out one press at a time, fitted on the others); folds are
    integer codes, named per trajectory (each presses with one indenter) rather than sorted sample by sample."""
    trajectories, first = np.unique(residual.trajectory_index, return_index=True)
    names, codes = np.unique(residual.indenter[first], return_inverse=True)
    if len(names) < 2:
        return residual.trajectory_index
    fold_of = np.zeros(int(trajectories.max()) + 1, dtype=int)
    fold_of[trajectories] = codes
    return fold_of[residual.trajectory_index]


def heldout(effect: Effect, lin: Linearisation, r: np.ndarray, folds: np.ndarray) -> tuple[float | None, np.ndarray]:
    """Leave-one-fold-out about `lin` (folds (N,): `heldout_folds`): the effect fitted (linearised) on the other
    folds predicts each left-out one. (whitened RMS of the left-out residuals, those residuals (N,), NaN where no
    prediction); (None, all NaN) with fewer than two folds: nothing is held out."""
    target = r - lin.offset
    order = np.argsort(folds, kind="stable")  # each fold's rows contiguous, in their own order: slices, not masks
    ordered = folds[order]
    edges = np.flatnonzero(ordered[1:] != ordered[:-1]) + 1
    if len(edges) < 1:
        return None, np.full_like(target, np.nan)
    jac, fold_target = lin.jac[order], target[order]
    blocks = [slice(a, b) for a, b in zip((0, *edges), (*edges, len(order)), strict=True)]
    parts = [reduced(jac[block], fold_target[block]) for block in blocks]  # each fold's rows reduced once
    left_out = np.empty_like(target)
    for k, block in enumerate(blocks):
        others = [part for j, part in enumerate(parts) if j != k]
        delta = linear_fit(effect, lin.point, np.vstack([m for m, _ in others]), np.concatenate([t for _, t in others]))
        left_out[order[block]] = fold_target[block] - jac[block] @ delta
    return whitened_rms(left_out), left_out


def judge_heldout(
    candidate: Candidate, model: TwinModel, predictor: Predictor, base: Base, columns: TwinModel | None = None
) -> Base:
    """Held-out RMS about the refitted values (the residual about the refitted model, each sensor's PDC gain
    profiled about that model's own PDC, `Base.about`; the effect linearised again there: one fe replay per
    parameter for a physics effect), whether that held-out residual passes the noise test, which allows
    for the error the fits on the other indenters carry into it (`significance.out_of_fold_excess`; the
    parameter bounds of the fits are not modelled), and whether that test has power (`record_heldout`: the
    base residual on the same samples); and which refitted parameters sit at a bound. With `columns` (the model on
    another fe mesh, `judgement_models`), the linearisation's columns are differences of that mesh's replays about
    its own prediction at the fit; the residual about the fit stays `model`'s. Returns the residual about the fit."""
    effect = EFFECTS[candidate.name]
    about = base.about(predictor, model.with_effects({candidate.name: candidate.refit_parameters}))
    if columns is None or columns == model:
        at_fit = linearise(effect, model, candidate.refit_parameters, predictor, about)
    else:
        on_columns = about.about(predictor, columns.with_effects({candidate.name: candidate.refit_parameters}))
        columns_base = replace(on_columns, residual=about.residual)
        at_fit = linearise(effect, columns, candidate.refit_parameters, predictor, columns_base)
    folds = heldout_folds(about.residual)
    rms, left_out = heldout(effect, at_fit, about.residual.values, folds)
    out_of_fold = out_of_fold_excess(at_fit.jac, folds)
    record_heldout(
        candidate, rms, left_out, base.residual.values, lambda r: about.noise_test(r, out_of_fold=out_of_fold)
    )
    candidate.at_bound = parameters_at_bound(candidate.name, candidate.refit_parameters)
    return about


def judgement_models(
    candidates: list[Candidate], model: TwinModel, columns: TwinModel | None = None
) -> list[TwinModel]:
    """The models whose replays `judge_heldout` of each candidate needs: the fit and each column's step on `model`,
    or, with `columns` on another mesh, the fit on `model` and the whole linearisation on `columns`."""
    models = []
    for c in candidates:
        at_fit = model.with_effects({c.name: c.refit_parameters})
        linearisation = linearisation_models(EFFECTS[c.name], columns or model, c.refit_parameters)
        models += linearisation if columns is None else [at_fit, *linearisation]  # its first model: the fit
    return models


def judge_model_effects(model: TwinModel, predictor: Predictor, base: Base) -> list[Candidate]:
    """Each library effect `model` carries (fitted earlier, e.g. by `twin improve`), judged held out as a refitted
    candidate is (`judge_heldout` at the model's own values: fitted linearly on the other indenters, each left-out one
    predicted), their replays solved as one batch. A residual that passes the noise test in sample rests on these
    fits; one that does not hold out was fitted to these data without generalising."""
    named = [name for name in model.effects if name in EFFECTS]
    values = {name: EFFECTS[name].values(model.effects[name]) for name in named}
    base.prefetch(predictor, [m for name in named for m in linearisation_models(EFFECTS[name], model, values[name])])
    judged = []
    for name in named:
        candidate = Candidate(
            name,
            EFFECTS[name].kind,
            values[name],
            0.0,
            0.0,
            0.0,
            refit_rms=whitened_rms(base.residual.values),
            refit_parameters=values[name],
        )
        judge_heldout(candidate, model, predictor, base)
        judged.append(candidate)
    return judged


def record_heldout(
    candidate: Candidate,
    rms: float | None,
    left_out: np.ndarray,
    base_residual: np.ndarray,
    test: Callable[[np.ndarray], NoiseTest],
) -> None:
    """Set the candidate's held-out figures: `rms` and the held-out residual `left_out` (N,; NaN where
    there is no prediction), whether `test` (the held-out noise test) passes it, the RMS the test allows,
    and the power rule (`twin.analysis.verdict`): the whitened RMS of `base_residual` (N,, the residual
    without the effect) on the same samples and whether the same test rejects it. With nothing held out
    (`rms` None: a single fold) the candidate is left unjudged (`heldout_is_noise` None: never named)."""
    if rms is None:
        candidate.heldout_rms, candidate.heldout_is_noise, candidate.heldout_has_power = None, None, None
        return
    held = test(left_out)
    without = np.where(np.isfinite(left_out), base_residual, np.nan)
    candidate.heldout_rms = rms
    candidate.heldout_is_noise = bool(held.is_noise)  # plain bools: `twin improve` writes them to its history
    candidate.heldout_rms_threshold = float(held.rms_threshold)
    candidate.heldout_base_rms = whitened_rms(without)
    candidate.heldout_has_power = not bool(test(without).is_noise)


def identifiability(candidate: Candidate, lin: Linearisation) -> None:
    """Parameter correlations and the condition of J^T J (scaled, `twin.analysis.fit.uncertainty`) of the
    parameters that act on these data; flag non-identifiable fits. A parameter at its off value whose column is
    zero on every sample is inert, not unidentified (an F/T range on an axis whose reading never reaches it): it
    is left out (its correlations 0); a candidate with no parameter acting is not identifiable."""
    parameters = EFFECTS[candidate.name].parameters
    inert = np.array([lin.point[p.name] == p.off for p in parameters]) & ~np.any(lin.jac != 0.0, axis=0)
    acting = np.flatnonzero(~inert)
    spread = fit_uncertainty(lin.jac[:, acting], np.array([parameters[i].scale for i in acting]))
    correlation = np.zeros((len(parameters), len(parameters)))
    correlation[np.ix_(acting, acting)] = spread.correlation
    candidate.condition = spread.condition
    candidate.correlation = correlation.round(4).tolist()
    off_diagonal = np.abs(correlation - np.diag(np.diag(correlation)))
    candidate.identifiable = bool(
        acting.size > 0 and candidate.condition < 1e8 and (off_diagonal.max(initial=0.0) < 0.98)
    )


def whitened_rms(residual: np.ndarray) -> float:
    """Whitened RMS of a residual, skipping samples without a prediction (NaN)."""
    return float(np.sqrt(np.nanmean(residual**2)))
