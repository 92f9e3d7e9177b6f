"""Effects found in turn (issue 20, two effects at once): diagnose, add what the diagnosis names, refit every effect
jointly (`twin.analysis.refit.fit_jointly`), diagnose the improved model, until the residual reaches the noise or
nothing more can be added: what a user does by hand with `twin diagnose` and `twin improve`.

When two effects are missing, neither alone may bring the residual to the noise, and the diagnosis says
"unexplained" with its closest candidate (`Diagnosis.next_step`: the refitted one of least held-out RMS, when that
is below the base residual). Once in a search that candidate is added on trial: it is kept only if a later
diagnosis ends at the noise, which then rests on every effect the model carries holding out
(`twin.analysis.heldout.judge_model_effects`); otherwise the search ends "unexplained" and the model returned is the
last one reached by named effects alone.
"""

from __future__ import annotations

import json
from collections.abc import Callable
from dataclasses import dataclass

from twin.analysis.diagnose import Diagnosis, strict_json
from twin.analysis.predict import TwinModel
from twin.analysis.refit import EffectFit
from twin.analysis.verdict import NOTHING_BEYOND_NUISANCES
from twin.effects import EFFECTS

AT_THE_NOISE = ("nothing", NOTHING_BEYOND_NUISANCES)
"""Diagnosis verdicts that end a search: the residual of the model as it stands is noise."""


@dataclass
class Turn:
    """One diagnosis of the search and what was added after it (None: the search ended there): "named" (the
    diagnosis's verdict) or "closest" (its closest candidate, on trial), with the joint refit that added it."""

    diagnosis: Diagnosis
    added: str | None = None
    via: str = ""
    fit: EffectFit | None = None

    def to_dict(self) -> dict:
        """JSON-ready form: the diagnosis (`Diagnosis.to_dict`), what was added and the fit's figures."""
        fit = None
        if self.fit is not None:
            fit = {
                "values": self.fit.values,
                "rms_before": self.fit.rms_before,
                "rms_after": self.fit.rms_after,
                "heldout_rms": self.fit.heldout_rms,
                "heldout_is_noise": self.fit.heldout_is_noise,
                "at_bound": self.fit.at_bound,
            }
        return {"diagnosis": self.diagnosis.to_dict(), "added": self.added, "via": self.via or None, "fit": fit}


@dataclass
class InTurn:
    """The search's outcome: its turns, a verdict (the effects added in turn joined by " + " when the residual
    reached the noise with them; else the last diagnosis's verdict), why, and the model it leaves (the effects
    kept, refitted)."""

    turns: list[Turn]
    verdict: str
    reason: str
    model: TwinModel

    @property
    def added(self) -> list[str]:
        """The effects added, in turn."""
        return [t.added for t in self.turns if t.added is not None]

    def to_dict(self) -> dict:
        """JSON-ready form (the `twin diagnose --in-turn N --json` shape)."""
        return {
            "verdict": self.verdict,
            "reason": self.reason,
            "added": self.added,
            "model": self.model.to_dict(),
            "turns": [t.to_dict() for t in self.turns],
        }

    def to_json(self) -> str:
        """Strict JSON text of `to_dict` (a NaN or infinite number becomes null)."""
        return json.dumps(strict_json(self.to_dict()), allow_nan=False)


def find_in_turn(
    diagnose_model: Callable[[TwinModel], Diagnosis],
    improve: Callable[[TwinModel, str], EffectFit],
    model: TwinModel,
    additions: int = 2,
) -> InTurn:
    """Diagnose `model` (`diagnose_model`), add what the diagnosis names (`improve(model, effect)`: the effect fitted
    and every effect refitted with it, `fit_jointly`), diagnose again, at most `additions` times; an "unexplained"
    verdict's closest candidate is added once, on trial (see the module docstring)."""
    if additions < 1:
        raise ValueError(f"a search in turn adds at least one effect, got additions={additions}")
    turns: list[Turn] = []
    current = kept = model
    trial: str | None = None  # the closest candidate added on trial, if any
    while True:
        diagnosis = diagnose_model(current)
        turn = Turn(diagnosis)
        turns.append(turn)
        added = [t.added for t in turns[:-1]]
        if diagnosis.verdict in AT_THE_NOISE:
            if not added:
                return InTurn(turns, diagnosis.verdict, diagnosis.reason, current)
            steps = ", then ".join(f"{t.added} ({t.via})" for t in turns[:-1])
            reason = f"added in turn: {steps}; with them the residual is noise ({diagnosis.reason})"
            return InTurn(turns, " + ".join(added), reason, current)
        if len(added) < additions:
            if diagnosis.verdict in EFFECTS:
                turn.added, turn.via = diagnosis.verdict, "named"
            elif trial is None and (closest := diagnosis.next_step()) is not None:
                turn.added, turn.via = closest.name, "closest"
        if turn.added is None:
            if trial is not None:  # never named: the trial failed
                reason = (
                    f"{trial}, added on trial as the closest candidate, is not kept: nothing after it brought the "
                    f"residual to the noise (last diagnosis: {diagnosis.verdict}, {diagnosis.reason})"
                )
                return InTurn(turns, "unexplained", reason, kept)
            reason = diagnosis.reason
            if diagnosis.verdict in EFFECTS:
                reason += f"; not added: {additions} effect(s) added already (the search's limit)"
            return InTurn(turns, diagnosis.verdict, reason, kept)
        turn.fit = improve(current, turn.added)
        current = turn.fit.model
        if turn.via == "closest":
            trial = turn.added
        elif trial is None:
            kept = current
