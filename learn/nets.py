"""Torch networks from electrode values to normalised targets: PointNet++-style and a plain MLP.

Both take (B, 19) normalised electrode values and return a dict of (B, d) normalised predictions, one
linear head per target ("contact_loc": 3, "force": 3, "nodal": 3 K).

PointNet++ (the paper's architecture): the 19 electrodes are points with features (value, x, y, z).
Three set-abstraction levels down to 32, 8 and 1 points with ball radii 2.5 mm, 7 mm and infinity and
shared MLPs [64, 64, 128], [128, 128, 256], [256, 256, 512], max-pooled over each ball; then two fully
connected layers of 1024. Hidden layers are batch-normalised as in PointNet++ (without it training
sits on the mean predictor for several epochs). Electrode positions are the same on every BioTac, so sampling (farthest
point) and grouping (ball query) are computed once from them and stored as index buffers. Sampling 32
centres from 19 points repeats the farthest-point order cyclically (PointNet++ samples with repetition
when asked for more centres than points).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import torch
from torch import nn

LEVEL_CENTRES = (32, 8, 1)
LEVEL_RADII = (2.5e-3, 7e-3, float("inf"))
LEVEL_MLPS = ((64, 64, 128), (128, 128, 256), (256, 256, 512))
LEVEL_GROUP_SIZES = (8, 16)
"""Ball-query group sizes of the first two levels (the third groups all points)."""
FC_WIDTH = 1024
POSITION_SCALE = 10e-3
"""Absolute electrode coordinates enter as features divided by this length (m)."""


def farthest_point_order(points: np.ndarray, count: int) -> np.ndarray:
    """(count,) ids: farthest-point sampling from point 0, repeated cyclically past len(points)."""
    order = [0]
    dist = np.linalg.norm(points - points[0], axis=1)
    while len(order) < len(points):
        nxt = int(np.argmax(dist))
        if dist[nxt] == 0.0:
            break
        order.append(nxt)
        dist = np.minimum(dist, np.linalg.norm(points - points[nxt], axis=1))
    return np.resize(np.asarray(order), count)


def ball_groups(points: np.ndarray, centres: np.ndarray, radius: float, size: int) -> np.ndarray:
    """(S, size) ids of the nearest points within ``radius`` (m) of each centre, padded with the nearest."""
    dist = np.linalg.norm(centres[:, None, :] - points[None, :, :], axis=2)
    nearest = np.argsort(dist, axis=1, kind="stable")[:, :size]
    inside = np.take_along_axis(dist, nearest, axis=1) <= radius
    return np.where(inside, nearest, nearest[:, :1])


class ChannelBatchNorm(nn.Module):
    """Batch normalisation of the last axis (channels) over every other axis."""

    def __init__(self, width: int) -> None:
        super().__init__()
        self.norm = nn.BatchNorm1d(width)

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        return self.norm(x.reshape(-1, x.shape[-1])).reshape(x.shape)


def shared_mlp(width_in: int, widths: tuple[int, ...], batch_norm: bool = False) -> nn.Sequential:
    """Linear (+ batch norm) + ReLU layers applied to the last axis."""
    layers: list[nn.Module] = []
    for w in widths:
        layers += [nn.Linear(width_in, w), *([ChannelBatchNorm(w)] if batch_norm else []), nn.ReLU()]
        width_in = w
    return nn.Sequential(*layers)


class Heads(nn.Module):
    """One linear head per target from a shared feature vector."""

    def __init__(self, width_in: int, target_dims: dict[str, int]) -> None:
        super().__init__()
        self.heads = nn.ModuleDict({k: nn.Linear(width_in, d) for k, d in target_dims.items()})

    def forward(self, features: torch.Tensor) -> dict[str, torch.Tensor]:
        return {k: head(features) for k, head in self.heads.items()}


@dataclass(frozen=True)
class LevelPlan:
    """One set-abstraction level on fixed points: groups (S, G) ids into the previous level's distinct
    outputs (each row's distinct members, padded by repeating its first), offsets (S, G, 3) neighbour
    minus centre coordinates over the radius, centres (S, 3) m."""

    groups: np.ndarray
    offsets: np.ndarray
    centres: np.ndarray


def _distinct_rows(groups: np.ndarray) -> np.ndarray:
    """Each row's distinct ids in order, padded with its first id to the longest row."""
    rows = [list(dict.fromkeys(row.tolist())) for row in groups]
    width = max(len(r) for r in rows)
    return np.array([r + [r[0]] * (width - len(r)) for r in rows])


def plan_levels(positions: np.ndarray) -> list[LevelPlan]:
    """The three levels of the paper's network on the given points (m).

    Computed as PointNet++ does (centres by farthest-point sampling, cyclic past the number of points;
    ball query of fixed size, padded with the nearest), then reduced without changing the function:
    repeated centres give repeated rows and repeated group members cannot change a max-pool, so each
    level keeps only distinct centres and distinct members.
    """
    points = np.asarray(positions, dtype=float)  # the previous level's outputs, repeats included
    owner = np.arange(len(points))  # points[i] is the previous level's distinct output owner[i]
    plans = []
    for count, radius, size in zip(LEVEL_CENTRES[:2], LEVEL_RADII[:2], LEVEL_GROUP_SIZES, strict=True):
        order = farthest_point_order(points, count)
        centres_all = points[order]
        groups = owner[ball_groups(points, centres_all, radius, size)]
        distinct = list(dict.fromkeys(order.tolist()))
        first_row = [int(np.flatnonzero(order == c)[0]) for c in distinct]
        rows = _distinct_rows(groups[first_row])
        centres = centres_all[first_row]
        reps = np.zeros((owner.max() + 1, 3))
        reps[owner] = points
        plans.append(LevelPlan(rows, (reps[rows] - centres[:, None]) / radius, centres))
        owner = np.array([distinct.index(c) for c in order])
        points = centres_all
    last = plans[-1].centres
    plans.append(LevelPlan(np.arange(len(last))[None], last[None] / POSITION_SCALE, np.zeros((1, 3))))
    return plans


class SetAbstraction(nn.Module):
    """Shared MLP on (member features, member offset) of each group, max-pooled over the group.

    The first layer is linear in the concatenation, so it is applied once per point (features) plus
    once per member (offsets) instead of once per member on the concatenation: the same function.
    Every layer is batch-normalised, as in PointNet++.
    """

    def __init__(self, plan: LevelPlan, width_in: int, widths: tuple[int, ...]) -> None:
        super().__init__()
        self.register_buffer("groups", torch.as_tensor(plan.groups, dtype=torch.long))
        self.register_buffer("offsets", torch.as_tensor(plan.offsets, dtype=torch.float32))
        self.point_layer = nn.Linear(width_in, widths[0])
        self.offset_layer = nn.Linear(3, widths[0], bias=False)
        self.first_norm = ChannelBatchNorm(widths[0])
        self.rest = shared_mlp(widths[0], widths[1:], batch_norm=True)

    def forward(self, features: torch.Tensor) -> torch.Tensor:
        """(B, P, C) point features -> (B, S, widths[-1]) centre features."""
        first = self.point_layer(features)[:, self.groups] + self.offset_layer(self.offsets)
        return self.rest(torch.relu(self.first_norm(first))).amax(dim=2)


class PointNet2(nn.Module):
    """The paper's PointNet++ regressor on the 19 electrodes (positions (19, 3) m, biotac frame)."""

    def __init__(self, positions: np.ndarray, target_dims: dict[str, int]) -> None:
        super().__init__()
        pos = np.asarray(positions, dtype=float)
        self.register_buffer("point_features", torch.as_tensor(pos / POSITION_SCALE, dtype=torch.float32))
        widths_in = (4, LEVEL_MLPS[0][-1], LEVEL_MLPS[1][-1])
        self.levels = nn.ModuleList(
            SetAbstraction(plan, w, mlp) for plan, w, mlp in zip(plan_levels(pos), widths_in, LEVEL_MLPS, strict=True)
        )
        self.fc = shared_mlp(LEVEL_MLPS[2][-1], (FC_WIDTH, FC_WIDTH), batch_norm=True)
        self.heads = Heads(FC_WIDTH, target_dims)

    def forward(self, values: torch.Tensor) -> dict[str, torch.Tensor]:
        """(B, 19) normalised electrode values -> normalised targets."""
        xyz = self.point_features.expand(values.shape[0], -1, -1)
        features = torch.cat([values[..., None], xyz], dim=-1)
        for level in self.levels:
            features = level(features)
        return self.heads(self.fc(features[:, 0]))


class PlainMLP(nn.Module):
    """Baseline: electrode values -> hidden layers (ReLU) -> heads."""

    def __init__(self, n_inputs: int, target_dims: dict[str, int], hidden: tuple[int, ...] = (256, 256)) -> None:
        super().__init__()
        self.trunk = shared_mlp(n_inputs, hidden)
        self.heads = Heads(hidden[-1], target_dims)

    def forward(self, values: torch.Tensor) -> dict[str, torch.Tensor]:
        return self.heads(self.trunk(values))
