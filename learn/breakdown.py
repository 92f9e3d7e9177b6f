"""Per-row errors broken down by a row property (numpy only): where an estimator's error comes from.

`by_group` takes (N,) errors and (N,) group labels (any hashable: an indenter name, a bin label) and
returns, per group, the row count, its share of the rows, the mean and median error and the group's
share of the summed error (how much of the overall mean it carries). `force_bins` labels rows by
force magnitude. Units are the caller's (mm in the location study).
"""

from __future__ import annotations

import numpy as np

FORCE_EDGES = (0.0, 0.1, 0.5, 1.0, 2.0, 5.0, np.inf)
"""Edges (N) of the force-magnitude bins: < 0.1 N is F/T noise (no contact), 0.5 N the paper's F/T threshold."""


def force_bins(force: np.ndarray, edges: tuple[float, ...] = FORCE_EDGES) -> np.ndarray:
    """(N,) labels "lo-hi N" of the bin holding each row's |F| ((N, 3) N); bins are [lo, hi)."""
    magnitude = np.linalg.norm(force, axis=1)
    labels = np.array([f"{lo:g}-{hi:g} N" for lo, hi in zip(edges[:-1], edges[1:], strict=True)])
    index = np.searchsorted(np.asarray(edges), magnitude, side="right") - 1
    if np.any(index < 0) or np.any(index >= len(labels)):
        raise ValueError(f"force magnitudes outside the bins {edges[0]}..{edges[-1]} N")
    return labels[index]


def by_group(errors: np.ndarray, groups: np.ndarray) -> dict[str, dict[str, float]]:
    """{group: {n, row_share, mean, median, error_share}} in the order groups first appear sorted.

    row_share: fraction of the rows in the group; error_share: fraction of sum(errors) it carries (so the
    overall mean is sum over groups of row_share * mean, and error_share says which groups dominate it).
    """
    errors, groups = np.asarray(errors, dtype=float), np.asarray(groups)
    if errors.shape != groups.shape or errors.ndim != 1:
        raise ValueError(f"errors {errors.shape} and groups {groups.shape} must be the same (N,) shape")
    total = errors.sum()
    out = {}
    for group in sorted(set(groups.tolist()), key=str):
        rows = groups == group
        out[str(group)] = {
            "n": int(rows.sum()),
            "row_share": float(rows.mean()),
            "mean": float(errors[rows].mean()),
            "median": float(np.median(errors[rows])),
            "error_share": float(errors[rows].sum() / total) if total > 0 else float("nan"),
        }
    return out
