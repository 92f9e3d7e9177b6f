"""Learned forward model: FE nodal field -> 19 tared electrode values, fitted to a real sensor's data.

Features are physics: the log relative film impedance ``log z_e`` of each electrode from
`ElectrodeModel` (the user's skin mesh). The learned map is the physics read-out (voltage divider) with
a fitted gain ``g_e`` and load ratio ``lambda_e`` per electrode, plus a small MLP over all 19 features
for what the physics misses (cross-talk, nonlinearity); the MLP sees its inputs clipped to the training
range, so outside it only the physics extrapolates:

    tared_e = g_e * 4095 * (1 / (1 + lambda_e z_e) - 1 / (1 + lambda_e)) + MLP(log z)_e   (counts)

Fit it on pairs (FE nodal displacement of a trajectory sample, that sample's measured tared electrodes)
and the simulator speaks like that sensor: ``counts(vertices)``. Early stopping on 10 % held-out
trajectories. Torch is used for fitting and inference.
"""

from __future__ import annotations

import hashlib
from dataclasses import dataclass, field
from pathlib import Path

import h5py
import numpy as np
import torch
from torch import nn

from fe.electrodes import ADC_MAX, DEFAULT_SKIN_THICKNESS, ElectrodeModel
from learn.data import CHUNK_ROWS, N_ELECTRODES
from learn.nets import shared_mlp
from learn.normalize import MinMax
from learn.splits import contiguous

FORMAT = "biotac-twin-forward/1"


def physics_features(model: ElectrodeModel, vertices: np.ndarray) -> np.ndarray:
    """(19,) log relative impedance of each electrode for deformed mid-surface vertices (V, 3) m."""
    return np.log(model.relative_impedance(vertices))


@dataclass
class FieldSamples:
    """Training pairs: features (N, 19) log z, tared electrodes (N, 19) counts, trajectory (N,) ids."""

    features: np.ndarray
    electrodes: np.ndarray
    trajectory: np.ndarray

    def content_hash(self) -> str:
        """sha256 (hex) of the arrays."""
        h = hashlib.sha256()
        for a in (self.features, self.electrodes, self.trajectory):
            h.update(np.ascontiguousarray(a).tobytes())
        return h.hexdigest()

    def subset(self, rows: np.ndarray) -> FieldSamples:
        return FieldSamples(self.features[rows], self.electrodes[rows], self.trajectory[rows])


def campaign_field_samples(path: str | Path, skin_thickness: float = DEFAULT_SKIN_THICKNESS) -> FieldSamples:
    """Features and measured electrodes of a campaign file holding ``nodal_res`` and ``mesh``.

    skin_thickness: m, of the FE skin that produced the fields (the campaign's).
    """
    with h5py.File(path, "r") as f:
        if "nodal_res" not in f or "mesh" not in f:
            raise ValueError(f"{path}: needs nodal_res and mesh/ (a simulated campaign) to fit a forward model")
        reference = f["mesh/vertices"][:]
        model = ElectrodeModel.from_mesh(reference, f["mesh/triangles"][:], skin_thickness=skin_thickness)
        nodal = f["nodal_res/data"]
        features = np.empty((nodal.shape[0], N_ELECTRODES))
        for start in range(0, nodal.shape[0], CHUNK_ROWS):
            block = nodal[start : start + CHUNK_ROWS]
            features[start : start + len(block)] = [physics_features(model, reference + u) for u in block]
        return FieldSamples(features, f["electrode_vals/data"][:], f["trajectory_id/data"][:].astype(np.int64))


class _ForwardNet(nn.Module):
    """Divider read-out with fitted per-electrode gain and load ratio + bounded MLP residual (counts)."""

    def __init__(self, hidden: tuple[int, ...], feature_scale: MinMax, output_span: np.ndarray) -> None:
        super().__init__()
        self.raw_gain = nn.Parameter(torch.zeros(N_ELECTRODES))  # gain = exp(raw_gain), starts at 1
        self.raw_load = nn.Parameter(torch.zeros(N_ELECTRODES))  # load ratio = exp(raw_load), starts at 1
        last = nn.Linear(hidden[-1], N_ELECTRODES)
        nn.init.zeros_(last.weight)
        nn.init.zeros_(last.bias)
        self.mlp = nn.Sequential(shared_mlp(N_ELECTRODES, hidden), last)
        self.register_buffer("low", torch.as_tensor(feature_scale.low, dtype=torch.float32))
        self.register_buffer("span", torch.as_tensor(feature_scale.span, dtype=torch.float32))
        self.register_buffer("output_span", torch.as_tensor(output_span, dtype=torch.float32))

    def forward(self, log_z: torch.Tensor) -> torch.Tensor:
        """(B, 19) log relative impedances -> (B, 19) tared counts."""
        load = torch.exp(self.raw_load)
        divider = torch.exp(self.raw_gain) * ADC_MAX * (1.0 / (1.0 + load * torch.exp(log_z)) - 1.0 / (1.0 + load))
        within = ((log_z - self.low) / self.span).clamp(0.0, 1.0)  # residual never extrapolates
        return divider + self.output_span * self.mlp(within)


