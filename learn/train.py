"""Training of the torch estimators (PointNet++ and the plain MLP) with early stopping.

`NeuralEstimator` follows the API of learn.baselines: ``fit(data) -> self``, ``predict(data)``,
``get_state()`` / ``from_state()``. Targets are min-max scaled to [0, 1] on the training data (the
paper's normalisation), the loss is the sum over targets of the mean squared scaled error, and the
best epoch on a held-out 10 % of the training *trajectories* is kept (never the test data).
Fine-tuning (``fit(data, init=pretrained)``) starts from a pretrained estimator's weights and scalers.
"""

from __future__ import annotations

import copy
import time
from collections.abc import Callable
from dataclasses import asdict, dataclass, field

import numpy as np
import torch
from torch import nn

from learn.data import TactileData
from learn.dataset import ElectrodeDataset
from learn.metrics import ANGLE_MIN_FORCE
from learn.nets import PlainMLP, PointNet2
from learn.normalize import MinMax
from learn.splits import contiguous

TARGETS = ("contact_loc", "force", "nodal")
NETWORKS = ("pointnet", "mlp")
DEVICES = ("auto", "cpu", "cuda")


@dataclass(frozen=True)
class TrainConfig:
    """How to train. network: "pointnet" | "mlp". targets: any of TARGETS the data has.
    max_epochs / patience (epochs without validation improvement) / time_limit_s (s) stop training;
    learning_rate halves after lr_patience epochs without improvement. threads: torch CPU threads.
    device: "cpu", "cuda" or "auto" (cuda when torch sees a GPU, else cpu). scale_tail: inputs and
    targets are scaled so that the scale_tail and 1 - scale_tail quantiles of the training rows map to
    0 and 1 (0: min-max, the paper's; 0.01 by default: a 1 % tail of bottoming-out rows at 20-50 N
    otherwise sets the force span and the loss neglects the ~1 N bulk, docs/learn.md).
    angle_weight: weight of the force-direction term of the loss, the mean of 1 - cos(angle between
    predicted and true force) over rows with |F_true| >= metrics.ANGLE_MIN_FORCE (0: no such term;
    0.1 by default: with it PointNet++ went from 0.46 to 0.20 rad on the FE campaign, docs/learn.md).
    magnitude_weight: weight of the force-magnitude term, the mean of ((|F_pred| - |F_true|) /
    (|F_true| + ANGLE_MIN_FORCE))^2 over all rows: relative, so a min-max span set by a few 50 N rows
    does not hide errors of the ~1 N bulk (0: no such term)."""

    network: str = "pointnet"
    targets: tuple[str, ...] = TARGETS
    max_epochs: int = 300
    batch_size: int = 128
    learning_rate: float = 1e-3
    lr_patience: int = 5
    patience: int = 15
    val_fraction: float = 0.1
    time_limit_s: float = float("inf")
    seed: int = 0
    threads: int = 2
    device: str = "auto"
    scale_tail: float = 0.01
    angle_weight: float = 0.1
    magnitude_weight: float = 0.0

    def __post_init__(self) -> None:
        if self.network not in NETWORKS:
            raise ValueError(f"unknown network {self.network!r}; choose one of {', '.join(NETWORKS)}")
        unknown = set(self.targets) - set(TARGETS)
        if unknown or not self.targets:
            raise ValueError(f"targets must be a non-empty subset of {TARGETS}, got {self.targets}")
        if self.device not in DEVICES:
            raise ValueError(f"unknown device {self.device!r}; choose one of {', '.join(DEVICES)}")


def resolve_device(device: str) -> str:
    """The torch device ("cuda" or "cpu") a TrainConfig.device names ("auto": cuda when torch sees a GPU)."""
    if device == "auto":
        return "cuda" if torch.cuda.is_available() else "cpu"
    return device


@dataclass
class EpochRecord:
    epoch: int
    train_loss: float
    val_loss: float
    seconds: float


def _build(network: str, target_dims: dict[str, int], positions: np.ndarray) -> nn.Module:
    return PointNet2(positions, target_dims) if network == "pointnet" else PlainMLP(len(positions), target_dims)


