"""Physics effects of the skin model against analytic membrane theory: Gent stiffening, Prony relaxation,
trapped air; and the finite-difference check of their energy terms."""

import numpy as np
import pytest
import trimesh
from scipy.optimize import brentq

from fe.balloon import analytic_balloon_pressure, inflate_balloon, sphere_mesh
from fe.newton import NewtonSettings, solve_equilibrium
from fe.params import SkinParameters
from fe.shell import ShellMesh, ShellSystem
from fe.trapped_air import TrappedAir, TrappedAirProblem
from fe.viscoelastic import SkinRelaxation, step_factors

NEWTON = NewtonSettings(force_tolerance=1e-12)


def _gradient_and_hessian(system: ShellSystem, x: np.ndarray) -> tuple[callable, np.ndarray]:
    """Energy-and-gradient function of the elastic energy and its assembled Hessian at x."""
    n = 3 * system.n_vertices
    t = system.evaluate(x, want_hessian=True)
    H = np.zeros((n, n))
    families = ((t["membrane_hessian"], system.mesh.triangles), (t["bending_hessian"], system.bending_stencils))
    for blocks, nodes in families:
        for el, blk in zip(nodes, blocks, strict=True):
            dofs = (3 * el[:, None] + np.arange(3)).ravel()
            H[np.ix_(dofs, dofs)] += blk

    def energy_and_gradient(y: np.ndarray) -> tuple[float, np.ndarray]:
        terms = system.evaluate(y, want_hessian=False)
        return terms["elastic_energy"], terms["elastic_gradient"].ravel()

    return energy_and_gradient, H


def _deformed_sphere(params: SkinParameters) -> tuple[ShellSystem, np.ndarray]:
    sphere = trimesh.creation.icosphere(subdivisions=1, radius=5e-3)
    rest = np.asarray(sphere.vertices)
    mesh = ShellMesh(rest, np.asarray(sphere.faces, dtype=np.int32), np.zeros(len(rest), dtype=bool))
    x = rest * 1.15 + np.random.default_rng(3).normal(scale=2e-4, size=rest.shape)
    return ShellSystem(mesh, params), x


def test_gent_and_relaxation_terms_match_finite_differences() -> None:
    params = SkinParameters(thickness=1e-3, mu_nh=2e5, gent_inverse_jm=0.5, relaxation_fraction=0.4)
    system, x = _deformed_sphere(params)
    relaxation = SkinRelaxation(system, np.array([0.4]), np.array([0.5]))
    relaxation.reset(system.mesh.vertices)
    relaxation.prepare(0.0)
    relaxation.advance(0.0, 0.5 * (x + system.mesh.vertices))
    relaxation.prepare(0.3)  # frozen membrane stress and shifted bending rest angles are now installed
    energy_and_gradient, H = _gradient_and_hessian(system, x)
    _, g = energy_and_gradient(x)
    rng = np.random.default_rng(0)
    for _ in range(3):
        d = rng.normal(size=x.shape)
        h = 1e-8
        (ep, gp), (em, gm) = energy_and_gradient(x + h * d), energy_and_gradient(x - h * d)
        assert (ep - em) / (2 * h) == pytest.approx(g @ d.ravel(), rel=1e-5)
        fd_hd = (gp - gm) / (2 * h)
        assert np.linalg.norm(fd_hd - H @ d.ravel()) <= 1e-4 * np.linalg.norm(fd_hd)


def test_gent_is_neo_hookean_at_zero_and_stiffer_otherwise() -> None:
    base, x = _deformed_sphere(SkinParameters(thickness=1e-3, mu_nh=2e5))
    same, _ = _deformed_sphere(SkinParameters(thickness=1e-3, mu_nh=2e5, gent_inverse_jm=1e-13))
    gent, _ = _deformed_sphere(SkinParameters(thickness=1e-3, mu_nh=2e5, gent_inverse_jm=0.5))
    e_base, e_same, e_gent = (s.evaluate(x, False)["elastic_energy"] for s in (base, same, gent))
    assert e_same == pytest.approx(e_base, rel=1e-12)
    assert e_gent > 1.05 * e_base


def test_gent_balloon_follows_membrane_theory() -> None:
    ratios = [1.2, 1.6, 2.2, 7**0.5, 3.0, 3.375]  # stretch up to 1.5
    beta = 0.3
    points = inflate_balloon(0.01, 1e-4, 1e5, ratios, subdivisions=3, max_volume_step=0.25, gent_inverse_jm=beta)
    assert all(p.converged for p in points)
    errors = [abs(p.pressure_pa / p.analytic_pressure_pa - 1) for p in points]
    assert max(errors) < 0.01, errors
    # Strain stiffening removes the Neo-Hookean pressure maximum: the pressure keeps rising (x2 at l = 1.5).
    pressures = np.array([p.pressure_pa for p in points])
    assert np.all(np.diff(pressures) > 0)
    assert points[-1].analytic_pressure_pa > 1.9 * analytic_balloon_pressure(1.5, 0.01, 1e-4, 1e5)


def _balloon(params: SkinParameters, subdivisions: int = 2) -> tuple[ShellSystem, np.ndarray, float]:
    system = ShellSystem(sphere_mesh(params.thickness * 5.0, subdivisions), params)
    q = system.free_coordinates(system.x)
    return system, q, system.linearize(q, 0.0, want_matrix=False).volume


