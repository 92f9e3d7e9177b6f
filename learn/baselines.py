"""Classical estimators from the literature, and the mean predictor (numpy only).

All follow one small API: ``fit(data) -> self``, ``predict(data) -> {target: array}`` (SI units,
biotac frame), ``get_state() -> dict`` / ``from_state(state)`` for checkpoints. Inputs are tared
electrode values; a *drop* (negative tared value) is where the skin approaches an electrode.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from learn.data import TactileData
from learn.metrics import location_errors

RADIUS_GRID = np.arange(5.0e-3, 11.01e-3, 0.25e-3)
"""Skin-model radii (m) the weighted centroid searches."""
POWER_GRID = (1.0, 2.0, 3.0)
"""Weight exponents the weighted centroid searches."""
RIDGE = 1e-6
"""Relative ridge regularisation of the weighted-sum least squares."""


def project_to_skin_model(points: np.ndarray, radius: float) -> np.ndarray:
    """(N, 3) m: points pushed radially onto the public simple skin model (facts/biotac.md): a sphere of
    ``radius`` about the origin for x > 0 joined to a cylinder of ``radius`` about the x axis for x <= 0."""
    out = points.copy()
    tip = points[:, 0] > 0.0
    norm_tip = np.maximum(np.linalg.norm(points[tip], axis=1, keepdims=True), 1e-12)
    out[tip] = radius * points[tip] / norm_tip
    side = ~tip
    norm_side = np.maximum(np.linalg.norm(points[side, 1:], axis=1, keepdims=True), 1e-12)
    out[side, 1:] = radius * points[side, 1:] / norm_side
    return out


@dataclass
class MeanPredictor:
    """Predicts the training mean of every target: the floor any model must beat."""

    means: dict[str, np.ndarray] = field(default_factory=dict)
    name: str = "mean"

    def fit(self, data: TactileData) -> MeanPredictor:
        self.means = {k: v.mean(axis=0) for k, v in data.targets().items()}
        return self

    def predict(self, data: TactileData) -> dict[str, np.ndarray]:
        return {k: np.broadcast_to(m, (len(data), *m.shape)).copy() for k, m in self.means.items()}

    def get_state(self) -> dict:
        return {k: v.tolist() for k, v in self.means.items()}

    @classmethod
    def from_state(cls, state: dict) -> MeanPredictor:
        return cls(means={k: np.asarray(v, dtype=float) for k, v in state.items()})


def weighted_centroid(electrodes: np.ndarray, positions: np.ndarray, radius: float, power: float) -> np.ndarray:
    """(N, 3) m: centroid of the electrodes (projected on the skin model) weighted by drop^power, then
    projected on the skin model (Wettels 2011, Lin 2013). Rows without any drop give NaN."""
    weights = np.maximum(-electrodes, 0.0) ** power
    total = weights.sum(axis=1, keepdims=True)
    with np.errstate(invalid="ignore", divide="ignore"):
        centroid = weights @ project_to_skin_model(positions, radius) / total
    return project_to_skin_model(centroid, radius)


@dataclass
class WeightedCentroid:
    """Contact location by weighted centroid; radius and weight exponent fitted on training data."""

    radius: float = 7.0e-3
    power: float = 1.0
    fallback: np.ndarray = field(default_factory=lambda: np.zeros(3))
    name: str = "weighted_centroid"

    def fit(self, data: TactileData) -> WeightedCentroid:
        if data.contact_loc is None:
            raise ValueError("WeightedCentroid needs contact_loc targets")
        self.fallback = data.contact_loc.mean(axis=0)
        best = np.inf
        for power in POWER_GRID:
            for radius in RADIUS_GRID:
                self.radius, self.power = float(radius), power
                err = location_errors(self.predict(data)["contact_loc"], data.contact_loc).mean()
                if err < best:
                    best, chosen = err, (float(radius), power)
        self.radius, self.power = chosen
        return self

    def predict(self, data: TactileData) -> dict[str, np.ndarray]:
        loc = weighted_centroid(data.electrodes, data.electrode_positions, self.radius, self.power)
        loc[~np.all(np.isfinite(loc), axis=1)] = self.fallback
        return {"contact_loc": loc}

    def get_state(self) -> dict:
        return {"radius": self.radius, "power": self.power, "fallback": self.fallback.tolist()}

    @classmethod
    def from_state(cls, state: dict) -> WeightedCentroid:
        return cls(radius=state["radius"], power=state["power"], fallback=np.asarray(state["fallback"]))


@dataclass
class WeightedSumForce:
    """Force as a weighted sum of electrode normals, F = sum_e s_e * value_e * n_e (Su 2012); the 19
    scales s_e (N per count) by ridge least squares on training data."""

    scales: np.ndarray = field(default_factory=lambda: np.zeros(19))
    name: str = "weighted_sum"

    def _design(self, data: TactileData) -> np.ndarray:
        """(N, 3, 19): value_e * n_e for each sample."""
        return data.electrodes[:, None, :] * data.electrode_normals.T[None]

    def fit(self, data: TactileData) -> WeightedSumForce:
        if data.force is None:
            raise ValueError("WeightedSumForce needs force targets")
        a = self._design(data).reshape(-1, 19)
        gram = a.T @ a
        gram += RIDGE * np.trace(gram) / 19 * np.eye(19)
        self.scales = np.linalg.solve(gram, a.T @ data.force.ravel())
        return self

    def predict(self, data: TactileData) -> dict[str, np.ndarray]:
        return {"force": self._design(data) @ self.scales}

    def get_state(self) -> dict:
        return {"scales": self.scales.tolist()}

    @classmethod
    def from_state(cls, state: dict) -> WeightedSumForce:
        return cls(scales=np.asarray(state["scales"], dtype=float))


@dataclass
class Classical:
    """The literature's pair side by side: weighted-centroid location + weighted-sum force."""

    location: WeightedCentroid = field(default_factory=WeightedCentroid)
    force: WeightedSumForce = field(default_factory=WeightedSumForce)
    name: str = "classical"

    def fit(self, data: TactileData) -> Classical:
        if data.contact_loc is not None:
            self.location.fit(data)
        if data.force is not None:
            self.force.fit(data)
        return self

    def predict(self, data: TactileData) -> dict[str, np.ndarray]:
        return self.location.predict(data) | self.force.predict(data)

    def get_state(self) -> dict:
        return {"location": self.location.get_state(), "force": self.force.get_state()}

    @classmethod
    def from_state(cls, state: dict) -> Classical:
        return cls(WeightedCentroid.from_state(state["location"]), WeightedSumForce.from_state(state["force"]))
