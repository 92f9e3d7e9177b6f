"""Inflated BioTac fe models, built and checked in one place.

Light on purpose (assets and fe only): the environments and views build their model here without
importing the campaign's dataset stack (h5py), and the campaign builds its own the same way.
"""

from __future__ import annotations

from assets.biotac import BioTacGeometry
from fe.params import SkinParameters
from fe.sensor import BioTacModel


def inflated_model(geometry: BioTacGeometry, params: SkinParameters) -> BioTacModel:
    """A BioTac fe model inflated to the sensor's 15.1 mm thickness; raises if inflation fails."""
    model = BioTacModel(geometry, params)
    result = model.inflate()
    if not result.converged:
        raise RuntimeError(f"inflation did not converge: {result.message}")
    return model
