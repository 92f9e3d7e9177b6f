"""The loop on plants with hidden effects: every library effect is found and fixed; nothing is claimed
when nothing is hidden; an effect outside the library comes out "unexplained".

Each case hides one effect, drawn with its size from a seed inside `twin.hidden`, in a plant; the
diagnosis sees only the campaign file. The seed can be changed with BIOTAC_TWIN_HIDDEN_SEED to draw
other sizes, trajectory points and noise. Measurement effects the library's draws never produce (an F/T gain
on z only, a range clipping the axis that moves most, a quantised reading, a PDC drift) are applied to the null
campaign's raw streams by `effect_generator`, code separate from the plant and the analysis. The fe replays of
the nominal model and its finite-difference neighbours are shared between cases (same paths), so each case pays
for its campaign and its refits.
"""

import json
import os
from pathlib import Path

import h5py
import numpy as np
import pytest
from effect_generator import apply_ft_clip, apply_ft_drift, apply_ft_map, apply_ft_quantise, apply_pdc_map
from measurement import strip_plant_view

from twin.analysis.compare import noise_estimate
from twin.analysis.data import load_campaign
from twin.analysis.diagnose import diagnose
from twin.analysis.heldout import NOISE_TOLERANCE
from twin.analysis.predict import Predictor, TwinModel
from twin.analysis.refit import fit_effect, fit_jointly
from twin.demo import CHECK_CONFIG, LoopResult, run_loop
from twin.effects import COMPLIANCE, EFFECTS, UNLISTED_EFFECTS
from twin.hidden import draw_hidden

CONFIG = CHECK_CONFIG
SEED = int(os.environ.get("BIOTAC_TWIN_HIDDEN_SEED", "5"))


@pytest.fixture(scope="module")
def predictor() -> Predictor:
    return Predictor()


def _loop(tmp_path: Path, hidden: str | None, predictor: Predictor) -> LoopResult:
    return run_loop(
        tmp_path, hidden, SEED, CONFIG, workers=2, reports=False, say=lambda _: None, predictor=predictor, top=1
    )


CONFOUNDED: dict[str, str] = {}
"""Library effects this small campaign does not find (measured; seen in benchmarks/diagnose_bench.py): their
cases run every time and report as expected failures with the reason; a fix shows as XPASS. None at present:
seed 5's skin_relaxation, listed until session 17 (ft_calibration ranked first and was the only one refitted),
passes with session 17's changes (XPASS on the whole file at 52d8581, 2026-11-27; docs/analysis.md)."""


SIZED: dict[str, float] = {COMPLIANCE: 0.2}
"""Library effects whose fitted values their case checks against the hidden ones, with the relative tolerance."""


@pytest.mark.parametrize(
    "hidden",
    [
        pytest.param(e, marks=pytest.mark.xfail(reason=CONFOUNDED[e], strict=False)) if e in CONFOUNDED else e
        for e in sorted(EFFECTS)
    ],
)
def test_a_hidden_library_effect_ranks_first_and_adding_it_brings_the_error_to_the_noise(
    hidden: str, tmp_path: Path, predictor: Predictor
) -> None:
    result = _loop(tmp_path, hidden, predictor)
    diagnosis = result.diagnosis
    ranking = [(c.name, round(c.evidence, 1)) for c in diagnosis.candidates[:4]]
    shows = diagnosis.rms_threshold  # the noise test's threshold on these data
    assert diagnosis.base_rms > shows, f"the hidden {hidden} must show in the residual: {diagnosis.reason}"
    assert diagnosis.candidates[0].name == hidden, (ranking, diagnosis.reason)
    assert diagnosis.verdict in (hidden, "ambiguous"), diagnosis.reason
    assert result.fit is not None and result.fit.name == hidden
    assert result.fit.rms_after <= NOISE_TOLERANCE and result.fit.rms_before > shows, result.fit
    assert result.fit.heldout_rms is not None and result.fit.heldout_rms <= NOISE_TOLERANCE, result.fit
    if hidden in SIZED:
        assert result.fit.values == pytest.approx(draw_hidden(hidden, SEED)[hidden], rel=SIZED[hidden])


@pytest.fixture(scope="module")
def null_loop(tmp_path_factory: pytest.TempPathFactory, predictor: Predictor) -> LoopResult:
    return _loop(tmp_path_factory.mktemp("null"), None, predictor)


def test_with_nothing_hidden_nothing_is_claimed(null_loop: LoopResult) -> None:
    assert null_loop.diagnosis.verdict == "nothing", null_loop.diagnosis.reason
    assert null_loop.fit is None
    with h5py.File(null_loop.dataset, "r") as f:
        provenance = json.loads(f.attrs["provenance"])
    assert provenance["config"]["seed"] == SEED, "points and noise must come from the seed"
    assert "registration_error_m" not in provenance, "the registration error is the plant's truth"


