"""BioTac inflation to the 15.1 mm sensor thickness is mesh-independent (it used to stall on some meshes)."""

import numpy as np
import pytest

from assets.biotac import make_biotac
from fe.sensor import SENSOR_THICKNESS, BioTacModel


@pytest.fixture(scope="module")
def inflations() -> dict[float, tuple]:
    out = {}
    for edge in (2e-3, 1.5e-3, 1e-3):
        model = BioTacModel(make_biotac(max_edge=edge))
        out[edge] = (model, model.inflate())
    return out


def test_inflation_converges_on_every_mesh(inflations: dict[float, tuple]) -> None:
    for model, result in inflations.values():
        assert result.converged, result.message
        assert result.thickness == pytest.approx(SENSOR_THICKNESS, abs=1e-6)
        assert model.thickness(model.reference) == pytest.approx(SENSOR_THICKNESS, abs=1e-6)


def test_inflation_pressure_and_volume_agree_across_meshes(inflations: dict[float, tuple]) -> None:
    pressures = np.array([inflations[h][1].pressure for h in (2e-3, 1.5e-3, 1e-3)])
    volumes = np.array([inflations[h][1].volume_change for h in (2e-3, 1.5e-3, 1e-3)])
    # A pressurised membrane: tens of kPa for ~0.4 cm^3 of added fluid, the pressure the same on every mesh
    # to a few %. The added volume also absorbs each mesh's faceting of the unpressurised cavity.
    assert np.all((pressures > 2e4) & (pressures < 6e4))
    assert np.ptp(pressures) <= 0.08 * pressures[-1]
    assert np.ptp(volumes) <= 0.15 * volumes[-1]
