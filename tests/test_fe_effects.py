"""Physics effects of the skin model against analytic membrane theory: Gent stiffening, Prony relaxation,
trapped air; and the finite-difference check of their energy terms. All on the one FE engine
(`fe.batched.BatchedShell`, `fe.batched_stepper.BatchedStepper`), CPU device."""

import dataclasses

import numpy as np
import pytest
import trimesh
import warp as wp
from scipy.optimize import brentq

from fe.balloon import analytic_balloon_pressure, inflate_balloon, sphere_mesh
from fe.batched import BatchedShell, InflatedSkin
from fe.batched_stepper import BatchedStepper
from fe.bending import build_stencils
from fe.params import NewtonSettings, SkinParameters
from fe.trapped_air import TrappedAir
from fe.viscoelastic import SkinRelaxation, step_factors

NEWTON = NewtonSettings(force_tolerance=1e-12, relative_force_tolerance=1e-10)
FAR = (np.eye(3)[None], np.array([[0.0, 0.0, 1.0]]))  # indenter pose 1 m away: never in contact
ROW = np.array([0])


def _shell(params: SkinParameters, vertices: np.ndarray, triangles: np.ndarray) -> BatchedShell:
    """One system, nothing held, indenter far away (its default pose)."""
    skin = InflatedSkin.at_rest(vertices, triangles, np.zeros(len(vertices), dtype=bool), params, newton=NEWTON)
    return BatchedShell(skin, [(0, (5e-3, 0.0, 0.0, 0.0))])


def _evaluate(shell: BatchedShell, x: np.ndarray, want_hessian: bool = False) -> tuple[float, np.ndarray]:
    """Total energy (J; elastic only here: no pressure, no air, no contact) and elastic gradient (V,3) N."""
    lin = shell.evaluate(wp.array(x[None], dtype=wp.vec3d), want_hessian, np.zeros(1))
    return float(lin.energy[0]), shell.gradients[0].numpy()[0].copy()


def _hessian(shell: BatchedShell, x: np.ndarray) -> np.ndarray:
    """The engine's elastic Hessian at x, assembled densely from its per-element blocks."""
    _evaluate(shell, x, want_hessian=True)
    H = np.zeros((3 * shell.n_vertices,) * 2)
    stencils = build_stencils(shell.skin.triangles)[0][: shell.n_bending]
    families = (
        (shell.buf["membrane_hessian"].numpy()[0], shell.skin.triangles),
        (shell.buf["bending_hessian"].numpy()[0], stencils),
    )
    for blocks, nodes in families:
        for el, blk in zip(nodes, blocks, strict=True):
            dofs = (3 * np.asarray(el)[:, None] + np.arange(3)).ravel()
            np.add.at(H, np.ix_(dofs, dofs), blk)
    return H


def _deformed_sphere(params: SkinParameters) -> tuple[BatchedShell, np.ndarray]:
    sphere = trimesh.creation.icosphere(subdivisions=1, radius=5e-3)
    rest = np.asarray(sphere.vertices, dtype=np.float64)
    x = rest * 1.15 + np.random.default_rng(3).normal(scale=2e-4, size=rest.shape)
    return _shell(params, rest, np.asarray(sphere.faces, dtype=np.int32)), x


def test_gent_and_relaxation_terms_match_finite_differences() -> None:
    params = SkinParameters(thickness=1e-3, mu_nh=2e5, gent_inverse_jm=0.5, relaxation_fraction=0.4)
    shell, x = _deformed_sphere(params)
    assert shell.relaxes and shell.n_bending > 0
    rest = shell.skin.vertices
    relaxation = SkinRelaxation(shell, np.array([0.4]), np.array([0.5]))
    relaxation.reset(ROW, rest[None])
    relaxation.prepare(ROW, np.array([0.0]))
    relaxation.advance(ROW, np.array([0.0]), 0.5 * (x + rest)[None])
    relaxation.prepare(ROW, np.array([0.3]))  # frozen membrane stress and shifted bending rest angles installed
    assert not relaxation.at_rest(ROW)[0]
    H = _hessian(shell, x)
    _, g = _evaluate(shell, x)
    g = g.ravel()
    rng = np.random.default_rng(0)
    for _ in range(3):
        d = rng.normal(size=x.shape)
        h = 1e-8
        (ep, gp), (em, gm) = _evaluate(shell, x + h * d), _evaluate(shell, x - h * d)
        assert (ep - em) / (2 * h) == pytest.approx(g @ d.ravel(), rel=1e-5)
        fd_hd = (gp - gm).ravel() / (2 * h)
        assert np.linalg.norm(fd_hd - H @ d.ravel()) <= 1e-4 * np.linalg.norm(fd_hd)


