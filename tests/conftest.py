"""Shared fixtures: a coarse inflated BioTac (2 mm mesh) reused across FE tests."""

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
