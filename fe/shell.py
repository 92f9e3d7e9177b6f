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


def lumped_areas(vertices: np.ndarray, triangles: np.ndarray) -> np.ndarray:
    """One third of the adjacent triangle areas per vertex (m^2): (V,) of vertices (V, 3) m, or (R, V) of R meshes
    (R, V, 3) at once (each the same, bit for bit, as alone)."""
    many = np.reshape(vertices, (-1, *np.shape(vertices)[-2:]))
    p0, p1, p2 = (many[:, triangles[:, k]] for k in range(3))
    area = 0.5 * np.linalg.norm(np.cross(p1 - p0, p2 - p0), axis=2)
    bins = (np.arange(len(many))[:, None] * many.shape[1] + triangles.ravel()).ravel()
    summed = np.bincount(bins, weights=np.repeat(area / 3.0, 3, axis=1).ravel(), minlength=many.size // 3)
    return summed.reshape(np.shape(vertices)[:-1])
