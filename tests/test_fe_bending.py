"""Discrete-shell bending coefficient against plate theory: a flat disk bent into a spherical cap."""

import numpy as np
import pytest

from fe.dome import disk_mesh
from fe.params import SkinParameters
from fe.shell import ShellSystem


@pytest.mark.parametrize("max_edge", [1e-3, 0.5e-3])
def test_bending_energy_of_a_spherical_cap_is_the_plate_energy(max_edge: float) -> None:
    # Plate theory (nu = 1/2, D = mu t^3 / 3): E = (D / 2) int (k1 + k2)^2 dA = (D / 2) (2 / rho)^2 A for a
    # flat plate bent to a sphere of radius rho (Gaussian term left out, as for clamped or closed shells).
    radius, rho, t, mu = 5e-3, 50e-3, 0.5e-3, 1e5
    mesh = disk_mesh(radius, max_edge)
    bent = mesh.vertices.copy()
    r2 = (bent[:, :2] ** 2).sum(axis=1)
    bent[:, 2] = rho - np.sqrt(rho**2 - r2)
    energies = [
        ShellSystem(mesh, SkinParameters(thickness=t, mu_nh=mu, bending=on)).evaluate(bent, False)["elastic_energy"]
        for on in (True, False)
    ]
    p0, p1, p2 = (mesh.vertices[mesh.triangles[:, k]] for k in range(3))
    area = 0.5 * np.linalg.norm(np.cross(p1 - p0, p2 - p0), axis=1).sum()
    plate = 0.5 * (mu * t**3 / 3.0) * (2.0 / rho) ** 2 * area
    # The boundary edges have no hinge: a loss of about one ring of the disk's area.
    assert energies[0] - energies[1] == pytest.approx(plate, rel=0.06 + 2 * max_edge / radius)
