"""Quadrature rules on a triangle for the surface-integrated indenter contact (`fe.contact`).

A rule is an (n, 4) array of rows (N0, N1, N2, w): the barycentric coordinates of a point (the linear shape
functions of the triangle's three nodes there, summing to 1) and its weight, a fraction of the triangle's
area (the weights sum to 1). Dunavant's symmetric rules (Int. J. Numer. Meth. Eng. 21, 1985, table of
degree 2, 4 and 5) integrate polynomials of that degree exactly; the contact energy density is only C1 at
the contact edge (it starts quadratically in the gap), where a rule of many evenly spread points, the
centroids of the triangle's k x k similar pieces ("split-k", the midpoint rule on the subdivision), follows
the edge more closely than a high degree does.
"""

import numpy as np

_DUNAVANT = {
    "dunavant-3": [((2 / 3, 1 / 6), 1 / 3)],
    "dunavant-6": [
        ((0.108103018168070, 0.445948490915965), 0.223381589678011),
        ((0.816847572980459, 0.091576213509771), 0.109951743655322),
    ],
    "dunavant-7": [
        ((0.059715871789770, 0.470142064105115), 0.132394152788506),
        ((0.797426985353087, 0.101286507323456), 0.125939180544827),
    ],
}
"""Orbits (a, b) of the points (a, b, b) and their permutations, with each point's weight."""


def _dunavant(name: str) -> np.ndarray:
    rows = [(1 / 3, 1 / 3, 1 / 3, 0.225)] if name == "dunavant-7" else []
    for (a, b), w in _DUNAVANT[name]:
        rows += [(a, b, b, w), (b, a, b, w), (b, b, a, w)]
    return np.array(rows)


def _split(k: int) -> np.ndarray:
    """Centroids of the k^2 similar pieces of the triangle (k^2 upward and downward ones), equal weights."""
    rows = []
    for i in range(k):
        for j in range(k - i):
            rows.append(((i + 1 / 3) / k, (j + 1 / 3) / k))
            if i + j < k - 1:
                rows.append(((i + 2 / 3) / k, (j + 2 / 3) / k))
    uv = np.array(rows)
    return np.column_stack([1.0 - uv.sum(axis=1), uv, np.full(len(uv), 1.0 / k**2)])


def rule(name: str) -> np.ndarray:
    """The rule `name` ("centroid", "dunavant-3", "dunavant-6", "dunavant-7" or "split-K" for K >= 1) as
    (n, 4) rows (N0, N1, N2, w)."""
    if name == "centroid":
        return np.array([[1 / 3, 1 / 3, 1 / 3, 1.0]])
    if name in _DUNAVANT:
        return _dunavant(name)
    if name.startswith("split-") and name[6:].isdigit() and int(name[6:]) >= 1:
        return _split(int(name[6:]))
    raise ValueError(f"unknown surface quadrature rule {name!r}")
