"""Analytic skin deformations (numpy only): a cheap stand-in for the FE when testing electrode models.

A smooth dent: free skin vertices move inward along their normals by ``depth * exp(-d^2 / (2 width^2))``
(d = distance to the contact point) and slide tangentially by ``shear`` times the same profile. Not
mechanics: it has the right shape (local, monotone in depth) and nothing else. Metres, biotac frame.
"""

from __future__ import annotations

import numpy as np

from assets.biotac import BioTacGeometry, vertex_normals


def gaussian_dent(
    geometry: BioTacGeometry,
    reference: np.ndarray,
    point: np.ndarray,
    depth: float,
    width: float = 2.0e-3,
    shear: np.ndarray | None = None,
) -> np.ndarray:
    """(V, 3) m: the reference mid-surface dented at ``point`` (3,) m by ``depth`` m (peak inward motion).

    width: m, standard deviation of the dent profile. shear: (3,) m, peak tangential displacement
    (its normal component at each vertex is removed). Anchored vertices do not move.
    """
    normals = vertex_normals(reference, geometry.skin.triangles)
    dist2 = np.sum((reference - np.asarray(point, dtype=float)) ** 2, axis=1)
    profile = np.exp(-0.5 * dist2 / width**2) * ~geometry.skin.anchored
    motion = -depth * normals
    if shear is not None:
        s = np.asarray(shear, dtype=float)
        motion = motion + s - (normals @ s)[:, None] * normals
    return reference + profile[:, None] * motion
