"""The stopping rule and the verdict (issue 20): a chi-square test that scales with the data, and an effect
named only when its fit generalises to held-out data.

No fe work: the noise test is checked on simulated white Gaussian noise whose standard deviation is
estimated here the way a campaign's is (MAD of successive differences), independently of the code;
the verdict on candidates with given figures.
"""

import json
from dataclasses import replace

import numpy as np
import pytest
from scipy.stats import chi2, norm

from twin.analysis.diagnose import Diagnosis, diagnose
from twin.analysis.heldout import heldout, heldout_folds, record_heldout, whitened_rms
from twin.analysis.predict import TwinModel
from twin.analysis.residual import Base, GainNuisance, Residual
from twin.analysis.sensitivity import Linearisation
from twin.analysis.significance import (
    NoiseTest,
    noise_test,
    out_of_fold_excess,
    ratio_threshold,
    weighted_chi2_quantile,
)
from twin.analysis.verdict import NOTHING_BEYOND_NUISANCES, Candidate, order_candidates, parameters_at_bound, verdict
from twin.effects import EFFECTS

CHANNELS = 4


def _whitened_ratio(rng: np.random.Generator, n: int, trajectories: int, excess: float) -> tuple[float, float]:
    """Simulate `trajectories` recordings of 4 channels with `n` samples each in all: unit noise plus a
    slow signal of variance `excess` the model lacks; whiten each channel by its MAD-of-differences
    noise estimate, project each trajectory's channel offsets; return (R, its threshold at alpha 0.05)."""
    squares, counts = [], []
    length = n // trajectories
    for _ in range(CHANNELS):
        t = np.linspace(0.0, 1.0, length)
        parts = [
            rng.standard_normal(length) + np.sqrt(2 * excess) * np.sin(2 * np.pi * (t + rng.uniform()))
            for _ in range(trajectories)
        ]
        differences = np.concatenate([np.diff(p) for p in parts])
        sigma = 1.4826 * np.median(np.abs(differences - np.median(differences))) / np.sqrt(2.0)
        whitened = np.concatenate([(p - p.mean()) / sigma for p in parts])
        squares.append(float(whitened @ whitened))
        counts.append(len(whitened))
    noise_samples = [trajectories * (length - 1)] * CHANNELS
    test = noise_test(squares, counts, noise_samples, CHANNELS * trajectories, alpha=0.05)
    return test.ratio, test.threshold


def test_the_noise_test_holds_its_false_alarm_rate_and_its_spread_on_pure_noise() -> None:
    rng = np.random.default_rng(20)
    ratios = np.array([_whitened_ratio(rng, 4000, 4, 0.0)[0] for _ in range(600)])
    threshold, dof = ratio_threshold([4000] * CHANNELS, [4 * 999] * CHANNELS, 16, alpha=0.05)
    predicted_sd = (threshold - 1.0) / 1.6449
    assert np.mean(ratios) == pytest.approx(1.0, abs=0.01)
    assert np.std(ratios) == pytest.approx(predicted_sd, rel=0.15), "the variance formula (noise estimate included)"
    alarms = np.mean(ratios > threshold)
    assert 0.025 <= alarms <= 0.08, alarms  # 0.05 expected; binomial sd 0.009 over 600 draws


def test_the_noise_test_sees_a_small_excess_on_many_samples_and_not_on_few() -> None:
    rng = np.random.default_rng(21)
    many = [_whitened_ratio(rng, 200_000, 20, 0.02) for _ in range(3)]
    few = [_whitened_ratio(rng, 2_000, 2, 0.02) for _ in range(20)]
    assert all(ratio > threshold for ratio, threshold in many), many
    assert np.mean([ratio > threshold for ratio, threshold in few]) < 0.5, few
    rms_many = np.sqrt(ratio_threshold([50_000] * 4, [50_000] * 4, 80)[0])
    rms_few = np.sqrt(ratio_threshold([500] * 4, [500] * 4, 8)[0])
    assert 1.0 < rms_many < 1.02 < 1.05 < rms_few < 1.3, (rms_many, rms_few)


