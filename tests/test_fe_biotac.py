"""BioTac FE on a coarse mesh: inflation, conservation, equilibrium, symmetry, Coulomb bound, bad input."""

import numpy as np
import pytest
import warp as wp

from assets.indenters import INDENTERS, get_indenter
from fe.indentation import IndentationStepper, drive
from fe.params import SkinParameters
from fe.sensor import SENSOR_THICKNESS, BioTacModel
from fe.surface_quadrature import rule

MIDLINE_POINT = np.array([-6e-3, 0.0, -9e-3])


def _enclosed_volume(x: np.ndarray, triangles: np.ndarray, origin: np.ndarray) -> float:
    """Signed volume (m^3) of the cones from `origin` to the skin triangles (numpy, independent of fe/); with the
    anchored rim fixed, differences between two states do not depend on the origin."""
    a, b, c = (x[triangles[:, k]] - origin for k in range(3))
    return float(np.einsum("ij,ij->", a, np.cross(b, c)) / 6.0)


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
    reference = frictionless_biotac.reference
    triangles = frictionless_biotac.geometry.skin.triangles
    origin = frictionless_biotac.geometry.core.vertices.mean(axis=0)
    v_ref = _enclosed_volume(reference, triangles, origin)
    for inc in increments:
        assert abs(inc.volume - target) <= 1e-6 * abs(target)
        # The incompressible fluid's volume, measured here from the nodal positions alone.
        assert abs(_enclosed_volume(reference + inc.displacement, triangles, origin) - v_ref) <= 1e-6 * abs(target)
        assert inc.equilibrium_error <= 1e-6
    force = last.force
    assert force[2] > 0.1, "pressing on the ventral pad pushes the skin toward +z"
    assert abs(force[1]) <= 1e-2 * np.linalg.norm(force), "no lateral force by mirror symmetry"
    fz = [inc.force[2] for inc in increments]
    assert np.all(np.diff(fz) > 0)
    assert last.pressure > frictionless_biotac.pressure


def test_angled_indentation_tangential_force_bounded_by_friction(frictional_biotac: BioTacModel) -> None:
    model = frictional_biotac
    path = model.plan_trajectory(get_indenter("sphere_medium"), MIDLINE_POINT, 30.0, 0.0, 0.6e-3, 0.2e-3)
    stepper = IndentationStepper(model.inflated_skin(), "sphere_medium", path.touch_point)
    increments = list(drive(stepper, path))
    assert len(increments) == len(path.depths) and all(inc.converged for inc in increments)
    assert all(inc.equilibrium_error <= 1e-6 for inc in increments)
    # Re-evaluate the final state's contact terms (pose, slip start and lagged normal forces as the last solve
    # left them).
    shell = stepper.engine.shell
    shell.evaluate(wp.array(stepper.x[None], dtype=wp.vec3d), False, np.array([stepper.pressure]))
    f = -shell.gradients.numpy()[2, 0]  # indenter force on each skin vertex: normal (lumped) + friction
    normal_force = shell.buf["indenter_vertex_force"].numpy()[0]  # the surface contact's, lumped to vertices
    f_n = np.linalg.norm(normal_force, axis=1)
    friction = f - normal_force
    f_t = np.linalg.norm(friction, axis=1)
    lagged, n = shell.lagged_force.numpy()[0], shell.lagged_normal.numpy()[0]
    # Per contact node: friction acts in the plane normal to its lagged normal, Coulomb: |f_t| <= mu f_n.
    contact = lagged > 0
    assert contact.any() and np.all(f[(f_n == 0.0) & ~contact] == 0.0)
    assert np.all(np.abs(np.einsum("ij,ij->i", friction, n))[contact] <= 1e-9 * f_t[contact] + 1e-15)
    assert np.all(f_t[contact] <= model.params.friction * lagged[contact] * (1 + 1e-9) + 1e-12)
    # Against the normal forces of the final state itself (the lagged ones trail them by the refresh tolerance).
    assert f_t.sum() <= model.params.friction * f_n.sum() * 1.01
    assert np.allclose(f.sum(axis=0), increments[-1].force, rtol=1e-9, atol=1e-12)  # the state reported
    # Friction is engaged: some contact nodes slide, at the Coulomb limit.
    assert np.max(f_t[contact] / (model.params.friction * lagged[contact])) > 0.99
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


@pytest.mark.parametrize("indenter_name, angle_deg", [("sphere_small", 0.0), ("cube", 30.0), ("ring", 0.0)])
def test_the_first_touch_is_where_the_first_skin_point_meets_the_contact_law(
    frictionless_biotac: BioTacModel, indenter_name: str, angle_deg: float
) -> None:
    """Checked against every vertex and quadrature point of the outer skin: none inside the indenter's contact
    reach at the planned touch point, some 1 um deeper (the search drops points as its bracket narrows)."""
    model, indenter = frictionless_biotac, INDENTERS[indenter_name]
    path = model.plan_trajectory(indenter, np.array([-6e-3, 0.0, -9e-3]), angle_deg, 40.0, 1e-3, 1e-3)
    x = model.inflated_skin().reference
    weights = rule(model.rest_skin.contact.surface_rule)[:, :3]
    points = np.concatenate([x, np.einsum("qk,tkd->tqd", weights, x[model.geometry.skin.triangles]).reshape(-1, 3)])

    def smallest_gap(tip: np.ndarray) -> float:
        return float(indenter.sdf((points - tip) @ path.rotation).min() - model.rest_skin.indenter_half_layer)

    assert -1e-12 < smallest_gap(path.touch_point) < 1e-9
    assert smallest_gap(path.touch_point + 1e-6 * path.direction) < -0.5e-6
