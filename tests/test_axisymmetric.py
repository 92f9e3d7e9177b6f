"""Physics checks of the axisymmetric dome reference solution (fe/axisymmetric.py)."""

from __future__ import annotations

import math

import pytest

from fe.axisymmetric import DomeState, closed_sphere_pressure, indent_dome, inflate_dome

R = 10e-3  # m
T = 0.1e-3  # m
MU = 1.0e5  # Pa
MU_T_R = MU * T / R  # Pa, pressure scale
RATIO = 1.5
R_IND = 5e-3  # m
H = 0.02e-3  # m, finite-difference step in depth
DEPTHS = [0.0, 0.5e-3, 1e-3 - H, 1e-3, 1e-3 + H, 2e-3, 3e-3]  # m


@pytest.fixture(scope="module")
def indentation() -> dict[float, DomeState]:
    states = indent_dome(R, T, MU, RATIO, R_IND, DEPTHS)
    return {s.depth: s for s in states}


@pytest.mark.parametrize("stretch", [1.2, 1.6])
def test_closed_sphere_matches_closed_form(stretch: float) -> None:
    exact = 2.0 * MU_T_R * (1.0 / stretch - stretch**-7)
    assert closed_sphere_pressure(R, T, MU, stretch) == pytest.approx(exact, rel=1e-7)


def test_small_inflation_matches_linear_membrane_theory() -> None:
    # Linear theory (incompressible, nu = 1/2): p = 12 mu t eps / R and dV / V0 = 3 eps; the pinned rim
    # only adds a boundary layer that vanishes with the strain.
    ratio = 1.02
    state = inflate_dome(R, T, MU, ratio)
    assert state.pressure == pytest.approx(4.0 * MU_T_R * (ratio - 1.0), rel=5e-3)
    assert state.force == 0.0 and state.depth == 0.0 and state.contact_radius == 0.0


def test_inflation_energy_derivative_is_pressure() -> None:
    dv_ratio = 0.002
    v0 = 2.0 / 3.0 * math.pi * R**3
    lo, mid, hi = (inflate_dome(R, T, MU, 1.2 + k * dv_ratio) for k in (-1, 0, 1))
    assert (hi.strain_energy - lo.strain_energy) / (2.0 * dv_ratio * v0) == pytest.approx(mid.pressure, rel=2e-5)
    assert lo.pressure < mid.pressure < hi.pressure


def test_inflated_rim_carries_pressure_load() -> None:
    state = inflate_dome(R, T, MU, 2.0)
    assert state.volume == pytest.approx(2.0 * 2.0 / 3.0 * math.pi * R**3, rel=1e-8)
    assert state.rim_force == pytest.approx(state.pressure * math.pi * R**2, rel=1e-7)


def test_indentation_volume_held(indentation: dict[float, DomeState]) -> None:
    v = RATIO * 2.0 / 3.0 * math.pi * R**3
    for state in indentation.values():
        assert state.volume == pytest.approx(v, rel=1e-8)


def test_indentation_force_starts_at_zero_and_increases(indentation: dict[float, DomeState]) -> None:
    states = [indentation[d] for d in sorted(indentation)]
    assert states[0].force == 0.0 and states[0].contact_radius == 0.0
    forces = [s.force for s in states]
    radii = [s.contact_radius for s in states]
    assert all(b > a for a, b in zip(forces, forces[1:], strict=False))
    assert all(b > a for a, b in zip(radii, radii[1:], strict=False))
    assert all(s.pressure > states[0].pressure for s in states[1:])


def test_force_is_energy_derivative_at_fixed_volume(indentation: dict[float, DomeState]) -> None:
    lo, mid, hi = indentation[1e-3 - H], indentation[1e-3], indentation[1e-3 + H]
    assert (hi.strain_energy - lo.strain_energy) / (2.0 * H) == pytest.approx(mid.force, rel=1e-4)
    # Coarse check over the whole path: trapezoidal work of F equals the stored energy.
    d = sorted(indentation)
    work = sum(0.5 * (indentation[a].force + indentation[b].force) * (b - a) for a, b in zip(d, d[1:], strict=False))
    assert work == pytest.approx(indentation[d[-1]].strain_energy - indentation[0.0].strain_energy, rel=2e-2)


def test_vertical_equilibrium(indentation: dict[float, DomeState]) -> None:
    for state in indentation.values():
        assert state.rim_force + state.force == pytest.approx(state.pressure * math.pi * R**2, rel=1e-7)


def test_results_follow_input_order() -> None:
    states = indent_dome(R, T, MU, RATIO, R_IND, [1e-3, 0.0, 1e-3])
    assert [s.depth for s in states] == [1e-3, 0.0, 1e-3]
    assert states[0] == states[2] and states[1].force == 0.0


def test_deep_indentation_at_large_inflation() -> None:
    ratio, depth = 3.0, 0.3 * R
    (state,) = indent_dome(R, T, MU, ratio, 2e-3, [depth])
    assert state.volume == pytest.approx(ratio * 2.0 / 3.0 * math.pi * R**3, rel=1e-8)
    assert state.force > 0.0 and state.contact_radius > 0.0
    assert state.rim_force + state.force == pytest.approx(state.pressure * math.pi * R**2, rel=1e-7)


@pytest.mark.parametrize(
    "args",
    [
        (0.0, T, MU, RATIO),
        (R, -T, MU, RATIO),
        (R, T, 0.0, RATIO),
        (R, T, MU, 1.0),
        (R, T, MU, 0.8),
        (R, T, math.nan, RATIO),
    ],
)
def test_bad_inflation_input(args: tuple[float, float, float, float]) -> None:
    with pytest.raises(ValueError):
        inflate_dome(*args)
    with pytest.raises(ValueError):
        indent_dome(*args, R_IND, [1e-3])


@pytest.mark.parametrize("indenter, depths", [(0.0, [1e-3]), (-1e-3, [1e-3]), (R_IND, [-1e-4]), (R_IND, [math.inf])])
def test_bad_indentation_input(indenter: float, depths: list[float]) -> None:
    with pytest.raises(ValueError):
        indent_dome(R, T, MU, RATIO, indenter, depths)
