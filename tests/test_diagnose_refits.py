"""Which candidates diagnosis refits, a refit caught in a basin, and the residual about a model whose replay
failed part of the way (issue 20, session 17).

No fe work: candidates with given figures, and residuals built from simulated loading curves and noise.
"""

from types import SimpleNamespace

import numpy as np
import pytest

from twin.analysis.predict import Predictor, TwinModel
from twin.analysis.refit import refit, starts_across
from twin.analysis.residual import Base, GainNuisance, Residual, recentred, whitened
from twin.analysis.sensitivity import sensitivity
from twin.analysis.verdict import CLOSE_FIT, MOST_REFITS, Candidate, order_candidates, to_refit, verdict
from twin.effects import EFFECTS

CHANNELS = 4


def _ranked(drops: list[float], parameters: int = 1, n: int = 20_000) -> list[Candidate]:
    """Candidates with the given chi-square drops, best first (evidence: the drop less the BIC penalty)."""
    return [
        Candidate(f"effect{i}", "physics", {}, drop, drop - parameters * np.log(n), 0.5) for i, drop in enumerate(drops)
    ]


def test_a_candidate_whose_linearised_fit_comes_close_to_the_best_is_refitted_too() -> None:
    # seed 6's fluid volume (measured): ranked second, 42 behind in evidence, both fits leaving ~46 300 of 245 600
    chi2 = 245_600.0
    ranked = _ranked([199_272.7, 199_210.6, 142_715.7, 122_867.1])
    assert to_refit(ranked, 1, chi2) == 2, "the close second is refitted, the third (2.2x the chi-square left) not"
    assert to_refit(ranked, 3, chi2) == 3, "what was asked for is refitted whatever it leaves"
    assert to_refit(ranked, 0, chi2) == 0, "no refits asked for: none added"


def test_close_refits_stop_at_the_cap_and_never_add_a_candidate_without_evidence() -> None:
    chi2 = 30_000.0
    close = _ranked([9_990.0 + i for i in range(MOST_REFITS + 3)][::-1])
    assert to_refit(close, 1, chi2) == MOST_REFITS
    assert to_refit(close, MOST_REFITS + 2, chi2) == MOST_REFITS + 2, "more asked for than the cap: all refitted"
    # on a null every fit leaves about the same chi-square; a candidate that explains nothing significant is not added
    null = _ranked([12.0, 8.0, 5.0])
    assert all(c.evidence < 0 for c in null[1:])
    assert to_refit(null, 1, 20_000.0) == 1
    left = chi2 - close[0].chi2_drop
    far = _ranked([close[0].chi2_drop, chi2 - CLOSE_FIT * left * 1.01])
    assert to_refit(far, 1, chi2) == 1, "beyond CLOSE_FIT times what the best leaves: not refitted"


def test_recentred_takes_each_groups_mean_over_its_finite_entries_only() -> None:
    values = np.array([1.0, 3.0, np.nan, 10.0, 14.0])
    group = np.array([0, 0, 0, 2, 2])
    out = recentred(values, group)
    assert out[:2] == pytest.approx([-1.0, 1.0]) and np.isnan(out[2])
    assert out[3:] == pytest.approx([-2.0, 2.0])


def _base_of(data: list[np.ndarray], sigma: np.ndarray) -> Base:
    """A Base of trajectories (T, 4) whose model predicts them exactly but for the noise (no replays)."""
    masks = [np.ones(len(d), bool) for d in data]
    whitened_data = whitened(data, masks, sigma)
    index = np.concatenate([np.full(CHANNELS * len(d), i) for i, d in enumerate(data)])
    axis = np.concatenate([np.tile(np.arange(CHANNELS), len(d)) for d in data])
    sensor = np.zeros(len(index), int)
    covariates = {"axis": axis, "sensor": sensor}
    residual = Residual(np.zeros(len(index)), index, np.full(len(index), "sphere"), covariates, sigma)
    nuisance = GainNuisance(np.zeros(len(index)), axis, sensor)
    return Base([], sigma, residual, masks, np.zeros(len(index)), nuisance, whitened_data)


