"""Never a wrong number marked converged (issue 17, review F1-F3): nothing passes through the skin unseen.

Independent references: trimesh's signed distance to the core mesh; the indenter's numpy SDF
(`assets.indenters`); forces of the same press taken in small steps. A 3 mm BioTac mesh keeps each test to
seconds.
"""

import re

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


def test_the_step_guard_reads_the_quadrature_points_gaps(biotac: BioTacModel) -> None:
    """Review (session 11): sphere_small (1.75 mm radius, smaller than a 3 mm skin triangle) 1.4 mm in one step
    from first touch. The guard read only the skin vertices' gaps, which change 0.45 mm (the ball goes in
    between them), and solved the step; the surface contact's quadrature points under the ball move with it,
    their gaps closing by the whole 1.4 mm (a point on the ball's axis: exactly the travel), more than the
    0.79 mm half-thickness. The step is now refused as too large before any solve, measured at the travel."""
    name = "sphere_small"
    path = biotac.plan_trajectory(get_indenter(name), POINT, 0.0, 0.0, 1e-3, 1e-3)
    stepper = BatchedStepper(biotac.inflated_skin(), [name])
    assert stepper.step(path.rotation[None], path.touch_point[None])[0].converged
    deep = stepper.step(path.rotation[None], (path.touch_point + 1.4e-3 * path.direction)[None])[0]
    assert stepper.too_large[0] and not deep.converged, deep.message
    moved_mm = float(re.search(r"moves ([0-9.]+) mm", deep.message).group(1))
    assert 1.3 <= moved_mm <= 1.4 + 1e-9, deep.message  # 1-Lipschitz: no gap changes by more than the travel


def _deepest_reach(skin, indenter_name: str, rotation: np.ndarray, tip: np.ndarray, x: np.ndarray) -> float:
    """Smallest numpy SDF (m) of the indenter head at pose (rotation, tip) over the skin mid-surface at x (V,3):
    every triangle sampled with 24 nodes to an edge (an independent check of the engine's sampling)."""
    k = 24
    uv = np.array([(i / k, j / k) for i in range(k + 1) for j in range(k + 1 - i)])
    bary = np.column_stack([1.0 - uv.sum(axis=1), uv])
    points = np.einsum("qk,tkd->tqd", bary, x[skin.triangles]).reshape(-1, 3)
    return float(get_indenter(indenter_name).sdf((points - tip) @ rotation).min())


def test_a_ball_smaller_than_a_skin_triangle_does_not_pass_between_its_vertices(biotac: BioTacModel) -> None:
    """sphere_small (1.75 mm radius) against the 3 mm mesh in 0.5 mm steps: with contact at the skin vertices
    only, the ball went in between them (its surface 0.075 mm inside the mid-surface at 0.5 mm, 1.38 mm at 2
    mm) while every increment read converged, the force turning round at 2 mm (1.51 N at 1.5 mm, 0.56 N
    after). Now every converged increment keeps the ball at least the floor (min_stretch of the half-layer)
    from every point of the skin's mid-surface, sampled here independently of the engine, its force rising
    with depth; an increment that would not is refused as inadmissible."""
    skin, name = biotac.inflated_skin(), "sphere_small"
    path = biotac.plan_trajectory(get_indenter(name), POINT, 0.0, 0.0, 1e-3, 1e-3)
    floor = skin.contact.min_stretch * 0.5 * biotac.params.thickness
    rows = _press(biotac, name, 4.0, 0.5)
    accepted = [r for r in rows[1:] if r.converged]
    assert len(accepted) >= 6  # converged at least to 3 mm: the check does not refuse honest states
    for r in accepted:
        x = skin.reference + r.displacement
        tip = path.touch_point + r.depth * path.direction
        assert _deepest_reach(skin, name, path.rotation, tip, x) >= floor, r.depth
    magnitudes = [float(np.linalg.norm(r.force)) for r in accepted]
    assert np.all(np.diff(magnitudes) > 0.0), magnitudes
    assert all(r.converged or r.message.startswith("inadmissible") for r in rows), [r.message for r in rows]


def test_the_skin_clearance_of_a_ball_is_its_exact_distance_to_the_skin_triangles(biotac: BioTacModel) -> None:
    """`BatchedShell.indenter_skin_clearance` (over all triangles) against trimesh's exact closest point on the
    mid-surface mesh: a ball placed with its surface 0.1-0.3 mm inside the mid-surface at the centres of three
    skin triangles (where no vertex reaches it), its shank pointing away, reads its depth to the sampling's
    resolution (nodes 0.05 mm apart on a 1.75 mm ball: < 1 um); a ball clear of the skin reads at least the
    floor."""
    skin, name = biotac.inflated_skin(), "sphere_small"
    radius = get_indenter(name).dims[0]
    stepper = BatchedStepper(skin, [name] * 4)
    mesh = trimesh.Trimesh(skin.reference, skin.triangles, process=False)
    faces = [20, 90, 160]
    centroids = skin.reference[skin.triangles[faces]].mean(axis=1)
    outward = mesh.face_normals[faces]
    depths = np.array([0.1e-3, 0.3e-3, 0.2e-3, -5e-3])  # the last ball stays 5 mm off the skin
    centres = np.vstack([centroids, centroids[:1]]) + (radius - depths)[:, None] * np.vstack([outward, outward[:1]])
    axes = np.vstack([outward, outward[:1]])  # body axis (+z) outward: the shank points away from the skin
    side = np.cross(axes, [0.3, 0.5, 0.8])
    side /= np.linalg.norm(side, axis=1)[:, None]
    rotation = np.stack([side, np.cross(axes, side), axes], axis=2)
    tips = centres - radius * axes  # the ball's centre sits radius above its tip
    stepper.shell.set_poses(rotation, tips, rotation, tips)
    x = wp.array(np.stack([skin.reference] * 4), dtype=wp.vec3d)
    floor = np.full(4, 0.2e-3)
    reach = stepper.shell.indenter_skin_clearance(x, np.full(4, 0.05e-3), floor, np.ones(4, dtype=bool)).min(axis=1)
    exact = trimesh.proximity.closest_point(mesh, centres)[1] - radius
    assert np.all(reach[:3] - exact[:3] >= -1e-12) and np.all(reach[:3] - exact[:3] <= 1e-6), (reach, exact)
    assert np.all(exact[:3] < 0.0) and reach[3] >= floor[3]
    nearest_vertex = np.linalg.norm(skin.reference[None] - centres[:3, None], axis=2).min(axis=1)
    assert np.all(nearest_vertex > radius)  # between the vertices: a vertex-only check saw nothing
