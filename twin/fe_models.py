"""Inflated BioTac fe models, built and checked in one place.

Light on purpose (assets and fe only): the environments and views build their model here without
importing the campaign's dataset stack (h5py), and the campaign and the model replays build theirs the same
way. Two inflation rules: "thickness" (fill until the sensor is 15.1 mm thick, the twin's default) or
"thermal" (the paper's rule: the fluid expands from the reference to `SkinParameters.fluid_temperature`).
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import asdict

from assets.biotac import BioTacGeometry, make_biotac
from assets.refine import Refinement
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
    skin: SkinParameters, mesh_max_edge: float, inflation: str = "thickness", refinement: Refinement | None = None
) -> tuple[BioTacModel, InflationResult]:
    """A BioTac fe model of `skin` meshed at `mesh_max_edge` (m), finer about a press point with a `refinement`,
    and inflated by the rule `inflation` (see the module docstring), with its InflationResult (which says
    whether it converged)."""
    model = BioTacModel(make_biotac(mesh_max_edge, refinement=refinement), skin)
    return model, model.inflate(SENSOR_THICKNESS if inflation == "thickness" else None)


class ModelCache:
    """Inflated fe models keyed by (skin, mesh, inflation rule), each built once (`inflated_fe_model`, with its
    InflationResult, converged or not); beyond `size` models the oldest is dropped and `on_drop(model)` told, so
    that whoever keeps data by model identity can forget it. The one model cache: the model replays keep one
    (`twin.analysis.predict.Predictor`), and `shared_model` is the process's nominal one."""

    def __init__(self, size: int, on_drop: Callable[[BioTacModel], None] | None = None) -> None:
        if size < 1:
            raise ValueError(f"a model cache holds at least one model, got size={size!r}")
        self.size, self.on_drop = size, on_drop
        self._entries: dict[tuple, tuple[BioTacModel, InflationResult]] = {}

    def get(
        self, skin: SkinParameters, mesh_max_edge: float, inflation: str = "thickness"
    ) -> tuple[BioTacModel, InflationResult]:
        """(fe model, its InflationResult) of `skin` meshed at `mesh_max_edge` (m), inflated by `inflation`."""
        key = (tuple(sorted(asdict(skin).items())), mesh_max_edge, inflation)
        if key not in self._entries:
            built = inflated_fe_model(skin, mesh_max_edge, inflation)
            if len(self._entries) >= self.size:
                dropped = self._entries.pop(next(iter(self._entries)))[0]
                if self.on_drop is not None:
                    self.on_drop(dropped)
            self._entries[key] = built
        return self._entries[key]


_NOMINAL = ModelCache(4)
"""The process's nominal models (`shared_model`)."""


def shared_model(mesh_mm: float) -> BioTacModel:
    """An inflated nominal BioTac fe model with `mesh_mm` (mm) largest edges, built once per process (the
    environments' and the views' model)."""
    if not 0.3 <= mesh_mm <= 5.0:
        raise ValueError(f"mesh_mm must be in [0.3, 5] mm, got {mesh_mm!r}")
    model, result = _NOMINAL.get(SkinParameters(), mesh_mm * 1e-3)
    if not result.converged:
        raise RuntimeError(f"inflation did not converge: {result.message}")
    return model
