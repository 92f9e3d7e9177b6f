"""Pose-driven indentation stepper on a coarse inflated BioTac: path independence, release, symmetry, failure."""

import dataclasses
import time

import numpy as np
import pytest

from assets.indenters import get_indenter
from fe.indentation import IndentationStepper
from fe.sensor import BioTacModel

MIDLINE_POINT = np.array([-6e-3, 0.0, -9e-3])


def _normal_path(model: BioTacModel, depth: float, step: float):
    return model.plan_trajectory(get_indenter("sphere_medium"), MIDLINE_POINT, 0.0, 0.0, depth, step)


def _spin(rotation: np.ndarray, angle: float) -> np.ndarray:
    """The same indenter rotated by `angle` (rad) about its own z axis."""
    c, s = np.cos(angle), np.sin(angle)
    return rotation @ np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])


def test_stepper_matches_indent_and_frictionless_equilibrium_is_path_independent(
    frictionless_biotac: BioTacModel,
) -> None:
    model = frictionless_biotac
    path = _normal_path(model, 0.4e-3, 0.1e-3)
    by_indent = list(model.indent("sphere_medium", MIDLINE_POINT, depth=0.4e-3, step=0.1e-3))
    stepper = model.stepper("sphere_medium")
    by_steps = [stepper.step(path.rotation, path.touch_point + d * path.direction) for d in path.depths]
    for a, b in zip(by_indent, by_steps, strict=True):
        assert b.converged and b.depth == pytest.approx(a.depth, abs=1e-12)
        assert np.allclose(b.force, a.force, rtol=1e-9, atol=1e-12)
    # Without friction the equilibrium depends on the pose only: one big step lands on the same state.
    stepper.reset()
    stepper.step(path.rotation, path.touch_point)
    direct = stepper.step(path.rotation, path.touch_point + 0.4e-3 * path.direction)
    assert direct.converged and direct.depth == pytest.approx(0.4e-3)
    assert np.allclose(direct.force, by_steps[-1].force, rtol=1e-4, atol=1e-6)
    assert direct.pressure == pytest.approx(by_steps[-1].pressure, rel=1e-6)


def test_out_of_contact_pose_is_free_and_release_restores_the_inflated_state(frictionless_biotac: BioTacModel) -> None:
    model = frictionless_biotac
    path = _normal_path(model, 0.3e-3, 0.3e-3)
    stepper = model.stepper("sphere_medium")
    above = path.touch_point - 2e-3 * path.direction
    start = time.perf_counter()
    free = stepper.step(path.rotation, above)
    assert time.perf_counter() - start < 0.2
    assert free.converged and free.newton_iterations == 0 and free.depth == 0.0
    assert np.all(free.force == 0.0) and free.contact_area == 0.0
    assert free.pressure == model.pressure and np.all(free.displacement == 0.0)
    pressed = stepper.step(path.rotation, path.touch_point + 0.3e-3 * path.direction)
    assert pressed.converged and pressed.force[2] > 0.05 and pressed.depth == pytest.approx(2.3e-3)
    released = stepper.step(path.rotation, above)
    assert released.converged and np.all(released.force == 0.0)
    assert released.pressure == model.pressure and np.all(released.displacement == 0.0)
    again = stepper.step(path.rotation, path.touch_point + 0.3e-3 * path.direction)
    assert np.allclose(again.force, pressed.force, rtol=1e-4, atol=1e-6)


def test_spinning_a_sphere_about_its_axis_changes_nothing_without_friction(frictionless_biotac: BioTacModel) -> None:
    model = frictionless_biotac
    path = _normal_path(model, 0.3e-3, 0.3e-3)
    tip = path.touch_point + 0.3e-3 * path.direction
    stepper = model.stepper("sphere_medium")
    straight = stepper.step(path.rotation, tip)
    spun = stepper.step(_spin(path.rotation, 0.7), tip)
    assert spun.converged
    assert np.allclose(spun.force, straight.force, rtol=1e-6, atol=1e-9)
    assert spun.contact_radius == pytest.approx(straight.contact_radius, rel=1e-6)


def test_non_converged_step_is_reported_and_blocks_until_reset(frictionless_biotac: BioTacModel) -> None:
    model = frictionless_biotac
    path = _normal_path(model, 0.3e-3, 0.3e-3)
    skin = model.inflated_skin()
    capped = dataclasses.replace(skin, newton=dataclasses.replace(skin.newton, max_iterations=1))
    stepper = IndentationStepper(capped, "sphere_medium")
    failed = stepper.step(path.rotation, path.touch_point + 0.3e-3 * path.direction)
    assert not failed.converged and failed.message == "iteration limit"
    with pytest.raises(RuntimeError, match="reset"):
        stepper.step(path.rotation, path.touch_point)
    stepper.reset()
    assert stepper.failure is None
    free = stepper.step(path.rotation, path.touch_point - 1e-3 * path.direction)
    assert free.converged and np.all(free.displacement == 0.0) and free.pressure == model.pressure


def test_bad_poses_are_refused(frictionless_biotac: BioTacModel) -> None:
    stepper = frictionless_biotac.stepper("sphere_medium")
    with pytest.raises(ValueError, match="rotation"):
        stepper.step(np.diag([1.0, 1.0, -1.0]), np.zeros(3))
    with pytest.raises(ValueError, match="pose"):
        stepper.step(np.eye(3), np.zeros(2))
    with pytest.raises(ValueError, match="non-finite"):
        stepper.step(np.eye(3), np.array([0.0, np.nan, 0.0]))
    with pytest.raises(ValueError, match="unknown indenter|valid"):
        frictionless_biotac.stepper("teapot")


def test_solving_a_held_pose_again_changes_nothing_with_friction(frictional_biotac: BioTacModel) -> None:
    """Nothing moves, nothing relaxes: the skin's state, and the force on the indenter, must stay as they are."""
    model = frictional_biotac
    path = model.plan_trajectory(get_indenter("sphere_medium"), np.array([-3e-3, 2e-3, -9e-3]), 30.0, 45.0, 1e-3, 1e-4)
    stepper = model.stepper("sphere_medium")
    for depth in path.depths:
        held = stepper.step(path.rotation, path.touch_point + depth * path.direction)
        assert held.converged, held.message
    again = [stepper.step(path.rotation, path.touch_point + path.depths[-1] * path.direction) for _ in range(5)]
    assert all(result.converged for result in again)
    drift = max(np.linalg.norm(result.force - held.force) for result in again)
    assert drift <= 1e-3 * np.linalg.norm(held.force), f"the force moved {drift * 1e3:.2f} mN at a held pose"
    moved = max(np.abs(result.displacement - held.displacement).max() for result in again)
    assert moved <= 1e-3 * np.abs(held.displacement).max(), f"the skin moved {moved * 1e6:.3f} um at a held pose"
