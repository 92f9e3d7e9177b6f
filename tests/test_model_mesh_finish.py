"""A refit made on a coarser fe mesh, finished on the model's own (`refit.finish_on_model_mesh`, issue 18).

A coarse mesh's facets put the skin's contact elsewhere, so a physics effect fitted on it (a registration offset, a
backlash: the indenter's path) is off on the model's mesh by more than the noise allows. Here the fe is a stand-in
whose coarse mesh answers a backlash as the model's mesh does a slightly larger one (a bias of `COARSE_BIAS`): the
coarse refit lands off, the finish, with the coarse columns, lands on the model mesh's fit.
"""

from types import SimpleNamespace

import numpy as np
from stand_ins import SolvedModels

from twin.analysis.predict import TwinModel
from twin.analysis.refit import FINISH_REACH, finish_on_model_mesh, refit
from twin.analysis.sensitivity import linearise
from twin.analysis.verdict import Candidate
from twin.effects import EFFECTS

BACKLASH = EFFECTS["robot_backlash"]
LAG_TRUE = 3.1e-4  # m
COARSE_BIAS = 3e-5  # m: the coarse mesh's answer to a lag is the model mesh's to lag + this
MODEL, COARSE = TwinModel(mesh_max_edge=1e-3), TwinModel(mesh_max_edge=2e-3)


class _TwoMeshes(SolvedModels):
    """Stands in for `twin.analysis.residual.Base` on either mesh: the whitened residual of a campaign with a backlash
    of `LAG_TRUE` on the model's mesh (unit noise) about the base model there; a model's shift from the base model
    on its own mesh; the models solved so far, in the batches that solved them."""

    def __init__(self) -> None:
        super().__init__(MODEL, COARSE)
        self.t = np.linspace(0.0, 1.0, 400)
        noise = np.random.default_rng(5).standard_normal(len(self.t))
        self.residual = SimpleNamespace(values=self.response(LAG_TRUE, MODEL) - self.response(0.0, MODEL) + noise)
        self.nuisance = SimpleNamespace(chi2=lambda r: float(np.nansum(r**2)))

    def response(self, lag: float, model: TwinModel) -> np.ndarray:
        x = (lag + (COARSE_BIAS if model.mesh_max_edge == COARSE.mesh_max_edge else 0.0)) / 1e-4
        return 20.0 * np.sin(2.0 * np.pi * self.t) * np.tanh(x) + 3.0 * np.cos(5.0 * self.t) * x**2

    def shifted(self, predictor: object, model: TwinModel) -> np.ndarray:
        self.prefetch(predictor, [model])
        lag = model.effects.get(BACKLASH.name, {}).get("lag", 0.0)
        return self.response(lag, model) - self.response(0.0, model)

    def noise_test(self, values: np.ndarray) -> SimpleNamespace:
        return SimpleNamespace(is_noise=bool(np.sqrt(np.nanmean(values**2)) < 1.05), rms_threshold=1.05)


def _coarse_fit(base: _TwoMeshes, ahead: bool) -> Candidate:
    predictor = SimpleNamespace(solve_ahead=ahead)
    lin = linearise(BACKLASH, COARSE, {"lag": 2.5e-4}, predictor, base)
    candidate = Candidate(BACKLASH.name, "physics", {}, 0.0, 0.0, 0.0)
    refit(candidate, COARSE, predictor, base, lin)
    return candidate


def _rms_on_model_mesh(base: _TwoMeshes, lag: float) -> float:
    misfit = base.residual.values - base.shifted(None, MODEL.with_effects({BACKLASH.name: {"lag": lag}}))
    return float(np.sqrt(np.mean(misfit**2)))


def test_a_coarse_refit_finished_on_the_model_mesh_reaches_its_noise() -> None:
    out = {}
    for ahead in (False, True):
        base = _TwoMeshes()
        candidate = _coarse_fit(base, ahead)
        coarse_lag = candidate.refit_parameters["lag"]
        assert _rms_on_model_mesh(base, coarse_lag) > 1.3, coarse_lag  # the coarse fit: the model's mesh rejects it
        base.batches.clear()
        finish_on_model_mesh(candidate, MODEL, SimpleNamespace(solve_ahead=ahead), base, COARSE, base)
        lag = candidate.refit_parameters["lag"]
        assert abs(lag - LAG_TRUE) < 0.1 * COARSE_BIAS, lag
        assert candidate.refit_rms == _rms_on_model_mesh(base, lag) < 1.05
        out[ahead] = (lag, len(base.batches))
    assert out[True][0] == out[False][0]  # the same fit, its columns solved ahead or not
    assert out[True][1] < out[False][1]


