"""Sets of straight indentation trajectories for batched FE runs (`fe.batched_runner.run_trajectories`).

`random_paths` draws touch points on the ventral skin of an inflated `fe.sensor.BioTacModel`, each
approached along a direction tilted up to `max_tilt_deg` from the inward normal (random azimuth), cycling
through the given indenters. `to_trajectories` turns such paths into per-pose trajectories: tip
positions touch + travel * direction for a shared list of travels (m past first touch; negative ones
are approach poses). Units: m, degrees; frame: the sensor (biotac) frame.
"""

from __future__ import annotations

from typing import TYPE_CHECKING

import numpy as np

from assets.indenters import get_indenter
from fe.batched_runner import PoseTrajectory

if TYPE_CHECKING:
    from fe.sensor import BioTacModel

PATH_KEYS = ("names", "touch", "direction", "rotation")
"""Arrays of a path set: indenter names (M,), touch points (M,3) m, unit directions (M,3) and indenter
rotations (M,3,3) body -> sensor frame."""


def random_paths(
    model: BioTacModel, count: int, indenters: list[str], seed: int, depth: float, max_tilt_deg: float = 20.0
) -> dict[str, np.ndarray]:
    """`count` straight paths at random ventral points of the inflated `model` (indenters cycled in the given
    order, each planned to `depth` m), as arrays keyed by `PATH_KEYS`; points the planner rejects (an
    indenter that would not reach the skin there) are redrawn."""
    if count < 1 or not indenters:
        raise ValueError(f"need at least one trajectory and one indenter, got {count} and {indenters}")
    if model.reference is None:
        raise RuntimeError("inflate() the model before planning trajectories on it")
    shapes = [get_indenter(name) for name in indenters]
    rng = np.random.default_rng(seed)
    ventral = model.reference[model.geometry.skin.ventral]
    rows: dict[str, list] = {key: [] for key in PATH_KEYS}
    while len(rows["names"]) < count:
        k = len(rows["names"]) % len(indenters)
        point = ventral[rng.integers(len(ventral))]
        tilt, azimuth = rng.uniform(0, max_tilt_deg), rng.uniform(0, 360)
        try:
            path = model.plan_trajectory(shapes[k], point, tilt, azimuth, depth, 1e-3)
        except ValueError:
            continue
        for key, value in zip(PATH_KEYS, (indenters[k], path.touch_point, path.direction, path.rotation), strict=True):
            rows[key].append(value)
    return {key: np.asarray(value) for key, value in rows.items()}


def press_travels(depth: float, step: float) -> np.ndarray:
    """Tip travels (m past first touch) of a press: one approach pose a step before touch, then `step` m
    increments to `depth` m."""
    return np.arange(-1, int(round(depth / step)) + 1) * step


def to_trajectories(paths: dict[str, np.ndarray], travels: np.ndarray) -> list[PoseTrajectory]:
    """One `PoseTrajectory` per path: the path's rotation at every pose, tips at touch + travel * direction
    for each of `travels` (m)."""
    travels = np.asarray(travels, dtype=np.float64)
    return [
        PoseTrajectory(str(name), np.repeat(rotation[None], len(travels), 0), touch + travels[:, None] * direction)
        for name, touch, direction, rotation in zip(*(paths[key] for key in PATH_KEYS), strict=True)
    ]


def round_robin(names: np.ndarray) -> np.ndarray:
    """An order of the trajectories that cycles through the indenters (the k-th of each, then the k+1-th),
    so that a run's queue keeps the indenter mix from start to end."""
    names = np.asarray(names)
    rank = np.zeros(len(names), dtype=int)
    for name in np.unique(names):
        rank[names == name] = np.arange(np.count_nonzero(names == name))
    return np.lexsort((names, rank))
