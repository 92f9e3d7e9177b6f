"""Energy conservation of a frictionless load-unload cycle on the inflated BioTac (2 mm mesh).

Without friction the skin, its squeezed half-layers and the incompressible fluid (held volume: the pressure
does no work) are conservative, so along the quasi-static path the work the indenter does on the skin,
W = integral of F . dx (F the force on the skin, N; x the tip position, m; trapezoid rule over the
increments), is the total potential energy's change: it returns to zero after press and release, and over
the loading half it equals E(deepest) - E(touch) up to the trapezoid rule's error.
"""

import numpy as np
import pytest
import warp as wp

from assets.indenters import get_indenter
from fe.sensor import BioTacModel

DEPTH, STEP = 2.0e-3, 0.1e-3  # m


def _trapezoid(forces: np.ndarray, tips: np.ndarray) -> float:
    """Work (J) of forces (n,3) N along tip positions (n,3) m, trapezoid rule."""
    return float(np.sum(0.5 * (forces[1:] + forces[:-1]) * np.diff(tips, axis=0)))


@pytest.mark.parametrize("angle_deg", [0.0, 30.0])
def test_frictionless_press_and_release_returns_the_work(frictionless_biotac: BioTacModel, angle_deg: float) -> None:
    model, name = frictionless_biotac, "sphere_medium"
    path = model.plan_trajectory(get_indenter(name), np.array([-6e-3, 0.0, -9e-3]), angle_deg, 0.0, DEPTH, STEP)
    stepper = model.stepper(name)
    shell = stepper.engine.shell
    n = len(path.depths)
    depths = np.r_[path.depths, path.depths[-2::-1]]  # down to DEPTH and back to first touch
    tips = path.touch_point + depths[:, None] * path.direction
    forces, energies = [], []
    for tip in tips:
        result = stepper.step(path.rotation, tip)
        assert result.converged, (tip, result.message)
        forces.append(result.force)
        x = wp.array(stepper.x[None], dtype=wp.vec3d, device=shell.device)
        energies.append(float(shell.evaluate(x, False, np.array([stepper.pressure])).energy[0]))
    forces = np.array(forces)
    load = _trapezoid(forces[:n], tips[:n])
    assert load > 1e-3  # J: a real press (about 4 mJ to 2 mm)
    # Press and release: the same equilibria both ways (to Newton's 1e-6 relative force tolerance).
    assert abs(_trapezoid(forces, tips)) < 1e-5 * load
    assert energies[-1] == pytest.approx(energies[0], abs=1e-9 * load)
    # Loading: work = stored energy, within the trapezoid rule's error. The integrand f = F . u (u the unit
    # press direction) has slope kinks where a ring of nodes enters contact, so Richardson does not apply;
    # on an interval over which f's slope changes by j the error is at most h^2 |j| / 8 (the triangle between
    # the chord and a kink at mid-interval; a smooth f errs by h^3 |f''| / 12, less), with j estimated by the
    # change of the secant slopes around the interval.
    stored = energies[n - 1] - energies[0]
    f = forces[:n] @ path.direction
    secant = np.diff(f) / STEP
    kinks = np.abs(np.diff(secant))
    bound = STEP**2 / 8.0 * (kinks.sum() + kinks.max())  # the two ends' intervals counted with the largest
    assert abs(load - stored) < bound, (load, stored, bound)
    assert bound < 2e-3 * load  # and the bound is tight: it allows 0.2 % of the work at most


def test_a_frictional_press_and_release_dissipates(frictional_biotac: BioTacModel) -> None:
    """With friction (mu 0.5) the cycle's work is what friction dissipated: positive (the second law; a stick
    anchor moved the wrong way would give work back), and the release returns less work than the press took."""
    model, name = frictional_biotac, "sphere_medium"
    path = model.plan_trajectory(get_indenter(name), np.array([-6e-3, 0.0, -9e-3]), 30.0, 0.0, DEPTH, STEP)
    stepper = model.stepper(name)
    n = len(path.depths)
    tips = path.touch_point + np.r_[path.depths, path.depths[-2::-1]][:, None] * path.direction
    forces = []
    for tip in tips:
        result = stepper.step(path.rotation, tip)
        assert result.converged, (tip, result.message)
        forces.append(result.force)
    forces = np.array(forces)
    load, cycle = _trapezoid(forces[:n], tips[:n]), _trapezoid(forces, tips)
    assert load > 1e-3
    assert cycle > 1e-3 * load, (cycle, load)
