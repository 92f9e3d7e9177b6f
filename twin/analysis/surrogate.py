"""Stand-ins for an effect's own fe replays in its first, ranking linearisation (`twin.analysis.sensitivity`,
`SURROGATES`), built from elastic replays that a diagnosis solves anyway.

The one here is the skin's viscoelastic relaxation (`skin_relaxation`: one Prony branch of fraction g and time tau,
`fe.viscoelastic`). Off in the model, it is linearised at its probe (g = 0.15), where its own replays are timed:
every hold time-stepped, 2.7x the first batch's wall on an H100 (docs/scale.md, issue 18). To first order in g its
prediction change follows from the sensitivity S(t) = dPred/d(ln mu_nh) of the elastic skin alone. Quasi-linear
viscoelasticity makes the skin's stress (1 - g) sigma_e(t) + h(t), about the long-term (relaxed) state it is
inflated in, with the branch's memory h(t) = g sum_k gamma_k dsigma_e,k exp(-(t - t_k) / tau) of the elastic stress
changes dsigma_e,k since, each ramped over the dt_k before the pose's solve at t_k (gamma_k = (1 - e^(-x)) / x,
x = dt_k / tau: `fe.viscoelastic.step_factors`). The first term is the elastic skin at (1 - g) mu_nh: -g S(t),
exact to first order. The memory holds only what the indentation adds to the inflation's prestress, whose own share
of S (a, `PRESTRESS_SHARE`, measured: every stiffness scales with mu_nh, so S cannot tell it apart) is relaxed from the
start. Taking the response at t to each earlier pose change for that change of S, through the share of its contact
left at t (c: the size of the force's sensitivity; the skin can only push, so what the indenter has let go of reads
no memory), the change per unit g is

    dPred(t) / g = -S(t) + (1 - a) sum_k gamma_k min(1, c(t) / c(t_k)) [S(t_k) - S(t_k-)] e^(-(t - t_k) / tau),

evaluated at the events a timed replay solves (`twin.analysis.predict.solve_events`) and held from each to the next
sample, as a timed replay's samples are. S is the finite difference of the skin modulus's elastic replay
(mu_nh x (1 + `MODULUS_STEP`): the `skin_modulus` candidate's own column replay while that effect is off) from the
base's. The change is linear in g, so the g column (differenced back to off, as the real one) is that of the formula;
the tau column is the same forward difference as the real one's, of this change.

Only the ranking uses it: `twin.analysis.diagnose` linearises a candidate ranked on it again with its own replays
before refitting and judging it (`Linearisation.surrogate`). Measured against the timed finite-difference columns,
docs/analysis.md (issue 18) and tests/test_surrogate.py.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass, replace

import numpy as np

from fe.viscoelastic import step_factors
from twin.analysis.compare import FORCE_CHANNELS
from twin.analysis.predict import Predictor, TwinModel, solve_events
from twin.analysis.residual import Base, fullrate_prediction
from twin.controller import Recording
from twin.effects import EFFECTS
from twin.sim_backend import RELAXATION_SOLVE_INTERVAL_S

Shift = Callable[[TwinModel], np.ndarray]
"""The profiled whitened change (N,) of the prediction from the base to a model (`Base.shifted`'s form)."""

RELAXATION = "skin_relaxation"
"""The effect whose first linearisation `RELAXATION_SURROGATE` stands in for."""
MODULUS_STEP = EFFECTS["skin_modulus"].parameters[0].scale
"""Relative step of the skin modulus mu_nh whose elastic replay gives S (the `skin_modulus` column's step)."""
PRESTRESS_SHARE = 0.6
"""The share of the elastic skin's modulus sensitivity S borne by its inflation prestress, which a relaxing skin holds
at its long-term moduli from the start (it is inflated relaxed): only the rest, what the indentation's stresses add,
has a memory that decays (module docstring). Every stiffness of the skin scales with mu_nh, so S alone cannot split
the two: measured, the share that brings the full-rate change at g = 0.15, tau = 1 s closest to the timed replays'
on the demo campaign: 2.7-4.2 % RMS per channel at 0.6 (0.5: 2.8-4.6 %, 0.7: 4.0-6.0 %; with no share and no
contact scaling, `relaxation_response`, 20-22 %); the same share is best on a tiny campaign of 1.6 s pauses
(docs/analysis.md, issue 18)."""


@dataclass(frozen=True)
class Surrogate:
    """A stand-in for an effect's replays in its first linearisation while it is off in the model: `models(model)`,
    the models whose replays it needs (elastic: solved with the base's), and `shift(model, predictor, base)`, the
    change (`Shift`) of the prediction to `model` with the effect at given values, from those replays."""

    models: Callable[[TwinModel], list[TwinModel]]
    shift: Callable[[TwinModel, Predictor, Base], Shift]


def modulus_stepped(model: TwinModel) -> TwinModel:
    """`model` with its nominal skin modulus mu_nh times 1 + `MODULUS_STEP`: with `skin_modulus` off, the skin of that
    effect's column (its replays the same); a step of the nominal skin, which a `ModelFor` (which sets effects: a
    sensor's own skin modulus) keeps."""
    return replace(model, skin=replace(model.skin, mu_nh=model.skin.mu_nh * (1.0 + MODULUS_STEP)))


def relaxation_response(raw: Recording, slope: np.ndarray, time_s: float) -> np.ndarray:
    """(T, 4) the change per unit relaxing fraction g of a trajectory's full-rate prediction (tared force N, PDC
    counts) with relaxation time `time_s` (s), to first order in g (module docstring), from the elastic sensitivity
    `slope` (T, 4) = dPred/d(ln mu_nh) on the recording `raw`'s samples (NaN where the replays failed: NaN from the
    first pose change that reads one on). A pose change's memory acts on the indenter through the contact that is
    left of it: it is scaled by min(1, c(t) / c(t_k)), c the size of the force's sensitivity (the contact force's, the
    skin being homogeneous in mu_nh) at t and at the change's pose (0 at a pose out of contact): the skin can only
    push, so once the indenter has let go of it no memory reaches the readings."""
    times, indices = solve_events(raw, RELAXATION_SOLVE_INTERVAL_S)
    moved = np.r_[True, np.diff(indices) != 0]  # each pose's first event, where the indenter moves
    first_sample = np.r_[0, np.flatnonzero(np.diff(raw.increment)) + 1]
    sample_of = dict(zip(raw.increment[first_sample] + 1, first_sample, strict=True))  # path index -> first sample
    pose = np.array([sample_of[i] for i in indices])  # each event's pose, by its first sample
    at = pose[moved]
    before = np.where((at > 0)[:, None], slope[np.maximum(at - 1, 0)], 0.0)  # the inflated start: no change yet
    jumps = slope[at] - before
    ramps = np.diff(times, prepend=times[0])[moved]
    _, gamma = step_factors(np.ones(len(ramps)), np.full(len(ramps), time_s), ramps)
    age = times[:, None] - times[moved][None, :]
    after = age >= 0.0
    contact = np.nan_to_num(np.linalg.norm(slope[:, : len(FORCE_CHANNELS)], axis=1))
    left = np.divide(contact[pose][:, None], contact[at][None, :], out=np.zeros(age.shape), where=contact[at] > 0.0)
    weight = np.where(after, np.exp(-np.clip(age, 0.0, None) / time_s), 0.0) * gamma * np.minimum(left, 1.0)
    failed = np.isnan(jumps)
    memory = weight @ np.where(failed, 0.0, jumps)
    memory[(after.astype(float) @ failed.astype(float)) > 0] = np.nan
    event = np.clip(np.searchsorted(times, raw.time, side="right") - 1, 0, None)
    return (1.0 - PRESTRESS_SHARE) * memory[event] - slope


def _relaxation_shift(model: TwinModel, predictor: Predictor, base: Base) -> Shift:
    """The relaxation's `Shift` about `model` (its skin elastic) from the base's and `modulus_stepped`'s replays, on
    full-rate trajectories (a row-only file, low-passed, never has this candidate: `rows_only.RAW_ONLY_EFFECTS`)."""
    trajectories, model_for = base.trajectories, base.model_for
    elastic = fullrate_prediction(predictor, model, trajectories, model_for)
    stiffer = fullrate_prediction(predictor, modulus_stepped(model), trajectories, model_for)
    slopes = [(s - e) / np.log1p(MODULUS_STEP) for s, e in zip(stiffer, elastic, strict=True)]
    effect = EFFECTS[RELAXATION]

    def shift(changed: TwinModel) -> np.ndarray:
        values = effect.values(changed.effects.get(RELAXATION))
        responses = [relaxation_response(t.raw, s, values["time_s"]) for t, s in zip(trajectories, slopes, strict=True)]
        return base.shift_of([e + values["fraction"] * r for e, r in zip(elastic, responses, strict=True)])

    return shift


RELAXATION_SURROGATE = Surrogate(lambda model: [modulus_stepped(model)], _relaxation_shift)
"""`skin_relaxation`'s first linearisation from the skin modulus's elastic replays (module docstring). They are asked
for whether or not `skin_modulus` is a candidate: with it off and a candidate they are its column's; otherwise (not a
candidate, or on in the model) one elastic replay a trajectory more in the first batch, still no timed one."""
