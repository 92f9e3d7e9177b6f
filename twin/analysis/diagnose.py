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

The top few (and, when none of them holds held out, those whose linearised fits come close to the
best's) are then refitted with chord iterations (the same J, re-predicting nonlinearly after each step; the
candidates side by side, each step's replays of all of them solved in one batch, `twin.analysis.lockstep`)
and judged held out about their refit: each indenter in turn is left out of the fit (linearised at the
refitted values) and predicted. The verdict (`twin.analysis.verdict`) names an effect only when that
held-out residual passes the noise test (`twin.analysis.significance`, a chi-square test whose threshold
shrinks as the data grow), its parameters are identifiable and no other comes close; "nothing" when the
base residual passes the test; "unexplained" otherwise.
"""

from __future__ import annotations

import json
from collections.abc import Callable
from dataclasses import dataclass, field, replace
from functools import partial

import numpy as np

from twin.analysis.data import CampaignData
from twin.analysis.heldout import (
    generalises,
    heldout,
    heldout_folds,
    identifiability,
    judge_heldout,
    judge_model_effects,
    judgement_models,
    whitened_rms,
)
from twin.analysis.lockstep import run_in_lockstep
from twin.analysis.nuisances import NUISANCE_EFFECTS, fit_nuisances
from twin.analysis.predict import Predictor, TwinModel
from twin.analysis.refit import finish_on_model_mesh, refit, refit_on_reached
from twin.analysis.residual import CHANNELS, Base, Residual, base_residual
from twin.analysis.rows_only import RAW_ONLY_EFFECTS
from twin.analysis.sensitivity import (
    Linearisation,
    data_estimate,
    first_models,
    linear_fit,
    linearisation_models,
    linearise,
    sensitivities,
    start_models,
)
from twin.analysis.subset import sampled
from twin.analysis.verdict import (
    CLOSEST_SHOWN,
    NOTHING_BEYOND_NUISANCES,
    Candidate,
    candidate_figures,
    closest_refitted,
    on_every_sample,
    order_candidates,
    to_refit,
    verdict,
)
from twin.effects import EFFECTS
from twin.lanes import thread_map


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
    ranked_on: dict | None = None  # the trajectories that ranked the candidates (`subset.RankedOn`); None: all
    sampled: dict | None = None  # the trajectories diagnosed (`subset.RankedOn`), every stage; None: all
    ranked_mesh: float | None = None  # fe mesh (m) the candidates were ranked and refitted on; None: the model's
    samples: dict | None = None  # {"reached": residual samples the base model's replays reached, "of": the data's}
    jointly: dict | None = None  # the closest candidate fitted jointly with the nuisances (`named_jointly`) when it ran

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
            "ranked_on": self.ranked_on,
            "sampled": self.sampled,
            "ranked_mesh_mm": None if self.ranked_mesh is None else 1e3 * self.ranked_mesh,
            "samples": self.samples,
            "jointly": self.jointly,
        }

    def next_step(self) -> Candidate | None:
        """On an "unexplained" verdict, its closest candidate (the refitted one of least held-out RMS, the first the
        reason shows) when that lowers the held-out residual below the base residual: the step a user takes when two
        effects are missing (neither alone reaches the noise); never a cause. None otherwise."""
        if self.verdict != "unexplained":
            return None
        judged = [c for c in self.candidates if c.refitted and c.heldout_rms is not None]
        closest = min(judged, key=lambda c: c.heldout_rms, default=None)
        if closest is None or not closest.heldout_rms < self.base_rms:
            return None
        return closest

    def nuisances_closest(self) -> list[str]:
        """On an "unexplained" verdict without the nuisance stage, the nuisance effects (`NUISANCE_EFFECTS`: what every
        real campaign carries, registration and unit-to-unit skin) among its closest candidates (the refitted ones
        of least held-out RMS, as many as the reason shows), best first: the residual may be those nuisances
        together, which `diagnose(..., nuisances=True)` fits first. Empty otherwise."""
        if self.verdict != "unexplained" or self.nuisances is not None:
            return []
        return [c.name for c in closest_refitted(self.candidates)[:CLOSEST_SHOWN] if c.name in NUISANCE_EFFECTS]

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


def diagnose(
    datasets: list[CampaignData],
    model: TwinModel,
    predictor: Predictor | None = None,
    candidates: list[str] | None = None,
    top: int = 3,
    on_progress: Callable[[str, str], None] | None = None,
    nuisances: bool = False,
    rank_per_stratum: int | None = None,
    per_stratum: int | None = None,
    rank_mesh: float | None = None,
) -> Diagnosis:
    """Rank the library's effects (off in `model`) by how well each explains the residual; the first
    `top` of the ranking are refitted and judged held out about their refit (`twin.analysis.verdict`); when none
    of them is supported held out and the base residual is not noise, so are the next ones whose linearised fits
    come close to the best's (`twin.analysis.verdict.to_refit`).
    With `nuisances`, the standard unknowns of a real campaign (`twin.analysis.nuisances`: registration
    per arm, skin per sensor) are fitted first, candidates are ranked on what remains (their signatures
    less what the nuisances can absorb) and are never the nuisance effects themselves; when none is named, the
    closest is fitted again jointly with the nuisances (`named_jointly`).
    on_progress(stage, effect) is called before each candidate is scored ("evidence"; every candidate's
    sensitivity is solved first, their replays batched, `sensitivities`) and refitted
    ("refit"), and with ("nuisances", what) during the nuisance fit.
    Without `nuisances`, an effect with a surrogate (`sensitivity.SURROGATES`: a relaxing skin, from the skin
    modulus's elastic replays, `twin.analysis.surrogate`) is ranked on it, and linearised again on its own replays
    before it is refitted: no verdict rests on a surrogate.
    With `rank_per_stratum`, candidates are linearised and ranked on at most that many trajectories of each
    sensor x indenter x path kind (`twin.analysis.subset`; not with `nuisances`); the top ones are linearised
    again, refitted and judged held out on every trajectory, and `ranked_on` says which trajectories ranked.
    With `rank_mesh` (m), candidates are linearised, ranked and refitted on replays of that fe mesh (a coarser one
    costs several times less; not with `nuisances`): each column is a difference of two replays of that mesh, scored
    against the residual of the model's own mesh (`ranking_base`); each physics fit is finished on the model's mesh
    (`refit.finish_on_model_mesh`: a coarse mesh biases a fit of the indenter's path); each refitted one is judged
    held out about the model mesh's residual at its fit (the fold fits' columns from that mesh's replays,
    `judge_heldout`), and its `refit_rms` is that residual's, so a verdict rests on the model mesh's residual at each
    fit.
    With `per_stratum`, the whole diagnosis runs on at most that many trajectories of each stratum
    (`twin.analysis.subset.sampled`), and `sampled` says which. On row-only data (`twin.analysis.rows_only`) the
    effects those cannot identify (`RAW_ONLY_EFFECTS`) are not candidates (ValueError when asked for)."""
    if top < 0:
        raise ValueError(f"the number of candidates to refit must be >= 0, got {top}")
    if rank_per_stratum is not None and nuisances:
        raise ValueError("ranking on a subset of the trajectories is not combined with the nuisance fit")
    if rank_mesh is not None and nuisances:
        raise ValueError("ranking on another fe mesh is not combined with the nuisance fit")
    if rank_mesh is not None and not rank_mesh > 0:
        raise ValueError(f"the ranking mesh must be a positive edge length (m), got {rank_mesh}")
    if nuisances and set(candidates or ()) & set(NUISANCE_EFFECTS):
        raise ValueError(f"with the nuisances fitted, {sorted(NUISANCE_EFFECTS)} cannot be candidates")
    report = on_progress or (lambda stage, name: None)
    sampled_on = None
    if per_stratum is not None:
        datasets, sampled_on = sampled(datasets, per_stratum)
    predictor = predictor or Predictor(electrodes=False)  # the residual has force and PDC only
    rows_only = any(t.rows_only for d in datasets for t in d.trajectories)
    blind = set(RAW_ONLY_EFFECTS) if rows_only else set()
    if blind & set(candidates or ()):
        named = sorted(blind & set(candidates or ()))
        raise ValueError(f"a row-only file cannot identify {', '.join(named)}: {RAW_ONLY_EFFECTS[named[0]]}")
    excluded = set(model.effects) | (set(NUISANCE_EFFECTS) if nuisances else set()) | blind
    names = candidates if candidates is not None else [k for k in EFFECTS if k not in excluded]
    ranking_sets, ranked_on = sampled(datasets, rank_per_stratum) if rank_per_stratum is not None else (datasets, None)
    rank_model = model if rank_mesh is None else replace(model, mesh_max_edge=rank_mesh)
    if not nuisances:  # the base's replays and the candidates' first linearisations' in one batch (no fit between)
        on_ranking = [t for d in ranking_sets for t in d.trajectories]
        every = [t for d in datasets for t in d.trajectories]
        own = [(rank_model, every)] if rank_model != model else []  # the base on the ranking (and refitting) mesh
        effects = [EFFECTS[k] for k in names]
        # with the trials' declared starts, which do not depend on the residual either: fewer waves of replays
        first = [
            (m, on_ranking)
            for m in [*first_models(effects, rank_model, None, True), *start_models(effects, rank_model)]
        ]
        predictor.prefetch_many([(model, every), *own, *first])
    fitted = fit_nuisances(datasets, model, predictor, lambda text: report("nuisances", text)) if nuisances else None
    base = fitted.base if fitted is not None else base_residual(datasets, model, predictor)
    residual = base.residual
    base_rms = float(np.sqrt(base.nuisance.chi2(residual.values) / len(residual.values)))
    ranked: list[tuple[Candidate, Linearisation]] = []
    ranking = ranking_base(base, ranking_sets if ranked_on is not None else None, model, rank_model, predictor)
    # ranked on surrogates where an effect has one (`SURROGATES`; not about the nuisances: their confounding test
    # reads the columns, and a verdict never rests on a surrogate), linearised again before any refit
    lins = sensitivities([EFFECTS[name] for name in names], rank_model, predictor, ranking, surrogates=fitted is None)
    r = ranking.residual.values  # the candidates are scored on the ranking trajectories (all, by default)
    n = len(r)
    chi2 = ranking.nuisance.chi2(r)
    excess = chi2 - n

    def scored_candidate(named: tuple[str, Linearisation]) -> tuple[Candidate, Linearisation]:
        name, lin = named
        effect = EFFECTS[name]
        scored = lin
        if fitted is not None:  # what a joint refit with the nuisances would leave of the effect's signature
            scored = replace(lin, offset=fitted.project(lin.offset), jac=fitted.project(lin.jac))
        delta = linear_fit(effect, scored.point, scored.jac, r - scored.offset)
        drop = chi2 - ranking.nuisance.chi2(r - scored.offset - scored.jac @ delta)
        candidate = Candidate(
            name=name,
            kind=effect.kind,
            parameters={p.name: lin.point[p.name] + d for p, d in zip(effect.parameters, delta, strict=True)},
            chi2_drop=drop,
            evidence=drop - len(delta) * np.log(n),
            explained_fraction=drop / excess if excess > 0 else 0.0,
            onset=lin.data_start.to_dict() if lin.data_start is not None else None,
        )
        candidate.heldout_rms = heldout(effect, scored, r, folds)[0]
        return candidate, lin

    folds = heldout_folds(ranking.residual)
    for name, lin in zip(names, lins, strict=True):
        report("evidence", name)
        if fitted is not None:  # how much of its signature the nuisances can take (`cannot_tell_apart`)
            fitted.confounding(name, lin.jac)
    ranked += thread_map(scored_candidate, list(zip(names, lins, strict=True)))  # numpy over the residual, each
    # Evidence can be fooled by a flexible effect that fits every indenter its own way: those that
    # also predict left-out indenters to within the tolerance rank ahead of those that do not.
    ranked.sort(key=lambda item: (not generalises(item[0]), -item[0].evidence))
    base_test = base.noise_test(residual.values)
    is_noise = base_test.is_noise and (fitted is None or fitted.heldout_is_noise)
    cannot_tell = set(fitted.cannot_tell_apart()) if fitted is not None else set()

    # refitted on the ranking mesh (every trajectory), judged on the model's
    fit_base = ranking if ranked_on is None else ranking_base(base, None, model, rank_model, predictor)

    def refit_and_judge(chosen: list[tuple[Candidate, Linearisation]]) -> None:
        # ranked on a subset or a surrogate: linearised again (every trajectory, own replays, the refits' mesh),
        # replays in one batch
        again = [ranked_on is not None or lin.surrogate for _, lin in chosen]
        redo = [(EFFECTS[c.name], lin) for (c, lin), fresh in zip(chosen, again, strict=True) if fresh]
        fit_base.prefetch(predictor, [m for e, lin in redo for m in linearisation_models(e, rank_model, lin.point)])
        chosen = [
            (
                c,
                replace(
                    linearise(EFFECTS[c.name], rank_model, lin.point, predictor, fit_base), data_start=lin.data_start
                ),
            )
            if fresh
            else (c, lin)
            for (c, lin), fresh in zip(chosen, again, strict=True)
        ]
        for candidate, lin in chosen:
            report("refit", candidate.name)
            identifiability(candidate, lin)
            if candidate.name in cannot_tell:
                candidate.identifiable = False  # never named: the nuisances could be what it fits
        # side by side, their replays solved together (`twin.analysis.lockstep`): the same fits, fewer waves
        run_in_lockstep(predictor, [partial(refit, c, rank_model, base=fit_base, lin=lin) for c, lin in chosen])
        if rank_model != model:  # each physics fit continued on the model's mesh, its columns still the ranking mesh's
            finishes = [
                partial(
                    finish_on_model_mesh,
                    c,
                    model,
                    base=base,
                    coarse=rank_model,
                    columns=fit_base,
                    starts=data_estimate(EFFECTS[c.name], lin, model),
                )
                for c, lin in chosen
            ]
            run_in_lockstep(predictor, finishes)
        # the held-out judgements' replays in one batch: about each fit on the model's mesh, columns on the ranking mesh
        columns = rank_model if rank_model != model else None
        base.prefetch(predictor, judgement_models([c for c, _ in chosen], model, columns))
        # each fit that reaches samples the model without it did not, fitted again on all it reaches (then its
        # judgement's replays are solved anew; none when no fit reaches more)
        run_in_lockstep(predictor, [partial(refit_on_reached, c, model, base=base) for c, _ in chosen])
        base.prefetch(predictor, judgement_models([c for c, _ in chosen], model, columns))
        judged = thread_map(lambda c: judge_heldout(c, model, predictor, base, columns), [c for c, _ in chosen])
        for (candidate, _), about_fit in zip(chosen, judged, strict=True):
            if rank_model != model:  # the refit's own figure on the model's mesh (the judgement's residual)
                candidate.refit_rms = whitened_rms(about_fit.residual.values)

    refit_and_judge(ranked[:top])
    # When none of those is supported held out, the next ones whose linearised fits come close to the best's are
    # refitted too (`verdict.to_refit`); not when the base residual is noise (the verdict is "nothing" whatever).
    if not is_noise and not any(c.supported_heldout and c.identifiable for c, _ in ranked[:top]):
        refit_and_judge(ranked[top : to_refit([c for c, _ in ranked], top, chi2)])
    ordered = order_candidates([c for c, _ in ranked])
    threshold = base_test.rms_threshold
    outcome, reason, tied = verdict(base_rms, is_noise, threshold, ordered, fitted is not None)
    joint = None
    if fitted is not None and outcome == "unexplained":  # the closest found about nuisances fitted without it
        joint = named_jointly(datasets, model, predictor, ordered, cannot_tell, report)
        if joint is not None and joint["named"]:
            outcome, reason, tied = joint["effect"], joint["reason"], []
    if outcome in ("nothing", NOTHING_BEYOND_NUISANCES):  # a residual at the noise rests on the model's own fits
        unheld = [c for c in judge_model_effects(model, predictor, base) if c.heldout_is_noise is False]
        if unheld:
            outcome, tied = "unexplained", []
            shown = "; ".join(map(candidate_figures, unheld))
            reason += (
                f", but the model's own {shown} does not hold out: fitted to these data without generalising, it is "
                "no explanation, so nothing is claimed"
            )
    if cannot_tell:
        reason += f"; these data cannot tell {', '.join(fitted.cannot_tell_apart())} from the nuisances"
    samples = {"reached": base.reached, "of": base.samples}
    covered = on_every_sample(outcome, reason, base.reached, base.samples)
    if covered[0] != outcome:
        outcome, reason = covered
    elif samples["reached"] < samples["of"]:
        reason += (
            f"; the model's replays reached {samples['reached']} of the data's {samples['of']} samples (a replay stops "
            "at an fe increment that does not converge): its residual and the ranking cover those only"
        )
    summary = fitted.to_dict() if fitted is not None else None
    return Diagnosis(
        base_rms,
        signatures(residual),
        ordered,
        outcome,
        reason,
        tied,
        threshold,
        summary,
        ranked_on.to_dict() if ranked_on is not None else None,
        sampled_on.to_dict() if sampled_on is not None else None,
        rank_mesh,
        samples,
        joint,
    )


def named_jointly(
    datasets: list[CampaignData],
    model: TwinModel,
    predictor: Predictor,
    ordered: list[Candidate],
    cannot_tell: set[str],
    report: Callable[[str, str], None],
) -> dict | None:
    """With the nuisances fitted first, the closest refitted candidate that they can be told from is fitted again
    jointly with them (`fit_nuisances(..., jointly=...)`, from its refit): the nuisances were fitted with its effect in
    the data and may have taken part of it (a delay during a constant-speed press looks like a depth offset), which
    biases its refit about them. It is named when the joint fit reaches the noise in sample (its parameters counted)
    and held out (each trajectory predicted by the nuisances and the effect fitted without it, whitened by its
    predictive spread); its refit parameters then become the joint fit's. The joint fit's summary
    (`NuisanceFit.to_dict`) with "effect", "named" and the verdict's "reason"; None when no candidate qualifies."""
    lead = next((c for c in ordered if c.refitted and c.identifiable and c.name not in cannot_tell), None)
    if lead is None or not lead.refit_parameters:
        return None
    report("nuisances", f"{lead.name} fitted jointly with them")
    start = model.with_effects({lead.name: lead.refit_parameters})
    joint = fit_nuisances(datasets, start, predictor, lambda text: report("nuisances", text), (lead.name,))
    named = bool(joint.is_noise and joint.heldout_is_noise)
    summary = {"effect": lead.name, "named": named, "reason": None, **joint.to_dict()}
    if not named:
        return summary
    values = joint.values.as_dict()
    lead.refit_parameters = {name: values[f"{lead.name}.{name}"] for name in lead.refit_parameters}
    bound = [label for label in joint.at_bound if label.startswith(f"{lead.name}.")]
    summary["reason"] = (
        f"fitted jointly with the nuisances (fitted without it, they took part of it), {lead.name} brings the residual "
        f"to the noise: {joint.rms_after:.2f}x in sample, held out {joint.heldout_predictive_rms:.2f}x of its "
        f"predictive spread ({joint.heldout_rms:.2f}x raw)" + (f"; {', '.join(bound)} at a bound" if bound else "")
    )
    return summary


def ranking_base(
    base: Base, subset: list[CampaignData] | None, model: TwinModel, rank_model: TwinModel, predictor: Predictor
) -> Base:
    """The residual the candidates are ranked on: `base`'s, or on a `subset` of its trajectories (the noise as
    estimated on all of them); with `rank_model` on another fe mesh, that residual (data less `model`'s
    prediction) about `rank_model`'s prediction, so each candidate's column, a difference of two `rank_model`
    replays, leaves the meshes' discretisation difference out of the score."""
    ranking = base if subset is None else base_residual(subset, model, predictor, sigma=base.sigma)
    if rank_model == model:
        return ranking
    return replace(ranking.about(predictor, rank_model), residual=ranking.residual)
