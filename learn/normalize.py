"""Min-max scaling to [0, 1] per component, fitted on training data (numpy only).

``MinMax.fit`` spans the training extremes (the paper's normalisation); ``MinMax.fit_quantile`` spans a
central quantile range instead, so a few extreme rows (a skin bottoming out on the core at 20-50 N) do
not squeeze the bulk of the data into a sliver of [0, 1]; values outside the range map outside [0, 1].
"""

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

    @classmethod
    def fit_quantile(cls, values: np.ndarray, tail: float) -> MinMax:
        """Fit on (N, ...) training values so that the ``tail`` and ``1 - tail`` quantiles map to 0 and 1."""
        if len(values) == 0:
            raise ValueError("MinMax.fit_quantile: no samples")
        if not 0.0 <= tail < 0.5:
            raise ValueError(f"MinMax.fit_quantile: tail must be in [0, 0.5), got {tail}")
        low, high = np.quantile(values, [tail, 1.0 - tail], axis=0)
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