@dataclass
class ForwardModel:
    """Fitted map from physics features to tared counts. hidden: residual MLP widths.
    max_epochs / patience / learning_rate / seed / threads (torch CPU threads) control the fit."""

    hidden: tuple[int, ...] = (64, 64)
    max_epochs: int = 2000
    patience: int = 100
    learning_rate: float = 3e-3
    seed: int = 0
    threads: int = 1
    net: _ForwardNet | None = None
    history: list[float] = field(default_factory=list)

    def fit(self, samples: FieldSamples) -> ForwardModel:
        """Full-batch Adam on the squared error over each electrode's training range; keeps the best
        epoch on 10 % held-out trajectories."""
        torch.manual_seed(self.seed)
        torch.set_num_threads(self.threads)
        self.net = _ForwardNet(self.hidden, MinMax.fit(samples.features), MinMax.fit(samples.electrodes).span)
        if len(np.unique(samples.trajectory)) >= 4:
            train_rows, val_rows = contiguous(samples.trajectory, 0.1, self.seed)
        else:
            train_rows = val_rows = np.arange(len(samples.features))
        x = torch.as_tensor(samples.features, dtype=torch.float32)
        y = torch.as_tensor(samples.electrodes, dtype=torch.float32)

        def loss_on(rows: np.ndarray) -> torch.Tensor:
            return (((self.net(x[rows]) - y[rows]) / self.net.output_span) ** 2).mean()

        optimiser = torch.optim.Adam(self.net.parameters(), lr=self.learning_rate)
        best, best_state, stale = np.inf, None, 0
        self.history = []
        for _ in range(self.max_epochs):
            loss = loss_on(train_rows)
            optimiser.zero_grad()
            loss.backward()
            optimiser.step()
            with torch.no_grad():
                val = loss_on(val_rows).item()
            self.history.append(val)
            if val < best:
                best, stale = val, 0
                best_state = {k: v.clone() for k, v in self.net.state_dict().items()}
            else:
                stale += 1
                if stale >= self.patience:
                    break
        if best_state is not None:
            self.net.load_state_dict(best_state)
        return self

    def predict(self, features: np.ndarray) -> np.ndarray:
        """(N, 19) tared counts for (N, 19) physics features."""
        if self.net is None:
            raise RuntimeError("fit the forward model first")
        with torch.no_grad():
            return self.net(torch.as_tensor(np.atleast_2d(features), dtype=torch.float32)).numpy().astype(float)

    def save(self, path: str | Path, training: dict | None = None) -> Path:
        """Write the fitted model (torch.save of plain types and tensors) with a training record."""
        if self.net is None:
            raise RuntimeError("fit the forward model first")
        payload = {
            "format": FORMAT,
            "hidden": list(self.hidden),
            "state_dict": self.net.state_dict(),
            "training": training or {},
        }
        path = Path(path)
        torch.save(payload, path)
        return path

    @classmethod
    def load(cls, path: str | Path) -> tuple[ForwardModel, dict]:
        """The model saved by `save` and its training record."""
        payload = torch.load(Path(path), map_location="cpu", weights_only=True)
        if not isinstance(payload, dict) or payload.get("format") != FORMAT:
            raise ValueError(f"{path}: not a forward-model file ({FORMAT})")
        model = cls(hidden=tuple(payload["hidden"]))
        blank = MinMax(np.zeros(N_ELECTRODES), np.ones(N_ELECTRODES))  # buffers come from the state dict
        model.net = _ForwardNet(model.hidden, blank, np.ones(N_ELECTRODES))
        model.net.load_state_dict(payload["state_dict"])
        return model, payload["training"]

    def counts(self, physics: ElectrodeModel, vertices: np.ndarray) -> np.ndarray:
        """(19,) tared counts this sensor would read for deformed mid-surface vertices (V, 3) m."""
        return self.predict(physics_features(physics, vertices))[0]


def fit_and_score(
    samples: FieldSamples, test_fraction: float = 0.2, seed: int = 0, model: ForwardModel | None = None
) -> tuple[ForwardModel, dict[str, float]]:
    """Fit on a contiguous (by trajectory) training split, score RMSE (counts) on the rest.

    Returns the model and {"rmse_counts", "mean_predictor_rmse_counts", "n_train", "n_test"}.
    """
    train_rows, test_rows = contiguous(samples.trajectory, test_fraction, seed)
    fitted = (model if model is not None else ForwardModel(seed=seed)).fit(samples.subset(train_rows))
    truth = samples.electrodes[test_rows]
    rmse = float(np.sqrt(np.mean((fitted.predict(samples.features[test_rows]) - truth) ** 2)))
    mean = float(np.sqrt(np.mean((samples.electrodes[train_rows].mean(axis=0) - truth) ** 2)))
    return fitted, {
        "rmse_counts": rmse,
        "mean_predictor_rmse_counts": mean,
        "n_train": len(train_rows),
        "n_test": len(test_rows),
    }
