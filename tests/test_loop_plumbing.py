"""The loop's plumbing (issue 24): refits never end above their start, strict JSON from `twin diagnose
--json`, the refit count as an option with progress per candidate, the history kept beside the data.

No fe work here: the residual and the model's response are stand-ins with known answers.
"""

import json
from dataclasses import replace
from pathlib import Path

import numpy as np
import pytest
from typer.testing import CliRunner

import twin.analysis.diagnose as diagnose_module
import twin.analysis.refit as refit_module
import twin.cli.loop as cli_loop
from twin.analysis.diagnose import Diagnosis
from twin.analysis.history import read_history
from twin.analysis.predict import Predictor, TwinModel
from twin.analysis.refit import EffectFit, refit
from twin.analysis.sensitivity import Linearisation, sensitivity, start_models
from twin.analysis.verdict import Candidate
from twin.cli import app
from twin.cli.common import out_console
from twin.cli.loop import LARGE_CAMPAIGN, large_campaign_hint
from twin.effects import EFFECTS

runner = CliRunner()


class _StepResponse:
    """A null data set (the residual is pure noise) and a delay whose effect comes in whole samples: any
    delay above zero moves the prediction by a fixed pattern, so no delay beats the model as it is."""

    def __init__(self, n: int = 400) -> None:
        rng = np.random.default_rng(1)
        self.residual = type("R", (), {"values": rng.standard_normal(n)})()
        self.pattern = 3.0 * np.sign(np.sin(np.arange(n)))

    def prefetch(self, predictor: object, models: list[TwinModel]) -> int:
        return 0  # no replays to solve: `shifted` is analytic

    def shifted(self, predictor: object, model: TwinModel) -> np.ndarray:
        seconds = model.effects.get("time_delay", {}).get("seconds", 0.0)
        return self.pattern if seconds > 0.0 else np.zeros_like(self.pattern)


def test_a_refit_never_ends_above_its_starting_point() -> None:
    base = _StepResponse()
    noise = base.residual.values
    # The linearisation points along the noise itself, so its step goes to a delay of 0.1 s that fits worse.
    lin = Linearisation({"seconds": 0.0}, np.zeros_like(noise), 10.0 * noise[:, None])
    candidate = Candidate("time_delay", "measurement", {}, 0.0, 0.0, 0.0)
    refit(candidate, TwinModel(), None, base, lin)
    start_rms = float(np.sqrt(np.mean(noise**2)))
    assert candidate.refit_rms <= start_rms + 1e-12
    assert candidate.refit_parameters == {"seconds": 0.0}


def _raise_on_constant(name: str) -> None:
    raise ValueError(f"not strict JSON: {name}")


def _diagnosis_with_nan() -> Diagnosis:
    candidate = Candidate("time_delay", "measurement", {"seconds": 0.05}, 12.0, 5.0, 0.5, heldout_rms=float("nan"))
    return Diagnosis(float("nan"), {"corr": float("inf")}, [candidate], "unexplained", "no fit")


def test_diagnosis_json_is_strict_with_nan_as_null() -> None:
    text = _diagnosis_with_nan().to_json()
    parsed = json.loads(text, parse_constant=_raise_on_constant)
    assert parsed["base_rms_over_noise"] is None
    assert parsed["signatures"]["corr"] is None
    assert parsed["candidates"][0]["condition"] is None  # never computed: NaN in the dataclass
    assert parsed["candidates"][0]["chi2_drop"] == 12.0


@pytest.fixture
def fake_inputs(monkeypatch: pytest.MonkeyPatch, tmp_path: Path) -> Path:
    """A dataset path and `_inputs` returning no data and the nominal model (no file is read)."""
    dataset = tmp_path / "data" / "biotac2.hdf5"
    dataset.parent.mkdir()
    dataset.write_bytes(b"")
    monkeypatch.setattr(cli_loop, "_inputs", lambda datasets, model: ([], TwinModel()))
    return dataset


