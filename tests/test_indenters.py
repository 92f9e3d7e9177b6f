"""Tests of the nine indenters: numpy SDFs, their warp twins, meshes, and the public reference meshes."""

from pathlib import Path

import numpy as np
import pytest
import trimesh
import warp as wp

from assets.indenters import (
    INDENTERS,
    KIND_BOX,
    KIND_CYLINDER_FLAT,
    KIND_CYLINDER_SIDE,
    KIND_SPHERE,
    KIND_TORUS,
    TEXTURE_FILLET,
    TEXTURE_RIM,
    Indenter,
    get_indenter,
    texture_bump_centres,
)
from fe.indenter_sdf import indenter_sdf_and_grad
from fe.params import SKIN_PARAMETERS, SkinParameters

REFERENCE = Path(__file__).resolve().parents[1] / ".." / "shared" / "reference" / "biotac_sim"
PUBLIC = {
    "sphere_small": "sphere_3-5mm",
    "sphere_medium": "sphere_7mm",
    "sphere_large": "sphere_14mm",
    "cylinder_short_small": "cylinder_short_3-5mm",
    "cylinder_short_medium": "cylinder_short_7mm",
    "cylinder_long": "cylinder_long_7mm",
    "cube": "cube_14mm",
    "ring": "ring_7mm",
}
# a flat punch exercises KIND_CYLINDER_FLAT, which none of the nine uses
FLAT_PUNCH = Indenter("flat_punch", KIND_CYLINDER_FLAT, (5e-3, 4e-3, 0.5e-3, 0.0), "test flat punch")
ALL = [*INDENTERS.values(), FLAT_PUNCH]
IDS = [ind.name for ind in ALL]
MESH_EDGE = 1.0e-3


@pytest.fixture(scope="module")
def meshes() -> dict[str, trimesh.Trimesh]:
    """Meshes of every tested indenter at a coarse (fast) max edge."""
    return {ind.name: ind.mesh(max_edge=MESH_EDGE) for ind in ALL}


def pressing_band(ind: Indenter) -> float:
    """Height above the tip (m) below which the mesh is pure head (no shank), for surface checks."""
    return min(0.5 * ind.head_height(), 3.0e-3)


def near_surface_points(
    ind: Indenter, mesh: trimesh.Trimesh, rng: np.random.Generator
) -> tuple[np.ndarray, np.ndarray]:
    """Points 0.02-0.25 mm either side of the head surface, from mesh vertices moved along the normal."""
    v = mesh.vertices[mesh.vertices[:, 2] <= pressing_band(ind)]
    v = v[np.abs(ind.sdf(v)) < 1e-6]
    v = v[rng.choice(len(v), size=min(400, len(v)), replace=False)]
    delta = rng.uniform(0.02e-3, 0.25e-3, len(v)) * rng.choice([-1.0, 1.0], len(v))
    return v + delta[:, None] * ind.sdf_gradient(v), delta


def box_points(ind: Indenter, rng: np.random.Generator, n: int = 1500) -> np.ndarray:
    """Random points in a box around the head, including below the tip and deep inside."""
    lo, hi = ind._mesh_bounds()
    hi = hi.copy()
    hi[2] = ind.head_height() + 1e-3
    lo = lo - np.array([2e-3, 2e-3, 4e-3])
    return rng.uniform(lo, hi + np.array([2e-3, 2e-3, 0.0]), (n, 3))


@wp.kernel
def _eval64(
    kind: int,
    dims: wp.vec4d,
    pts: wp.array(dtype=wp.vec3d),
    d: wp.array(dtype=wp.float64),
    g: wp.array(dtype=wp.vec3d),
):
    i = wp.tid()
    r = indenter_sdf_and_grad(kind, dims, pts[i])
    d[i] = r[0]
    g[i] = wp.vec3d(r[1], r[2], r[3])


@wp.kernel
def _eval32(
    kind: int,
    dims: wp.vec4,
    pts: wp.array(dtype=wp.vec3),
    d: wp.array(dtype=wp.float32),
    g: wp.array(dtype=wp.vec3),
):
    i = wp.tid()
    r = indenter_sdf_and_grad(kind, dims, pts[i])
    d[i] = r[0]
    g[i] = wp.vec3(r[1], r[2], r[3])


def warp_eval(ind: Indenter, p: np.ndarray, double: bool) -> tuple[np.ndarray, np.ndarray]:
    """Distance and gradient from the warp functions, float64 or float32 overload."""
    vec3, vec4, real, kernel = (
        (wp.vec3d, wp.vec4d, wp.float64, _eval64) if double else (wp.vec3, wp.vec4, wp.float32, _eval32)
    )
    d = wp.zeros(len(p), dtype=real, device="cpu")
    g = wp.zeros(len(p), dtype=vec3, device="cpu")
    pts = wp.array(p, dtype=vec3, device="cpu")
    wp.launch(kernel, len(p), inputs=[ind.kind, vec4(*ind.dims), pts, d, g], device="cpu")
    return d.numpy().astype(float), g.numpy().astype(float)


