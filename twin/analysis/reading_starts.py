"""`ft_saturation`'s data-driven start (`twin.analysis.sensitivity.DATA_STARTS`): each axis whose raw readings
hold their largest magnitude on a plateau (`twin.analysis.readings.plateaus`) starts with its limit there; no fe
replay. Unclipped readings have no plateau: the start is then None and the effect is linearised at its off value
only."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from twin.analysis.predict import Predictor, TwinModel
from twin.analysis.readings import Plateaus, force_readings, plateaus
from twin.analysis.residual import Base
from twin.effects import EFFECTS, FORCE_AXES


@dataclass(frozen=True)
class RangeEstimate:
    """The plateaus of a campaign's raw force readings, as a start of `ft_saturation`."""

    found: Plateaus

    def start(self, current: dict[str, float]) -> dict[str, float] | None:
        """`current` with each clipped axis's limit at its plateau; None when no axis clips."""
        if not self.found.clipped.any():
            return None
        bounds = {p.name: (p.lower, p.upper) for p in EFFECTS["ft_saturation"].parameters}
        out = dict(current)
        for axis, largest, clipped in zip(FORCE_AXES, self.found.largest, self.found.clipped, strict=True):
            if clipped:
                out[axis] = float(np.clip(largest, *bounds[axis]))
        return out

    def estimate(self, current: dict[str, float]) -> dict[str, float] | None:
        """The start (`start`): a limit where an axis clips, none otherwise."""
        return self.start(current)

    def to_dict(self) -> dict:
        return {
            "largest_reading_n": [float(v) for v in self.found.largest],
            "samples_at_largest": [int(v) for v in self.found.held],
            "clipped_axes": [axis for axis, c in zip(FORCE_AXES, self.found.clipped, strict=True) if c],
        }


def range_start(predictor: Predictor, model: TwinModel, base: Base) -> RangeEstimate:
    """`ft_saturation`'s data-driven start (`DATA_STARTS`): the plateaus of `base`'s raw readings."""
    return RangeEstimate(plateaus(force_readings(base.trajectories)))
