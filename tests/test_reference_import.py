"""Tests of the importer for the public BioTac FE meshes (assets/reference_mesh.py).

The reference files live outside the project (../shared/reference); tests that need them skip
when they are absent.
"""

from pathlib import Path

import numpy as np
import pytest

from assets.biotac import DEFAULT_DIMENSIONS, boundary_vertices, make_biotac, outer_surface, signed_volume
from assets.reference_mesh import (
    file_to_biotac,
    load_reference_biotac,
    load_tet_mesh,
    point_mesh_distance,
    split_components,
    tet_boundary,
    to_biotac_frame,
)

MM = 1e-3
D = DEFAULT_DIMENSIONS
MESHES = Path(__file__).resolve().parents[1] / ".." / "shared" / "reference" / "biotac_sim" / "meshes" / "biotac"
TET = MESHES / "int_ext_skin" / "int_ext_skin_combined_ftw.tet"
CORE = MESHES / "bc" / "top_side_core_bc.obj"

needs_reference = pytest.mark.skipif(
    not (TET.exists() and CORE.exists()),
    reason=f"public BioTac reference meshes not found under {MESHES} (optional, not shipped)",
)


@pytest.fixture(scope="module")
def surfaces():
    vertices, tets = load_tet_mesh(TET)
    return vertices, tets, split_components(vertices, tet_boundary(vertices, tets))


@pytest.fixture(scope="module")
def reference():
    return load_reference_biotac(TET, CORE)


def test_load_tet_mesh_rejects_garbage(tmp_path):
    bad = tmp_path / "bad.tet"
    bad.write_text("# nothing here\n")
    with pytest.raises(ValueError, match="no 'v'"):
        load_tet_mesh(bad)
    bad.write_text("v 0 0 0 0\nv 1 0 0 0\nv 0 1 0 0\nt 0 1 2 3\n")
    with pytest.raises(ValueError, match="indices"):
        load_tet_mesh(bad)


def test_frame_transform_is_a_proper_rotation():
    transform = file_to_biotac()
    rotation = transform[:3, :3]
    np.testing.assert_allclose(rotation @ rotation.T, np.eye(3))
    assert np.linalg.det(rotation) == pytest.approx(1.0)
    # file +y (indenter travel, toward the nail) is biotac +z; file -x (the tip) is biotac +x
    np.testing.assert_allclose(rotation @ [0, 1, 0], [0, 0, 1])
    np.testing.assert_allclose(rotation @ [-1, 0, 0], [1, 0, 0])


@needs_reference
def test_counts_and_bounds_match_the_published_mesh(surfaces):
    vertices, tets, parts = surfaces
    assert vertices.shape == (4246, 3) and tets.shape == (15410, 4)
    assert len(parts) == 2
    (outer_v, _), (inner_v, _) = parts
    assert len(outer_v) == 1686 and len(inner_v) == 1586
    np.testing.assert_allclose(outer_v.min(axis=0) / MM, [-21.31, -8.31, -7.11], atol=0.01)
    np.testing.assert_allclose(outer_v.max(axis=0) / MM, [6.65, 5.33, 7.11], atol=0.01)
    np.testing.assert_allclose(inner_v.min(axis=0) / MM, [-19.74, -6.69, -5.54], atol=0.01)
    np.testing.assert_allclose(inner_v.max(axis=0) / MM, [5.08, 3.76, 5.54], atol=0.01)


@needs_reference
def test_boundary_orientation_points_out_of_the_skin(surfaces):
    _, _, ((outer_v, outer_t), (inner_v, inner_t)) = surfaces
    centre = outer_v.mean(axis=0)
    assert signed_volume(outer_v, outer_t, centre) > 0.0  # outer surface: normals outward
    assert signed_volume(inner_v, inner_t, centre) < 0.0  # inner surface: normals toward the core


@needs_reference
def test_biotac_frame_places_tip_pad_and_thickness(surfaces):
    _, _, ((outer_v, _), _) = surfaces
    p = to_biotac_frame(outer_v)
    assert p[:, 0].max() == pytest.approx(9.06 * MM, abs=0.05 * MM)  # rounded tip at +x
    assert p[:, 2].min() == pytest.approx(-8.31 * MM, abs=0.01 * MM)  # ventral pad at -z
    assert np.ptp(p[:, 2]) == pytest.approx(13.64 * MM, abs=0.01 * MM)


@needs_reference
def test_imported_geometry_is_consistent(reference):
    skin = reference.skin
    t = skin.triangles
    directed = np.vstack([t[:, [0, 1]], t[:, [1, 2]], t[:, [2, 0]]])
    assert len(np.unique(directed, axis=0)) == len(directed)
    _, counts = np.unique(np.sort(directed, axis=1), axis=0, return_counts=True)
    assert counts.max() <= 2
    assert skin.anchored[boundary_vertices(t, len(skin.vertices))].all()
    assert skin.ventral.sum() > 0.5 * (~skin.anchored).sum()
    assert skin.vertices[:, 0].min() >= D.proximal_x - D.anchor_band
    assert reference.core_gap == pytest.approx(0.79 * MM, abs=0.03 * MM)
    assert reference.dorsal_top_z == pytest.approx(5.33 * MM, abs=0.01 * MM)
    core_volume = signed_volume(reference.core.vertices, reference.core.triangles, np.zeros(3))
    assert core_volume == pytest.approx(1398e-9, rel=0.01)  # the core body, boxes dropped
    assert 250e-9 < reference.cavity_volume_reference < 450e-9


@needs_reference
def test_importer_refines_and_falls_back_to_inner_core():
    geo = load_reference_biotac(TET, max_edge=0.4 * MM)
    p = geo.skin.vertices[geo.skin.triangles]
    assert np.linalg.norm(p - p[:, [1, 2, 0]], axis=2).max() <= 0.4 * MM
    assert geo.cavity_volume_reference == 0.0
    with pytest.raises(ValueError, match="max_edge"):
        load_reference_biotac(TET, max_edge=-1.0)


@needs_reference
def test_parametric_outer_surface_fits_the_reference(surfaces):
    _, _, ((outer_v, outer_t), _) = surfaces
    ref = to_biotac_frame(outer_v)
    ventral = (ref[:, 0] >= D.proximal_x + D.anchor_band) & (ref[:, 2] <= D.dorsal_anchor_z - D.anchor_band)
    geo = make_biotac(1e-3)
    mine = outer_surface(geo.skin, 2 * geo.core_gap)
    dist = point_mesh_distance(ref[ventral], mine, geo.skin.triangles)
    assert ventral.sum() > 500
    assert np.sqrt(np.mean(dist**2)) < 0.25 * MM  # target 1 mm; the fit gives ~0.14 mm
    assert dist.max() < 0.5 * MM
    back = point_mesh_distance(mine[geo.skin.ventral], ref, outer_t)
    assert np.sqrt(np.mean(back**2)) < 0.25 * MM
