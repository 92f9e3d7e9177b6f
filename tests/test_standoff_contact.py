"""A press whose standoff pose already touches the skin: the recording is tared there, under load, and on a real
testbed the arm's move to it (not in the data) set the skin's friction state. `Predictor.standoff_force` tells it
from the model's fe; the nuisance stage names such presses (session 31)."""

import pytest

from twin.analysis.data import CampaignData, load_campaign
from twin.analysis.predict import Predictor, TwinModel
from twin.effects import REGISTRATION, registration_values
from twin.protocol import QUICK_SETTINGS

GAP_MARGIN = 0.3e-3
"""m: how far short of, or past, the standoff's gap the indenter is moved."""
LOADED_N = 0.01
"""A standoff force above this (the F/T noise, 1 sigma) is contact; a free indenter's is exactly zero."""


@pytest.fixture(scope="module")
def data(tmp_path_factory: pytest.TempPathFactory, make_tiny_campaign) -> CampaignData:
    return load_campaign(make_tiny_campaign(tmp_path_factory.mktemp("standoff")))


@pytest.mark.parametrize(
    "moved, loaded", [(QUICK_SETTINGS.standoff - GAP_MARGIN, False), (QUICK_SETTINGS.standoff + GAP_MARGIN, True)]
)
def test_a_press_starts_in_contact_exactly_when_its_indenter_is_moved_past_the_standoff_gap(
    data: CampaignData, moved: float, loaded: bool
) -> None:
    """The tiny campaign's normal press is tared `standoff` (1 mm) before the nominal skin, along the press. A model
    whose indenter is moved `moved` along the press finds the skin loaded there exactly when that exceeds the gap
    (geometry, not the code's own output); its nominal replay starts free."""
    normal = next(t for t in data.trajectories if t.normal)
    model = TwinModel(mesh_max_edge=data.mesh_max_edge)
    predictor = Predictor(workers=1)
    assert predictor.standoff_force(model, normal) == 0.0
    shifted = model.with_effects({REGISTRATION: registration_values(moved * normal.direction)})
    force = predictor.standoff_force(shifted, normal)
    assert (force > LOADED_N) == loaded, force
