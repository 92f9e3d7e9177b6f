"""Linearisations solved ahead (`Predictor.solve_ahead`, issue 18): the same fits in fewer batches.

On a GPU a batch of replays costs about its longest replay's chain of solves, not its size, so the analyses may
solve a linearisation's replays with its point's. Here the fe is a stand-in with a known nonlinear response of a
physics effect (a backlash), each model's "replay" noted in the batch that solved it: the numbers must not depend on
`solve_ahead`, and the batches (waves) must be fewer with it.
"""

from types import SimpleNamespace

import numpy as np
import pytest
from stand_ins import SolvedModels

from twin.analysis import sensitivity
from twin.analysis.predict import Predictor, TwinModel
from twin.analysis.refit import refit
from twin.analysis.sensitivity import linearise, sensitivities, start_models
from twin.analysis.verdict import Candidate
from twin.effects import EFFECTS

BACKLASH = EFFECTS["robot_backlash"]
LAG_TRUE = 3.1e-4  # m: inside the range (0-0.5 mm), away from its declared starts (0.1, 0.25 mm)


class _Response(SolvedModels):
    """Stands in for `twin.analysis.residual.Base`: the whitened residual of a campaign with a backlash of
    `LAG_TRUE` (a response nonlinear in the lag, unit noise), and the replays of every model solved so far, with
    the batches that solved them. As `Base.shifted` does, a prediction whose replays are not solved yet solves
    them first (a batch of its own)."""

    def __init__(self) -> None:
        super().__init__(TwinModel())
        rng = np.random.default_rng(3)
        self.t = np.linspace(0.0, 1.0, 400)
        self.residual = SimpleNamespace(values=self.response(LAG_TRUE) + rng.standard_normal(len(self.t)))
        self.nuisance = SimpleNamespace(chi2=lambda r: float(np.nansum(r**2)))

    def response(self, lag: float) -> np.ndarray:
        x = lag / 1e-4
        return 20.0 * np.sin(2.0 * np.pi * self.t) * np.tanh(x) + 3.0 * np.cos(5.0 * self.t) * x**2

    def shifted(self, predictor: object, model: TwinModel) -> np.ndarray:
        self.prefetch(predictor, [model])
        return self.response(model.effects.get(BACKLASH.name, {}).get("lag", 0.0))

    def noise_test(self, values: np.ndarray) -> SimpleNamespace:
        return SimpleNamespace(is_noise=bool(np.sqrt(np.nanmean(values**2)) < 1.05))


def _predictor(ahead: bool) -> SimpleNamespace:
    return SimpleNamespace(solve_ahead=ahead)


def test_a_predictor_solves_ahead_on_a_gpu_only_unless_told() -> None:
    assert not Predictor("cpu").solve_ahead
    assert Predictor("cpu", solve_ahead=True).solve_ahead
    assert Predictor("cuda:0", workers=1).solve_ahead  # no device is touched until a replay is solved


class _DataStart:
    """A data-driven start (`sensitivity.DATA_STARTS`) that proposes a backlash of `lag` (m)."""

    def __init__(self, lag: float) -> None:
        self.lag = lag

    def start(self, current: dict[str, float]) -> dict[str, float]:
        return {"lag": self.lag}

    def estimate(self, current: dict[str, float]) -> dict[str, float]:
        return self.start(current)

    def to_dict(self) -> dict:
        return {"lag": self.lag}


@pytest.mark.parametrize("proposed", [LAG_TRUE * 1.02, None])  # the data-driven start best; a declared start best
def test_the_best_trials_linearisation_comes_with_the_trials(
    proposed: float | None, monkeypatch: pytest.MonkeyPatch
) -> None:
    """The trials of an off backlash: the linear fit's step, a data-driven start when there is one, the declared
    starts (0.1, 0.25 mm; solved with the first batch, as a diagnosis does). Ahead, the linearisations at the
    data-driven start and at the best declared start come with the trials: no batch after them whichever wins."""
    starts = {BACKLASH.name: lambda predictor, model, base: _DataStart(proposed)} if proposed else {}
    monkeypatch.setattr(sensitivity, "DATA_STARTS", starts)
    out = {}
    for ahead in (False, True):
        base = _Response()
        base.prefetch(None, start_models([BACKLASH], TwinModel()))
        base.batches.clear()
        (lin,) = sensitivities([BACKLASH], TwinModel(), _predictor(ahead), base)
        out[ahead] = (lin, len(base.batches))
    (plain, plain_batches), (ahead, ahead_batches) = out[False], out[True]
    assert plain.point == ahead.point == {"lag": proposed or 2.5e-4}  # moved to that trial: linearised again there
    np.testing.assert_array_equal(plain.jac, ahead.jac)
    np.testing.assert_array_equal(plain.offset, ahead.offset)
    assert (plain_batches, ahead_batches) == (3, 2)  # first, trials (, the best trial's linearisation)


@pytest.mark.parametrize("start", [0.0, 2.5e-4])
def test_a_refit_solved_ahead_ends_where_it_ends_alone_in_fewer_batches(start: float) -> None:
    out = {}
    for ahead in (False, True):
        base = _Response()
        lin = linearise(BACKLASH, TwinModel(), {"lag": start}, _predictor(ahead), base)
        base.batches.clear()
        candidate = Candidate(BACKLASH.name, "physics", {}, 0.0, 0.0, 0.0)
        refit(candidate, TwinModel(), _predictor(ahead), base, lin)
        out[ahead] = (candidate.refit_parameters, candidate.refit_rms, len(base.batches))
    (plain_values, plain_rms, plain_batches), (ahead_values, ahead_rms, ahead_batches) = out[False], out[True]
    assert plain_values == ahead_values and plain_rms == ahead_rms
    assert abs(plain_values["lag"] - LAG_TRUE) < 0.1 * LAG_TRUE  # the stand-in's fit is a real one
    assert ahead_batches < plain_batches, (plain_batches, ahead_batches)
