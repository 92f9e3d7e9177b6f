"""Local red-green refinement (assets/refine.py) keeps a surface mesh conforming, oriented and on its surface,
and halves the edges where it is asked to; the BioTac skin refined about a press point (assets/biotac.py)."""

import numpy as np
import pytest
import trimesh

from assets.biotac import DEFAULT_DIMENSIONS, make_biotac, project_to_skin, region_flags
from assets.refine import Refinement, refine_near


def _edge_counts(triangles: np.ndarray) -> np.ndarray:
    """How many triangles use each undirected edge."""
    edges = np.sort(np.concatenate([triangles[:, [0, 1]], triangles[:, [1, 2]], triangles[:, [2, 0]]]), axis=1)
    return np.unique(edges, axis=0, return_counts=True)[1]


def _longest_edges(vertices: np.ndarray, triangles: np.ndarray) -> np.ndarray:
    corners = vertices[triangles]
    return np.linalg.norm(corners - np.roll(corners, -1, axis=1), axis=2).max(axis=1)


def _unit_rows(p: np.ndarray) -> np.ndarray:
    return p / np.linalg.norm(p, axis=1, keepdims=True)


def _smallest_angle(vertices: np.ndarray, triangles: np.ndarray) -> float:
    """The smallest corner angle (degrees) of the mesh."""
    corners = vertices[triangles]
    edges = np.roll(corners, -1, axis=1) - corners
    lengths = np.linalg.norm(edges, axis=2)
    cosines = [
        np.einsum("ij,ij->i", edges[:, k], -edges[:, k - 1]) / (lengths[:, k] * lengths[:, k - 1]) for k in range(3)
    ]
    return float(np.degrees(np.arccos(np.clip(np.max(cosines), -1.0, 1.0))))


def _grid(n: int, spacing: float) -> tuple[np.ndarray, np.ndarray]:
    """A flat square of n x n cells in z = 0, two triangles a cell, normals +z."""
    i, j = np.meshgrid(np.arange(n + 1), np.arange(n + 1), indexing="ij")
    vertices = np.column_stack([i.ravel() * spacing, j.ravel() * spacing, np.zeros(i.size)])
    ids = np.arange((n + 1) ** 2).reshape(n + 1, n + 1)
    a, b, c, d = ids[:-1, :-1].ravel(), ids[1:, :-1].ravel(), ids[1:, 1:].ravel(), ids[:-1, 1:].ravel()
    return vertices, np.vstack([np.column_stack([a, b, c]), np.column_stack([a, c, d])])


@pytest.mark.parametrize("levels", [1, 2, 3])
def test_a_flat_mesh_stays_conforming_oriented_and_of_the_same_area(levels: int) -> None:
    vertices, triangles = _grid(30, 1.0)
    refined = refine_near(vertices, triangles, np.array([15.0, 15.0, 0.0]), 1.5, levels, lambda p: p)
    v, t = refined.vertices, refined.triangles
    # Conforming: an edge is shared by two triangles, or lies on the square's boundary (120 unit edges, halved
    # nowhere there: the refined zone does not reach it).
    counts = _edge_counts(t)
    assert set(np.unique(counts)) <= {1, 2} and np.sum(counts == 1) == 120
    normals = np.cross(v[t[:, 1]] - v[t[:, 0]], v[t[:, 2]] - v[t[:, 0]])
    assert np.all(normals[:, 2] > 0)
    assert np.isclose(0.5 * normals[:, 2].sum(), 900.0, rtol=1e-12)
    # The originals keep their ids; every new vertex is the midpoint of its parents.
    assert np.array_equal(v[: len(vertices)], vertices)
    np.testing.assert_allclose(v[len(vertices) :], 0.5 * (v[refined.parents[:, 0]] + v[refined.parents[:, 1]]))
    # Within the radius the edges are halved `levels` times (the grid's longest is a diagonal, sqrt 2).
    near = np.linalg.norm(v[t].mean(axis=1) - [15.0, 15.0, 0.0], axis=1) < 1.0
    assert _longest_edges(v, t)[near].max() <= np.sqrt(2.0) / 2**levels + 1e-12
    far = np.linalg.norm(v[t].mean(axis=1) - [15.0, 15.0, 0.0], axis=1) > 1.5 * 2**levels + 2.0
    assert np.allclose(_longest_edges(v, t)[far], np.sqrt(2.0))


