"""The skin's triangle mesh: a mid-surface with held vertices, and its lumped vertex areas.

Positions are metres in the sensor frame (`biotac` for the BioTac). The FE engine that solves it is
`fe.batched` (energies, Newton) and `fe.batched_stepper` (indentation).
"""

from dataclasses import dataclass

import numpy as np


@dataclass(frozen=True)
class ShellMesh:
    """A triangle mid-surface (m) whose right-hand normals point out of the fluid cavity.

    `fixed` marks vertices held in place (anchors, pinned rims), shape (V,), or single held
    coordinates, shape (V,3); every boundary vertex must be fixed for the enclosed volume to be meaningful.
    """

    vertices: np.ndarray
    triangles: np.ndarray
    fixed: np.ndarray

    def __post_init__(self) -> None:
        v, t, f = self.vertices, self.triangles, self.fixed
        if v.ndim != 2 or v.shape[1] != 3 or t.ndim != 2 or t.shape[1] != 3 or f.shape not in ((len(v),), (len(v), 3)):
            raise ValueError("ShellMesh needs vertices (V,3), triangles (T,3) and fixed (V,) or (V,3)")
        if t.size and (t.min() < 0 or t.max() >= len(v)):
            raise ValueError("triangle indices out of range")


def triangle_areas(p0: np.ndarray, p1: np.ndarray, p2: np.ndarray) -> np.ndarray:
    """Areas (m^2) of the triangles with corners p0, p1, p2 (..., 3) m."""
    return 0.5 * np.linalg.norm(np.cross(p1 - p0, p2 - p0), axis=-1)


def lumped_areas(vertices: np.ndarray, triangles: np.ndarray) -> np.ndarray:
    """One third of the adjacent triangle areas per vertex (m^2): (V,) of vertices (V, 3) m."""
    area = triangle_areas(*(vertices[triangles[:, k]] for k in range(3)))
    return np.bincount(triangles.ravel(), weights=np.repeat(area / 3.0, 3), minlength=len(vertices))


def pressed_areas(vertices: np.ndarray, pressed: np.ndarray, triangles: np.ndarray) -> np.ndarray:
    """(R,) the lumped areas (`lumped_areas`, m^2) of the `pressed` (R, V) vertices of R meshes (R, V, 3) m summed,
    from the triangles that touch a pressed vertex only (a contact patch is a small part of the skin)."""
    rows, touching = np.nonzero(counts := pressed[:, triangles].sum(axis=2))  # pressed corners (R, T)
    area = triangle_areas(*(vertices[rows, triangles[touching, k]] for k in range(3)))
    return np.bincount(rows, weights=area * counts[rows, touching] / 3.0, minlength=len(vertices))