def test_the_verdict_is_the_same_without_the_plants_fe_view(
    null_loop: LoopResult, predictor: Predictor, tmp_path: Path
) -> None:
    data = load_campaign(strip_plant_view(null_loop.dataset, tmp_path / "measured.hdf5"))
    model = TwinModel(mesh_max_edge=data.mesh_max_edge)
    again = diagnose([data], model, predictor, top=1)
    assert again.verdict == null_loop.diagnosis.verdict
    assert again.base_rms == pytest.approx(null_loop.diagnosis.base_rms, rel=1e-12)


def test_a_refit_on_a_null_never_ends_above_the_nominal_model(null_loop: LoopResult, predictor: Predictor) -> None:
    data = load_campaign(null_loop.dataset)
    fit = fit_effect([data], TwinModel(mesh_max_edge=data.mesh_max_edge), "time_delay", predictor)
    assert fit.rms_after <= fit.rms_before


@pytest.mark.parametrize("hidden", sorted(UNLISTED_EFFECTS))
def test_an_effect_outside_the_library_is_unexplained(hidden: str, tmp_path: Path, predictor: Predictor) -> None:
    result = _loop(tmp_path, hidden, predictor)
    assert result.diagnosis.base_rms > NOISE_TOLERANCE, "the unlisted effect must show in the residual"
    assert result.diagnosis.verdict == "unexplained", result.diagnosis.reason
    assert result.fit is None


@pytest.fixture(scope="module")
def z_gain_file(null_loop: LoopResult, tmp_path_factory: pytest.TempPathFactory) -> Path:
    """The null campaign with an F/T gain of 0.88 on z only, applied to the raw streams by independent code."""
    return apply_ft_map(null_loop.dataset, tmp_path_factory.mktemp("zgain") / "zgain.hdf5", np.diag([1.0, 1.0, 0.88]))


def test_a_z_only_ft_gain_is_named_as_the_calibration_map(z_gain_file: Path, predictor: Predictor) -> None:
    data = load_campaign(z_gain_file)
    diagnosis = diagnose([data], TwinModel(mesh_max_edge=data.mesh_max_edge), predictor, top=1)
    best = diagnosis.candidates[0]
    assert diagnosis.verdict == "ft_calibration", diagnosis.reason
    assert best.refit_parameters["zz"] == pytest.approx(0.88, abs=0.01)
    assert best.refit_parameters["xx"] == pytest.approx(1.0, abs=0.03)
    assert best.heldout_is_noise and best.heldout_rms <= best.heldout_rms_threshold
    assert diagnosis.rms_threshold < diagnosis.base_rms


def test_a_fit_that_does_not_generalise_is_not_named(z_gain_file: Path, predictor: Predictor) -> None:
    """The issue's case: without the map, crosstalk and a common gain fit part of a z-only gain in sample,
    but neither predicts left-out indenters to the noise: "unexplained", with their held-out figures."""
    data = load_campaign(z_gain_file)
    model = TwinModel(mesh_max_edge=data.mesh_max_edge)
    diagnosis = diagnose([data], model, predictor, candidates=["ft_crosstalk", "ft_gain"], top=2)
    assert diagnosis.verdict == "unexplained", diagnosis.reason
    assert all(c.refitted and not c.heldout_is_noise for c in diagnosis.candidates)
    assert all(f"{c.name} (held out {c.heldout_rms:.2f}x" in diagnosis.reason for c in diagnosis.candidates)


def _raw_force(dataset: Path) -> np.ndarray:
    """(T, 3) every raw F/T force reading of a campaign file (N, sensor frame, untared)."""
    with h5py.File(dataset, "r") as f:
        return np.concatenate([f[f"raw/{k}/wrench"][()][:, :3] for k in f["raw"]])


def test_a_clipped_ft_range_is_named_with_its_limit(
    null_loop: LoopResult, predictor: Predictor, tmp_path: Path
) -> None:
    """The axis whose reading moves most is clipped halfway between its rest and its peak magnitude."""
    readings = _raw_force(null_loop.dataset)
    rest, peak = np.abs(readings[0]), np.abs(readings).max(axis=0)
    axis = int(np.argmax(peak - rest))
    limits = np.full(3, 1e3)
    limits[axis] = 0.5 * (rest[axis] + peak[axis])
    data = load_campaign(apply_ft_clip(null_loop.dataset, tmp_path / "clipped.hdf5", limits))
    diagnosis = diagnose([data], TwinModel(mesh_max_edge=data.mesh_max_edge), predictor, top=1)
    best = diagnosis.candidates[0]
    assert diagnosis.verdict == "ft_saturation", diagnosis.reason
    assert best.refit_parameters["f" + "xyz"[axis]] == pytest.approx(limits[axis], abs=0.01)  # the F/T noise
    assert best.heldout_is_noise and best.heldout_rms <= best.heldout_rms_threshold