def test_gent_is_neo_hookean_at_zero_and_stiffer_otherwise() -> None:
    base, x = _deformed_sphere(SkinParameters(thickness=1e-3, mu_nh=2e5))
    same, _ = _deformed_sphere(SkinParameters(thickness=1e-3, mu_nh=2e5, gent_inverse_jm=1e-13))
    gent, _ = _deformed_sphere(SkinParameters(thickness=1e-3, mu_nh=2e5, gent_inverse_jm=0.5))
    e_base, e_same, e_gent = (_evaluate(s, x)[0] for s in (base, same, gent))
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


def _balloon(params: SkinParameters, subdivisions: int = 2) -> tuple[InflatedSkin, BatchedStepper]:
    """An unloaded closed sphere of radius 5 t and its engine (one system, indenter far away)."""
    mesh = sphere_mesh(params.thickness * 5.0, subdivisions)
    skin = InflatedSkin.at_rest(mesh.vertices, mesh.triangles, mesh.fixed, params, newton=NEWTON)
    return skin, BatchedStepper(skin, ["sphere_medium"])


@pytest.mark.parametrize("bending", [True, False])
def test_balloon_held_at_fixed_volume_relaxes_exponentially(bending: bool) -> None:
    # Bending barely resists a uniformly inflating sphere (its dihedral angles are scale-free), and QLV scales
    # membrane and bending stresses alike, so both checks hold with and without it.
    g, tau = 0.35, 0.8
    params = SkinParameters(thickness=1e-3, mu_nh=2.8e5, bending=bending, relaxation_fraction=g, relaxation_time_s=tau)
    _, engine = _balloon(params)
    v0, relaxation = engine.rest_volumes[0], engine.relaxation
    assert relaxation is not None
    for ratio in (1.1, 1.2, 1.3):  # a fast inflation (no time passes): the glassy response
        relaxation.prepare(ROW, np.array([0.0]))
        converged, messages = engine.hold_volume(np.array([ratio * v0]))
        assert converged[0], messages
        relaxation.advance(ROW, np.array([0.0]), engine.x[:1])
    p0 = float(engine.pressure[0])
    glassy = analytic_balloon_pressure(1.3 ** (1 / 3), 5e-3, 1e-3, 2.8e5)
    assert p0 == pytest.approx(glassy, rel=0.02)
    # Held at V = 1.3 V0 (the engine keeps the last held volume) while time passes, indenter far away.
    (start,) = engine.step(*FAR, times=np.array([0.0]))  # starts the clock: no time passes
    assert start.converged and start.pressure == pytest.approx(p0, rel=1e-9)
    t = 0.0
    for dt in (0.05, 0.1, 0.25, 0.5, 1.0, 2.0, 4.0):
        t += dt
        (result,) = engine.step(*FAR, times=np.array([t]))
        assert result.converged, result.message
        assert result.volume == pytest.approx(1.3 * v0, rel=1e-9)
        # QLV at a held strain: every stress scales by G(t) = (1 - g) + g exp(-t / tau), at any stretch.
        assert result.pressure == pytest.approx(p0 * (1 - g + g * np.exp(-t / tau)), rel=1e-7)


def test_relaxation_scales_held_internal_forces_by_the_relaxation_function() -> None:
    """Membrane and bending alike: after a jump to x and a hold of dt, the internal forces at x are
    G(dt) = (1 - g) + g exp(-dt / tau) times the elastic ones (the rest state is stress-free)."""
    g, tau, dt = 0.3, 2.0, 0.7
    params = SkinParameters(thickness=1e-3, mu_nh=2e5, relaxation_fraction=g, relaxation_time_s=tau)
    shell, x = _deformed_sphere(params)
    relaxation = SkinRelaxation(shell, np.array([g]), np.array([tau]))
    relaxation.reset(ROW, shell.skin.vertices[None])
    assert relaxation.at_rest(ROW)[0]
    relaxation.prepare(ROW, np.array([0.0]))
    _, elastic = _evaluate(shell, x)
    relaxation.advance(ROW, np.array([0.0]), x[None])
    relaxation.prepare(ROW, np.array([dt]))
    _, held = _evaluate(shell, x)
    assert np.allclose(held, (1 - g + g * np.exp(-dt / tau)) * elastic, rtol=1e-9, atol=1e-12 * np.abs(elastic).max())
    assert not relaxation.at_rest(ROW)[0]


