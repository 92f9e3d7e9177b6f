"""Train/test splits of the paper (numpy only). Each returns (train_rows, test_rows), sorted int arrays.

- ``contiguous``: whole trajectories to test (about ``test_fraction`` of them): the honest split.
- ``noncontiguous``: random samples to test; neighbours of a test sample sit in training (leaky).
- ``indenter:<name>``: every sample of one indenter to test (leave one indenter out).
Cross-sensor and pretrain-then-fine-tune are protocols over files, not row splits (see learn.train).
"""

from __future__ import annotations

import numpy as np

from learn.data import TactileData

SPLITS = ("contiguous", "noncontiguous", "indenter:<name>", "none")


def contiguous(trajectory: np.ndarray, test_fraction: float, seed: int) -> tuple[np.ndarray, np.ndarray]:
    """Hold out about ``test_fraction`` of the trajectories, whole (at least one, never all)."""
    ids = np.unique(trajectory)
    if len(ids) < 2:
        raise ValueError("a contiguous split needs at least 2 trajectories")
    n_test = int(np.clip(round(test_fraction * len(ids)), 1, len(ids) - 1))
    test_ids = np.random.default_rng(seed).choice(ids, size=n_test, replace=False)
    test = np.isin(trajectory, test_ids)
    return np.flatnonzero(~test), np.flatnonzero(test)


def noncontiguous(n: int, test_fraction: float, seed: int) -> tuple[np.ndarray, np.ndarray]:
    """Hold out a random ``test_fraction`` of the samples."""
    order = np.random.default_rng(seed).permutation(n)
    n_test = int(np.clip(round(test_fraction * n), 1, n - 1))
    return np.sort(order[n_test:]), np.sort(order[:n_test])


def leave_indenter_out(indenter: np.ndarray, held_out: int) -> tuple[np.ndarray, np.ndarray]:
    """Test on every sample of indenter index ``held_out``, train on the rest."""
    test = indenter == held_out
    if not test.any() or test.all():
        raise ValueError(f"indenter {held_out} has {int(test.sum())} of {len(indenter)} samples: nothing to split")
    return np.flatnonzero(~test), np.flatnonzero(test)


def split(data: TactileData, name: str, test_fraction: float = 0.2, seed: int = 0) -> tuple[np.ndarray, np.ndarray]:
    """Rows of a named split (see module docstring); "none" tests on everything and trains on nothing."""
    if name == "contiguous":
        return contiguous(data.trajectory, test_fraction, seed)
    if name == "noncontiguous":
        return noncontiguous(len(data), test_fraction, seed)
    if name.startswith("indenter:"):
        indenter = name.split(":", 1)[1]
        if indenter not in data.indenter_names:
            raise ValueError(f"unknown indenter {indenter!r}; this data has {', '.join(data.indenter_names)}")
        return leave_indenter_out(data.indenter, data.indenter_names.index(indenter))
    if name == "none":
        return np.array([], dtype=np.int64), np.arange(len(data))
    raise ValueError(f"unknown split {name!r}; choose one of {', '.join(SPLITS)}")
