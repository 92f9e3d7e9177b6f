"""The FE dome (membrane only) against the independent axisymmetric reference, converging under refinement."""

import numpy as np
import pytest

from fe.axisymmetric import indent_dome
from fe.dome import run_dome
from fe.params import ContactSettings

R, T, MU, RATIO, R_IND = 10e-3, 0.1e-3, 1e5, 1.5, 5e-3  # m, m, Pa, -, m
DEPTHS = np.array([0.0, 1.0e-3, 1.5e-3])  # m past first touch


@pytest.fixture(scope="module")
def reference() -> tuple[np.ndarray, np.ndarray]:
    states = indent_dome(R, T, MU, RATIO, R_IND, list(DEPTHS))
    return np.array([s.pressure for s in states]), np.array([s.force for s in states])


def _fe(max_edge: float) -> tuple[np.ndarray, np.ndarray]:
    result = run_dome(R, T, MU, RATIO, False, R_IND, DEPTHS, max_edge, refine_levels=0)
    assert all(inc.converged for inc in result.increments)
    return np.array([inc.pressure for inc in result.increments]), np.array([-inc.force[2] for inc in result.increments])


def test_fe_dome_matches_axisymmetric_membrane_theory_and_converges(reference: tuple[np.ndarray, np.ndarray]) -> None:
    p_ref, f_ref = reference
    p_coarse, _ = _fe(R / 6)
    p_fine, f_fine = _fe(R / 12)
    err_coarse, err_fine = np.abs(p_coarse / p_ref - 1), np.abs(p_fine / p_ref - 1)
    assert np.all(err_fine < 0.005), err_fine
    assert np.all(err_fine < err_coarse), (err_coarse, err_fine)
    # The contact force is resolved by a few rings of nodes only: a few % on the finer mesh.
    assert f_fine[0] == 0.0
    assert np.all(np.abs(f_fine[1:] / f_ref[1:] - 1) < 0.05), (f_fine, f_ref)


TARGET_RATIO, TARGET_RADIUS = 1.5, 5e-3  # -, m: one case of issue 17's grid (docs/fe.md tabulates all four)
TARGET_DEPTHS = np.arange(7) * 0.25e-3  # m: first touch, then 0.25 ... 1.5 mm


@pytest.fixture(scope="module")
def target_reference() -> np.ndarray:
    """Apex force (N) of the axisymmetric reference at `TARGET_DEPTHS` past first touch (0.25 ... 1.5 mm)."""
    states = indent_dome(R, T, MU, TARGET_RATIO, TARGET_RADIUS, list(TARGET_DEPTHS))
    return np.array([s.force for s in states])[1:]


def _target_forces(max_edge: float, rule: str) -> np.ndarray:
    """FE apex forces (N) at 0.25 ... 1.5 mm on a uniform mesh of `max_edge` (m), contact quadrature `rule`."""
    contact = ContactSettings(surface_rule=rule)
    result = run_dome(R, T, MU, TARGET_RATIO, False, TARGET_RADIUS, TARGET_DEPTHS, max_edge, contact, refine_levels=0)
    assert all(inc.converged for inc in result.increments)
    return np.array([-inc.force[2] for inc in result.increments])[1:]


@pytest.fixture(scope="module")
def half_millimetre() -> np.ndarray:
    """FE apex forces on the uniform 0.5 mm mesh with the default rule (split-4)."""
    return _target_forces(0.5e-3, ContactSettings().surface_rule)


def test_dome_force_is_within_two_percent_of_the_reference_on_a_quarter_millimetre_mesh(
    target_reference: np.ndarray,
) -> None:
    """Issue 17's target (2 % at every depth >= 0.25 mm) holds on a 0.25 mm mesh: measured +1.6 % at 0.25 mm,
    within 0.6 % deeper (docs/fe.md)."""
    error = _target_forces(0.25e-3, "split-4") / target_reference - 1.0
    assert np.all(np.abs(error) < 0.02), error


