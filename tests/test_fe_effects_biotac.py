"""Physics effects on a coarse inflated BioTac (2 mm mesh, frictionless): each changes the indentation force
the way physics says, relaxation follows the stepper's clock, and every effect off changes nothing."""

import numpy as np
import pytest

from assets.indenters import get_indenter
from fe.indentation import IncrementResult, IndentationStepper
from fe.params import SkinParameters
from fe.sensor import BioTacModel
from fe.trapped_air import ATMOSPHERIC_PRESSURE

MIDLINE_POINT = np.array([-6e-3, 0.0, -9e-3])
DEPTHS = np.array([0.0, 0.25e-3, 0.5e-3, 0.75e-3, 1.0e-3])
RATE = 1e-3
"""Indentation speed (m/s) of the timed runs."""


def _enclosed_volume(model: BioTacModel, x: np.ndarray) -> float:
    """Signed volume (m^3) of the cones from the core's centroid to the skin triangles at positions x (V,3),
    in numpy (independent of fe/); with the anchored rim fixed, differences between states are the fluid's."""
    origin = model.geometry.core.vertices.mean(axis=0)
    a, b, c = (x[model.geometry.skin.triangles[:, k]] - origin for k in range(3))
    return float(np.einsum("ij,ij->", a, np.cross(b, c)) / 6.0)


def _inflated(like: BioTacModel, **params: float) -> BioTacModel:
    """A frictionless model of `like`'s geometry with the given skin parameters, inflated to 15.1 mm."""
    model = BioTacModel(like.geometry, SkinParameters(friction=0.0, **params))
    assert model.inflate().converged
    return model


def _press(
    model: BioTacModel, times: np.ndarray | None = None, stepper: IndentationStepper | None = None
) -> tuple[list[IncrementResult], IndentationStepper, tuple[np.ndarray, np.ndarray]]:
    """Normal sphere indentation to 1 mm (on `stepper` if given); the results, the stepper and the last
    pose (rotation, tip)."""
    path = model.plan_trajectory(get_indenter("sphere_medium"), MIDLINE_POINT, 0.0, 0.0, DEPTHS[-1], DEPTHS[1])
    stepper = stepper or model.stepper("sphere_medium")
    results = []
    for k, depth in enumerate(path.depths):
        tip = path.touch_point + depth * path.direction
        results.append(stepper.step(path.rotation, tip, None if times is None else times[k]))
        assert results[-1].converged, results[-1].message
    return results, stepper, (path.rotation, tip)


@pytest.fixture(scope="module")
def baseline(frictionless_biotac: BioTacModel) -> list[IncrementResult]:
    return _press(frictionless_biotac)[0]


def test_effects_off_change_nothing(frictionless_biotac: BioTacModel, baseline: list[IncrementResult]) -> None:
    timed = _press(frictionless_biotac, DEPTHS / RATE)[0]  # the clock is ignored by an elastic skin
    for a, b in zip(baseline, timed, strict=True):
        assert np.array_equal(a.force, b.force) and a.pressure == b.pressure


def test_viscoelastic_force_relaxes_during_a_pause_towards_the_long_term_elastic_skin(
    frictionless_biotac: BioTacModel,
) -> None:
    g, tau = 0.3, 0.5
    model = _inflated(frictionless_biotac, relaxation_fraction=g, relaxation_time_s=tau)
    relaxed_skin = _inflated(frictionless_biotac, mu_nh=(1 - g) * model.params.mu_nh)
    # The sensor sat inflated for long: its inflated state is that of the long-term (relaxed) skin.
    assert model.pressure == pytest.approx(relaxed_skin.pressure, rel=1e-9)
    times = DEPTHS / RATE
    results, stepper, pose = _press(model, times)
    with pytest.raises(ValueError, match="time of every step"):
        stepper.step(*pose)
    with pytest.raises(ValueError, match="goes back"):
        stepper.step(*pose, times[-1] - 0.1)
    paused = stepper.step(*pose, times[-1] + 1.0)  # the testbed's 1 s pause at a fixed pose
    assert paused.converged and paused.force[2] < 0.97 * results[-1].force[2]
    assert paused.pressure < results[-1].pressure
    # Long after: the long-term elastic skin's state. (Two steps: a single long step would leave the branch
    # a share tau/dt of the creep, as the integrator spreads each step's stress change evenly over it.)
    stepper.step(*pose, times[-1] + 10.0 * tau)
    settled = stepper.step(*pose, times[-1] + 60.0 * tau)
    long_term = _press(relaxed_skin)[0][-1]
    assert settled.force[2] < paused.force[2]
    newton_tolerance = 1e-6 * np.linalg.norm(long_term.force)
    assert np.allclose(settled.force, long_term.force, rtol=0, atol=newton_tolerance)
    assert settled.pressure == pytest.approx(long_term.pressure, rel=1e-6)
    # reset() clears the branches: the same timed run repeats exactly.
    stepper.reset()
    again = _press(model, times, stepper)[0]
    assert np.allclose(again[-1].force, results[-1].force, rtol=1e-9, atol=1e-12)


