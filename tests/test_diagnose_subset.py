"""Ranking on a stratified subset of the trajectories (`twin diagnose --rank-per-stratum`, issue 18): the subset
takes every kind of press, and on a campaign with a hidden effect the subset's verdict is the full diagnosis's."""

from dataclasses import replace
from pathlib import Path
from types import SimpleNamespace

import pytest

from twin.analysis.data import load_campaign
from twin.analysis.diagnose import diagnose
from twin.analysis.predict import Predictor, TwinModel
from twin.analysis.subset import stratified, stratum
from twin.campaign import QUICK_CONFIG, run_campaign
from twin.demo import loop_setup

HIDDEN = "skin_thickness"
SEED = 5
CONFIG = replace(
    QUICK_CONFIG,
    sensors=(2,),
    indenters=("sphere_small", "cylinder_long"),
    settings=replace(QUICK_CONFIG.settings, points_per_indenter=2),
)
"""Two points per indenter, each pressed normal and angled: up to two trajectories of each of four strata (seed 5
keeps 7 of 8: a path the robot cannot run is dropped)."""


def _press(sensor: int, indenter: str, normal: bool, k: int) -> SimpleNamespace:
    return SimpleNamespace(sensor_id=sensor, indenter=indenter, normal=normal, trajectory_id=k)


def test_the_subset_takes_each_stratum_at_most_so_often_spread_over_it_in_order() -> None:
    presses = [_press(1, "a", k % 2 == 0, k) for k in range(10)] + [_press(2, "a", True, 10 + k) for k in range(3)]
    chosen = stratified(presses, 2)
    assert [t.trajectory_id for t in chosen] == [0, 1, 8, 9, 10, 12]  # first and last of each stratum, in order
    assert {stratum(t) for t in chosen} == {stratum(t) for t in presses}
    assert stratified(presses, 100) == presses
    assert [t.trajectory_id for t in stratified(presses, 1)] == [0, 1, 10]
    with pytest.raises(ValueError, match="at least 1"):
        stratified(presses, 0)


@pytest.fixture(scope="module")
def campaign(tmp_path_factory: pytest.TempPathFactory) -> Path:
    config, plant = loop_setup(HIDDEN, SEED, CONFIG)
    result = run_campaign(config, tmp_path_factory.mktemp("subset") / "campaign", workers=2, plant=plant)
    return next(iter(result.files.values()))


def test_ranking_on_one_trajectory_per_stratum_names_the_hidden_effect_as_the_full_diagnosis(campaign: Path) -> None:
    data = load_campaign(campaign)
    model = TwinModel(mesh_max_edge=data.mesh_max_edge)
    strata = {stratum(t) for t in data.trajectories}
    assert len(strata) == 4 and len(data.trajectories) >= 7  # the subset below: 4 of them (one may be dropped)
    predictor = Predictor()  # shared: the subset's replays are the full run's (same models, same paths)
    full = diagnose([data], model, predictor, top=1)
    subset = diagnose([data], model, predictor, top=1, rank_per_stratum=1)
    assert full.verdict == HIDDEN, full.reason
    assert subset.verdict == full.verdict, subset.reason
    assert full.ranked_on is None and full.to_dict()["ranked_on"] is None
    ranked_on = subset.to_dict()["ranked_on"]
    used = {(p["sensor"], p["trajectory"]) for p in ranked_on["trajectories"]}
    expected = (len(data.trajectories), 4, 1, 4)
    assert (ranked_on["of"], ranked_on["strata"], ranked_on["per_stratum"], len(used)) == expected
    by_id = {(t.sensor_id, t.trajectory_id): t for t in data.trajectories}
    assert {stratum(by_id[u]) for u in used} == strata
    # the named effect was refitted and judged held out on every trajectory: the same figures as the full run's
    named, full_named = subset.candidates[0], full.candidates[0]
    assert named.name == full_named.name == HIDDEN
    assert named.refit_rms == pytest.approx(full_named.refit_rms, rel=1e-6)
    assert named.heldout_rms == pytest.approx(full_named.heldout_rms, rel=1e-6)
    assert subset.base_rms == full.base_rms


def test_diagnosing_one_trajectory_per_stratum_names_the_hidden_effect_and_says_which(campaign: Path) -> None:
    """`per_stratum`: every stage on the sample alone (4 of the campaign's trajectories), the hidden effect named,
    and the same diagnosis as of a campaign that held only those trajectories."""
    data = load_campaign(campaign)
    model = TwinModel(mesh_max_edge=data.mesh_max_edge)
    predictor = Predictor()
    sample = diagnose([data], model, predictor, top=1, per_stratum=1)
    assert sample.verdict == HIDDEN, sample.reason
    on = sample.sampled
    assert on["of"] == len(data.trajectories) and on["strata"] == 4 and on["per_stratum"] == 1
    chosen = {(t.sensor_id, t.trajectory_id) for t in stratified(data.trajectories, 1)}
    assert {(t["sensor"], t["trajectory"]) for t in on["trajectories"]} == chosen and len(chosen) == 4
    alone = replace(data, trajectories=[t for t in data.trajectories if (t.sensor_id, t.trajectory_id) in chosen])
    direct = diagnose([alone], model, predictor, top=1)
    assert direct.base_rms == sample.base_rms and direct.verdict == sample.verdict
    assert sample.candidates[0].refit_parameters == direct.candidates[0].refit_parameters