def test_prony_step_factors() -> None:
    decay, weight = step_factors(np.array([0.2, 0.3]), np.array([1.0, 10.0]), 0.0)
    assert np.array_equal(decay, [1.0, 1.0]) and np.array_equal(weight, [0.2, 0.3])
    decay, weight = step_factors(np.array([0.2]), np.array([1.0]), np.inf)  # fully relaxed
    assert decay[0] == 0.0 and weight[0] == 0.0
    with pytest.raises(ValueError):
        step_factors(np.array([0.2]), np.array([1.0]), -1.0)


def _enclosed(x: np.ndarray, triangles: np.ndarray) -> float:
    """Volume (m^3) a closed mesh encloses, by trimesh (independent of the engine's volume kernel)."""
    return float(trimesh.Trimesh(x, triangles, process=False).volume)


def test_balloon_with_trapped_air_follows_membrane_theory_and_boyle() -> None:
    """Add liquid to an inflated sphere holding an air bubble: the pressure solves p = p_membrane(V) with
    V = V_liquid + k / (p_atm + p), and rises less than without air."""
    radius, thickness, mu, fraction = 5e-3, 1e-3, 2.8e5, 0.3
    skin, engine = _balloon(SkinParameters(thickness=thickness, mu_nh=mu, bending=False), subdivisions=3)
    v0, triangles = engine.rest_volumes[0], skin.triangles
    assert v0 == pytest.approx(_enclosed(skin.vertices, triangles), rel=1e-12)
    converged, messages = engine.hold_volume(np.array([1.3 * v0]))
    assert converged[0], messages
    x_inflated, p_inflated = engine.x[0].copy(), float(engine.pressure[0])
    k = TrappedAir.boyle(fraction, 1.3 * v0, p_inflated)
    air = TrappedAir(np.array([k]))
    assert air.volume(p_inflated)[0] == pytest.approx(fraction * 1.3 * v0)
    liquid = 1.3 * v0 - air.volume(p_inflated)[0] + 0.1 * v0  # 0.1 V0 of liquid added
    airy = dataclasses.replace(skin, air_boyle=k, reference=x_inflated, pressure=p_inflated, target_volume=1.3 * v0)
    with_air = BatchedStepper(airy, ["sphere_medium"])
    assert with_air.rest_volumes[0] == pytest.approx(1.3 * v0, rel=1e-9)
    # hold_volume holds the liquid at target - V_air(p now): target 1.4 V0 adds 0.1 V0 of liquid.
    converged, messages = with_air.hold_volume(np.array([1.4 * v0]))
    assert converged[0], messages
    assert with_air.newton.iterations[0] <= 8
    p_air = float(with_air.pressure[0])
    enclosed = _enclosed(with_air.x[0], triangles)
    # Boyle holds: the liquid is as added and the rest of the enclosed volume is air at k / (p_atm + p).
    assert with_air.newton.volume[0] == pytest.approx(liquid, rel=1e-9)
    assert enclosed - liquid == pytest.approx(k / (TrappedAir(np.zeros(1)).atmospheric_pressure + p_air), rel=1e-8)
    converged, messages = engine.hold_volume(np.array([1.4 * v0]))  # the same liquid added, no air
    assert converged[0], messages
    p_without = float(engine.pressure[0])
    # The skin is in the state the air-free sphere takes at the same enclosed volume.
    converged, messages = engine.hold_volume(np.array([enclosed]))
    assert converged[0], messages
    assert float(engine.pressure[0]) == pytest.approx(p_air, rel=1e-8)

    def membrane(volume: float) -> float:
        return float(analytic_balloon_pressure((volume / v0) ** (1 / 3), radius, thickness, mu))

    def boyle(volume: float) -> float:  # gauge pressure of the bubble compressed to `volume`
        return k / volume - air.atmospheric_pressure

    volume = brentq(lambda v: membrane(v) - boyle(v - liquid), liquid + 1e-15, 2 * v0)
    assert p_air == pytest.approx(membrane(volume), rel=0.01)
    assert p_without == pytest.approx(membrane(1.4 * v0), rel=0.01)
    # The pressure rise: air takes up part of the added liquid (the mesh's own 0.4% error largely cancels).
    rise_air, rise = p_air - p_inflated, p_without - p_inflated
    theory_air, theory = membrane(volume) - membrane(1.3 * v0), membrane(1.4 * v0) - membrane(1.3 * v0)
    assert rise_air / rise == pytest.approx(theory_air / theory, rel=0.01)
    assert rise_air < 0.9 * rise
