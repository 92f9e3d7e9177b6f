"""Local refinement of a triangle surface mesh around a point (red-green, conforming).

A contact patch that is one element wide is not resolved by linear triangles (docs/fe.md, the dome):
`refine_near` halves the edges near a press point, level by level over shrinking distances, so the rest of
the mesh keeps its nodes.

Each level splits the marked triangles into four (red: edge midpoints) and closes the mesh: a triangle with
two or three split edges is split red as well, one with a single split edge is halved (green). Every new
vertex is an edge midpoint, moved onto the smooth surface by the caller's `project`. Orientation is kept.
Lengths in the units of the vertices (m here).
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass

import numpy as np

Projection = Callable[[np.ndarray], np.ndarray]
"""Maps (N, 3) points near the surface onto it, (N, 3)."""


@dataclass(frozen=True)
class Refinement:
    """Where and how much to refine (`refine_near`): edges halved `levels` times within `radius` of `centre`
    (vertex units, m here), coarser levels over twice the distance of the next."""

    centre: tuple[float, float, float]
    radius: float = 1.5e-3
    levels: int = 1


@dataclass(frozen=True)
class RefinedMesh:
    """A refined mesh: the original vertices first, then the new ones.

    parents: (V_new, 2) int, the two vertices of the edge each new vertex split (ids into `vertices`,
    possibly themselves new): attributes of a new vertex may be taken from both (e.g. held only if both are).
    """

    vertices: np.ndarray
    triangles: np.ndarray
    parents: np.ndarray


def _edges(triangles: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Unique undirected edges (E, 2) and each triangle's edge ids (T, 3), edge k from corner k to k+1."""
    directed = np.stack([triangles, np.roll(triangles, -1, axis=1)], axis=2).reshape(-1, 2)
    unique, inverse = np.unique(np.sort(directed, axis=1), axis=0, return_inverse=True)
    return unique, inverse.reshape(-1, 3)


def _close(marked: np.ndarray, tri_edges: np.ndarray, n_edges: int) -> tuple[np.ndarray, np.ndarray]:
    """Grow `marked` until no unmarked triangle has two split edges; returns (red mask, split-edge mask)."""
    while True:
        split = np.zeros(n_edges, dtype=bool)
        split[tri_edges[marked].ravel()] = True
        grow = ~marked & (split[tri_edges].sum(axis=1) >= 2)
        if not grow.any():
            return marked, split
        marked = marked | grow


def _split(
    vertices: np.ndarray, triangles: np.ndarray, marked: np.ndarray, project: Projection
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """One red-green pass: the marked triangles into four, their neighbours closed. Returns
    (vertices, triangles, parents of the new vertices)."""
    edges, tri_edges = _edges(triangles)
    red, split = _close(marked, tri_edges, len(edges))
    new_id = np.full(len(edges), -1)
    new_id[split] = len(vertices) + np.arange(split.sum())
    parents = edges[split]
    midpoints = project(0.5 * (vertices[parents[:, 0]] + vertices[parents[:, 1]]))
    m = new_id[tri_edges]  # (T, 3): midpoint of edge k (corner k to k+1), -1 where unsplit
    a, b, c = triangles[red].T
    mab, mbc, mca = m[red].T
    out = [np.column_stack(corners) for corners in ((a, mab, mca), (mab, b, mbc), (mca, mbc, c), (mab, mbc, mca))]
    green = ~red & (m >= 0).any(axis=1)
    k = np.argmax(m[green] >= 0, axis=1)  # the one split edge, corners (k, k+1); the opposite corner k+2
    rows = np.arange(green.sum())
    t = triangles[green]
    p, q, r, mid = t[rows, k], t[rows, (k + 1) % 3], t[rows, (k + 2) % 3], m[green][rows, k]
    out += [np.column_stack([p, mid, r]), np.column_stack([mid, q, r]), triangles[~red & ~green]]
    return np.vstack([vertices, midpoints]), np.vstack(out).astype(triangles.dtype), parents


def refine_near(
    vertices: np.ndarray, triangles: np.ndarray, centre: np.ndarray, radius: float, levels: int, project: Projection
) -> RefinedMesh:
    """Halve the edges near `centre` `levels` times: level k (k = 1 ... levels) splits every triangle whose
    centroid lies within radius * 2^(levels - k) of `centre` (and at least those within one and a half of its
    edges of the nearest one), so the finest level covers about `radius` (centroids of the level's mesh) and each
    coarser one twice the distance of the next (a graded transition, a few elements a level).

    Args:
        vertices: (V, 3) surface vertices. triangles: (T, 3) vertex ids, consistently oriented.
        centre: (3,) the point to refine about. radius: reach of the finest level (> 0, vertex units).
        levels: how many times the edges at `centre` are halved (>= 0; 0 returns the mesh unchanged).
        project: moves new edge midpoints onto the smooth surface the mesh approximates.

    Returns:
        The refined mesh (original vertices first, their ids unchanged) and the parents of its new vertices.
    """
    centre = np.asarray(centre, dtype=float)
    if not (np.isfinite(radius) and radius > 0) or int(levels) != levels or levels < 0:
        raise ValueError(f"refine_near: radius > 0 and a whole levels >= 0 needed, got {radius!r}, {levels!r}")
    if centre.shape != (3,) or not np.all(np.isfinite(centre)):
        raise ValueError(f"refine_near: centre must be 3 finite coordinates, got {centre!r}")
    v, t = np.asarray(vertices, dtype=float), np.asarray(triangles)
    parents = np.zeros((0, 2), dtype=int)
    for k in range(1, int(levels) + 1):
        corners = v[t]
        distance = np.linalg.norm(corners.mean(axis=1) - centre, axis=1)
        nearest = np.argmin(distance)
        size = np.linalg.norm(corners[nearest] - np.roll(corners[nearest], -1, axis=0), axis=1).max()
        # At least the ring about the nearest triangle: split alone, its halved neighbours would be halved
        # again at the next level, and their angles with them.
        reach = max(radius * 2.0 ** (levels - k), distance[nearest] + 1.5 * size)
        v, t, new_parents = _split(v, t, distance <= reach, project)
        parents = np.vstack([parents, new_parents])
    return RefinedMesh(v, t, parents)
