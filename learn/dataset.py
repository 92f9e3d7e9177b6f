"""A torch Dataset of normalised electrode values and targets."""

from __future__ import annotations

import numpy as np
import torch
from torch.utils.data import Dataset

from learn.data import TactileData
from learn.normalize import MinMax


class ElectrodeDataset(Dataset):
    """Item i: ((19,) float32 scaled electrode values, {target: (d,) float32 scaled target}).

    Targets are flattened ((128, 3) nodal -> 384) and scaled by the given `MinMax` scalers (fitted on
    training data). Indexing with a LongTensor of rows returns a whole batch at once.
    """

    def __init__(self, data: TactileData, input_scale: MinMax, target_scales: dict[str, MinMax]) -> None:
        self.inputs = torch.as_tensor(input_scale.transform(data.electrodes), dtype=torch.float32)
        available = data.targets()
        missing = [k for k in target_scales if k not in available]
        if missing:
            raise ValueError(f"{data.source or data.sensor}: no {', '.join(missing)} targets in this data")
        self.targets = {
            k: torch.as_tensor(s.transform(available[k]).reshape(len(data), -1), dtype=torch.float32)
            for k, s in target_scales.items()
        }

    def __len__(self) -> int:
        return len(self.inputs)

    def __getitem__(self, rows: int | torch.Tensor | np.ndarray) -> tuple[torch.Tensor, dict[str, torch.Tensor]]:
        return self.inputs[rows], {k: v[rows] for k, v in self.targets.items()}