def test_a_pause_resolved_every_tenth_of_a_second_relaxes_as_one_step_of_it_does(
    frictionless_biotac: BioTacModel,
) -> None:
    # The re-solves of a pause start from the creep's extrapolation (`BatchedStepper._predict`): where they
    # converge is the integrator's business alone, so ten steps of 0.1 s end where one of 1 s does (the
    # integrator is exact for an elastic stress linear in time over a step: 0.07 % over a 1 s pause, docs/fe.md)
    # and the force falls at every re-solve, less each time (one branch: exp(-t / tau)).
    model = _inflated(frictionless_biotac, relaxation_fraction=0.3, relaxation_time_s=0.5)
    times = DEPTHS / RATE
    results, stepper, pose = _press(model, times)
    held = [stepper.step(*pose, times[-1] + 0.1 * k) for k in range(1, 11)]
    assert all(r.converged for r in held)
    stepper.reset()
    one_step = _press(model, times, stepper)[0][-1:] + [stepper.step(*pose, times[-1] + 1.0)]
    drops = -np.diff([results[-1].force[2], *(r.force[2] for r in held)])
    assert np.all(drops > 0.0) and np.all(np.diff(drops) < 0.0)
    assert held[-1].force[2] == pytest.approx(one_step[-1].force[2], rel=1e-3)
    assert held[-1].force[2] < 0.97 * results[-1].force[2]


def test_gent_stiffening_raises_the_force_at_depth(
    frictionless_biotac: BioTacModel, baseline: list[IncrementResult]
) -> None:
    gent = _press(_inflated(frictionless_biotac, gent_inverse_jm=0.5))[0]
    assert gent[-1].force[2] > 1.02 * baseline[-1].force[2]


def test_trapped_air_lowers_pressure_rise_and_force(
    frictionless_biotac: BioTacModel, baseline: list[IncrementResult]
) -> None:
    model = _inflated(frictionless_biotac, air_volume_fraction=0.1)
    assert model.pressure == frictionless_biotac.pressure  # the air is defined at the inflated state
    # Boyle's law, written out here: the bubble holds 10 % of the fluid at the inflated pressure.
    boyle = 0.1 * model.fluid_volume() * (ATMOSPHERIC_PRESSURE + model.pressure)
    assert model.air_boyle() == pytest.approx(boyle, rel=1e-12)

    def air_volume(p: float) -> float:
        return boyle / (ATMOSPHERIC_PRESSURE + p)

    results = _press(model)[0]
    end, ref = results[-1], baseline[-1]
    assert end.converged and end.equilibrium_error <= 1e-6
    assert end.pressure - model.pressure < 0.97 * (ref.pressure - model.pressure)
    assert end.force[2] < 0.995 * ref.force[2]
    # The liquid is incompressible: the cavity, measured from the nodal positions, shrinks by exactly what
    # the air gives up.
    shrink = _enclosed_volume(model, model.reference) - _enclosed_volume(model, model.reference + end.displacement)
    assert shrink > 0.0
    assert shrink == pytest.approx(air_volume(model.pressure) - air_volume(end.pressure), rel=1e-6)
    assert results[0].volume - end.volume == pytest.approx(shrink, rel=1e-6)


def test_fill_volume_scale_adds_fluid_and_pretension(frictionless_biotac: BioTacModel) -> None:
    model = _inflated(frictionless_biotac, inflation_volume_scale=1.1)
    cavity = model.geometry.cavity_volume_reference
    added = frictionless_biotac.fluid_volume() - cavity
    assert model.fluid_volume() - cavity == pytest.approx(1.1 * added, rel=1e-9)
    assert model.pressure > 1.03 * frictionless_biotac.pressure
    assert model.thickness(model.reference) > model.thickness(frictionless_biotac.reference) + 0.1e-3