def test_a_quantised_null_is_nothing_and_its_noise_counts_the_rounding(
    null_loop: LoopResult, predictor: Predictor, tmp_path: Path
) -> None:
    """A 30 mN resolution, three times the F/T noise: no effect is claimed on it."""
    step = 0.03
    data = load_campaign(apply_ft_quantise(null_loop.dataset, tmp_path / "quantised.hdf5", step))
    noise = noise_estimate(data.trajectories)
    assert min(noise[c] for c in ("force_x", "force_y", "force_z")) >= step / np.sqrt(12.0)
    diagnosis = diagnose([data], TwinModel(mesh_max_edge=data.mesh_max_edge), predictor, top=1)
    assert diagnosis.verdict == "nothing", diagnosis.reason


def test_a_pdc_drift_is_named_with_its_rate(null_loop: LoopResult, predictor: Predictor, tmp_path: Path) -> None:
    data = load_campaign(apply_pdc_map(null_loop.dataset, tmp_path / "pdc.hdf5", 1.0, -0.3))
    diagnosis = diagnose([data], TwinModel(mesh_max_edge=data.mesh_max_edge), predictor, top=1)
    assert diagnosis.verdict == "pdc_drift", diagnosis.reason
    assert diagnosis.candidates[0].refit_parameters["rate"] == pytest.approx(-0.3, abs=0.03)


def test_two_generated_effects_are_found_in_turn(null_loop: LoopResult, predictor: Predictor, tmp_path: Path) -> None:
    """An F/T gain of 0.88 on z and a PDC drift of 0.3 counts/s, applied by the independent generator: neither
    alone brings the held-out residual to the noise, so the first diagnosis is "unexplained" with the F/T map
    closest; added (`fit_effect`, as `twin improve` does), the next diagnosis names the drift, and with both the
    residual is noise."""
    gained = apply_ft_map(null_loop.dataset, tmp_path / "gain.hdf5", np.diag([1.0, 1.0, 0.88]))
    data = load_campaign(apply_pdc_map(gained, tmp_path / "both.hdf5", 1.0, 0.3))
    model = TwinModel(mesh_max_edge=data.mesh_max_edge)
    first = diagnose([data], model, predictor, top=1)
    assert first.verdict == "unexplained" and first.candidates[0].name == "ft_calibration", first.reason
    gain = fit_effect([data], model, "ft_calibration", predictor)
    assert gain.values["zz"] == pytest.approx(0.88, abs=0.01)
    second = diagnose([data], gain.model, predictor, top=1)
    assert second.verdict == "pdc_drift", second.reason
    drift = fit_effect([data], gain.model, "pdc_drift", predictor)
    assert drift.values["rate"] == pytest.approx(0.3, abs=0.03) and set(drift.model.effects) == {
        "ft_calibration",
        "pdc_drift",
    }
    assert diagnose([data], drift.model, predictor, top=1).verdict == "nothing"


def test_an_earlier_fit_biased_by_a_missing_effect_is_corrected_when_it_is_added(
    null_loop: LoopResult, predictor: Predictor, tmp_path: Path
) -> None:
    """An F/T gain of 0.88 on z with the z bias drifting 4 mN/s, both applied by the independent generator. The F/T
    map fitted first, the drift missing, takes part of the drift as cross terms; adding the drift jointly
    (`fit_jointly`, what `twin improve` runs) refits the map with it and the cross terms go."""
    gained = apply_ft_map(null_loop.dataset, tmp_path / "gain.hdf5", np.diag([1.0, 1.0, 0.88]))
    data = load_campaign(apply_ft_drift(gained, tmp_path / "both.hdf5", np.array([0.0, 0.0, 0.004])))
    map_first = fit_effect([data], TwinModel(mesh_max_edge=data.mesh_max_edge), "ft_calibration", predictor)
    biased = map_first.values
    assert max(abs(biased["zx"]), abs(biased["zy"])) > 0.05, biased  # the drift taken as cross terms
    both = fit_jointly([data], map_first.model, "ft_drift", predictor)
    corrected = both.model.effects["ft_calibration"]
    assert corrected["zz"] == pytest.approx(0.88, abs=0.005), corrected
    assert max(abs(corrected["zx"]), abs(corrected["zy"])) < 0.02, corrected
    assert both.values["fz_rate"] == pytest.approx(0.004, abs=4e-4)
    assert both.rms_after <= NOISE_TOLERANCE and both.rms_before == pytest.approx(map_first.rms_after, rel=1e-9)
