"""Effects found in turn (`twin.analysis.in_turn`, `twin diagnose --in-turn`, issue 20): what is named is added and
kept; an unexplained verdict's closest candidate is added once, on trial, and kept only when a later diagnosis ends at
the noise; the search stops at its limit. The diagnoses and fits are stand-ins: a scripted sequence of verdicts."""

import json
from pathlib import Path

import pytest
from typer.testing import CliRunner

import twin.analysis.diagnose as diagnose_module
import twin.analysis.refit as refit_module
import twin.cli.loop as cli_loop
from twin.analysis.diagnose import Diagnosis
from twin.analysis.in_turn import find_in_turn
from twin.analysis.predict import TwinModel
from twin.analysis.refit import EffectFit
from twin.analysis.verdict import Candidate
from twin.cli import app


def _diagnosis(verdict: str, base_rms: float, closest: tuple[str, float] | None = None) -> Diagnosis:
    """A diagnosis with `verdict`; with `closest` (name, held-out RMS) one refitted candidate of that figure."""
    candidates = []
    if closest is not None:
        name, heldout = closest
        candidates.append(Candidate(name, "physics", {}, 1.0, 1.0, 0.5, heldout_rms=heldout, refit_rms=heldout))
    return Diagnosis(base_rms, {}, candidates, verdict, f"scripted {verdict}")


class _Script:
    """Diagnoses answered by the effects the model carries (a tuple of names -> Diagnosis); fits add the effect."""

    def __init__(self, answers: dict[tuple[str, ...], Diagnosis]) -> None:
        self.answers, self.diagnosed, self.added = answers, [], []

    def diagnose(self, model: TwinModel) -> Diagnosis:
        carried = tuple(sorted(model.effects))
        self.diagnosed.append(carried)
        return self.answers[carried]

    def improve(self, model: TwinModel, name: str) -> EffectFit:
        self.added.append(name)
        improved = model.with_effects({name: {}})  # at its off values: only the names matter here
        return EffectFit(name, {}, 5.0, 2.0, 2.1, improved, heldout_is_noise=False)


def test_two_named_effects_are_added_in_turn_until_the_residual_is_noise() -> None:
    script = _Script(
        {
            (): _diagnosis("skin_thickness", 8.0),
            ("skin_thickness",): _diagnosis("time_delay", 3.0),
            ("skin_thickness", "time_delay"): _diagnosis("nothing", 1.0),
        }
    )
    found = find_in_turn(script.diagnose, script.improve, TwinModel(), additions=2)
    assert found.verdict == "skin_thickness + time_delay" and found.added == ["skin_thickness", "time_delay"]
    assert sorted(found.model.effects) == ["skin_thickness", "time_delay"]
    assert len(script.diagnosed) == 3 and "with them the residual is noise" in found.reason


def test_a_closest_candidate_is_kept_only_when_a_later_diagnosis_ends_at_the_noise() -> None:
    closest = ("registration_offset", 4.0)  # below the base residual (9.0): it explains part held out
    confirmed = _Script(
        {
            (): _diagnosis("unexplained", 9.0, closest),
            ("registration_offset",): _diagnosis("time_delay", 3.5),
            ("registration_offset", "time_delay"): _diagnosis("nothing", 1.0),
        }
    )
    found = find_in_turn(confirmed.diagnose, confirmed.improve, TwinModel())
    assert found.verdict == "registration_offset + time_delay"
    assert [t.via for t in found.turns[:2]] == ["closest", "named"]
    refuted = _Script(
        {
            (): _diagnosis("unexplained", 9.0, closest),
            ("registration_offset",): _diagnosis("unexplained", 3.5, ("ft_gain", 3.0)),  # no second trial
        }
    )
    found = find_in_turn(refuted.diagnose, refuted.improve, TwinModel())
    assert found.verdict == "unexplained" and found.model.effects == {}  # the trial is not kept
    assert refuted.added == ["registration_offset"] and "is not kept" in found.reason


def test_a_search_stops_at_its_limit_and_when_nothing_explains_part() -> None:
    limited = _Script({(): _diagnosis("skin_thickness", 8.0), ("skin_thickness",): _diagnosis("time_delay", 3.0)})
    found = find_in_turn(limited.diagnose, limited.improve, TwinModel(), additions=1)
    assert found.verdict == "time_delay" and sorted(found.model.effects) == ["skin_thickness"]
    assert "the search's limit" in found.reason and limited.added == ["skin_thickness"]
    hopeless = _Script({(): _diagnosis("unexplained", 9.0, ("ft_gain", 9.5))})  # held out above the base: no step
    found = find_in_turn(hopeless.diagnose, hopeless.improve, TwinModel())
    assert found.verdict == "unexplained" and hopeless.added == [] and len(found.turns) == 1
    with pytest.raises(ValueError, match="at least one"):
        find_in_turn(hopeless.diagnose, hopeless.improve, TwinModel(), additions=0)


def test_twin_diagnose_in_turn_prints_each_turn_and_its_json(monkeypatch: pytest.MonkeyPatch, tmp_path: Path) -> None:
    dataset = tmp_path / "biotac2.hdf5"
    dataset.write_bytes(b"")
    monkeypatch.setattr(cli_loop, "_inputs", lambda datasets, model: ([], TwinModel()))
    script = _Script({(): _diagnosis("skin_thickness", 8.0), ("skin_thickness",): _diagnosis("nothing", 1.0)})
    monkeypatch.setattr(diagnose_module, "diagnose", lambda data, model, *args, **kwargs: script.diagnose(model))
    monkeypatch.setattr(refit_module, "fit_jointly", lambda data, model, name, predictor: script.improve(model, name))
    runner = CliRunner()
    result = runner.invoke(app, ["diagnose", str(dataset), "--in-turn", "2", "--json"])
    assert result.exit_code == 0, result.output
    parsed = json.loads(result.stdout)
    assert parsed["verdict"] == "skin_thickness" and parsed["added"] == ["skin_thickness"]
    assert [t["via"] for t in parsed["turns"]] == ["named", None] and parsed["turns"][0]["fit"]["rms_after"] == 2.0
    assert "skin_thickness" in parsed["model"]["effects"]
    table = runner.invoke(app, ["diagnose", str(dataset), "--in-turn", "2"])
    assert table.exit_code == 0 and "turn 1: residual 8.00 x noise, verdict skin_thickness" in table.stdout
    bad = runner.invoke(app, ["diagnose", str(dataset), "--in-turn", "-1"])
    assert bad.exit_code == 2 and "Traceback" not in bad.output
