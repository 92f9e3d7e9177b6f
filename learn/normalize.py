"""Min-max scaling to [0, 1] per component, fitted on training data (numpy only)."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np


@dataclass(frozen=True)
class MinMax:
    """x_scaled = (x - low) / span; span is 1 where a component is constant in the training data.

    low, span: arrays of the shape of one sample (e.g. (19,) or (128, 3)), in the data's units.
    """

    low: np.ndarray
    span: np.ndarray

    @classmethod
    def fit(cls, values: np.ndarray) -> MinMax:
        """Fit on (N, ...) training values."""
        if len(values) == 0:
            raise ValueError("MinMax.fit: no samples")
        low, high = values.min(axis=0), values.max(axis=0)
        span = high - low
        return cls(low=low, span=np.where(span > 0.0, span, 1.0))

    def transform(self, values: np.ndarray) -> np.ndarray:
        return (values - self.low) / self.span

    def inverse(self, scaled: np.ndarray) -> np.ndarray:
        return scaled * self.span + self.low

    def to_state(self) -> dict[str, list]:
        return {"low": self.low.tolist(), "span": self.span.tolist()}

    @classmethod
    def from_state(cls, state: dict[str, list]) -> MinMax:
        return cls(low=np.asarray(state["low"], dtype=float), span=np.asarray(state["span"], dtype=float))
