"""The residual field: per-sample force error magnitudes interpolated onto the skin mesh (biotac frame, m)."""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np
from scipy.spatial import cKDTree

from assets.biotac import make_biotac
from twin.analysis.compare import Comparison
from twin.analysis.report.stats import residuals

MIN_BANDWIDTH = 1e-3
"""Smallest kernel bandwidth (m) of the residual field; the mesh edge length when larger."""
KERNEL_REACH = 2.5
"""Kernel cut-off in bandwidths: vertices farther than this from every contact get no value."""


@dataclass(frozen=True)
class ResidualField:
    """RMS force error on the skin mesh (unpressurised mid-surface, biotac frame).

    values[v] = sqrt(sum_i w_iv |r_i|^2 / sum_i w_iv): the root of a Gaussian-kernel (Nadaraya-Watson)
    estimate of the mean squared force residual |r_i| (N) of the rows near vertex v, each row placed at the
    skin vertex nearest its contact location; NaN where no row lies within KERNEL_REACH bandwidths.
    support[v] = sum_i w_iv, the effective number of rows behind values[v].
    """

    vertices: np.ndarray  # (V, 3) m
    triangles: np.ndarray  # (T, 3) vertex indices
    values: np.ndarray  # (V,) N
    support: np.ndarray  # (V,)
    bandwidth: float  # m

    def save(self, path: Path) -> None:
        """Write the arrays (and the bandwidth in m) to an .npz file."""
        np.savez(path, **{k: getattr(self, k) for k in ("vertices", "triangles", "values", "support", "bandwidth")})


def residual_field(
    vertices: np.ndarray, triangles: np.ndarray, points: np.ndarray, residual: np.ndarray, bandwidth: float
) -> ResidualField:
    """Interpolate per-sample residual magnitudes at `points` (m) onto the mesh (see `ResidualField`)."""
    keep = np.isfinite(residual) & np.isfinite(points).all(axis=1)
    tree = cKDTree(vertices)
    _, anchor = tree.query(points[keep])
    squares = np.bincount(anchor, weights=residual[keep] ** 2, minlength=len(vertices))
    counts = np.bincount(anchor, minlength=len(vertices)).astype(float)
    used = np.flatnonzero(counts)
    neighbours = tree.query_ball_point(vertices[used], KERNEL_REACH * bandwidth)
    source = np.repeat(used, [len(n) for n in neighbours])
    target = np.concatenate([np.asarray(n, dtype=int) for n in neighbours]) if len(used) else np.zeros(0, int)
    weight = np.exp(-0.5 * (np.linalg.norm(vertices[target] - vertices[source], axis=1) / bandwidth) ** 2)
    numerator = np.bincount(target, weights=weight * squares[source], minlength=len(vertices))
    support = np.bincount(target, weights=weight * counts[source], minlength=len(vertices))
    with np.errstate(invalid="ignore", divide="ignore"):
        values = np.where(support > 0, np.sqrt(numerator / support), np.nan)
    return ResidualField(vertices, triangles, values, support, bandwidth)


def skin_residual_field(comparison: Comparison) -> ResidualField:
    """The rows' force residual magnitude on the skin mesh of the comparison's model mesh size."""
    edge = comparison.model.mesh_max_edge
    skin = make_biotac(edge).skin
    rows = comparison.rows
    points = np.column_stack([rows.labels[f"contact_{a}"] for a in "xyz"])
    return residual_field(skin.vertices, skin.triangles, points, residuals(rows)["force"], max(MIN_BANDWIDTH, edge))