def test_a_replay_that_fails_part_way_leaves_only_the_noise_on_the_samples_it_reached() -> None:
    """A loading curve and its noisy measurement; the model's replay is right but stops converging 85 % of
    the way through the first trajectory (its later samples NaN, as `Predictor.predict` leaves them). Centred
    over the samples it reached, its mean differs from the data's over all of them by a constant that is no
    misfit: the residual on the reached samples must be the noise, re-centred."""
    rng = np.random.default_rng(3)
    sigma = np.array([0.01, 0.01, 0.01, 1.0])
    t = np.linspace(0.0, 1.0, 800)
    curve = np.column_stack([0.1 * np.sin(np.pi * t), 0.05 * t, 2.0 * np.sin(np.pi * t) ** 2, 300 * np.sin(np.pi * t)])
    clean = [curve, 0.5 * curve]
    noise = [rng.standard_normal(c.shape) * sigma for c in clean]
    base = _base_of([c + e for c, e in zip(clean, noise, strict=True)], sigma)
    failed = [clean[0].copy(), clean[1]]
    failed[0][int(0.85 * len(t)) :] = np.nan
    prediction = whitened(failed, base.masks, sigma)
    misfit = base.misfit(prediction)
    reached = np.isfinite(prediction)
    assert np.array_equal(np.isfinite(misfit), reached)
    expected = recentred(
        np.where(reached, np.concatenate([(e / sigma).ravel() for e in noise]), np.nan),
        base.residual.trajectory_index * CHANNELS + base.residual.covariates["axis"],
    )
    assert misfit[reached] == pytest.approx(expected[reached], abs=1e-9)
    assert np.sqrt(np.nanmean(misfit**2)) < 1.05
    # the data less the prediction, each centred over its own samples, passes the difference of means for misfit
    assert np.sqrt(np.nanmean((base.data - prediction) ** 2)) > 2.0
    about = base.with_prediction(prediction)
    assert np.sqrt(np.nanmean(about.residual.values**2)) < 1.05


class _TwoBasins:
    """Data made with a skin modulus of 1.6 whose signature (a fixed pattern) the model reaches fully only near
    1.6 and partly near 0.9: linearised at the off value 1, a refit walks into the basin at 0.9."""

    def __init__(self, n: int = 600) -> None:
        rng = np.random.default_rng(4)
        self.pattern = 4.0 * np.sin(np.arange(n) / 9.0)
        self.residual = type("R", (), {"values": self.pattern + rng.standard_normal(n)})()

    def prefetch(self, predictor: object, models: list[TwinModel]) -> int:
        return 0  # no replays: `shifted` is analytic

    def shifted(self, predictor: object, model: TwinModel) -> np.ndarray:
        scale = model.effects.get("skin_modulus", {}).get("scale", 1.0)
        reach = np.exp(-(((scale - 1.6) / 0.08) ** 2)) + 0.4 * np.exp(-(((scale - 0.9) / 0.08) ** 2))
        return self.pattern * reach

    def noise_test(self, values: np.ndarray) -> SimpleNamespace:
        return SimpleNamespace(is_noise=bool(np.nanmean(values**2) < 1.2))


def test_a_refit_caught_in_a_basin_is_tried_again_from_across_the_range() -> None:
    base = _TwoBasins()
    effect = EFFECTS["skin_modulus"]
    lin = sensitivity(effect, TwinModel(), Predictor(), base)  # replays: the stand-in's
    assert lin.point["scale"] == 1.0
    candidate = Candidate("skin_modulus", "physics", {}, 0.0, 0.0, 0.0)
    refit(candidate, TwinModel(), Predictor(), base, lin)
    assert candidate.refit_parameters["scale"] == pytest.approx(1.6, abs=0.02)
    assert candidate.refit_rms < 1.1
    # the starts: five across the search range of one parameter, a 3 x 3 grid for two
    # (times log-spaced: 0.05 s x 200^(1/6, 3/6, 5/6))
    assert [round(s["scale"], 2) for s in starts_across(effect, {"scale": 1.0})] == [0.65, 0.95, 1.25, 1.55, 1.85]
    relaxation = starts_across(EFFECTS["skin_relaxation"], {"fraction": 0.0, "time_s": 1.0})
    assert len(relaxation) == 9 and sorted({round(s["time_s"], 3) for s in relaxation}) == [0.121, 0.707, 4.135]


def test_a_named_effect_says_which_others_also_pass_held_out_further_behind() -> None:
    """Seed 6's skin modulus (measured): an F/T gain scales the force alike and passes held out too; only the PDC
    gain's prior (a 29 % read-out gain) puts it 36 behind. The verdict names the first and says so."""
    modulus = _judged("skin_modulus", 236_646.5)
    gain = _judged("ft_gain", 236_610.1)
    outcome, reason, tied = verdict(3.56, False, 1.023, order_candidates([gain, modulus]))
    assert outcome == "skin_modulus" and tied == []
    assert reason.endswith("also held out within theirs, further behind in evidence: ft_gain (36.4 behind)")


def _judged(name: str, evidence: float) -> Candidate:
    """A refitted candidate whose held-out residual passes its test, a test with power."""
    return Candidate(
        name,
        "physics",
        {},
        evidence,
        evidence,
        1.0,
        heldout_rms=1.003,
        refit_rms=1.003,
        heldout_is_noise=True,
        heldout_rms_threshold=1.023,
        heldout_base_rms=3.6,
        heldout_has_power=True,
    )
