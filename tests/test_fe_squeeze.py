"""The skin's through-thickness compression (`fe.contact.layer_response`) against the incompressible
Neo-Hookean layer squeezed between rigid frictionless plates: nominal stress mu (lam - lam^-2) (Ogden,
Non-linear Elastic Deformations, sec. 7.2), lam = D / t for plates D apart around a layer of thickness t.

Two flat skin disks (1 mm thick) lie on a flat core, under a flat box indenter that closes in. Their in-plane
DOFs are held and their normals point opposite ways, so the fluid volume they enclose (to any origin) is
unchanged when both sink together: the held volume costs no pressure, and each mid-surface must move down
half the closure to balance its two half-layers (the solve finds that, starting from the indenter's predictor).
"""

import numpy as np
import pytest
import warp as wp

from assets.indenters import KIND_BOX, Indenter
from fe.batched import InflatedSkin
from fe.batched_stepper import BatchedStepper
from fe.contact import layer_response
from fe.dome import disk_mesh
from fe.params import SkinParameters

T, MU = 1e-3, 2.8e5  # skin thickness (m), shear modulus (Pa)
H = 0.5 * T  # half-layer (m): the core's and the indenter's offset from the mid-surface
PLATE = Indenter("plate", KIND_BOX, (20e-3, 20e-3, 5e-3, 1e-3), "flat box, 40 mm square")


def _squeeze_model() -> tuple[InflatedSkin, float]:
    """Two disks (radius 3 mm, 1 mm edges) at x = -/+ 5 mm in z = 0, the second one flipped; the core a flat
    square at z = -H. Returns the skin and the disks' total area (m^2, from the triangles)."""
    disk = disk_mesh(3e-3, 1e-3, clamp_rings=1)
    n = len(disk.vertices)
    vertices = np.vstack([disk.vertices - [5e-3, 0.0, 0.0], disk.vertices + [5e-3, 0.0, 0.0]])
    triangles = np.vstack([disk.triangles, disk.triangles[:, ::-1] + n])
    fixed = np.zeros((2 * n, 3), dtype=bool)
    fixed[:, :2] = True  # in-plane held: the layers alone carry the squeeze, the disks stay flat
    core_vertices = np.array([[-20e-3, -20e-3, -H], [20e-3, -20e-3, -H], [20e-3, 20e-3, -H], [-20e-3, 20e-3, -H]])
    core_triangles = np.array([[0, 1, 2], [0, 2, 3]])
    params = SkinParameters(thickness=T, mu_nh=MU, friction=0.0)
    rest = InflatedSkin.at_rest(
        vertices,
        triangles,
        fixed,
        params,
        core=(core_vertices, core_triangles, H),
        volume_origin=np.array([0, 0, -0.01]),
    )
    p0, p1, p2 = (vertices[triangles[:, k]] for k in range(3))
    area = 0.5 * np.linalg.norm(np.cross(p1 - p0, p2 - p0), axis=1).sum()
    return rest, float(area)


@pytest.fixture(scope="module")
def squeezed() -> tuple[list, np.ndarray, float]:
    """Increments of the plate closing from 2 % to 80 % of the thickness, the closures (m) and the area."""
    rest, area = _squeeze_model()
    skin = InflatedSkin(**{**rest.__dict__, "target_volume": 0.0})  # the disks' volumes cancel
    stepper = BatchedStepper(skin, [PLATE])
    closures = T * np.r_[np.arange(0.02, 0.72, 0.04), 0.8]
    results = []
    for closure in closures:
        (result,) = stepper.step(np.eye(3)[None], np.array([[0.0, 0.0, H - closure]]))
        results.append(result)
        if not result.converged:
            break
    return results, closures, area


