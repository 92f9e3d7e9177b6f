"""Never a wrong number marked converged (issue 17, review F1-F3): nothing passes through the skin unseen.

Independent references: trimesh's signed distance to the core mesh; the indenter's numpy SDF
(`assets.indenters`); forces of the same press taken in small steps. A 3 mm BioTac mesh keeps each test to
seconds.
"""

import numpy as np
import pytest
import trimesh
import warp as wp

from assets.biotac import make_biotac
from assets.indenters import get_indenter
from fe.batched_runner import PoseTrajectory, run_trajectories
from fe.batched_stepper import BatchedStepper
from fe.indentation import IndentationStepper
from fe.params import SkinParameters
from fe.sensor import BioTacModel

POINT = np.array([-6.0, 0.0, -9.0]) * 1e-3  # m, the review's press point (sensor frame)


@pytest.fixture(scope="module")
def biotac() -> BioTacModel:
    """A frictionless BioTac on a 3 mm mesh, inflated."""
    model = BioTacModel(make_biotac(max_edge=3e-3), SkinParameters(friction=0.0))
    assert model.inflate().converged
    return model


def test_a_skin_vertex_deep_inside_the_core_gets_its_true_negative_gap(biotac: BioTacModel) -> None:
    """Vertices 3.8-4.1 mm inside the core, farther from every face than the bounded search's reach
    (offset + 1 mm): the kernel's core gap is trimesh's signed distance minus the offset (review F3: it read
    +1 m, out of contact)."""
    skin = biotac.inflated_skin()
    stepper = BatchedStepper(skin, ["sphere_large"])
    core = trimesh.Trimesh(skin.core_vertices, skin.core_triangles, process=False)
    free = np.flatnonzero(~np.asarray(skin.fixed).reshape(len(skin.vertices), -1).all(axis=1))[:3]
    x = skin.reference.copy()
    x[free] = np.array([[-6.0, 0.0, -1.6], [-10.0, 0.5, -1.5], [-2.0, -0.5, -1.8]]) * 1e-3
    stepper.shell.evaluate(wp.array(x[None], dtype=wp.vec3d), False, stepper.pressure)
    gap = stepper.shell.buf["core_gap"].numpy()[0, free]
    expected = -trimesh.proximity.signed_distance(core, x[free]) - skin.core_offset
    assert np.all(expected < -(skin.core_offset + 1e-3))  # beyond the bounded search
    assert np.allclose(gap, expected, atol=1e-7), (gap, expected)


def _press(model: BioTacModel, name: str, depth_mm: float, step_mm: float) -> list:
    return list(model.indent(name, POINT, depth_mm * 1e-3, step_mm * 1e-3, 0.0))


def _same_or_refused(result, reference) -> None:
    """A converged increment carries the small-step path's force at its depth (5 %); else it says why not."""
    if result.converged:
        assert reference.converged and np.isclose(result.depth, reference.depth)
        assert np.linalg.norm(result.force - reference.force) <= 0.05 * np.linalg.norm(reference.force)
    else:
        assert result.message.startswith("inadmissible"), result.message


@pytest.mark.parametrize(("name", "depth_mm"), [("sphere_medium", 9.0), ("sphere_large", 5.0)])
def test_one_large_step_from_touch_does_not_tunnel_through_the_skin(
    biotac: BioTacModel, name: str, depth_mm: float
) -> None:
    """Review F1: one 9 mm step from first touch came back converged at 0 N, "no contact" (the ball passed
    through the skin). Now it is refused ("step too large", after three halvings) or carries the force of
    the same press taken in 0.5 mm steps; those steps (within the half-thickness) are never refused so."""
    path = _press(biotac, name, depth_mm, 0.5)
    assert not any("step too large" in r.message for r in path)
    assert path[1].converged and np.linalg.norm(path[1].force) > 0.0
    one = _press(biotac, name, depth_mm, depth_mm)[-1]
    reference = min(path, key=lambda r: abs(r.depth - one.depth))
    _same_or_refused(one, reference)