def _two_fold_design(rng: np.random.Generator, rows: int) -> tuple[np.ndarray, np.ndarray]:
    """A 9-column whitened sensitivity in two folds, as the F/T map's on two indenters: fold 0 barely
    excites six columns (the lateral ones) that fold 1 loads ten times as much."""
    weak = np.r_[np.full(6, 0.03), np.ones(3)]
    strong = np.r_[np.full(6, 0.3), np.ones(3)]
    jac = np.vstack([rng.standard_normal((rows, 9)) * weak, rng.standard_normal((rows, 9)) * strong])
    return jac, np.repeat([0, 1], rows)


def _held_out_squares(jac: np.ndarray, folds: np.ndarray, noise: np.ndarray) -> np.ndarray:
    """Sum of squares of each noise column (N, draws) predicted per fold by a least-squares fit on the other."""
    out = np.zeros(noise.shape[1])
    for g in np.unique(folds):
        test = folds == g
        fit = np.linalg.lstsq(jac[~test], noise[~test], rcond=None)[0]
        out += np.sum((noise[test] - jac[test] @ fit) ** 2, axis=0)
    return out


def test_the_weighted_chi_square_quantile_matches_the_chi_square_and_the_normal() -> None:
    for degrees, alpha in ((1, 0.01), (9, 0.001), (500, 0.001), (20_000, 0.001)):
        exact = 2.5 * chi2.isf(alpha, degrees)
        assert weighted_chi2_quantile(np.array([2.5]), np.array([degrees]), 0.0, alpha) == pytest.approx(
            exact, rel=0.01
        )
    # two chi-squares of one weight are one; a dominant normal term gives the normal quantile
    split = weighted_chi2_quantile(np.array([1.0, 1.0]), np.array([30, 70]), 0.0, 0.001)
    assert split == pytest.approx(chi2.isf(0.001, 100), rel=1e-4)
    normal = weighted_chi2_quantile(np.array([1e-6]), np.array([1]), 1e4, 0.001)
    assert normal == pytest.approx(100 * norm.isf(0.001), rel=0.01)


@pytest.mark.parametrize("unit", [1.0, 5e6])
def test_the_out_of_fold_excess_is_the_spectrum_of_the_explicit_held_out_projection(unit: float) -> None:
    # unit 5e6: columns in parameter units such as a registration offset's per metre (whitened residual per m)
    rng = np.random.default_rng(23)
    jac = rng.standard_normal((600, 4)) * np.array([1.0, 0.1, 0.5, 2.0]) * unit
    folds = rng.integers(0, 3, 600)
    explicit = np.zeros((600, 600))  # P: each fold's rows predicted by the fit on the others
    for g in range(3):
        test = folds == g
        explicit[np.ix_(test, ~test)] = jac[test] @ np.linalg.pinv(jac[~test])
    residual_map = np.eye(600) - explicit
    spectrum = np.linalg.eigvalsh(residual_map.T @ residual_map - np.eye(600))
    spectrum = spectrum[np.abs(spectrum) > 1e-9]
    assert np.sort(out_of_fold_excess(jac, folds).excess) == pytest.approx(np.sort(spectrum), abs=1e-8)


def test_the_held_out_test_allows_for_the_other_folds_fit_and_holds_its_false_alarm_rate() -> None:
    rng = np.random.default_rng(22)
    jac, folds = _two_fold_design(rng, 1000)
    excess = out_of_fold_excess(jac, folds)
    squares = _held_out_squares(jac, folds, rng.standard_normal((len(jac), 4000)))
    assert excess.mean > 0.05 * len(jac), "the design must make the out-of-fold error matter"
    assert np.mean(squares) - len(jac) == pytest.approx(excess.mean, rel=0.1)
    assert np.var(squares) == pytest.approx(2 * len(jac) + excess.variance, rel=0.1)
    # one channel, sigma known (a huge noise sample), no nuisances: the false alarms at alpha 0.05 and 0.01
    # (binomial sd over 4000 draws 0.0034 and 0.0016)
    for alpha, low, high in ((0.05, 0.04, 0.06), (0.01, 0.005, 0.016)):
        with_fit = noise_test([0.0], [len(jac)], [10**12], 0, alpha=alpha, out_of_fold=excess).threshold
        without = noise_test([0.0], [len(jac)], [10**12], 0, alpha=alpha).threshold
        assert low <= np.mean(squares / len(jac) > with_fit) <= high, alpha
        assert np.mean(squares / len(jac) > without) > 0.5, "ignoring the fit, pure noise fails the held-out test"