def test_plate_force_follows_the_neo_hookean_layer(squeezed: tuple[list, np.ndarray, float]) -> None:
    results, closures, area = squeezed
    accepted = [r for r in results if r.converged]
    assert len(accepted) == len(closures) - 1  # every closure up to 68 % of t; 80 % is refused below
    lam = (T - closures[: len(accepted)]) / T
    expected = area * MU * (lam**-2 - lam)  # N, the plate pushing the skin down (-z)
    force = -np.array([r.force for r in accepted])
    assert np.allclose(force[:, :2], 0.0, atol=1e-9 * expected.max())
    assert np.allclose(force[:, 2], expected, rtol=1e-5), force[:, 2] / expected - 1
    # Each mid-surface sank half the closure (both half-layers at lam), no fluid pressure needed.
    sink = np.array([r.displacement[:, 2] for r in accepted])
    assert np.allclose(sink, -0.5 * closures[: len(accepted), None], atol=1e-9)
    assert all(abs(r.pressure) * area < 1e-6 * f for r, f in zip(accepted, expected, strict=True))
    # Smooth and steep: force rising, its slope rising (no jumps), 9x stiffer at lam = 0.32 than near 1.
    slope = np.diff(force[:, 2]) / np.diff(closures[: len(accepted)])
    assert np.all(slope > 0.0) and np.all(np.diff(slope) > 0.0)
    assert slope[-1] > 9.0 * slope[0]


def test_squeezing_past_the_floor_is_refused(squeezed: tuple[list, np.ndarray, float]) -> None:
    """At 80 % closure each half-layer would sit at lam = 0.2, below `ContactSettings.min_stretch` (0.25)."""
    last = squeezed[0][-1]
    assert not last.converged
    assert "inadmissible" in last.message and "half-thickness" in last.message, last.message


@wp.kernel
def _law(g: wp.array(dtype=wp.float64), h: wp.float64, out: wp.array(dtype=wp.vec3d)):
    i = wp.tid()
    one = wp.float64(1.0)
    out[i] = layer_response(g[i], h, wp.float64(MU), one, wp.float64(1e11), wp.float64(0.25))


def test_the_law_per_vertex_is_the_layer_energy_and_its_derivatives_across_the_floor() -> None:
    """Per unit area: energy h (mu/2)(lam^2 + 2/lam - 3) above the floor (numpy, from the formula), its slope and
    curvature by central differences everywhere, continuous through lam = 1 and the floor lam = 0.25."""
    lam = np.r_[np.linspace(0.05, 1.2, 2301), 0.25, 1.0]
    g, step = (lam - 1.0) * H, 1e-9
    rows = np.concatenate([g - step, g, g + step])
    out = wp.zeros(len(rows), dtype=wp.vec3d, device="cpu")
    wp.launch(_law, len(rows), [wp.array(rows, dtype=wp.float64, device="cpu"), wp.float64(H), out], device="cpu")
    minus, law, plus = np.split(out.numpy(), 3)
    neo = (lam >= 0.25) & (lam < 1.0)
    expected = H * MU / 2 * (lam[neo] ** 2 + 2 / lam[neo] - 3)  # cancels to ~1e-16 of H mu near lam = 1
    assert np.allclose(law[neo, 0], expected, rtol=1e-12, atol=1e-14 * H * MU)
    assert np.all(law[lam >= 1.0] == 0.0)
    assert np.allclose(law[neo, 1], MU * (lam[neo] - lam[neo] ** -2), rtol=1e-12)  # nominal stress (Pa)
    scale = np.abs(law[:, 1:]).max(axis=0)
    assert np.allclose((plus[:, 0] - minus[:, 0]) / (2 * step), law[:, 1], atol=1e-6 * scale[0])
    smooth = np.abs(g) > step  # the stiffness jumps from 0 to 3 mu / h at lam = 1 (C1 there, not C2)
    curvature = (plus[smooth, 1] - minus[smooth, 1]) / (2 * step)
    assert np.allclose(curvature, law[smooth, 2], atol=1e-5 * scale[1])
    below = lam < 0.25
    assert np.all(np.isfinite(law)) and np.all(np.diff(law[np.argsort(lam), 1]) >= 0.0)  # convex, finite
    assert np.all(law[below, 2] == law[lam == 0.25, 2][0])  # quadratic past the floor