def test_a_ball_pressed_in_and_then_pushed_through_the_skin_is_not_released(biotac: BioTacModel) -> None:
    """Review F1: a ball 1 mm deep pushed on by 8 mm in one step ended beyond the skin and read 0 N, "no
    contact", converged (a release judged at the end pose only). Now refused, or the 0.5 mm path's force."""
    name = "sphere_medium"
    path = biotac.plan_trajectory(get_indenter(name), POINT, 0.0, 0.0, 1e-3, 1e-3)
    stepper = IndentationStepper(biotac.inflated_skin(), name, path.touch_point)
    for depth in (0.0, 0.5, 1.0):
        assert stepper.step(path.rotation, path.touch_point + depth * 1e-3 * path.direction).converged
    through = stepper.step(path.rotation, path.touch_point + 9e-3 * path.direction)
    reference = min(_press(biotac, name, 9.0, 0.5), key=lambda r: abs(r.depth - through.depth))
    _same_or_refused(through, reference)


def test_a_large_ball_never_reaches_the_core_through_the_skin(biotac: BioTacModel) -> None:
    """Review F2: sphere_large in 0.5 mm steps kept converging after the core passed through skin triangles
    between their vertices, its force falling with depth (24.4 N at 6.0 mm, 23.9 N at 6.5 mm on this mesh)
    while the ball sat inside the rigid core. Every converged increment must keep the ball's surface
    (trimesh: distance of its centre to the core, minus its radius) at least both half-layers at the floor
    from the core, with a force that grows with depth; the press ends refused."""
    skin, name = biotac.inflated_skin(), "sphere_large"
    radius = get_indenter(name).dims[0]
    path = biotac.plan_trajectory(get_indenter(name), POINT, 0.0, 0.0, 1e-3, 1e-3)
    core = trimesh.Trimesh(skin.core_vertices, skin.core_triangles, process=False)
    floor = skin.contact.min_stretch * (0.5 * biotac.params.thickness + skin.core_offset)
    rows = _press(biotac, name, 7.5, 0.5)
    accepted = [r for r in rows if r.converged]
    centres = np.array([path.touch_point + r.depth * path.direction + radius * path.rotation[:, 2] for r in accepted])
    clearance = np.abs(trimesh.proximity.signed_distance(core, centres)) - radius
    assert np.all(clearance >= floor), clearance
    magnitudes = [float(np.linalg.norm(r.force)) for r in accepted]
    assert np.all(np.diff(magnitudes) > 0.0), magnitudes
    assert not rows[-1].converged and "reached the core through the skin" in rows[-1].message, rows[-1].message


def test_a_step_refused_as_too_large_is_taken_in_halves_to_the_path_force(biotac: BioTacModel) -> None:
    """A 3 mm step from first touch (more than the 0.79 mm half-thickness against the skin) is refused before
    any solve and halved by the cut-back, without using up its cuts, until each piece is within the limit:
    frictionless, the result is the same equilibrium as the press in 0.5 mm steps (0.1 %)."""
    path = _press(biotac, "sphere_medium", 3.0, 0.5)
    one = _press(biotac, "sphere_medium", 3.0, 3.0)[-1]
    assert path[-1].converged and one.converged and one.depth == pytest.approx(3e-3)
    assert np.linalg.norm(one.force - path[-1].force) <= 1e-3 * np.linalg.norm(path[-1].force)


def test_the_batched_runner_halves_a_step_too_large_like_the_one_trajectory_stepper(biotac: BioTacModel) -> None:
    """`run_trajectories`: the 3 mm step from touch beside the same press in 0.5 mm steps, in one batch: three
    halvings (pieces of 0.375 mm), and the same force at 3 mm (0.1 %)."""
    path = biotac.plan_trajectory(get_indenter("sphere_medium"), POINT, 0.0, 0.0, 1e-3, 1e-3)

    def trajectory(depths_mm: list[float]) -> PoseTrajectory:
        tips = [path.touch_point + d * 1e-3 * path.direction for d in depths_mm]
        return PoseTrajectory("sphere_medium", np.stack([path.rotation] * len(tips)), np.array(tips))

    run = run_trajectories(biotac.inflated_skin(), [trajectory([0.0, 3.0]), trajectory(list(np.arange(7) * 0.5))])
    jump, steps = run.results[0][-1], run.results[1][-1]
    assert jump.converged and steps.converged and run.counters["cut_backs"] == 3
    assert np.linalg.norm(jump.force - steps.force) <= 1e-3 * np.linalg.norm(steps.force)
