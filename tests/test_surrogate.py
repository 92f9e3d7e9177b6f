"""The ranking linearisation of a relaxing skin from the skin modulus's elastic replays (`twin.analysis.surrogate`,
issue 18): no timed replay in the first batch, and its columns against the timed finite-difference ones."""

from collections.abc import Callable
from pathlib import Path

import numpy as np
import pytest

from twin.analysis.data import load_campaign
from twin.analysis.diagnose import diagnose
from twin.analysis.predict import Predictor, TwinModel, solve_events
from twin.analysis.residual import base_residual
from twin.analysis.sensitivity import first_models, first_points, linearisation_models, linearise
from twin.analysis.surrogate import RELAXATION, RELAXATION_SURROGATE, modulus_stepped, relaxation_response
from twin.controller import Recording
from twin.effects import EFFECTS, apply_skin
from twin.sim_backend import RELAXATION_SOLVE_INTERVAL_S

FRACTION_COLUMN = (0.08, 0.995)
"""The fraction's surrogate column against the timed one: largest |difference| / |timed|, least correlation
(measured on the tiny campaign of 1.6 s pauses: 0.048 and 0.999; with no prestress share and no contact scaling,
0.33 and 0.95)."""
TIME_COLUMN = (0.35, 0.95)
"""The same for the relaxation time's column (measured: 0.215 and 0.979; without the contact scaling 0.55 and 0.91;
per unit ~60x smaller than the fraction's, per finite-difference step of each 1/15; docs/analysis.md)."""


def test_the_first_batch_holds_no_relaxing_replay_and_shares_the_skin_modulus_column() -> None:
    model = TwinModel()
    effects = [EFFECTS[name] for name in EFFECTS]
    relaxing = [apply_skin(m.skin, m.effects).relaxation_fraction > 0.0 for m in first_models(effects, model)]
    assert any(relaxing), "without surrogates, the probe's replays are timed"
    assert not any(apply_skin(m.skin, m.effects).relaxation_fraction for m in first_models(effects, model, None, True))
    column = linearisation_models(EFFECTS["skin_modulus"], model, {"scale": 1.0})[1]
    assert apply_skin(modulus_stepped(model).skin, {}) == apply_skin(column.skin, column.effects), "the same replays"
    on = model.with_effects({RELAXATION: {"fraction": 0.2, "time_s": 0.5}})  # on in the model: its own replays
    relaxation = EFFECTS[RELAXATION]
    own = linearisation_models(relaxation, on, first_points([relaxation], on)[0])
    assert first_models([relaxation], on, None, True) == own


@pytest.fixture(scope="module")
def long_pauses(tmp_path_factory: pytest.TempPathFactory, make_tiny_campaign) -> Path:
    return make_tiny_campaign(tmp_path_factory.mktemp("surrogate"), pause_s=1.6)


def _agreement(surrogate: np.ndarray, timed: np.ndarray) -> tuple[float, float]:
    """(|surrogate - timed| / |timed|, correlation) over the samples both reach."""
    both = np.isfinite(surrogate) & np.isfinite(timed)
    a, b = surrogate[both], timed[both]
    return float(np.linalg.norm(a - b) / np.linalg.norm(b)), float(np.corrcoef(a, b)[0, 1])


def test_the_surrogate_columns_agree_with_the_timed_finite_differences(long_pauses: Path) -> None:
    data = load_campaign(long_pauses)
    model, predictor = TwinModel(mesh_max_edge=data.mesh_max_edge), Predictor(workers=1)
    base = base_residual([data], model, predictor)
    effect = EFFECTS[RELAXATION]
    point = first_points([effect], model)[0]
    assert point == {"fraction": 0.15, "time_s": 1.0}, "at the probe"
    surrogate = linearise(effect, model, point, predictor, base, RELAXATION_SURROGATE)
    assert surrogate.surrogate and predictor.missing([(m, base.trajectories) for m in [modulus_stepped(model)]]) == 0
    timed = linearise(effect, model, point, predictor, base)
    assert not timed.surrogate
    for column, (most, least) in zip(range(2), (FRACTION_COLUMN, TIME_COLUMN), strict=True):
        difference, correlation = _agreement(surrogate.jac[:, column], timed.jac[:, column])
        assert difference < most and correlation > least, (effect.parameters[column].name, difference, correlation)
    assert _agreement(surrogate.offset, timed.offset)[0] < FRACTION_COLUMN[0], "linear in the fraction: its column"


def test_a_candidate_ranked_on_the_surrogate_is_linearised_again_on_its_own_replays(long_pauses: Path) -> None:
    data = load_campaign(long_pauses)
    model, predictor = TwinModel(mesh_max_edge=data.mesh_max_edge), Predictor(workers=1)
    timed: list[int] = []
    solve = predictor.prefetch_many

    def counted(requests: list, progress: Callable[[int, int], None] | None = None) -> int:
        timed.append(sum(plan.timed for _, _, plan in predictor._missing(requests)))
        return solve(requests, progress)

    predictor.prefetch_many = counted
    diagnosis = diagnose([data], model, predictor, [RELAXATION], top=1)
    assert timed[0] == 0, "the first batch (the base's and the surrogate's replays) holds no timed replay"
    probe = model.with_effects({RELAXATION: first_points([EFFECTS[RELAXATION]], model)[0]})
    assert sum(timed) > 0 and predictor.missing([(probe, data.trajectories)]) == 0, "its refit began on its own replays"
    assert diagnosis.candidates[0].refit_parameters is not None


def _recording(time: np.ndarray, increment: np.ndarray) -> Recording:
    count = len(time)
    return Recording(
        time=time,
        joints=np.zeros((count, 7)),
        wrench=np.zeros((count, 6)),
        electrodes=np.zeros((count, 19)),
        pdc=np.zeros(count),
        depth_command=np.zeros(count),
        increment=increment,
        complete=False,
        message="stopped",
    )


def test_a_pose_reached_at_the_last_sample_is_solved_once_and_relaxes_nothing_yet() -> None:
    """A trajectory stopped as it reached a pose (one sample there, or one sample in all: found on a paper campaign,
    where the surrogate then failed) solves that pose once, and the relaxation's first-order response is defined
    there: nothing at a standoff out of contact."""
    single = _recording(np.array([3.0]), np.array([-1]))
    times, indices = solve_events(single, RELAXATION_SOLVE_INTERVAL_S)
    assert times.tolist() == [3.0] and indices.tolist() == [0]
    out_of_contact = np.zeros((1, 4))  # at the standoff the skin's modulus moves no reading
    assert np.array_equal(relaxation_response(single, out_of_contact, 1.0), out_of_contact)
    stopped = _recording(np.array([0.0, 0.5, 1.0, 1.5]), np.array([-1, -1, 0, 1]))
    times, indices = solve_events(stopped, RELAXATION_SOLVE_INTERVAL_S)
    assert indices[-1] == 2 and times[-1] == 1.5, "the last pose, reached at the last sample"
    assert np.all(np.isfinite(relaxation_response(stopped, np.ones((4, 4)), 1.0)))