def _candidate(
    name: str, evidence: float, refit: float, heldout: float, passes: bool, base: float = 2.0, threshold: float = 1.05
) -> Candidate:
    """A refitted candidate with given figures; its held-out test has power when `base` (the base residual's
    RMS on its left-out samples) exceeds the RMS its test allows, `threshold`."""
    return Candidate(
        name,
        "measurement",
        {},
        evidence,
        evidence,
        0.9,
        heldout,
        refit,
        heldout_is_noise=passes,
        heldout_rms_threshold=threshold,
        heldout_base_rms=base,
        heldout_has_power=base > threshold,
    )


def test_a_fit_that_does_not_generalise_is_not_named_and_its_bound_is_said() -> None:
    # The case: crosstalk fits in sample (1.27x) with zx at its bound but predicts held-out
    # indenters at 1.94x; the old rule (refit within 1.3x) named it.
    crosstalk = _candidate("ft_crosstalk", 900.0, 1.27, 1.94, False)
    crosstalk.at_bound = ["zx"]
    gain = _candidate("ft_gain", 400.0, 1.6, 1.62, False)
    ordered = order_candidates([crosstalk, gain])
    outcome, reason, tied = verdict(2.01, False, 1.02, ordered)
    assert outcome == "unexplained" and tied == []
    assert "ft_crosstalk (held out 1.94x, its noise test 1.050x, refit 1.27x; zx at its bound)" in reason
    assert "ft_gain (held out 1.62x" in reason
    shown = json.loads(Diagnosis(2.01, {}, ordered, outcome, reason, tied, 1.02).to_json())
    assert shown["candidates"][0]["at_bound"] == ["zx"] and shown["noise_rms_threshold"] == 1.02


def test_the_json_takes_numpy_scalars_as_the_analysis_leaves_them() -> None:
    # the noise test's verdict is a numpy.bool_ and the fits' numbers numpy floats; json refuses the former
    judged = _candidate("ft_gain", np.float64(400.0), np.float64(1.0), np.float64(np.nan), np.bool_(True))
    shown = json.loads(Diagnosis(np.float64(1.5), {}, [judged], "ft_gain", "", [], 1.02).to_json())
    assert shown["candidates"][0]["heldout_is_noise"] is True
    assert shown["candidates"][0]["evidence"] == 400.0 and shown["candidates"][0]["heldout_rms"] is None


def test_the_effect_whose_held_out_residual_is_noise_is_named_even_behind_in_evidence() -> None:
    flexible = _candidate("ft_crosstalk", 900.0, 1.1, 1.5, False)
    right = _candidate("ft_calibration", 850.0, 1.0, 1.01, True)
    unrefitted = Candidate("skin_modulus", "physics", {}, 10.0, -5.0, 0.0, heldout_rms=1.8)
    ordered = order_candidates([flexible, unrefitted, right])
    assert [c.name for c in ordered] == ["ft_calibration", "ft_crosstalk", "skin_modulus"]
    outcome, reason, _ = verdict(2.0, False, 1.02, ordered)
    assert outcome == "ft_calibration", reason


def _held_out(jac: np.ndarray, folds: np.ndarray, residual: np.ndarray) -> np.ndarray:
    """Each fold's residual less its prediction by the least-squares fit on the other folds (N,)."""
    return residual - _held_out_fit(jac, folds, residual[:, None])[:, 0]


def _held_out_fit(jac: np.ndarray, folds: np.ndarray, values: np.ndarray) -> np.ndarray:
    """(N, draws): each fold's rows of `values` predicted by the least-squares fit on the other folds."""
    out = np.zeros_like(values)
    for g in np.unique(folds):
        test = folds == g
        out[test] = jac[test] @ np.linalg.lstsq(jac[~test], values[~test], rcond=None)[0]
    return out


