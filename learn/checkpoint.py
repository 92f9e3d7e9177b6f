"""Checkpoints: a fitted estimator with what made it (training config, split, data hashes) and its metrics.

One file (torch.save of plain Python types and tensors, loadable with ``weights_only=True``)::

    {"format": FORMAT, "model": "pointnet" | "mlp" | "classical" | "mean", "state": estimator state,
     "training": {...}, "metrics": {...}}
"""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path

import torch

from assets.biotac import electrode_table
from learn.baselines import Classical, MeanPredictor
from learn.train import NETWORKS, NeuralEstimator, TrainConfig

FORMAT = "biotac-twin-learn/1"
MODELS = (*NETWORKS, "classical", "mean")

Estimator = NeuralEstimator | Classical | MeanPredictor


def make_estimator(model: str, config: TrainConfig | None = None) -> Estimator:
    """A fresh estimator by model name (MODELS); config applies to the networks."""
    if model in NETWORKS:
        base = config if config is not None else TrainConfig()
        return NeuralEstimator(TrainConfig(**{**base.__dict__, "network": model}))
    if model == "classical":
        return Classical()
    if model == "mean":
        return MeanPredictor()
    raise ValueError(f"unknown model {model!r}; choose one of {', '.join(MODELS)}")


@dataclass
class Checkpoint:
    """model: a MODELS name. training: files, per-file content hashes, split, seeds, node ids, config.
    metrics: the evaluation at training time (learn.experiment.evaluate's dict)."""

    model: str
    estimator: Estimator
    training: dict = field(default_factory=dict)
    metrics: dict = field(default_factory=dict)

    def save(self, path: str | Path) -> Path:
        path = Path(path)
        payload = {
            "format": FORMAT,
            "model": self.model,
            "state": self.estimator.get_state(),
            "training": self.training,
            "metrics": self.metrics,
        }
        tmp = path.with_name(path.name + ".tmp")
        torch.save(payload, tmp)
        tmp.replace(path)
        return path

    @classmethod
    def load(cls, path: str | Path) -> Checkpoint:
        payload = torch.load(Path(path), map_location="cpu", weights_only=True)
        if not isinstance(payload, dict) or payload.get("format") != FORMAT:
            raise ValueError(f"{path}: not a biotac-twin learn checkpoint ({FORMAT})")
        model, state = payload["model"], payload["state"]
        if model in NETWORKS:
            estimator = NeuralEstimator.from_state(state, electrode_table().positions)
        elif model == "classical":
            estimator = Classical.from_state(state)
        elif model == "mean":
            estimator = MeanPredictor.from_state(state)
        else:
            raise ValueError(f"{path}: unknown model {model!r}")
        return cls(model, estimator, payload["training"], payload["metrics"])
