"""Tests of the parametric BioTac geometry (assets/biotac.py): mesh quality, flags, electrodes, core."""

import dataclasses
import time

import numpy as np
import pytest
import trimesh

from assets.biotac import (
    BEVEL_NORMAL,
    DEFAULT_DIMENSIONS,
    BioTacDimensions,
    boundary_vertices,
    cavity_volume,
    electrode_table,
    inside_core,
    make_biotac,
    outer_surface,
    project_to_core,
    sample_ventral_points,
    signed_volume,
    skin_cut_z,
    vertex_normals,
)

MM = 1e-3
D = DEFAULT_DIMENSIONS


@pytest.fixture(scope="module", params=[2e-3, 1e-3])
def geo(request):
    return request.param, make_biotac(request.param)


def edge_lengths_and_min_angles(vertices, triangles):
    p = vertices[triangles]
    e = p[:, [1, 2, 0]] - p
    length = np.linalg.norm(e, axis=2)
    angles = [
        np.arccos(np.clip(np.einsum("ij,ij->i", e[:, k], -e[:, k - 1]) / (length[:, k] * length[:, k - 1]), -1, 1))
        for k in range(3)
    ]
    return length, np.degrees(np.min(angles, axis=0))


def radial_direction(points, axis_z, tip_x):
    """Unit vector from the skin axis (cylinder) or cap centre (hemisphere) to the points."""
    q = points - np.array([tip_x, 0.0, axis_z])
    q[:, 0] = np.maximum(q[:, 0], 0.0)
    return q / np.linalg.norm(q, axis=1, keepdims=True), np.linalg.norm(q, axis=1)


def test_types_and_shapes(geo):
    _, g = geo
    s = g.skin
    assert s.vertices.dtype == np.float64 and s.vertices.shape[1] == 3
    assert s.triangles.dtype == np.int32 and s.triangles.shape[1] == 3
    assert s.anchored.shape == s.ventral.shape == (len(s.vertices),)
    assert s.anchored.dtype == bool and s.ventral.dtype == bool
    assert g.core.triangles.dtype == np.int32
    assert np.abs(s.vertices).max() < 0.03  # metres, not millimetres
    assert g.core_gap == pytest.approx(0.5 * D.skin_thickness)
    assert g.dorsal_top_z == D.dorsal_top_z


def test_mesh_quality(geo):
    h, g = geo
    length, min_angle = edge_lengths_and_min_angles(g.skin.vertices, g.skin.triangles)
    assert length.max() <= h
    assert min_angle.min() > 20.0
    assert np.median(length) > 0.7 * h  # not needlessly fine


def test_vertices_on_mid_surface(geo):
    _, g = geo
    _, r = radial_direction(g.skin.vertices, D.axis_z, D.tip_center_x)
    np.testing.assert_allclose(r, D.skin_mid_radius, atol=1e-9)
    assert g.skin.vertices[:, 0].min() == pytest.approx(D.proximal_x - D.anchor_band)
    assert g.skin.vertices[:, 2].max() == pytest.approx(skin_cut_z(D))


def test_manifold_single_boundary_loop(geo):
    _, g = geo
    t = g.skin.triangles
    directed = np.vstack([t[:, [0, 1]], t[:, [1, 2]], t[:, [2, 0]]])
    assert len(np.unique(directed, axis=0)) == len(directed), "an edge is used twice in the same direction"
    undirected, counts = np.unique(np.sort(directed, axis=1), axis=0, return_counts=True)
    assert counts.max() <= 2
    boundary = undirected[counts == 1]
    degree = np.bincount(boundary.ravel(), minlength=len(g.skin.vertices))
    assert set(np.unique(degree[degree > 0])) == {2}
    assert len(np.unique(t)) == len(g.skin.vertices)
    # Euler characteristic of a disc: V - E + F = 1
    assert len(g.skin.vertices) - len(undirected) + len(t) == 1


