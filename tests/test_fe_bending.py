"""Discrete shell bending against Kirchhoff plate theory (nu = 1/2, D = mu t^3 / 3)."""

import numpy as np
import pytest

from fe.dome import disk_mesh
from fe.newton import NewtonSettings, solve_equilibrium
from fe.params import SkinParameters
from fe.shell import ShellSystem

T, MU = 1e-3, 1e6  # m, Pa
D = MU * T**3 / 3.0  # J


@pytest.mark.parametrize("max_edge", [1e-3, 0.5e-3])
def test_spherical_cap_stores_the_plate_energy(max_edge: float) -> None:
    # A flat plate bent to a sphere of radius rho: E = (D / 2) [(k1 + k2)^2 - 2 (1 - nu) k1 k2] A = (3 D / 2) A / rho^2.
    radius, rho = 5e-3, 50e-3
    mesh = disk_mesh(radius, max_edge)
    bent = mesh.vertices.copy()
    bent[:, 2] = rho - np.sqrt(rho**2 - (bent[:, :2] ** 2).sum(axis=1))
    system = ShellSystem(mesh, SkinParameters(thickness=T, mu_nh=MU))
    energies = system.evaluate(bent, False)["bending_energies"]
    # Triangles whose whole stencil lies away from the mesh's free edge.
    inner = np.all(np.linalg.norm(mesh.vertices[system.bending_stencils, :2], axis=2) < radius, axis=1)
    p0, p1, p2 = (mesh.vertices[mesh.triangles[inner, k]] for k in range(3))
    area = 0.5 * np.linalg.norm(np.cross(p1 - p0, p2 - p0), axis=1).sum()
    assert energies[inner].sum() == pytest.approx(1.5 * D * area / rho**2, rel=0.02)


def _clamped_plate_centre_deflection(max_edge: float, radius: float, pressure: float) -> float:
    params = SkinParameters(thickness=T, mu_nh=MU)
    system = ShellSystem(disk_mesh(radius, max_edge), params, volume_origin=np.array([0.0, 0.0, -0.05]))
    q0 = system.free_coordinates(system.x)
    # Pressure held fixed (no volume target): the load is p on the plate.
    result = solve_equilibrium(system, q0, pressure, None, NewtonSettings(force_tolerance=1e-14))
    assert result.converged, result.message
    return float(system.positions(result.q)[0, 2])


def test_clamped_plate_under_pressure_converges_to_kirchhoff_theory() -> None:
    # w0 = p a^4 / (64 D); w0 = t / 20 keeps the membrane (von Karman) correction below 0.2%.
    radius = 10e-3
    exact = T / 20
    pressure = 64 * D * exact / radius**4
    errors = [abs(_clamped_plate_centre_deflection(h, radius, pressure) / exact - 1) for h in (1.4e-3, 0.7e-3)]
    assert errors[1] < 0.15 and errors[1] < 0.6 * errors[0], errors