def test_a_closed_sphere_stays_closed_and_on_the_sphere() -> None:
    sphere = trimesh.creation.icosphere(subdivisions=2, radius=2.0)
    centre = sphere.vertices[0]
    refined = refine_near(
        sphere.vertices, sphere.faces, centre, 0.5, 2, lambda p: 2.0 * p / np.linalg.norm(p, axis=1)[:, None]
    )
    mesh = trimesh.Trimesh(refined.vertices, refined.triangles, process=False)
    assert mesh.is_watertight and mesh.is_winding_consistent and mesh.euler_number == 2
    assert np.allclose(np.linalg.norm(refined.vertices, axis=1), 2.0)
    assert mesh.volume > trimesh.Trimesh(sphere.vertices, sphere.faces).volume  # midpoints pushed out onto it
    assert len(refined.vertices) > len(sphere.vertices)


def test_a_radius_smaller_than_the_elements_still_splits_the_nearest_triangle() -> None:
    vertices, triangles = _grid(4, 1.0)
    refined = refine_near(vertices, triangles, np.array([2.2, 1.3, 0.0]), 1e-3, 1, lambda p: p)
    assert len(refined.triangles) > len(triangles) and len(refined.parents) >= 3


@pytest.mark.parametrize("radius", [1e-5, 1.5e-3])
def test_angles_do_not_shrink_level_after_level(radius: float) -> None:
    """Each level splits at least the ring about the nearest triangle, so a triangle halved at one level is not
    halved again at the next (that would halve its smallest angle each level: 0.8 degrees after five)."""
    d = DEFAULT_DIMENSIONS
    skin = make_biotac(1e-3).skin
    seam = np.array([d.tip_center_x, 0.0, d.axis_z - 8e-3])
    for levels in (3, 5):
        refined = refine_near(skin.vertices, skin.triangles, seam, radius, levels, lambda p: project_to_skin(p, d))
        assert _smallest_angle(refined.vertices, refined.triangles) > 12.0


def test_zero_levels_change_nothing_and_bad_input_is_refused() -> None:
    vertices, triangles = _grid(3, 1.0)
    same = refine_near(vertices, triangles, np.zeros(3), 1.0, 0, lambda p: p)
    assert np.array_equal(same.vertices, vertices) and np.array_equal(same.triangles, triangles)
    for radius, levels in [(0.0, 1), (np.nan, 1), (1.0, -1), (1.0, 1.5)]:
        with pytest.raises(ValueError, match="refine_near"):
            refine_near(vertices, triangles, np.zeros(3), radius, levels, lambda p: p)
    for centre in (np.full(3, np.nan), np.zeros(2)):
        with pytest.raises(ValueError, match="centre"):
            refine_near(vertices, triangles, centre, 1.0, 1, lambda p: p)


def test_the_biotac_skin_refined_about_a_press_point() -> None:
    d, point = DEFAULT_DIMENSIONS, np.array([-5e-3, 0.0, -9e-3])  # `twin fe indent`'s default point (outer skin)
    plain = make_biotac(1e-3)
    geometry = make_biotac(1e-3, refinement=Refinement(tuple(point), radius=1.5e-3, levels=1))
    skin = geometry.skin
    assert len(skin.vertices) > len(plain.skin.vertices)
    assert np.allclose(project_to_skin(skin.vertices, d), skin.vertices, atol=1e-12)  # on the mid-surface
    anchored, ventral = region_flags(skin.vertices, skin.triangles, d)
    assert np.array_equal(anchored, skin.anchored) and np.array_equal(ventral, skin.ventral)
    assert np.array_equal(anchored[: len(plain.skin.vertices)], plain.skin.anchored)
    assert trimesh.Trimesh(skin.vertices, skin.triangles, process=False).is_winding_consistent
    centre = project_to_skin(point[None], d)[0]
    near = np.linalg.norm(skin.vertices[skin.triangles].mean(axis=1) - centre, axis=1) < 1e-3
    assert _longest_edges(skin.vertices, skin.triangles)[near].max() <= 0.5e-3 + 1e-12