def test_diagnose_json_strict_refit_count_and_progress_per_candidate(
    fake_inputs: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    calls: dict = {}

    def fake_diagnose(
        data,
        model,
        predictor=None,
        top=3,
        on_progress=None,
        nuisances=False,
        rank_per_stratum=None,
        per_stratum=None,
        rank_mesh=None,
    ):
        calls["top"], calls["rank_per_stratum"] = top, rank_per_stratum
        calls["rank_mesh"] = rank_mesh
        calls["per_stratum"] = per_stratum
        for name in ("skin_modulus", "time_delay", "ft_gain"):
            on_progress("evidence", name)
        for name in ("skin_modulus", "time_delay")[:top]:
            on_progress("refit", name)
            calls.setdefault("refits", []).append(name)
        return _diagnosis_with_nan()

    monkeypatch.setattr(diagnose_module, "diagnose", fake_diagnose)
    result = runner.invoke(app, ["diagnose", str(fake_inputs), "--json", "--refit-top", "1"])
    assert result.exit_code == 0, result.output
    assert calls == {
        "top": 1,
        "rank_per_stratum": None,
        "per_stratum": None,
        "rank_mesh": None,
        "refits": ["skin_modulus"],
    }
    parsed = json.loads(result.stdout, parse_constant=_raise_on_constant)
    assert parsed["verdict"] == "unexplained" and parsed["ranked_on"] is None and parsed["sampled"] is None
    bad = runner.invoke(app, ["diagnose", str(fake_inputs), "--refit-top", "-1"])
    assert bad.exit_code == 2 and "Traceback" not in bad.output
    subset = runner.invoke(app, ["diagnose", str(fake_inputs), "--json", "--rank-per-stratum", "2"])
    assert subset.exit_code == 0 and calls["rank_per_stratum"] == 2, subset.output
    bad = runner.invoke(app, ["diagnose", str(fake_inputs), "--rank-per-stratum", "0"])
    assert bad.exit_code == 2 and "Traceback" not in bad.output
    sample = runner.invoke(app, ["diagnose", str(fake_inputs), "--json", "--per-stratum", "3"])
    assert sample.exit_code == 0 and calls["per_stratum"] == 3, sample.output
    bad = runner.invoke(app, ["diagnose", str(fake_inputs), "--per-stratum", "0"])
    assert bad.exit_code == 2 and "Traceback" not in bad.output
    coarse = runner.invoke(app, ["diagnose", str(fake_inputs), "--json", "--rank-mesh-mm", "1.5"])
    assert coarse.exit_code == 0 and calls["rank_mesh"] == pytest.approx(1.5e-3), coarse.output
    bad = runner.invoke(app, ["diagnose", str(fake_inputs), "--rank-mesh-mm", "0"])
    assert bad.exit_code == 2 and "Traceback" not in bad.output


def test_improve_keeps_the_history_beside_the_dataset_or_the_model(
    fake_inputs: Path, monkeypatch: pytest.MonkeyPatch, tmp_path: Path
) -> None:
    fitted = TwinModel().with_effects({"time_delay": {"seconds": 0.05}})
    fit = EffectFit("time_delay", {"seconds": 0.05}, 2.0, 1.0, 1.0, fitted)
    monkeypatch.setattr(refit_module, "fit_effect", lambda data, model, name, predictor=None: fit)
    elsewhere = tmp_path / "elsewhere"
    elsewhere.mkdir()
    monkeypatch.chdir(elsewhere)
    result = runner.invoke(app, ["improve", str(fake_inputs), "--add", "time_delay"], env={"COLUMNS": "300"})
    assert result.exit_code == 0, result.output
    beside = fake_inputs.parent / "twin-history.jsonl"
    assert [e["added"]["effect"] for e in read_history(beside)] == ["time_delay"]
    assert not (elsewhere / "twin-history.jsonl").exists()
    assert str(beside) in result.output.replace("\n", "")
    shown = runner.invoke(app, ["history", str(fake_inputs), "--json"])
    assert shown.exit_code == 0 and json.loads(shown.stdout)[0]["added"]["effect"] == "time_delay"

    model_file = tmp_path / "models" / "m.json"
    model_file.parent.mkdir()
    model_file.write_text(json.dumps(TwinModel().to_dict()))
    result = runner.invoke(app, ["improve", str(fake_inputs), "--add", "time_delay", "--model", str(model_file)])
    assert result.exit_code == 0, result.output
    assert len(read_history(model_file.parent / "twin-history.jsonl")) == 1


def test_improve_reports_the_held_out_tests_power_in_its_table_and_json(
    fake_inputs: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    """As diagnose does: the RMS the held-out test allows, and the base residual on the same left-out samples
    with whether it fails that test (the power rule); the existing keys keep their names."""
    fitted = TwinModel().with_effects({"time_delay": {"seconds": 0.05}})
    fit = EffectFit("time_delay", {"seconds": 0.05}, 2.0, 1.0, 1.01, fitted, True, [], 1.027, 1.02, False)
    monkeypatch.setattr(refit_module, "fit_effect", lambda data, model, name, predictor=None: fit)
    monkeypatch.setattr(out_console, "_width", 300)  # whatever COLUMNS was when the console was made
    shown = runner.invoke(app, ["improve", str(fake_inputs), "--add", "time_delay"])
    assert shown.exit_code == 0, shown.output
    assert "1.027" in shown.stdout and "1.02 (passes it too: the test has no power)" in shown.stdout
    result = runner.invoke(app, ["improve", str(fake_inputs), "--add", "time_delay", "--json"])
    assert result.exit_code == 0, result.output
    entry = json.loads(result.stdout, parse_constant=_raise_on_constant)
    assert entry["heldout_base_rms"] == 1.02 and entry["heldout_has_power"] is False
    assert entry["heldout_rms_threshold"] == 1.027
    assert {"rms_before", "rms_after", "heldout_rms", "heldout_is_noise", "at_bound", "added"} <= set(entry)
    assert read_history(fake_inputs.parent / "twin-history.jsonl")[-1]["heldout_has_power"] is False


class _NarrowBasin:
    """A delay whose signature appears only near its true size: the prediction moves by a fixed pattern
    weighted by a bump around 0.25 s (flat at zero delay), and the data hold that pattern plus noise."""

    def __init__(self, n: int = 400) -> None:
        rng = np.random.default_rng(2)
        self.pattern = 5.0 * np.sin(np.arange(n) / 7.0)
        noise = rng.standard_normal(n)
        self.residual = type("R", (), {"values": self.pattern + noise})()
        self.nuisance = type("N", (), {"chi2": staticmethod(lambda v: float(np.nansum(v**2)))})()

    def prefetch(self, predictor: object, models: list[TwinModel]) -> int:
        return 0  # no replays to solve: `shifted` is analytic

    def shifted(self, predictor: object, model: TwinModel) -> np.ndarray:
        seconds = model.effects.get("time_delay", {}).get("seconds", 0.0)
        return self.pattern * np.exp(-(((seconds - 0.25) / 0.05) ** 2))


def test_an_effect_far_from_its_off_value_is_found_from_its_starts() -> None:
    """Linearised at zero delay, the bump is flat and explains nothing; the start at 0.25 s finds it, and
    the refit from there reaches the noise."""
    base = _NarrowBasin()
    effect = EFFECTS["time_delay"]
    lin = sensitivity(effect, TwinModel(), Predictor(), base)  # replays: the stand-in's
    assert lin.point["seconds"] == pytest.approx(0.25)
    candidate = Candidate("time_delay", "measurement", {}, 0.0, 0.0, 0.0)
    refit(candidate, TwinModel(), None, base, lin)
    assert candidate.refit_parameters["seconds"] == pytest.approx(0.25, abs=0.01)
    assert candidate.refit_rms < 1.1


def test_an_unexplained_verdict_points_to_its_closest_candidate_only_when_it_explains_part_held_out() -> None:
    """Two effects missing: the refitted candidate of least held-out residual (the reason's first "closest"), when
    it lowers the held-out residual below the base's, is the user's next step (`twin diagnose` prints it); not when
    it does not, nor on any other verdict."""
    helps = Candidate("registration_offset", "physics", {}, 900.0, 800.0, 0.8, heldout_rms=2.95, refit_rms=2.92)
    unrefitted = Candidate("ft_gain", "measurement", {}, 950.0, 850.0, 0.85, heldout_rms=1.5)
    ranked_first = Candidate("skin_thickness", "physics", {}, 990.0, 870.0, 0.9, heldout_rms=4.1, refit_rms=1.2)
    unexplained = Diagnosis(7.84, {}, [unrefitted, ranked_first, helps], "unexplained", "no refitted candidate ...")
    assert unexplained.next_step() is helps
    worse = replace(helps, heldout_rms=8.0)
    assert replace(unexplained, candidates=[worse]).next_step() is None
    assert replace(unexplained, verdict="registration_offset").next_step() is None


def test_a_large_campaign_diagnosed_whole_gets_a_one_line_hint_to_sample_it() -> None:
    """Above `LARGE_CAMPAIGN` trajectories without `--per-stratum`: how to take a sample (and a coarser ranking mesh
    for a mesh under 1 mm); nothing for a small or already sampled campaign."""
    paper = TwinModel(mesh_max_edge=0.5e-3)
    hint = large_campaign_hint(905, paper, None, None)
    assert "905 trajectories" in hint and "--per-stratum 1" in hint and "--rank-mesh-mm 1" in hint
    assert "--rank-mesh-mm" not in large_campaign_hint(905, TwinModel(mesh_max_edge=2e-3), None, None)
    assert "--rank-mesh-mm" not in large_campaign_hint(905, paper, None, 1.0)
    assert large_campaign_hint(LARGE_CAMPAIGN, paper, None, None) == ""
    assert large_campaign_hint(905, paper, 1, None) == ""


def test_the_declared_starts_are_known_before_any_residual_and_tried_only_for_effects_off_in_the_model() -> None:
    """`start_models`: the models of each off effect's declared starts (solved with the first batch of a diagnosis),
    the very models `sensitivities` tries among its starts; none for an effect the model already carries."""
    model = TwinModel()
    registration, delay, thickness = (EFFECTS[n] for n in ("registration_offset", "time_delay", "skin_thickness"))
    models = start_models([registration, delay, thickness], model)
    assert len(models) == len(registration.starts) + len(delay.starts) and not thickness.starts
    offsets = {tuple(m.effects["registration_offset"].values()) for m in models if "registration_offset" in m.effects}
    assert len(offsets) == len(registration.starts), "each start its own model"
    on = model.with_effects({"registration_offset": {"dx": 1e-4, "dy": 0.0, "dz": 0.0}})
    assert start_models([registration], on) == []


def test_diagnose_says_when_the_models_replays_reached_part_of_the_samples(
    fake_inputs: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    """A replay stops at an fe increment that does not converge: the table output says how many samples the residual
    covers (and says nothing when it covers them all); the JSON carries them as `samples`."""
    covered = {"reached": 1605, "of": 3933}

    def fake_diagnose(data, model, predictor=None, top=3, on_progress=None, **_):
        return replace(_diagnosis_with_nan(), samples=covered)

    monkeypatch.setattr(diagnose_module, "diagnose", fake_diagnose)
    shown = runner.invoke(app, ["diagnose", str(fake_inputs)], env={"COLUMNS": "400"})
    assert shown.exit_code == 0, shown.output
    assert "reached 1605 of the data's 3933 samples" in shown.output
    parsed = json.loads(runner.invoke(app, ["diagnose", str(fake_inputs), "--json"]).stdout)
    assert parsed["samples"] == covered
    covered = {"reached": 3933, "of": 3933}
    assert "samples" not in runner.invoke(app, ["diagnose", str(fake_inputs)], env={"COLUMNS": "400"}).output