def test_a_held_out_test_that_cannot_tell_the_effect_from_none_does_not_name_it() -> None:
    # The registration case of issue 20 in miniature: a candidate of three parameters that one of the two folds
    # barely excites (3 %: the fit on it extrapolates, so the held-out test allows a lot), and a base residual of
    # 1.5x the noise that the candidate does not explain at all (an excess spread over every sample, outside its
    # signature). Its held-out residual passes that test; so would the residual without it: not named.
    rng = np.random.default_rng(24)
    jac = rng.standard_normal((2000, 3)) * np.repeat([0.03, 1.0], 1000)[:, None]
    folds = np.repeat([0, 1], 1000)
    excess = out_of_fold_excess(jac, folds)

    def held_out_test(values: np.ndarray) -> NoiseTest:  # one channel, sigma known, no nuisances
        finite = np.isfinite(values)
        return noise_test([float(np.sum(values[finite] ** 2))], [int(finite.sum())], [10**12], 0, out_of_fold=excess)

    residual = 1.5 * rng.standard_normal(len(jac))
    plain = noise_test([float(residual @ residual)], [len(residual)], [10**12], 0)
    assert not plain.is_noise, "the base residual is not noise"
    candidate = Candidate("registration_offset", "physics", {}, 500.0, 500.0, 0.1, refit_rms=1.45)
    left_out = _held_out(jac, folds, residual)
    record_heldout(candidate, whitened_rms(left_out), left_out, residual, held_out_test)
    assert candidate.heldout_is_noise, "the test allows the extrapolated fit so much that the candidate passes"
    assert candidate.heldout_base_rms == pytest.approx(whitened_rms(residual))
    assert candidate.heldout_base_rms < candidate.heldout_rms_threshold and candidate.heldout_has_power is False
    assert candidate.heldout_is_noise is True, "plain bools, as `twin improve` writes them to its JSON history"
    outcome, reason, _ = verdict(1.5, False, plain.rms_threshold, order_candidates([candidate]))
    assert outcome == "unexplained", reason
    assert "its held-out test cannot tell it from no effect (threshold" in reason
    assert f"base {candidate.heldout_base_rms:.2f}x)" in reason
    # The same candidate on a residual it does explain (noise plus its signature, large enough to show held out).
    signal = rng.standard_normal(len(jac)) + jac @ np.full(3, 5.0)
    left_out = _held_out(jac, folds, signal)
    record_heldout(candidate, whitened_rms(left_out), left_out, signal, held_out_test)
    assert candidate.heldout_is_noise and candidate.heldout_has_power, candidate
    assert verdict(whitened_rms(signal), False, plain.rms_threshold, [candidate])[0] == "registration_offset"


def _held_out(jac: np.ndarray, folds: np.ndarray, residual: np.ndarray) -> np.ndarray:
    """Each fold's residual (N,) less its prediction by the least-squares fit on the other fold(s)."""
    out = residual.copy()
    for g in np.unique(folds):
        test = folds == g
        out[test] -= jac[test] @ np.linalg.lstsq(jac[~test], residual[~test], rcond=None)[0]
    return out


def test_nothing_only_when_the_base_residual_passes_the_test() -> None:
    weak = _candidate("ft_gain", 50.0, 1.0, 1.0, True)
    assert verdict(1.0, True, 1.02, [weak])[0] == "nothing"
    # 1.18x was "nothing" under the fixed 1.3x rule; on data whose noise test allows 1.02x it is not.
    assert verdict(1.18, False, 1.02, [weak])[0] == "ft_gain"


def test_parameters_at_a_bound_are_found() -> None:
    assert parameters_at_bound("ft_crosstalk", {"zx": 0.2, "zy": -0.08, "xy": -0.2}) == ["xy", "zx"]
    assert parameters_at_bound("ft_gain", {"scale": 0.88}) == []


def test_a_residual_at_the_noise_once_the_nuisances_are_fitted_is_nothing_beyond_them() -> None:
    weak = _candidate("ft_gain", 50.0, 1.0, 1.0, True)
    outcome, reason, tied = verdict(1.0, True, 1.02, [weak], beyond_nuisances=True)
    assert outcome == NOTHING_BEYOND_NUISANCES == "nothing beyond the nuisances" and tied == []
    assert "nuisances fitted" in reason
    # Without the nuisance stage the same residual is plain "nothing"; above the noise, candidates decide.
    assert verdict(1.0, True, 1.02, [weak])[0] == "nothing"
    assert verdict(1.5, False, 1.02, [weak], beyond_nuisances=True)[0] == "ft_gain"


