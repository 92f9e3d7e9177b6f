"""BioTac FE on a coarse mesh: inflation, conservation, equilibrium, symmetry, Coulomb bound, bad input."""

import numpy as np
import pytest

from fe.params import SkinParameters
from fe.sensor import SENSOR_THICKNESS, BioTacModel

MIDLINE_POINT = np.array([-6e-3, 0.0, -9e-3])


def test_inflation_reaches_the_sensor_thickness(frictionless_biotac: BioTacModel) -> None:
    model = frictionless_biotac
    assert model.thickness(model.reference) == pytest.approx(SENSOR_THICKNESS, abs=1e-6)
    assert model.pressure > 0
    assert model.target_volume > model._volume0


def test_normal_midline_indentation_conserves_volume_balances_forces_and_is_symmetric(
    frictionless_biotac: BioTacModel,
) -> None:
    increments = list(frictionless_biotac.indent("sphere_medium", MIDLINE_POINT, depth=0.6e-3, step=0.2e-3))
    assert all(inc.converged for inc in increments)
    last = increments[-1]
    target = frictionless_biotac.target_volume
    for inc in increments:
        assert abs(inc.volume - target) <= 1e-6 * abs(target)
        assert inc.equilibrium_error <= 1e-6
    force = last.force
    assert force[2] > 0.1, "pressing on the ventral pad pushes the skin toward +z"
    assert abs(force[1]) <= 1e-2 * np.linalg.norm(force), "no lateral force by mirror symmetry"
    fz = [inc.force[2] for inc in increments]
    assert np.all(np.diff(fz) > 0)
    assert last.pressure > frictionless_biotac.pressure


def test_angled_indentation_tangential_force_bounded_by_friction(frictional_biotac: BioTacModel) -> None:
    model = frictional_biotac
    increments = list(model.indent("sphere_medium", MIDLINE_POINT, depth=0.6e-3, step=0.2e-3, angle_deg=30.0))
    assert all(inc.converged for inc in increments)
    system = model.system
    terms = system.evaluate(model.reference + increments[-1].displacement, want_hessian=False)
    normal_force = system.lagged_force * (terms["indenter_gap"] < 0)
    # Per contact node: friction = total contact force minus its normal part; Coulomb: |f_t| <= mu f_n.
    f = -terms["indenter_gradient"]
    n = terms["indenter_normal"]
    f_n = np.einsum("ij,ij->i", f, n)
    f_t = np.linalg.norm(f - f_n[:, None] * n, axis=1)
    contact = normal_force > 0
    assert contact.any()
    assert np.all(f_t[contact] <= model.params.friction * system.lagged_force[contact] * (1 + 1e-9) + 1e-12)
    # The resultant is tilted away from the surface normal, but no more than friction allows.
    total = increments[-1].force
    assert np.linalg.norm(total[:2]) > 0.02 * np.linalg.norm(total)


def test_bad_input_gives_clear_errors(frictionless_biotac: BioTacModel) -> None:
    with pytest.raises(ValueError, match="unknown indenter|valid"):
        list(frictionless_biotac.indent("teapot", MIDLINE_POINT, depth=1e-3))
    with pytest.raises(ValueError, match="from the skin"):
        list(frictionless_biotac.indent("sphere_medium", np.array([0.0, 0.0, -0.05]), depth=1e-3))
    with pytest.raises(ValueError, match="depth"):
        list(frictionless_biotac.indent("sphere_medium", MIDLINE_POINT, depth=-1e-3))
    with pytest.raises(ValueError, match="physical range"):
        SkinParameters(mu_nh=-5.0)
    with pytest.raises(ValueError, match="physical range"):
        SkinParameters(friction=12.0)


def test_indenting_before_inflating_is_refused() -> None:
    from assets.biotac import make_biotac

    model = BioTacModel(make_biotac(max_edge=3e-3))
    with pytest.raises(RuntimeError, match="inflate"):
        list(model.indent("sphere_medium", MIDLINE_POINT, depth=1e-3))
