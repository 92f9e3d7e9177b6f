"""Closed spherical Neo-Hookean (or Gent) membrane inflated under volume control: the analytic check of fe/.

Membrane theory: with energy w(lambda) per reference area under equibiaxial stretch lambda, p dV = dE for
E = 4 pi R^2 w and V = (4/3) pi R^3 lambda^3 gives p = w'(lambda) / (R lambda^2). For the incompressible
Gent membrane, w = -(mu t / 2) J_m ln(1 - (I1 - 3) / J_m) with I1 = 2 lambda^2 + lambda^-4, so
p = 2 mu t / R (1/lambda - 1/lambda^7) / (1 - (I1 - 3) / J_m); J_m -> infinity is Neo-Hookean, with a
pressure maximum at lambda = 7^(1/6) ~ 1.38 that volume control passes through.
"""

from dataclasses import dataclass

import numpy as np
import trimesh

from assets.indenters import get_indenter
from fe.batched import InflatedSkin
from fe.batched_stepper import BatchedStepper
from fe.newton import NewtonSettings
from fe.params import SkinParameters
from fe.shell import ShellMesh


@dataclass(frozen=True)
class BalloonPoint:
    """One equilibrium: volume ratio V/V0, stretch, FE pressure (Pa) and membrane-theory pressure (Pa)."""

    volume_ratio: float
    stretch: float
    pressure_pa: float
    analytic_pressure_pa: float
    converged: bool


def analytic_balloon_pressure(
    stretch: np.ndarray | float, radius: float, thickness: float, mu: float, gent_inverse_jm: float = 0.0
) -> np.ndarray:
    """p (Pa) of an incompressible Neo-Hookean (Gent with 1/J_m > 0) spherical membrane at stretch lambda."""
    lam = np.asarray(stretch, dtype=float)
    i1 = 2.0 * lam**2 + lam**-4
    return 2.0 * mu * thickness / radius * (1.0 / lam - 1.0 / lam**7) / (1.0 - gent_inverse_jm * (i1 - 3.0))


def sphere_mesh(radius: float, subdivisions: int) -> ShellMesh:
    """Icosphere (m) with six coordinates held to remove rigid motions but not uniform inflation."""
    sphere = trimesh.creation.icosphere(subdivisions=subdivisions, radius=radius)
    v = np.asarray(sphere.vertices, dtype=np.float64)
    fixed = np.zeros((len(v), 3), dtype=bool)
    north, south = int(np.argmax(v[:, 2])), int(np.argmin(v[:, 2]))
    equator = int(np.argmin(np.abs(v[:, 2]) + np.abs(v[:, 1]) - v[:, 0]))
    fixed[north, :2] = fixed[south, :2] = True
    fixed[equator, 1:] = True
    return ShellMesh(v, np.asarray(sphere.faces, dtype=np.int32), fixed)


def inflate_balloon(
    radius: float,
    thickness: float,
    mu: float,
    volume_ratios: list[float],
    subdivisions: int = 3,
    bending: bool = False,
    max_volume_step: float = 0.1,
    gent_inverse_jm: float = 0.0,
) -> list[BalloonPoint]:
    """Inflate a closed sphere (radius m, thickness m, shear modulus Pa, Gent 1/J_m) to each volume ratio.

    Between requested ratios the volume is raised in steps of at most `max_volume_step` V0.
    """
    if radius <= 0 or thickness <= 0 or mu <= 0:
        raise ValueError("radius, thickness and mu must be positive")
    if any(r <= 0 for r in volume_ratios):
        raise ValueError("volume ratios must be positive")
    params = SkinParameters(thickness=thickness, mu_nh=mu, bending=bending, gent_inverse_jm=gent_inverse_jm)
    mesh = sphere_mesh(radius, subdivisions)
    rest = InflatedSkin.at_rest(mesh.vertices, mesh.triangles, mesh.fixed, params, newton=NewtonSettings())
    engine = BatchedStepper(rest, [get_indenter("sphere_medium")])  # no indenter pose: it stays away
    v0, current, points = engine.rest_volumes[0], 1.0, []
    # Walk in small volume steps so that Newton always starts near the solution.
    for ratio in volume_ratios:
        n_steps = max(1, int(np.ceil(abs(ratio - current) / max_volume_step)))
        converged = np.ones(1, dtype=bool)
        for target in np.linspace(current, ratio, n_steps + 1)[1:]:
            converged, _ = engine.hold_volume(np.array([target * v0]))
            if not converged[0]:
                break
            current = target
        pressure = float(engine.pressure[0])
        stretch = ratio ** (1.0 / 3.0)
        points.append(
            BalloonPoint(
                volume_ratio=ratio,
                stretch=stretch,
                pressure_pa=pressure,
                analytic_pressure_pa=float(analytic_balloon_pressure(stretch, radius, thickness, mu, gent_inverse_jm)),
                converged=bool(converged[0]),
            )
        )
    return points
