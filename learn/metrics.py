"""The paper's error measures (numpy only). Inputs SI (m, N), outputs in the paper's units (mm, N, rad)."""

from __future__ import annotations

import numpy as np

ANGLE_MIN_FORCE = 0.5
"""Force angles are scored only where the true force is at least this large (N): the direction of a
near-zero (noise) force is undefined. The paper compared forces above 0.5 N for the same reason."""


def location_errors(predicted: np.ndarray, true: np.ndarray) -> np.ndarray:
    """(N,) Euclidean distance (m) between predicted and true points (N, 3)."""
    return np.linalg.norm(predicted - true, axis=1)


def force_angle_errors(predicted: np.ndarray, true: np.ndarray) -> np.ndarray:
    """(M,) angle (rad) between predicted and true forces (N, 3), over rows with |true| >= ANGLE_MIN_FORCE; NaN
    where a force is not finite (the readers count and report such rows)."""
    keep = np.linalg.norm(true, axis=1) >= ANGLE_MIN_FORCE
    p, t = predicted[keep], true[keep]
    with np.errstate(invalid="ignore"):
        cos = np.einsum("ij,ij->i", p, t) / np.maximum(np.linalg.norm(p, axis=1) * np.linalg.norm(t, axis=1), 1e-12)
    return np.arccos(np.clip(cos, -1.0, 1.0))


def _stat(values: np.ndarray, how: str) -> float:
    return float(getattr(np, how)(values)) if len(values) else float("nan")


def paper_metrics(predicted: dict[str, np.ndarray], true: dict[str, np.ndarray]) -> dict[str, float]:
    """The paper's table for the targets both dicts hold ("contact_loc", "force", "nodal").

    contact_loc_mean_mm / contact_loc_median_mm: distance to the true contact location.
    force_magnitude_median_N (and _mean_N): | |F_pred| - |F_true| |.
    force_angle_mean_rad / force_angle_median_rad: angle between the vectors (|F_true| >= 0.5 N).
    nodal_mean_mm: mean over samples and nodes of the nodal displacement error norm.
    n_samples: rows scored.
    """
    out: dict[str, float] = {}
    if "contact_loc" in predicted and "contact_loc" in true:
        err = location_errors(predicted["contact_loc"], true["contact_loc"]) * 1e3
        out.update(contact_loc_mean_mm=_stat(err, "mean"), contact_loc_median_mm=_stat(err, "median"))
    if "force" in predicted and "force" in true:
        mag = np.abs(np.linalg.norm(predicted["force"], axis=1) - np.linalg.norm(true["force"], axis=1))
        angle = force_angle_errors(predicted["force"], true["force"])
        out.update(
            force_magnitude_median_N=_stat(mag, "median"),
            force_magnitude_mean_N=_stat(mag, "mean"),
            force_angle_mean_rad=_stat(angle, "mean"),
            force_angle_median_rad=_stat(angle, "median"),
        )
    if "nodal" in predicted and "nodal" in true:
        err = np.linalg.norm(predicted["nodal"] - true["nodal"], axis=2) * 1e3
        out["nodal_mean_mm"] = _stat(err.ravel(), "mean")
    out["n_samples"] = float(len(next(iter(true.values())))) if true else 0.0
    return out