def test_orientation_points_away_from_core(geo):
    _, g = geo
    v, t = g.skin.vertices, g.skin.triangles
    p = v[t]
    normal = np.cross(p[:, 1] - p[:, 0], p[:, 2] - p[:, 0])
    radial, _ = radial_direction(p.mean(axis=1), D.axis_z, D.tip_center_x)
    assert np.all(np.einsum("ij,ij->i", normal, radial) > 0.0)
    apex = np.array([-5 * MM, 0.0, D.axis_z])
    assert signed_volume(v, t, apex) > 0.0
    # Pushing the free vertices outward by delta (anchored boundary fixed) grows the enclosed volume
    # by ~ free area * delta, whatever the apex of the closing cone.
    delta = 0.05 * MM
    pushed = v + delta * (~g.skin.anchored)[:, None] * vertex_normals(v, t)
    area = 0.5 * np.linalg.norm(normal, axis=1)
    free_tris = ~g.skin.anchored[t]
    gains = [signed_volume(pushed, t, a) - signed_volume(v, t, a) for a in (apex, np.array([2 * MM, 1 * MM, -2 * MM]))]
    assert gains[0] == pytest.approx(gains[1], rel=1e-9)
    assert area[free_tris.all(axis=1)].sum() < gains[0] / delta < area[free_tris.any(axis=1)].sum()


def test_anchored_and_ventral_flags(geo):
    _, g = geo
    s = g.skin
    x, z = s.vertices[:, 0], s.vertices[:, 2]
    assert s.anchored[boundary_vertices(s.triangles, len(x))].all()
    free = ~s.anchored
    assert np.all(x[free] > D.proximal_x) and np.all(z[free] < D.dorsal_anchor_z)
    assert np.all(s.anchored[(x < D.proximal_x - 1e-9) | (z > D.dorsal_anchor_z + 1e-9)])
    assert not np.any(s.ventral & s.anchored)
    assert 0.5 * len(x) < free.sum() and s.ventral.sum() > 0.5 * free.sum()
    middle = np.flatnonzero((x > -8 * MM) & (x < -2 * MM))
    assert s.ventral[middle[np.argmin(z[middle])]]
    tip = np.argmax(x)
    assert s.ventral[tip]


def test_fine_mesh_size_and_speed():
    start = time.perf_counter()
    g = make_biotac(0.5e-3)
    elapsed = time.perf_counter() - start
    assert 3000 <= len(g.skin.vertices) <= 6000
    assert elapsed < 5.0  # ~0.5 s on a laptop core; generous for CI


def test_electrode_table_matches_facts():
    e = electrode_table()
    assert e.positions.shape == e.normals.shape == (19, 3)
    np.testing.assert_allclose(np.linalg.norm(e.normals, axis=1), 1.0, atol=1e-12)
    np.testing.assert_allclose(e.positions[6], [4.763 * MM, 0.0, -2.330 * MM])
    np.testing.assert_allclose(e.positions[16:, 2], -5.08 * MM)
    tip = e.positions[6:10]  # E7-E10 on the tilted plane n.p = 4.40 mm
    np.testing.assert_allclose(tip @ BEVEL_NORMAL, 4.40 * MM, atol=0.01 * MM)
    np.testing.assert_allclose(e.normals[6:10], np.tile(BEVEL_NORMAL, (4, 1)), atol=1e-4)
    ring = e.positions[[1, 2, 3, 4, 5, 11, 12, 13, 14, 15, 16, 17, 18]]
    np.testing.assert_allclose(np.hypot(ring[:, 1], ring[:, 2]), 5.08 * MM, atol=0.01 * MM)
    left, right = e.positions[[0, 1, 2, 3, 4, 5]], e.positions[[10, 11, 12, 13, 14, 15]]
    np.testing.assert_allclose(left * [1, -1, 1], right)  # E1-E6 mirror E11-E16 across y = 0


def test_core_is_closed_outward_and_carries_electrodes():
    g = make_biotac(1e-3)
    v, t = g.core.vertices, g.core.triangles
    directed = np.vstack([t[:, [0, 1]], t[:, [1, 2]], t[:, [2, 0]]])
    assert len(np.unique(directed, axis=0)) == len(directed)
    _, counts = np.unique(np.sort(directed, axis=1), axis=0, return_counts=True)
    assert np.all(counts == 2), "core mesh is not watertight"
    volume = signed_volume(v, t, v.mean(axis=0))
    assert 1000e-9 < volume < 1600e-9  # m^3; the public core body is 1398 mm^3
    assert np.all(inside_core(v, D, tol=1e-6))
    e = electrode_table().positions
    assert np.all(inside_core(e, D, tol=1e-6))
    np.testing.assert_allclose(project_to_core(v, D), v, atol=1e-6)  # on the core (table: 1 um)
    on_core = [1, 2, 3, 4, 5, 6, 7, 8, 9, 11, 12, 13, 14, 15, 16, 17, 18]  # E1/E11 sit 0.1 mm deeper
    tris = v[t]
    for p in e[on_core]:
        gap = np.linalg.norm(trimesh.triangles.closest_point(tris, np.tile(p, (len(tris), 1))) - p, axis=1)
        assert gap.min() < (1e-3) ** 2 / (8 * D.core_radius) + 1e-6
    # the core lies inside the skin's inner surface over the free ventral skin
    s = g.skin
    skin_free = s.vertices[~s.anchored]
    assert not np.any(inside_core(skin_free, D, tol=g.core_gap))


