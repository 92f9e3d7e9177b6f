"""Inflated BioTac fe models, built and checked in one place.

Light on purpose (assets and fe only): the environments and views build their model here without
importing the campaign's dataset stack (h5py), and the campaign and the model replays build theirs the same
way. Two inflation rules: "thickness" (fill until the sensor is 15.1 mm thick, the twin's default) or
"thermal" (the paper's rule: the fluid expands from the reference to `SkinParameters.fluid_temperature`).
"""

from __future__ import annotations

from functools import lru_cache

from assets.biotac import BioTacGeometry, make_biotac
from fe.params import SkinParameters
from fe.sensor import SENSOR_THICKNESS, BioTacModel, InflationResult

INFLATION_RULES = ("thickness", "thermal")
"""How a model's skin is inflated (see the module docstring)."""


def inflated_model(geometry: BioTacGeometry, params: SkinParameters) -> BioTacModel:
    """A BioTac fe model inflated to the sensor's 15.1 mm thickness; raises if inflation fails."""
    model = BioTacModel(geometry, params)
    result = model.inflate()
    if not result.converged:
        raise RuntimeError(f"inflation did not converge: {result.message}")
    return model


def inflated_fe_model(
    skin: SkinParameters, mesh_max_edge: float, inflation: str = "thickness"
) -> tuple[BioTacModel, InflationResult]:
    """A BioTac fe model of `skin` meshed at `mesh_max_edge` (m) and inflated by the rule `inflation` (see the
    module docstring), with its InflationResult (which says whether it converged)."""
    model = BioTacModel(make_biotac(mesh_max_edge), skin)
    return model, model.inflate(SENSOR_THICKNESS if inflation == "thickness" else None)


@lru_cache(maxsize=4)
def shared_model(mesh_mm: float) -> BioTacModel:
    """An inflated nominal BioTac fe model with `mesh_mm` (mm) largest edges, built once per process (the
    environments' and the views' model)."""
    if not 0.3 <= mesh_mm <= 5.0:
        raise ValueError(f"mesh_mm must be in [0.3, 5] mm, got {mesh_mm!r}")
    return inflated_model(make_biotac(mesh_mm * 1e-3), SkinParameters())