def test_dome_force_on_the_half_millimetre_mesh_does_not_depend_on_the_contact_quadrature(
    half_millimetre: np.ndarray,
) -> None:
    """The contact integral is resolved: 64 points per triangle (split-8) give the 16-point rule's forces to
    0.3 %, so what remains of the error on this mesh is the discretisation of the contact patch (next test)."""
    finer = _target_forces(0.5e-3, "split-8")
    assert np.all(np.abs(half_millimetre / finer - 1.0) < 3e-3), (half_millimetre, finer)


@pytest.mark.xfail(
    strict=True,
    reason="the uniform 0.5 mm mesh misses 2 % (+3.9 % at 0.25 mm, +2.3 % at 0.75 mm) with the contact integral "
    "resolved (split-4 = split-8 to 0.1 %): the contact patch (0.54 mm radius at 0.25 mm) is one element wide, "
    "which linear triangles do not resolve; refined once under the indenter it is met (next test; docs/fe.md)",
)
def test_dome_force_is_within_two_percent_of_the_reference_on_the_uniform_half_millimetre_mesh(
    target_reference: np.ndarray, half_millimetre: np.ndarray
) -> None:
    error = half_millimetre / target_reference - 1.0
    assert np.all(np.abs(error) < 0.02), error


@pytest.mark.parametrize(
    ("volume_ratio", "indenter_radius", "levels", "refine_radius"),
    [(1.5, 5e-3, 1, 1.5e-3), (1.5, 2.5e-3, 1, 1.5e-3), (1.2, 5e-3, 1, 1.5e-3), (1.2, 2.5e-3, 1, 1.5e-3)]
    + [(1.35, 1.5e-3, 2, 1.5e-3)],
)
def test_dome_force_is_within_two_percent_on_the_half_millimetre_mesh_refined_under_the_indenter(
    volume_ratio: float, indenter_radius: float, levels: int, refine_radius: float
) -> None:
    """Issue 17's target on the 0.5 mm mesh with its edges halved within `refine_radius` of the apex
    (`fe.dome.refined_at_apex`, ~100 nodes more: 2738 against 2640): measured within 1.3 % at every depth for
    the four cases of docs/fe.md's grid, 0.5 % for a 1.5 mm sphere refined twice (3372 nodes; uniform: +7.0 %)."""
    states = indent_dome(R, T, MU, volume_ratio, indenter_radius, list(TARGET_DEPTHS))
    reference = np.array([s.force for s in states])
    result = run_dome(
        R,
        T,
        MU,
        volume_ratio,
        False,
        indenter_radius,
        TARGET_DEPTHS,
        0.5e-3,
        refine_levels=levels,
        refine_radius=refine_radius,
    )
    assert all(inc.converged for inc in result.increments)
    force = np.array([-inc.force[2] for inc in result.increments])
    assert force[0] == 0.0
    error = force[1:] / reference[1:] - 1.0
    assert np.all(np.abs(error) < 0.02), error
    # The contact edge: the farthest contact quadrature point lies within one refined element of the reference's
    # contact radius (measured 0.006-0.08 mm inside it for 0.25 mm elements).
    radius = np.array([inc.contact_radius for inc in result.increments])
    edge = 0.5e-3 / 2**levels
    assert np.all(np.abs(radius - [s.contact_radius for s in states]) < edge), radius


def test_the_dome_refines_under_its_indenter_by_default_and_meets_two_percent() -> None:
    """Without refinement options the dome refines by `fe.dome.contact_refinement` (one level within 1.5 mm for a
    10 mm sphere on the 0.5 mm mesh): V/V0 1.2, where the uniform mesh is -2.20 % off at 0.25 mm (measured)."""
    states = indent_dome(R, T, MU, 1.2, 10e-3, list(TARGET_DEPTHS))
    result = run_dome(R, T, MU, 1.2, False, 10e-3, TARGET_DEPTHS, 0.5e-3)
    assert (result.refine_levels, result.refine_radius, result.vertices) == (1, pytest.approx(1.5e-3), 2738)
    force = np.array([-inc.force[2] for inc in result.increments])
    error = force[1:] / np.array([s.force for s in states])[1:] - 1.0
    assert all(inc.converged for inc in result.increments) and np.all(np.abs(error) < 0.02), error