def test_cavity_volume_is_consistent():
    g = make_biotac(2e-3)
    assert 300e-9 < g.cavity_volume_reference < 550e-9
    coarse = cavity_volume(D, spacing=0.2 * MM)
    assert coarse == pytest.approx(g.cavity_volume_reference, rel=0.02)
    thicker = dataclasses.replace(D, skin_outer_radius=D.skin_outer_radius + 0.2 * MM)
    assert cavity_volume(thicker, spacing=0.2 * MM) > coarse


def test_outer_surface_offset(geo):
    _, g = geo
    outer = outer_surface(g.skin, 1.6 * MM)
    np.testing.assert_allclose(np.linalg.norm(outer - g.skin.vertices, axis=1), 0.8 * MM, rtol=1e-12)
    n = vertex_normals(g.skin.vertices, g.skin.triangles)
    assert np.all(np.einsum("ij,ij->i", outer - g.skin.vertices, n) > 0.0)
    with pytest.raises(ValueError, match="thickness"):
        outer_surface(g.skin, -1.0)


def test_sample_ventral_points_on_outer_surface_and_seeded(geo):
    h, g = geo
    pts, normals = sample_ventral_points(g, 500, np.random.default_rng(7))
    assert pts.shape == normals.shape == (500, 3)
    radial, r = radial_direction(pts, D.axis_z, D.tip_center_x)
    sagitta = h**2 / (4 * D.skin_mid_radius)
    assert np.abs(r - D.skin_outer_radius).max() < sagitta + 1e-6
    np.testing.assert_allclose(np.linalg.norm(normals, axis=1), 1.0)
    assert np.einsum("ij,ij->i", normals, radial).min() > 0.95
    assert pts[:, 0].min() >= D.proximal_x and pts[:, 2].max() <= D.dorsal_anchor_z
    again, _ = sample_ventral_points(g, 500, np.random.default_rng(7))
    other, _ = sample_ventral_points(g, 500, np.random.default_rng(8))
    np.testing.assert_array_equal(pts, again)
    assert not np.allclose(pts, other)
    assert pts[:, 2].min() < D.axis_z - 0.9 * D.skin_outer_radius  # reaches the pad


@pytest.mark.parametrize("max_edge", [0.0, -1e-3, float("nan"), float("inf"), 5.0])
def test_bad_max_edge_raises(max_edge):
    with pytest.raises(ValueError, match="max_edge"):
        make_biotac(max_edge)


@pytest.mark.parametrize(
    "change, message",
    [
        ({"skin_thickness": -1e-3}, "skin_thickness"),
        ({"skin_outer_radius": 7.0}, "skin_outer_radius"),
        ({"core_radius": 8e-3}, "core_radius"),
        ({"dorsal_anchor_z": 20e-3}, "dorsal_anchor_z"),
        ({"dorsal_anchor_z": 5.0e-3, "anchor_band": 3e-3}, "dorsal_anchor_z \\+ anchor_band"),
        ({"proximal_x": 5e-3}, "proximal_x"),
        ({"anchor_band": float("nan")}, "anchor_band"),
        ({"dorsal_top_z": 0.0}, "dorsal_top_z"),
    ],
)
def test_nonsense_dimensions_raise(change, message):
    with pytest.raises(ValueError, match=message):
        BioTacDimensions(**{**dataclasses.asdict(D), **change})


def test_sample_negative_count_raises():
    with pytest.raises(ValueError, match="n must be"):
        sample_ventral_points(make_biotac(2e-3), -1, np.random.default_rng(0))