@pytest.mark.parametrize("ind", ALL, ids=IDS)
def test_warp_matches_numpy(ind: Indenter, meshes: dict[str, trimesh.Trimesh]) -> None:
    rng = np.random.default_rng(1)
    p = np.concatenate([box_points(ind, rng), near_surface_points(ind, meshes[ind.name], rng)[0]])
    d_np, g_np = ind.sdf(p), ind.sdf_gradient(p)
    d64, g64 = warp_eval(ind, p, double=True)
    np.testing.assert_allclose(d64, d_np, rtol=0, atol=1e-9)
    np.testing.assert_allclose(g64, g_np, rtol=0, atol=1e-9)
    d32, g32 = warp_eval(ind, p, double=False)
    np.testing.assert_allclose(d32, d_np, rtol=0, atol=2e-8)
    near = np.abs(d_np) < 2e-3  # float32 gradients away from ridges
    assert np.quantile(np.abs(g32[near] - g_np[near]).max(axis=1), 0.99) < 1e-4


@pytest.mark.parametrize("ind", ALL, ids=IDS)
def test_gradient_is_unit_and_matches_finite_differences(ind: Indenter, meshes: dict[str, trimesh.Trimesh]) -> None:
    rng = np.random.default_rng(2)
    p, _ = near_surface_points(ind, meshes[ind.name], rng)
    g = ind.sdf_gradient(p)
    np.testing.assert_allclose(np.linalg.norm(g, axis=1), 1.0, atol=1e-12)
    h = 1e-9  # small: the curvature jumps where a fillet meets a flat (C1, not C2)
    fd = np.stack([(ind.sdf(p + h * e) - ind.sdf(p - h * e)) / (2 * h) for e in np.eye(3)], axis=1)
    np.testing.assert_allclose(g, fd, rtol=0, atol=1e-5)


@pytest.mark.parametrize("ind", ALL, ids=IDS)
def test_distance_is_euclidean_near_the_surface(ind: Indenter, meshes: dict[str, trimesh.Trimesh]) -> None:
    """Moving a surface point along its normal by delta gives sdf = delta (true distance, both sides)."""
    rng = np.random.default_rng(3)
    p, delta = near_surface_points(ind, meshes[ind.name], rng)
    np.testing.assert_allclose(ind.sdf(p), delta, rtol=0, atol=1e-12)


@pytest.mark.parametrize("ind", ALL, ids=IDS)
def test_mesh_is_watertight_and_on_the_surface(ind: Indenter, meshes: dict[str, trimesh.Trimesh]) -> None:
    mesh = meshes[ind.name]
    assert mesh.is_watertight and mesh.is_winding_consistent and mesh.volume > 0
    assert mesh.edges_unique_length.max() <= MESH_EDGE
    head = mesh.vertices[mesh.vertices[:, 2] <= pressing_band(ind)]
    assert len(head) > 50
    assert np.abs(ind.sdf(head)).max() < 1e-6
    assert mesh.bounds[1, 2] == pytest.approx(17.86e-3, abs=1e-6)


@pytest.mark.parametrize("ind", ALL, ids=IDS)
def test_tip_at_origin_body_above(ind: Indenter, meshes: dict[str, trimesh.Trimesh]) -> None:
    a, b, _, e = ind.dims
    if ind.kind == KIND_TORUS:  # origin = centre of the lip plane; the lip's flat annulus touches z = 0
        assert ind.sdf(np.zeros((1, 3)))[0] == pytest.approx(np.hypot(a + e, e) - e, abs=1e-12)
        assert ind.sdf(np.array([[0.5 * (a + b), 0.0, 0.0]]))[0] == pytest.approx(0.0, abs=1e-12)
    else:
        assert ind.sdf(np.zeros((1, 3)))[0] == pytest.approx(0.0, abs=1e-12)
        np.testing.assert_allclose(ind.sdf_gradient(np.zeros((1, 3))), [[0.0, 0.0, -1.0]], atol=1e-12)
    # a curved tip's lowest mesh vertex sits within ~h^2 / (8 R) of the tip (h = grid spacing)
    assert meshes[ind.name].vertices[:, 2].min() == pytest.approx(0.0, abs=3e-5)
    p = box_points(ind, np.random.default_rng(4))
    below = p[p[:, 2] < 0]
    assert np.all(ind.sdf(below) >= -below[:, 2] - 1e-12)  # nothing of the body below z = 0