def test_balloon_held_at_fixed_volume_relaxes_exponentially() -> None:
    g, tau = 0.35, 0.8
    params = SkinParameters(thickness=1e-3, mu_nh=2.8e5, bending=False, relaxation_fraction=g, relaxation_time_s=tau)
    system, q, v0 = _balloon(params)
    relaxation = SkinRelaxation(system, np.array([g]), np.array([tau]))
    relaxation.reset(system.x)
    pressure = 0.0
    for ratio in (1.1, 1.2, 1.3):  # a fast inflation (no time passes): the glassy response
        relaxation.prepare(0.0)
        result = solve_equilibrium(system, q, pressure, ratio * v0, NEWTON)
        assert result.converged
        q, pressure = result.q, result.pressure
        relaxation.advance(0.0, system.positions(q))
    p0 = pressure
    glassy = analytic_balloon_pressure(1.3 ** (1 / 3), 5e-3, 1e-3, 2.8e5)
    assert p0 == pytest.approx(glassy, rel=0.02)
    t = 0.0
    for dt in (0.05, 0.1, 0.25, 0.5, 1.0, 2.0, 4.0):  # held at V = 1.3 V0
        relaxation.prepare(dt)
        result = solve_equilibrium(system, q, pressure, 1.3 * v0, NEWTON)
        assert result.converged
        q, pressure, t = result.q, result.pressure, t + dt
        relaxation.advance(dt, system.positions(q))
        # QLV at a held strain: every stress scales by G(t) = (1 - g) + g exp(-t / tau), at any stretch.
        assert pressure == pytest.approx(p0 * (1 - g + g * np.exp(-t / tau)), rel=1e-7)


def test_relaxation_scales_held_internal_forces_by_the_relaxation_function() -> None:
    """Membrane and bending alike: after a jump to x and a hold of dt, the internal forces at x are
    G(dt) = (1 - g) + g exp(-dt / tau) times the elastic ones (the rest state is stress-free)."""
    g, tau, dt = 0.3, 2.0, 0.7
    params = SkinParameters(thickness=1e-3, mu_nh=2e5, relaxation_fraction=g, relaxation_time_s=tau)
    system, x = _deformed_sphere(params)
    relaxation = SkinRelaxation(system, np.array([g]), np.array([tau]))
    relaxation.reset(system.mesh.vertices)
    relaxation.prepare(0.0)
    elastic = system.evaluate(x, False)["elastic_gradient"]
    relaxation.advance(0.0, x)
    relaxation.prepare(dt)
    held = system.evaluate(x, False)["elastic_gradient"]
    assert np.allclose(held, (1 - g + g * np.exp(-dt / tau)) * elastic, rtol=1e-9, atol=1e-12 * np.abs(elastic).max())
    assert not relaxation.at_rest


def test_prony_step_factors() -> None:
    decay, weight = step_factors(np.array([0.2, 0.3]), np.array([1.0, 10.0]), 0.0)
    assert np.array_equal(decay, [1.0, 1.0]) and np.array_equal(weight, [0.2, 0.3])
    decay, weight = step_factors(np.array([0.2]), np.array([1.0]), np.inf)  # fully relaxed
    assert decay[0] == 0.0 and weight[0] == 0.0
    with pytest.raises(ValueError):
        step_factors(np.array([0.2]), np.array([1.0]), -1.0)


def test_balloon_with_trapped_air_follows_membrane_theory_and_boyle() -> None:
    """Add liquid to an inflated sphere holding an air bubble: the pressure solves p = p_membrane(V) with
    V = V_liquid + k / (p_atm + p), and rises less than without air."""
    radius, thickness, mu, fraction = 5e-3, 1e-3, 2.8e5, 0.3
    system, q, v0 = _balloon(SkinParameters(thickness=thickness, mu_nh=mu, bending=False), subdivisions=3)
    inflated = solve_equilibrium(system, q, 0.0, 1.3 * v0, NEWTON)
    assert inflated.converged
    air = TrappedAir.at_reference(fraction, 1.3 * v0, inflated.pressure)
    assert air.volume(inflated.pressure) == pytest.approx(fraction * 1.3 * v0)
    liquid = 1.3 * v0 - air.volume(inflated.pressure) + 0.1 * v0  # 0.1 V0 of liquid added
    with_air = solve_equilibrium(TrappedAirProblem(system, air), inflated.q, inflated.pressure, liquid, NEWTON)
    without = solve_equilibrium(system, inflated.q, inflated.pressure, 1.4 * v0, NEWTON)
    assert with_air.converged and without.converged and with_air.iterations <= 8
    assert with_air.volume == pytest.approx(liquid, rel=1e-9)
    # Boyle holds, and the skin is in the state the air-free sphere takes at the same enclosed volume.
    enclosed = system.evaluate(system.positions(with_air.q), False)["volume"]
    assert enclosed - liquid == pytest.approx(air.volume(with_air.pressure), rel=1e-9)
    same_volume = solve_equilibrium(system, with_air.q, with_air.pressure, enclosed, NEWTON)
    assert same_volume.pressure == pytest.approx(with_air.pressure, rel=1e-8)

    def membrane(volume: float) -> float:
        return float(analytic_balloon_pressure((volume / v0) ** (1 / 3), radius, thickness, mu))

    volume = brentq(lambda v: membrane(v) - air.pressure(v - liquid), liquid + 1e-15, 2 * v0)
    assert with_air.pressure == pytest.approx(membrane(volume), rel=0.01)
    assert without.pressure == pytest.approx(membrane(1.4 * v0), rel=0.01)
    # The pressure rise: air takes up part of the added liquid (the mesh's own 0.4% error largely cancels).
    rise_air, rise = with_air.pressure - inflated.pressure, without.pressure - inflated.pressure
    theory_air, theory = membrane(volume) - membrane(1.3 * v0), membrane(1.4 * v0) - membrane(1.3 * v0)
    assert rise_air / rise == pytest.approx(theory_air / theory, rel=0.01)
    assert rise_air < 0.9 * rise