@dataclass
class NeuralEstimator:
    """A trained network with the scalers that map its inputs and outputs to SI units."""

    config: TrainConfig = field(default_factory=TrainConfig)
    net: nn.Module | None = None
    input_scale: MinMax | None = None
    target_scales: dict[str, MinMax] = field(default_factory=dict)
    target_shapes: dict[str, tuple[int, ...]] = field(default_factory=dict)
    history: list[EpochRecord] = field(default_factory=list)
    _force_affine: tuple | None = field(default=None, repr=False)

    @property
    def name(self) -> str:
        return self.config.network

    def _loss(self, batch: tuple[torch.Tensor, dict[str, torch.Tensor]]) -> torch.Tensor:
        x, y = batch
        out = self.net(x)
        loss = sum(nn.functional.mse_loss(out[k], y[k]) for k in y)
        cfg = self.config
        if "force" in y and (cfg.angle_weight > 0.0 or cfg.magnitude_weight > 0.0):
            pred, true = self._newtons(out["force"]), self._newtons(y["force"])
            if cfg.angle_weight > 0.0:
                loss = loss + cfg.angle_weight * self._angle_loss(pred, true)
            if cfg.magnitude_weight > 0.0:
                size = true.norm(dim=1)
                relative = (pred.norm(dim=1) - size) / (size + ANGLE_MIN_FORCE)
                loss = loss + cfg.magnitude_weight * (relative**2).mean()
        return loss

    def _newtons(self, scaled: torch.Tensor) -> torch.Tensor:
        """(B, 3) N: scaled force targets or outputs mapped back to newtons (differentiable). The scaler
        is copied to the device once per device and dtype, not once per batch."""
        key = (scaled.device, scaled.dtype)
        if self._force_affine is None or self._force_affine[0] != key:
            scale = self.target_scales["force"]
            low, span = (torch.as_tensor(v, dtype=scaled.dtype, device=scaled.device) for v in (scale.low, scale.span))
            self._force_affine = (key, low, span)
        _, low, span = self._force_affine
        return scaled * span + low

    @staticmethod
    def _angle_loss(pred: torch.Tensor, true: torch.Tensor) -> torch.Tensor:
        """Mean 1 - cos of the angle between predicted and true forces (B, 3) N over rows with |F_true| >=
        ANGLE_MIN_FORCE; zero when a batch has none (no host synchronisation: a mask, not a branch)."""
        keep = (true.norm(dim=1) >= ANGLE_MIN_FORCE).to(pred.dtype)
        cos = nn.functional.cosine_similarity(pred, true, dim=1, eps=1e-6)
        return (keep * (1.0 - cos)).sum() / keep.sum().clamp(min=1.0)

    def _evaluate(self, dataset: ElectrodeDataset, device: torch.device) -> float:
        self.net.eval()
        with torch.no_grad():
            x, y = dataset[torch.arange(len(dataset))]
            loss = self._loss((x.to(device), {k: v.to(device) for k, v in y.items()}))
        self.net.train()
        return float(loss)

    def fit(
        self,
        data: TactileData,
        init: NeuralEstimator | None = None,
        on_epoch: Callable[[EpochRecord], None] | None = None,
    ) -> NeuralEstimator:
        """Train on ``data``; with ``init``, fine-tune a copy of its network (its scalers are kept).
        on_epoch: called with each epoch's record (progress display)."""
        cfg = self.config
        torch.manual_seed(cfg.seed)
        torch.set_num_threads(cfg.threads)
        device = torch.device(resolve_device(cfg.device))
        available = data.targets()
        targets = [k for k in cfg.targets if k in available]
        if not targets:
            raise ValueError(f"the data has none of the targets {cfg.targets}")
        if init is not None:
            self.input_scale, self.target_scales = init.input_scale, dict(init.target_scales)
            self.target_shapes, self.net = dict(init.target_shapes), copy.deepcopy(init.net)
        else:
            self.input_scale = MinMax.fit_quantile(data.electrodes, cfg.scale_tail)
            self.target_scales = {k: MinMax.fit_quantile(available[k], cfg.scale_tail) for k in targets}
            self.target_shapes = {k: available[k].shape[1:] for k in targets}
            dims = {k: int(np.prod(s)) for k, s in self.target_shapes.items()}
            self.net = _build(cfg.network, dims, data.electrode_positions)
        self.net.to(device)
        self._force_affine = None
        train_rows, val_rows = self._validation_rows(data)
        train = ElectrodeDataset(data.subset(train_rows), self.input_scale, self.target_scales)
        val = ElectrodeDataset(data.subset(val_rows), self.input_scale, self.target_scales) if len(val_rows) else train
        self._train_loop(train, val, device, on_epoch)
        self.net.to("cpu")
        return self

    def _validation_rows(self, data: TactileData) -> tuple[np.ndarray, np.ndarray]:
        if len(np.unique(data.trajectory)) < 4:
            return np.arange(len(data)), np.array([], dtype=np.int64)
        return contiguous(data.trajectory, self.config.val_fraction, self.config.seed + 1)

    def _train_loop(
        self,
        train: ElectrodeDataset,
        val: ElectrodeDataset,
        device: torch.device,
        on_epoch: Callable[[EpochRecord], None] | None,
    ) -> None:
        cfg = self.config
        optimiser = torch.optim.Adam(self.net.parameters(), lr=cfg.learning_rate)
        scheduler = torch.optim.lr_scheduler.ReduceLROnPlateau(optimiser, factor=0.5, patience=cfg.lr_patience)
        inputs = train.inputs.to(device)
        targets = {k: v.to(device) for k, v in train.targets.items()}
        best, best_state, stale, start = np.inf, None, 0, time.perf_counter()
        generator = torch.Generator().manual_seed(cfg.seed)
        self.history = []
        for epoch in range(cfg.max_epochs):
            total = 0.0
            for rows in torch.randperm(len(train), generator=generator).split(cfg.batch_size):
                if len(rows) < 2:  # batch norm needs two samples
                    continue
                rows = rows.to(device)
                loss = self._loss((inputs[rows], {k: v[rows] for k, v in targets.items()}))
                optimiser.zero_grad()
                loss.backward()
                optimiser.step()
                total += loss.item() * len(rows)
            val_loss = self._evaluate(val, device)
            scheduler.step(val_loss)
            elapsed = time.perf_counter() - start
            self.history.append(EpochRecord(epoch, total / len(train), val_loss, elapsed))
            if on_epoch is not None:
                on_epoch(self.history[-1])
            if val_loss < best:
                best, stale = val_loss, 0
                best_state = {k: v.detach().clone() for k, v in self.net.state_dict().items()}
            else:
                stale += 1
            if stale >= cfg.patience or elapsed > cfg.time_limit_s:
                break
        if best_state is not None:
            self.net.load_state_dict(best_state)

    def predict(self, data: TactileData, batch_size: int = 4096, device: str = "cpu") -> dict[str, np.ndarray]:
        """Targets in SI units: contact_loc (N, 3) m, force (N, 3) N, nodal (N, K, 3) m."""
        if self.net is None:
            raise RuntimeError("fit the estimator first")
        self.net.to(device).eval()
        x = torch.as_tensor(self.input_scale.transform(data.electrodes), dtype=torch.float32, device=device)
        with torch.no_grad():
            parts = [self.net(chunk) for chunk in x.split(batch_size)]
        self.net.to("cpu")
        out = {}
        for k, scale in self.target_scales.items():
            scaled = torch.cat([p[k] for p in parts]).cpu().numpy().astype(float)
            out[k] = scale.inverse(scaled.reshape(len(data), *self.target_shapes[k]))
        return out

    def get_state(self) -> dict:
        return {
            "config": asdict(self.config),
            "state_dict": self.net.state_dict(),
            "input_scale": self.input_scale.to_state(),
            "target_scales": {k: s.to_state() for k, s in self.target_scales.items()},
            "target_shapes": {k: list(s) for k, s in self.target_shapes.items()},
            "history": [asdict(h) for h in self.history],
        }

    @classmethod
    def from_state(cls, state: dict, positions: np.ndarray) -> NeuralEstimator:
        """Rebuild from ``get_state()``; positions: (19, 3) m electrode positions (the manual's table)."""
        cfg = state["config"]
        config = TrainConfig(**{**cfg, "targets": tuple(cfg["targets"])})
        shapes = {k: tuple(s) for k, s in state["target_shapes"].items()}
        net = _build(config.network, {k: int(np.prod(s)) for k, s in shapes.items()}, positions)
        net.load_state_dict(state["state_dict"])
        return cls(
            config=config,
            net=net,
            input_scale=MinMax.from_state(state["input_scale"]),
            target_scales={k: MinMax.from_state(s) for k, s in state["target_scales"].items()},
            target_shapes=shapes,
            history=[EpochRecord(**h) for h in state["history"]],
        )
