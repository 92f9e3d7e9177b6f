"""Closed spherical Neo-Hookean (or Gent) membrane inflated under volume control: the analytic check of fe/.

Membrane theory: with energy w(lambda) per reference area under equibiaxial stretch lambda, p dV = dE for
E = 4 pi R^2 w and V = (4/3) pi R^3 lambda^3 gives p = w'(lambda) / (R lambda^2). For the incompressible
Gent membrane, w = -(mu t / 2) J_m ln(1 - (I1 - 3) / J_m) with I1 = 2 lambda^2 + lambda^-4, so
p = 2 mu t / R (1/lambda - 1/lambda^7) / (1 - (I1 - 3) / J_m); J_m -> infinity is Neo-Hookean, with a
pressure maximum at lambda = 7^(1/6) ~ 1.38 that volume control passes through.
"""

from collections.abc import Callable
from dataclasses import dataclass

import numpy as np
import trimesh

from assets.indenters import get_indenter
from fe.batched import InflatedSkin
from fe.batched_stepper import BatchedStepper
from fe.params import NewtonSettings, SkinParameters
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


MAX_VOLUME_RATIO = 125.0
"""Largest V/V0 `inflate_balloon` accepts: equibiaxial stretch 5, past the elongation at break of elastomers."""


def balloon_steps(volume_ratios: list[float], max_volume_step: float) -> list[list[float]]:
    """The volume ratios `inflate_balloon` holds on the way to each requested one, starting from V0.

    Steps are geometric, each changing the volume by at most the fraction `max_volume_step`, so a ratio r
    costs about ln(r) / ln(1 + max_volume_step) steps (51 to `MAX_VOLUME_RATIO` at 0.1).
    """
    current, paths = 1.0, []
    for ratio in volume_ratios:
        n_steps = max(1, int(np.ceil(abs(np.log(ratio / current)) / np.log1p(max_volume_step))))
        paths.append([float(current * (ratio / current) ** (k / n_steps)) for k in range(1, n_steps + 1)])
        current = ratio
    return paths


def check_balloon_input(radius: float, thickness: float, mu: float, volume_ratios: list[float]) -> None:
    """ValueError unless the sizes (m) and modulus (Pa) are finite and positive and every ratio is in
    (1, MAX_VOLUME_RATIO]: at V/V0 <= 1 a closed membrane is at rest or in compression, which it cannot carry."""
    if not all(np.isfinite(x) and x > 0 for x in (radius, thickness, mu)):
        raise ValueError("radius, thickness and mu must be finite and positive")
    if not volume_ratios:
        raise ValueError("give at least one volume ratio")
    for ratio in volume_ratios:
        if not np.isfinite(ratio) or ratio <= 1.0:
            raise ValueError(
                f"volume ratio {ratio:g} must be > 1: at V/V0 <= 1 the membrane is at rest or in compression"
            )
        if ratio > MAX_VOLUME_RATIO:
            raise ValueError(
                f"volume ratio {ratio:g} is beyond {MAX_VOLUME_RATIO:g} (stretch {MAX_VOLUME_RATIO ** (1 / 3):g}, "
                "past any elastomer's elongation at break)"
            )


def inflate_balloon(
    radius: float,
    thickness: float,
    mu: float,
    volume_ratios: list[float],
    subdivisions: int = 3,
    bending: bool = False,
    max_volume_step: float = 0.1,
    gent_inverse_jm: float = 0.0,
    on_step: Callable[[int, int], None] | None = None,
) -> list[BalloonPoint]:
    """Inflate a closed sphere (radius m, thickness m, shear modulus Pa, Gent 1/J_m) to each volume ratio.

    The volume walks through `balloon_steps` (each step at most `max_volume_step` of the current volume);
    on_step(done, total) is called after each. ValueError on the input `check_balloon_input` refuses.
    """
    check_balloon_input(radius, thickness, mu, volume_ratios)
    paths = balloon_steps(volume_ratios, max_volume_step)
    total, done = sum(len(p) for p in paths), 0
    params = SkinParameters(thickness=thickness, mu_nh=mu, bending=bending, gent_inverse_jm=gent_inverse_jm)
    mesh = sphere_mesh(radius, subdivisions)
    rest = InflatedSkin.at_rest(mesh.vertices, mesh.triangles, mesh.fixed, params, newton=NewtonSettings())
    engine = BatchedStepper(rest, [get_indenter("sphere_medium")])  # no indenter pose: it stays away
    v0, points = engine.rest_volumes[0], []
    # Walk in small volume steps so that Newton always starts near the solution.
    for ratio, path in zip(volume_ratios, paths, strict=True):
        converged = np.ones(1, dtype=bool)
        for target in path:
            converged, _ = engine.hold_volume(np.array([target * v0]))
            done += 1
            if on_step:
                on_step(done, total)
            if not converged[0]:
                break
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
