"""Discrete shell bending against Kirchhoff plate theory (nu = 1/2, D = mu t^3 / 3), on the FE engine."""

import numpy as np
import pytest
import warp as wp

from fe.batched import BatchedShell, InflatedSkin
from fe.batched_stepper import BatchedStepper
from fe.bending import build_stencils
from fe.dome import disk_mesh
from fe.params import NewtonSettings, SkinParameters

T, MU = 1e-3, 1e6  # m, Pa
D = MU * T**3 / 3.0  # J


@pytest.mark.parametrize("max_edge", [1e-3, 0.5e-3])
def test_spherical_cap_stores_the_plate_energy(max_edge: float) -> None:
    # A flat plate bent to a sphere of radius rho: E = (D / 2) [(k1 + k2)^2 - 2 (1 - nu) k1 k2] A = (3 D / 2) A / rho^2.
    radius, rho = 5e-3, 50e-3
    mesh = disk_mesh(radius, max_edge)
    bent = mesh.vertices.copy()
    bent[:, 2] = rho - np.sqrt(rho**2 - (bent[:, :2] ** 2).sum(axis=1))
    skin = InflatedSkin.at_rest(mesh.vertices, mesh.triangles, mesh.fixed, SkinParameters(thickness=T, mu_nh=MU))
    shell = BatchedShell(skin, [(0, (5e-3, 0.0, 0.0, 0.0))])  # indenter at its default pose, 1 m away
    shell.evaluate(wp.array(bent[None], dtype=wp.vec3d), False, np.zeros(1))
    energies = shell.buf["bending_energy"].numpy()[0]
    stencils = build_stencils(mesh.triangles)[0]  # the engine's stencils: one per triangle
    assert len(energies) == len(stencils) == len(mesh.triangles)
    # Triangles whose whole stencil lies away from the mesh's free edge.
    inner = np.all(np.linalg.norm(mesh.vertices[stencils, :2], axis=2) < radius, axis=1)
    p0, p1, p2 = (mesh.vertices[mesh.triangles[inner, k]] for k in range(3))
    area = 0.5 * np.linalg.norm(np.cross(p1 - p0, p2 - p0), axis=1).sum()
    assert energies[inner].sum() == pytest.approx(1.5 * D * area / rho**2, rel=0.02)


def _clamped_plate(max_edge: float, radius: float, volume: float) -> tuple[float, float]:
    """Centre deflection (m) and pressure (Pa) of the clamped plate under a held fluid volume (m^3) below it.

    The engine holds volumes, not pressures: the plate's swept volume is prescribed and the pressure is the
    constraint's multiplier, so Kirchhoff's p-w relation is checked between the two engine outputs."""
    mesh = disk_mesh(radius, max_edge)
    params = SkinParameters(thickness=T, mu_nh=MU)
    # A part-per-billion force balance (a 1e-14 N absolute floor is below round-off: the line search fails).
    newton = NewtonSettings(force_tolerance=1e-12, relative_force_tolerance=1e-9)
    skin = InflatedSkin.at_rest(
        mesh.vertices, mesh.triangles, mesh.fixed, params, newton=newton, volume_origin=np.array([0.0, 0.0, -0.05])
    )
    engine = BatchedStepper(skin, ["sphere_medium"])
    converged, messages = engine.hold_volume(np.array([engine.rest_volumes[0] + volume]))
    assert converged[0], messages[0]
    return float(engine.x[0, 0, 2]), float(engine.pressure[0])


def test_clamped_plate_under_pressure_converges_to_kirchhoff_theory() -> None:
    # w = w0 (1 - r^2 / a^2)^2, w0 = p a^4 / (64 D), sweeping pi a^2 w0 / 3; w0 = t / 20 keeps the membrane
    # (von Karman) correction below 0.2%.
    radius = 10e-3
    w0 = T / 20
    volume = np.pi * radius**2 * w0 / 3
    errors = []
    for h in (1.4e-3, 0.7e-3):
        deflection, pressure = _clamped_plate(h, radius, volume)
        assert pressure > 0.0
        errors.append(abs(deflection / (pressure * radius**4 / (64 * D)) - 1))
    assert errors[1] < 0.15 and errors[1] < 0.6 * errors[0], errors