def test_a_nuisance_effect_cannot_also_be_a_candidate() -> None:
    with pytest.raises(ValueError, match="cannot be candidates"):
        diagnose([], TwinModel(), None, ["time_delay", "skin_modulus"], nuisances=True)


def test_an_unexplained_residual_closest_to_nuisances_points_to_the_nuisance_stage() -> None:
    """The issue's realistic null without the stage: "unexplained", registration_offset closest (refit 3.84x). The
    nuisance effects among the closest (by held-out RMS, as the reason shows them) are named for the stage; not once
    it ran, nor on a named verdict, nor beyond the closest shown."""
    closest = [
        _candidate("ft_gain", 300.0, 5.0, 6.0, False),
        _candidate("skin_thickness", 200.0, 4.5, 5.0, False),
        _candidate("registration_offset", 100.0, 3.84, 4.1, False),
        _candidate("time_delay", 50.0, 5.5, 5.8, False),
        _candidate("skin_modulus", 40.0, 7.0, 7.5, False),
    ]
    outcome, reason, tied = verdict(10.5, False, 1.02, order_candidates(closest))
    unexplained = Diagnosis(10.5, {}, closest, outcome, reason, tied, 1.02)
    assert outcome == "unexplained"
    assert unexplained.nuisances_closest() == ["registration_offset", "skin_thickness"]
    assert replace(unexplained, nuisances={"values": {}}).nuisances_closest() == []
    assert replace(unexplained, verdict="ft_gain").nuisances_closest() == []


def _profiled_held_out_test(base: Base, target: np.ndarray, jac: np.ndarray) -> NoiseTest:
    """The held-out test (one parameter, leave one indenter out, sigma known) of `target` on `jac`."""
    lin = Linearisation({"scale": 1.0}, np.zeros_like(target), jac[:, None])
    _, left_out = heldout(EFFECTS["skin_modulus"], lin, target, base.residual.indenter)
    axis = base.residual.covariates["axis"]
    squares = [float(np.sum(left_out[axis == c] ** 2)) for c in range(CHANNELS)]
    counts = [int(np.sum(axis == c)) for c in range(CHANNELS)]
    excess = out_of_fold_excess(jac[:, None], base.residual.indenter)
    return noise_test(squares, counts, [10**12] * CHANNELS, CHANNELS * 2 + 1, out_of_fold=excess)


def _gain_case(gain: float, pressure: float, force: float = 100.0) -> tuple[NoiseTest, NoiseTest]:
    """The held-out tests of the case below, profiled about the base's PDC and about the judged model's: a PDC
    read-out gain error `gain` (relative); the effect changes the whitened force z by `force` ramp^1.5 on the first
    indenter and the whitened PDC by `pressure` ramp^4 on the second (1500 samples each, unit noise)."""
    rng = np.random.default_rng(25)
    n = 1500
    ramp = np.linspace(0.0, 1.0, n)
    # per indenter (trajectory): whitened base PDC, and the effect's change of force z and of PDC per unit
    base_pdc, force_change, pdc_change = (
        [40 * ramp, 60 * ramp],
        [force * ramp**1.5, 3 * ramp**1.5],
        [5 * ramp**2, pressure * ramp**4],
    )

    def channels(
        z: np.ndarray, pdc: np.ndarray, x: float | np.ndarray = 0.0, y: float | np.ndarray = 0.0
    ) -> np.ndarray:
        """(x, y, z, pdc) per sample, flattened, each channel's offset projected out."""
        block = np.column_stack(np.broadcast_arrays(x, y, z, pdc))
        return (block - block.mean(axis=0)).ravel()

    base_prediction = np.concatenate([channels(np.zeros(n), p) for p in base_pdc])
    signature = np.concatenate([channels(f, p) for f, p in zip(force_change, pdc_change, strict=True)])
    judged = base_prediction + signature  # the model with the effect at its true value (1)
    noise = np.concatenate([channels(*rng.standard_normal((4, n))) for _ in range(2)])
    pdc_axis = np.tile(np.arange(CHANNELS), 2 * n) == 3
    data = judged + gain * np.where(pdc_axis, judged, 0.0) + noise
    axis = np.tile(np.arange(CHANNELS), 2 * n)
    sensor = np.full(len(data), 2)
    residual = Residual(
        data - base_prediction,
        np.repeat([0, 1], CHANNELS * n),
        np.repeat(["sphere_small", "cylinder_long"], CHANNELS * n).astype(object),
        {"axis": axis, "sensor": sensor},
        np.ones(CHANNELS),
    )
    gains = GainNuisance(base_prediction, axis, sensor)
    base = Base(
        [],
        np.ones(CHANNELS),
        replace(residual, values=gains.project(data - base_prediction)),
        [],
        base_prediction,
        gains,
        data,
    )
    about_base = _profiled_held_out_test(
        base, base.residual.values - gains.project(signature), gains.project(signature)
    )
    about = base.with_prediction(judged)
    assert about.residual.values == pytest.approx(about.nuisance.project(data - judged))
    return about_base, _profiled_held_out_test(about, about.residual.values, about.nuisance.project(signature))


