"""Shared fixtures: a coarse inflated BioTac (2 mm mesh) reused across FE tests; a tiny campaign."""

from dataclasses import replace
from pathlib import Path

import pytest

from assets.biotac import make_biotac
from fe.params import SkinParameters
from fe.sensor import BioTacModel


def inflated_biotac(**params: float) -> BioTacModel:
    """A coarse (2 mm edges) BioTac model inflated to 15.1 mm."""
    model = BioTacModel(make_biotac(max_edge=2e-3), SkinParameters(**params))
    result = model.inflate()
    assert result.converged, result.message
    return model


@pytest.fixture(scope="session")
def frictionless_biotac() -> BioTacModel:
    return inflated_biotac(friction=0.0)


@pytest.fixture(scope="session")
def frictional_biotac() -> BioTacModel:
    return inflated_biotac(friction=0.5)


def tiny_campaign_file(
    out: Path,
    plant=None,
    angled_depth: float = 0.2e-3,
    normal_depth: float = 0.4e-3,
    pause_s: float = 0.1,
    indenter: str = "sphere_medium",
) -> Path:
    """Sensor 2, `indenter`, one normal (`normal_depth` m) and one angled (`angled_depth` m) trajectory,
    `pause_s` pauses, 2 mm mesh; `plant` as in twin.campaign.run_campaign (None: the default plant)."""
    from twin.campaign import QUICK_CONFIG, run_campaign
    from twin.protocol import QUICK_SETTINGS

    settings = replace(QUICK_SETTINGS, normal_depth=normal_depth, angled_depth=angled_depth, pause_s=pause_s)
    config = replace(QUICK_CONFIG, sensors=(2,), indenters=(indenter,), settings=settings)
    return run_campaign(config, out, workers=1, plant=plant).files[2]


@pytest.fixture(scope="session")
def make_tiny_campaign():
    """`tiny_campaign_file`, for module fixtures that build their own tiny campaign."""
    return tiny_campaign_file