def test_a_finish_keeps_the_coarse_fit_when_the_model_mesh_agrees_and_leaves_measurement_effects() -> None:
    base = _TwoMeshes()
    at_truth = {"lag": LAG_TRUE}
    candidate = Candidate(BACKLASH.name, "physics", {}, 0.0, 0.0, 0.5, refit_rms=0.9, refit_parameters=at_truth)
    finish_on_model_mesh(candidate, MODEL, SimpleNamespace(solve_ahead=True), base, COARSE, base)
    assert candidate.refit_parameters == {"lag": LAG_TRUE}  # at the noise there: no step
    assert candidate.refit_rms == _rms_on_model_mesh(base, LAG_TRUE)
    gain = Candidate("ft_gain", "measurement", {}, 0.0, 0.0, 0.0, refit_rms=1.7, refit_parameters={"scale": 0.9})
    finish_on_model_mesh(gain, MODEL, SimpleNamespace(solve_ahead=True), base, COARSE, base)
    assert (gain.refit_parameters, gain.refit_rms) == ({"scale": 0.9}, 1.7)


def test_a_finish_goes_on_from_a_start_that_fits_the_model_mesh_better_than_the_coarse_fit() -> None:
    """A coarse fit far off (the backlash at its 0.5 mm bound) and the effect's data-driven start near the truth: both
    are tried on the model's mesh in one batch, and the finish goes on from the start (fewer steps than from the
    coarse fit alone)."""
    far = {"lag": BACKLASH.parameters[0].upper}
    predictor = SimpleNamespace(solve_ahead=True)
    out = {}
    for starts in ([{"lag": 2.7e-4}], []):
        base = _TwoMeshes()
        candidate = Candidate(BACKLASH.name, "physics", {}, 0.0, 0.0, 0.0, refit_rms=9.0, refit_parameters=dict(far))
        finish_on_model_mesh(candidate, MODEL, predictor, base, COARSE, base, starts=starts)
        assert abs(candidate.refit_parameters["lag"] - LAG_TRUE) < 0.1 * COARSE_BIAS
        assert candidate.refit_rms < 1.05
        first = {MODEL.with_effects({BACKLASH.name: values}).key() for values in [far, *starts]}
        assert first <= base.batches[0]  # the coarse fit and the start, tried together
        out[bool(starts)] = len(base.batches)
    assert out[True] < out[False]


def test_a_finish_takes_no_step_where_its_linearisation_leaves_the_fit_far_above_the_noise() -> None:
    """The same campaign with a large signal no backlash makes (10x the noise, a stand-in for what another effect or
    a nuisance leaves): the finish tries its starts on the model's mesh (one batch) and stops there, since the step's
    linearisation predicts a residual above `FINISH_REACH` times the noise; its figure is the best start's RMS. The
    same coarse fit on the campaign without that signal steps on (more batches)."""
    batches = {}
    for unexplained in (0.0, 10.0):
        base = _TwoMeshes()
        base.residual.values = base.residual.values + unexplained * np.sqrt(2.0) * np.cos(40.0 * np.pi * base.t)
        far = {"lag": 2.0e-4}
        candidate = Candidate(BACKLASH.name, "physics", {}, 0.0, 0.0, 0.0, refit_rms=9.0, refit_parameters=dict(far))
        finish_on_model_mesh(candidate, MODEL, SimpleNamespace(solve_ahead=True), base, COARSE, base)
        batches[unexplained] = len(base.batches)
        if unexplained:
            assert candidate.refit_parameters == far
            assert candidate.refit_rms == _rms_on_model_mesh(base, far["lag"]) > FINISH_REACH * 1.05
    assert batches[10.0] == 1 < batches[0.0]