def test_texture_design() -> None:
    tex = get_indenter("texture")
    rb, a, jit, half = tex.dims
    c = texture_bump_centres(tex.dims)
    assert len(c) == 25 and np.allclose(c[12], 0.0)
    sep = np.linalg.norm(c[:, None] - c[None], axis=2) + np.eye(len(c))
    assert sep.min() >= a - 2 * jit
    rho_f = np.sqrt(rb**2 + 2 * rb * TEXTURE_FILLET)  # radius of a bump's fillet foot
    assert np.abs(c).max() + rho_f < half - TEXTURE_RIM - 0.5e-3  # bumps clear of the rim
    np.testing.assert_allclose(tex.sdf(np.c_[c, np.zeros(len(c))]), 0.0, atol=1e-15)  # every apex at z = 0
    assert tex.sdf(np.array([[0.5 * a, 0.5 * a, rb]]))[0] == pytest.approx(0.0, abs=1e-12)  # plate face


def test_texture_distance_is_smooth_within_the_skin_layer() -> None:
    """The FE contact squeezes a half-layer h of skin (half its thickness) against the indenter, so the texture's
    distance must be smooth wherever it is below h: its kinks, the medial surfaces of each bump's concave foot,
    start TEXTURE_FILLET from the texture (and neighbouring feet must not meet). Checked for the paper's
    thickest skin (2 mm) and by scanning lines across the plate through every row's feet in 1 um steps: within
    the default skin's layer (0.785 mm) the gradient turns by no more than its curvature bound allows (a kink
    turns it by 0.1-1 at once; with the former 0.3 mm fillet the FE Newton stalled on one, issue 17)."""
    tex = get_indenter("texture")
    rb, a, jit, half = tex.dims
    c = texture_bump_centres(tex.dims)
    rho_f = np.sqrt(rb**2 + 2 * rb * TEXTURE_FILLET)
    assert TEXTURE_FILLET >= 0.5 * SKIN_PARAMETERS["thickness"].paper[1]
    assert (np.linalg.norm(c[:, None] - c[None], axis=2) + np.eye(len(c))).min() > 2 * rho_f  # feet apart
    h, step = 0.5 * SkinParameters().thickness, 1e-6
    x = np.arange(-half + 1e-3, half - 1e-3, step)
    for y in (np.arange(-2, 3) + 0.3) * a:
        for z in rb - np.array([0.2e-3, 0.45e-3, 0.7e-3]):
            p = np.c_[x, np.full_like(x, y), np.full_like(x, z)]
            d, g = tex.sdf(p), tex.sdf_gradient(p)
            both = (d[:-1] > 0.0) & (d[1:] > 0.0) & (d[:-1] < h) & (d[1:] < h)
            turn = np.linalg.norm(np.diff(g, axis=0), axis=1)[both]
            assert both.sum() > 1000 and turn.max() < step / (TEXTURE_FILLET - h), (y, z, turn.max())


def test_unknown_name_raises() -> None:
    with pytest.raises(ValueError, match="sphere_small"):
        get_indenter("sphere_huge")
    assert get_indenter("ring") is INDENTERS["ring"]
    assert len(INDENTERS) == 9


@pytest.mark.skipif(not REFERENCE.is_dir(), reason=f"public reference meshes not found at {REFERENCE}")
@pytest.mark.parametrize("name", sorted(PUBLIC))
def test_matches_public_mesh(name: str) -> None:
    """Public mesh vertices (tip at y = 0, shank along -y) lie on the analytic head; extents agree."""
    ind = INDENTERS[name]
    v = trimesh.load(REFERENCE / "meshes" / "indenters" / f"{PUBLIC[name]}.obj", force="mesh").vertices
    p = np.stack([v[:, 0], v[:, 2], -v[:, 1]], axis=1)  # public frame -> indenter frame
    assert p[:, 2].min() == pytest.approx(0.0, abs=2e-5)
    band = p[p[:, 2] <= pressing_band(ind)]
    assert len(band) > 50
    assert np.abs(ind.sdf(band)).max() < 2e-6
    a, b, _, _ = ind.dims
    expected = {
        KIND_SPHERE: (a, a),
        KIND_CYLINDER_SIDE: (0.5 * b, a),
        KIND_BOX: (a, b),
        KIND_TORUS: (b, b),
    }[ind.kind]
    head = p[p[:, 2] <= 0.5 * ind.head_height()]
    np.testing.assert_allclose(np.abs(head[:, :2]).max(axis=0), expected, atol=5e-5)  # public faceting