def test_the_pdc_gain_is_profiled_about_the_judged_model() -> None:
    """The registration offsets of issue 20 in miniature: a sensor whose PDC read-out is 3 % low, and an effect
    (at its true value, one parameter) that changes the pressure a lot on one indenter and the force on the other.
    About the true effect the residual is the gain error times that model's PDC, plus noise. Profiled about the base
    model's PDC (the effect off), the gain leaves 3 % of the effect's pressure change along its own signature, the
    two indenters' fits disagree and the held-out test fails; profiled about the judged model's own PDC
    (`Base.with_prediction`, what `judge_heldout` does), the residual is noise and the test passes."""
    about_base, about_judged = _gain_case(-0.03, 300.0)
    assert not about_base.is_noise, ("profiled about the base's PDC, 3 % of the pressure change is left", about_base)
    assert about_judged.is_noise, about_judged
    assert all(test.is_noise for test in _gain_case(0.0, 300.0)), "with an exact read-out gain both ways agree"


def test_one_indenter_is_held_out_press_by_press_and_one_press_holds_nothing_out() -> None:
    """A campaign of one indenter holds out one trajectory at a time (fitted on the others); with a single
    trajectory nothing is held out, the candidate is left unjudged and not named, and the verdict says why."""
    rng = np.random.default_rng(3)
    n = 400
    jac = rng.standard_normal(n)
    target = 0.3 * jac + rng.standard_normal(n)  # an effect of 0.3 in unit noise, the same on both presses
    lin = Linearisation({"scale": 1.0}, np.zeros(n), jac[:, None])
    covariates = {"axis": np.zeros(n, dtype=int), "sensor": np.zeros(n, dtype=int)}
    one_indenter = Residual(
        target, np.repeat([0, 1], n // 2), np.full(n, "sphere_medium", dtype=object), covariates, np.ones(4)
    )
    folds = heldout_folds(one_indenter)
    np.testing.assert_array_equal(folds, one_indenter.trajectory_index)
    rms, left_out = heldout(EFFECTS["skin_modulus"], lin, target, folds)
    for press in (0, 1):  # each press predicted by the fit on the other, by hand
        train, test = folds != press, folds == press
        slope = float(jac[train] @ target[train] / (jac[train] @ jac[train]))
        np.testing.assert_allclose(left_out[test], target[test] - slope * jac[test], rtol=1e-12)
    assert rms == pytest.approx(whitened_rms(left_out))
    one_press = replace(one_indenter, trajectory_index=np.zeros(n, dtype=int))
    rms, left_out = heldout(EFFECTS["skin_modulus"], lin, target, heldout_folds(one_press))
    assert rms is None and np.isnan(left_out).all()
    candidate = Candidate("skin_modulus", "physics", {}, 900.0, 900.0, 0.9, refit_rms=0.99, refit_parameters={})
    record_heldout(candidate, rms, left_out, target, lambda r: pytest.fail("nothing is held out to test"))
    assert candidate.heldout_is_noise is None and not candidate.supported_heldout
    outcome, reason, _ = verdict(1.4, False, 1.02, order_candidates([candidate]))
    assert outcome == "unexplained" and "nothing can be held out" in reason
