"""Batched FE on a warp device (here the CPU device): the batched CG against a direct solve, and B
trajectories stepped together against the per-trajectory CPU stepper on the coarse 2 mm mesh.

Stated tolerances (docs/scale.md): frictionless, forces within 1e-6 of |F|, displacements within 1e-9 m
and contact areas within 1e-6 (both paths converge to the same equilibrium to the Newton tolerance);
with friction, forces within 1e-3 of |F|, displacements within 1e-6 m and contact areas within 1e-4,
since the lagged friction forces are only refreshed until they change by less than 0.1% and the two
paths refresh at different iterates.
"""

import dataclasses
from pathlib import Path

import numpy as np
import pytest
import warp as wp
from conftest import inflated_biotac

from assets.indenters import get_indenter
from fe.batched import BatchLinearization, InflatedSkin, NewtonBatch, get_rows, put_rows
from fe.batched_runner import PoseTrajectory, run_trajectories
from fe.batched_stepper import BatchedStepper
from fe.device_solver import CG_CONVERGED, CG_NEGATIVE_CURVATURE, BatchedBlockMatrix, BatchedCG, BlockPattern
from fe.indentation import Trajectory
from fe.sensor import BioTacModel
from fe.trapped_air import TrappedAir

PATHS = [  # indenter, point (m), angle (deg), azimuth (deg)
    ("sphere_medium", np.array([-6e-3, 0.0, -9e-3]), 0.0, 0.0),
    ("sphere_medium", np.array([-3e-3, 2e-3, -9e-3]), 20.0, 30.0),
    ("cylinder_short_small", np.array([-8e-3, -1e-3, -8e-3]), 10.0, 90.0),
]
STEPS = np.array([-0.2e-3, 0.0, 0.3e-3, 0.6e-3])
"""Tip travel (m) past first touch; the first pose is out of contact."""
CAPPED_NEWTON = 5
"""A Newton iteration cap under which the full steps fail (the uncapped ones take more). Not 4: with the
contact integrated over the triangles the first increment in contact takes 5 iterations at any step size
(the uncapped press in 0.05 mm steps too), as the set of quadrature points in contact forms."""


def _random_spd(rng: np.random.Generator, n: int) -> np.ndarray:
    a = rng.standard_normal((n, n))
    return a @ a.T + n * np.eye(n)


def test_batched_cg_matches_a_direct_solve_and_flags_negative_curvature() -> None:
    rng = np.random.default_rng(3)
    n_nodes, batch = 12, 2
    elements = np.array([[i, i + 1] for i in range(n_nodes - 1)] + [[0, 5], [3, 9]])
    pattern = BlockPattern.from_connectivities([elements], n_nodes)
    free = np.ones((n_nodes, 3))
    free[0] = 0.0  # node 0 fixed
    free[4, 2] = 0.0  # one coordinate of node 4 fixed
    matrix = BatchedBlockMatrix(pattern, batch, free, "cpu")
    blocks = np.stack([[_random_spd(rng, 6) for _ in elements] for _ in range(batch)])
    blocks[1, 2] -= 40.0 * np.eye(6)  # system 1 becomes indefinite
    mat66 = wp.types.matrix(shape=(6, 6), dtype=wp.float64)
    matrix.assemble([(0, wp.array(blocks, dtype=mat66), None)], np.zeros(batch))
    rhs = rng.standard_normal((3, n_nodes, 3)) * free
    solver = BatchedCG(matrix, 3)
    x, iterations, state = solver.solve(
        wp.array(rhs, dtype=wp.vec3d), np.array([0, 1, 0]), np.array([True, True, False]), np.full(3, 1e-12), 500
    )
    dense = np.zeros((3 * n_nodes, 3 * n_nodes))
    for e, nodes in enumerate(elements):
        dofs = (3 * nodes[:, None] + np.arange(3)).ravel()
        dense[np.ix_(dofs, dofs)] += blocks[0, e]
    keep = free.ravel() > 0
    reduced = dense[np.ix_(keep, keep)]
    # The CG's products read the blocks rounded to float32: it solves that matrix to its tolerance, and the
    # exact one to the rounding's effect, cond x 2^-24.
    rounded = np.zeros(3 * n_nodes)
    rounded[keep] = np.linalg.solve(reduced.astype(np.float32).astype(np.float64), rhs[0].ravel()[keep])
    exact = np.zeros(3 * n_nodes)
    exact[keep] = np.linalg.solve(reduced, rhs[0].ravel()[keep])
    assert state[0] == CG_CONVERGED and 0 < iterations[0] <= 3 * n_nodes
    solution = x.numpy()[0].ravel()
    np.testing.assert_allclose(solution, rounded, rtol=1e-8, atol=1e-12)
    error = np.abs(solution - exact).max() / np.abs(exact).max()
    assert 0.0 < error <= np.linalg.cond(reduced) * 2.0**-24
    assert state[1] == CG_NEGATIVE_CURVATURE
    assert state[2] == CG_CONVERGED and iterations[2] == 0 and not x.numpy()[2].any()


def test_a_warm_column_starts_from_its_last_solution_when_that_is_closer() -> None:
    """A warm CG column solves to the same tolerance from its last converged solution, in fewer iterations when
    the right-hand side changed little, and from 0 (as a cold column) when the last solution is further away than
    0 is; a column that did not run (inactive) keeps its last solution."""
    rng = np.random.default_rng(5)
    side = 24  # springs along the edges of a square grid: CG needs many iterations, far fewer than the unknowns
    n_nodes = side * side
    grid = np.arange(n_nodes).reshape(side, side)
    elements = np.concatenate(
        [np.c_[grid[:, :-1].ravel(), grid[:, 1:].ravel()], np.c_[grid[:-1].ravel(), grid[1:].ravel()]]
    )
    pattern = BlockPattern.from_connectivities([elements], n_nodes)
    free = np.ones((n_nodes, 3))
    free[0] = 0.0
    matrix = BatchedBlockMatrix(pattern, 1, free, "cpu")
    mat66 = wp.types.matrix(shape=(6, 6), dtype=wp.float64)
    blocks = np.stack([[np.kron([[1.0, -1.0], [-1.0, 1.0]], np.eye(3)) + 1e-3 * np.eye(6) for _ in elements]])
    matrix.assemble([(0, wp.array(blocks, dtype=mat66), None)], np.zeros(1))
    warm, cold = BatchedCG(matrix, 1, warm=np.array([True])), BatchedCG(matrix, 1)
    b = rng.standard_normal((1, n_nodes, 3)) * free

    def solve(solver: BatchedCG, rhs: np.ndarray, active: bool = True) -> tuple[np.ndarray, int]:
        x, iterations, state = solver.solve(
            wp.array(rhs, dtype=wp.vec3d), np.zeros(1), np.array([active]), np.full(1, 1e-6), 2000
        )
        assert state[0] == CG_CONVERGED
        return x.numpy()[0].copy(), int(iterations[0])

    first, n_first = solve(warm, b)
    assert n_first == solve(cold, b)[1] > 20  # nothing to start from yet: the same as cold
    solve(warm, b, active=False)  # an inactive column keeps its last solution
    nudged = b + 1e-5 * rng.standard_normal(b.shape) * free
    again, n_again = solve(warm, nudged)
    reference, n_cold = solve(cold, nudged)
    assert n_again < n_cold / 2
    scale = np.abs(reference).max()
    assert np.abs(again - reference).max() <= 1e-4 * scale and np.abs(again - first).max() > 0.0
    _, n_far = solve(warm, -10.0 * nudged)  # the last solution is further from this one than 0 is
    assert n_far == solve(cold, -10.0 * nudged)[1]


def _paths(model: BioTacModel) -> list:
    return [model.plan_trajectory(get_indenter(name), p, a, z, 1e-3, 1e-3) for name, p, a, z in PATHS]


def _cpu(model: BioTacModel, paths: list) -> list[list]:
    return [_cpu_steps(model, name, path) for (name, *_), path in zip(PATHS, paths, strict=True)]


def _cpu_steps(model: BioTacModel, name: str, path: Trajectory) -> list:
    """The CPU stepper's increments along a planned path, at the travels STEPS past first touch."""
    stepper = model.stepper(name)
    return [stepper.step(path.rotation, path.touch_point + s * path.direction) for s in STEPS]


def _pose_trajectory(name: str, path: Trajectory) -> PoseTrajectory:
    """A planned path's poses at the travels STEPS past first touch, for `run_trajectories`."""
    return PoseTrajectory(
        name, np.repeat(path.rotation[None], len(STEPS), 0), path.touch_point + STEPS[:, None] * path.direction
    )


def _batched(model: BioTacModel, paths: list, tmp_path: Path) -> list[list]:
    """The batched stepper, the third trajectory starting one step late (inactive systems wait)."""
    skin = model.inflated_skin()
    skin.save(tmp_path / "skin.npz")
    stepper = BatchedStepper(InflatedSkin.load(tmp_path / "skin.npz"), [name for name, *_ in PATHS], "cpu")
    out: list[list] = [[] for _ in PATHS]
    rotation = np.stack([p.rotation for p in paths])
    for k in range(len(STEPS) + 1):
        index = np.array([k, k, k - 1])
        active = (index >= 0) & (index < len(STEPS))
        travel = STEPS[np.clip(index, 0, len(STEPS) - 1)]
        translation = np.stack([p.touch_point + s * p.direction for p, s in zip(paths, travel, strict=True)])
        for i, result in enumerate(stepper.step(rotation, translation, active)):
            assert (result is None) == (not active[i])
            if result is not None:
                out[i].append(result)
    return out


TOLERANCES = [("frictionless_biotac", 1e-6, 1e-9, 1e-6), ("frictional_biotac", 1e-3, 1e-6, 1e-4)]
"""Fixture, force (relative to |F|), displacement (m) and contact-area (relative) tolerances."""


def _assert_agree(cpu: list, batched: list, force_rtol: float, displacement_atol: float, area_rtol: float) -> None:
    """Increment-by-increment agreement of one trajectory, converged throughout."""
    assert len(batched) == len(cpu)
    for a, b in zip(cpu, batched, strict=True):
        assert a.converged and b.converged, b.message
        assert b.depth == pytest.approx(a.depth, abs=1e-12)
        scale = max(np.linalg.norm(a.force), 1e-3)
        assert np.linalg.norm(b.force - a.force) <= force_rtol * scale
        assert b.pressure == pytest.approx(a.pressure, rel=1e-5)
        np.testing.assert_allclose(b.displacement, a.displacement, rtol=0, atol=displacement_atol)
        assert b.contact_area == pytest.approx(a.contact_area, rel=area_rtol, abs=1e-12)
        assert b.equilibrium_error < 1e-5


@pytest.mark.parametrize(("fixture", "force_rtol", "displacement_atol", "area_rtol"), TOLERANCES)
def test_batched_stepper_matches_the_cpu_stepper(
    fixture: str,
    force_rtol: float,
    displacement_atol: float,
    area_rtol: float,
    request: pytest.FixtureRequest,
    tmp_path: Path,
) -> None:
    model: BioTacModel = request.getfixturevalue(fixture)
    paths = _paths(model)
    cpu, batched = _cpu(model, paths), _batched(model, paths, tmp_path)
    for trajectory_cpu, trajectory_batched in zip(cpu, batched, strict=True):
        assert len(trajectory_batched) == len(STEPS)
        assert trajectory_batched[0].message == "no contact" and trajectory_batched[0].newton_iterations == 0
        _assert_agree(trajectory_cpu, trajectory_batched, force_rtol, displacement_atol, area_rtol)
        assert trajectory_batched[-1].force[2] > 0.1  # pressed into the pad


@pytest.mark.parametrize(("fixture", "force_rtol", "displacement_atol", "area_rtol"), TOLERANCES)
def test_continuous_batching_matches_the_cpu_stepper(
    fixture: str, force_rtol: float, displacement_atol: float, area_rtol: float, request: pytest.FixtureRequest
) -> None:
    """Three trajectories of two indenters on fewer slots, systems admitted while others iterate: without
    friction on one slot (which changes indenter), with friction on two slots and a force limit that ends
    trajectories early."""
    model: BioTacModel = request.getfixturevalue(fixture)
    paths = _paths(model)
    cpu = _cpu(model, paths)
    frictional = fixture == "frictional_biotac"
    limit, slots = (0.9 * max(np.linalg.norm(t[-2].force) for t in cpu), 2) if frictional else (np.inf, 1)
    trajectories = [_pose_trajectory(name, p) for (name, *_), p in zip(PATHS, paths, strict=True)]
    ended: list[int] = []
    run = run_trajectories(
        model.inflated_skin(),
        trajectories,
        "cpu",
        slots=slots,
        force_limit=limit,
        on_trajectory=lambda index, increments: ended.append(index),
    )
    assert run.slots == slots and len(run.round_end_s) == len(run.round_systems) == run.iterations
    assert 1 <= run.round_systems.min() and run.round_systems.max() <= slots and np.all(np.diff(run.round_end_s) >= 0)
    assert sorted(ended) == [0, 1, 2]
    for trajectory_cpu, trajectory_batched in zip(cpu, run.results, strict=True):
        over = [np.linalg.norm(r.force) > limit for r in trajectory_cpu]
        stop = over.index(True) + 1 if any(over) else len(STEPS)  # the first increment past the limit ends it
        _assert_agree(trajectory_cpu[:stop], trajectory_batched, force_rtol, displacement_atol, area_rtol)
    if np.isfinite(limit):
        assert any(len(t) < len(STEPS) for t in run.results)


def test_the_longest_trajectories_start_first(frictionless_biotac: BioTacModel) -> None:
    """On one slot the trajectory with the most poses runs first, then the others by length (ties in their
    order); each one's increments are those it gets when run alone."""
    model = frictionless_biotac
    full = [_pose_trajectory(name, p) for (name, *_), p in zip(PATHS, _paths(model), strict=True)]
    lengths = (2, len(STEPS), 3)
    trajectories = [
        PoseTrajectory(t.indenter, t.rotations[:n], t.translations[:n]) for t, n in zip(full, lengths, strict=True)
    ]
    skin = model.inflated_skin()
    ended: list[int] = []
    run = run_trajectories(skin, trajectories, "cpu", slots=1, on_trajectory=lambda k, _: ended.append(k))
    assert ended == [1, 2, 0]
    for trajectory, together in zip(trajectories, run.results, strict=True):
        alone = run_trajectories(skin, [trajectory], "cpu", slots=1).results[0]
        assert len(together) == len(alone) == len(trajectory.rotations)
        for a, b in zip(alone, together, strict=True):
            assert a.converged and b.converged
            np.testing.assert_array_equal(a.force, b.force)
            np.testing.assert_array_equal(a.displacement, b.displacement)


def test_trapped_air_in_a_batch_follows_boyle_and_bad_poses_are_refused(frictionless_biotac: BioTacModel) -> None:
    """Two presses with a bubble of 10 % of the fluid, stepped together: the liquid is incompressible, so
    the enclosed volume changes by exactly the bubble's Boyle's-law change, (p_atm + p) V_air = k."""
    model = frictionless_biotac
    skin = model.inflated_skin()
    k = TrappedAir.boyle(0.1, model.fluid_volume(), model.pressure)
    with_air = dataclasses.replace(skin, params=dataclasses.replace(skin.params, air_volume_fraction=0.1), air_boyle=k)
    paths = _paths(model)[:2]
    stepper = BatchedStepper(with_air, [name for name, *_ in PATHS[:2]], "cpu")
    rotation = np.stack([p.rotation for p in paths])
    for s in STEPS[1:]:
        results = stepper.step(rotation, np.stack([p.touch_point + s * p.direction for p in paths]))
    air = TrappedAir(np.array([k]))
    for result in results:
        assert result.converged and result.pressure > model.pressure
        boyle_change = air.volume(np.array([result.pressure]))[0] - air.volume(np.array([model.pressure]))[0]
        assert result.volume - stepper.rest_volumes[0] == pytest.approx(boyle_change, rel=1e-6, abs=1e-15)
    with pytest.raises(ValueError, match="orthonormal"):
        BatchedStepper(skin, ["sphere_medium"], "cpu").step(np.zeros((1, 3, 3)), np.zeros((1, 3)))


def test_failed_steps_are_cut_back(frictionless_biotac: BioTacModel) -> None:
    """With Newton capped at a few iterations the 0.3 mm steps fail; halving them (poses through the
    midpoints, not reported) reaches every pose, at the same equilibria as the uncapped CPU stepper."""
    model = frictionless_biotac
    paths = _paths(model)
    cpu = _cpu(model, paths)[1]
    skin = model.inflated_skin()
    capped = dataclasses.replace(skin, newton=dataclasses.replace(skin.newton, max_iterations=CAPPED_NEWTON))
    name, path = PATHS[1][0], paths[1]  # the tilted sphere: its last step needs more than the cap
    trajectory = _pose_trajectory(name, path)
    plain = run_trajectories(capped, [trajectory], "cpu", slots=1, max_cuts=0).results[0]
    assert not plain[-1].converged  # the cap bites without cut-backs
    cut = run_trajectories(capped, [trajectory], "cpu", slots=1, max_cuts=3)
    _assert_agree(cpu, cut.results[0], 1e-6, 1e-9, 1e-6)
    assert cut.counters["cut_backs"] > 0


def test_strict_forcing_reaches_the_same_equilibria(frictionless_biotac: BioTacModel) -> None:
    """The CG tolerance rule changes the work, not the converged states; CG (the GPU's linear algebra, here
    on the CPU device) reaches the equilibria of the direct factorisation."""
    model = frictionless_biotac
    paths = _paths(model)
    skin = model.inflated_skin()
    trajectories = [_pose_trajectory(name, p) for (name, *_), p in zip(PATHS, paths, strict=True)]
    direct = run_trajectories(skin, trajectories, "cpu", slots=3)
    adaptive = run_trajectories(skin, trajectories, "cpu", slots=3, linear="cg")
    strict = run_trajectories(skin, trajectories, "cpu", slots=3, forcing="strict", linear="cg")
    # Two states that each meet Newton's tolerance (a part per million of the largest nodal load, about 0.15 N
    # here, at every node) differ by up to that residual summed over the contact nodes: ~1e-6 N, a few 1e-6 of
    # these 0.5 N forces; the CG's float32 products leave its last Newton step that far from the direct one.
    for d, a, b in zip(direct.results, adaptive.results, strict.results, strict=True):
        _assert_agree(d, a, 1e-5, 1e-8, 1e-5)
        _assert_agree(a, b, 1e-5, 1e-8, 1e-5)
    assert strict.counters["cg_iterations_mean"] > adaptive.counters["cg_iterations_mean"]
    with pytest.raises(ValueError, match="forcing"):
        BatchedStepper(skin, ["sphere_medium"], "cpu", forcing="exact")


def test_runner_checks_its_input_and_stops_at_its_time_limit(frictionless_biotac: BioTacModel) -> None:
    skin = frictionless_biotac.inflated_skin()
    with pytest.raises(ValueError, match="rotations"):
        PoseTrajectory("sphere_medium", np.eye(3), np.zeros(3))
    with pytest.raises(ValueError, match="no trajectories"):
        run_trajectories(skin, [], "cpu")
    trajectory = PoseTrajectory("sphere_medium", np.eye(3)[None], np.array([[0.0, 0.0, 1.0]]))
    empty = PoseTrajectory("sphere_medium", np.zeros((0, 3, 3)), np.zeros((0, 3)))
    ended: list[int] = []
    run = run_trajectories(skin, [empty, trajectory, empty], "cpu", slots=1, on_trajectory=lambda k, _: ended.append(k))
    assert run.complete and [len(r) for r in run.results] == [0, 1, 0] and sorted(ended) == [0, 1, 2]
    with pytest.raises(ValueError, match="every trajectory is timed or none"):
        run_trajectories([skin, skin], [trajectory, dataclasses.replace(trajectory, times=np.zeros(1))], "cpu")
    with pytest.raises(ValueError, match="slots"):
        run_trajectories(skin, [trajectory], "cpu", slots=0)
    with pytest.raises(ValueError, match="max_cuts"):
        run_trajectories(skin, [trajectory], "cpu", max_cuts=-1)
    stopped = run_trajectories(skin, [trajectory], "cpu", time_limit_s=0.0)
    assert not stopped.complete and stopped.results == [[]]
    free = run_trajectories(skin, [trajectory], "cpu")  # 1 m away from the skin: no contact, no Newton work
    assert free.complete and free.results[0][0].message == "no contact" and free.iterations == 0


def test_a_non_finite_system_is_flagged_not_solved() -> None:
    """CG marks a column whose right-hand side or matrix holds NaN as unusable instead of converged or
    running to its iteration cap."""
    n_nodes = 4
    elements = np.array([[0, 1], [1, 2], [2, 3]])
    matrix = BatchedBlockMatrix(BlockPattern.from_connectivities([elements], n_nodes), 2, np.ones((n_nodes, 3)), "cpu")
    blocks = np.stack([[_random_spd(np.random.default_rng(e), 6) for e in range(3)] for _ in range(2)])
    blocks[1, 0, 0, 0] = np.nan  # system 1's matrix
    mat66 = wp.types.matrix(shape=(6, 6), dtype=wp.float64)
    matrix.assemble([(0, wp.array(blocks, dtype=mat66), None)], np.zeros(2))
    rhs = np.ones((3, n_nodes, 3))
    rhs[0, 2, 1] = np.nan  # column 0 (system 0): a NaN right-hand side
    _, iterations, state = BatchedCG(matrix, 3).solve(
        wp.array(rhs, dtype=wp.vec3d), np.array([0, 1, 0]), np.ones(3, dtype=bool), np.full(3, 1e-10), 1000
    )
    assert state[0] == CG_NEGATIVE_CURVATURE and state[1] == CG_NEGATIVE_CURVATURE
    assert state[2] == CG_CONVERGED and iterations[1] < 1000


def test_a_failed_first_increment_is_not_cut_back_onto_itself(frictionless_biotac: BioTacModel) -> None:
    """A trajectory's first pose has no earlier pose to step back to: it fails once, not max_cuts times."""
    skin = frictionless_biotac.inflated_skin()
    capped = dataclasses.replace(skin, newton=dataclasses.replace(skin.newton, max_iterations=3))
    path = _paths(frictionless_biotac)[0]
    trajectory = PoseTrajectory(PATHS[0][0], path.rotation[None], (path.touch_point + 0.6e-3 * path.direction)[None])
    plain = run_trajectories(capped, [trajectory], "cpu", slots=1, max_cuts=0)
    cut = run_trajectories(capped, [trajectory], "cpu", slots=1, max_cuts=3)
    assert not cut.results[0][-1].converged and len(cut.results[0]) == 1
    assert cut.counters["evaluations"] == plain.counters["evaluations"]


@pytest.mark.parametrize(("fixture", "force_rtol", "displacement_atol", "area_rtol"), TOLERANCES)
def test_an_indenter_on_the_clamped_rim_moves_no_fixed_vertex(
    fixture: str, force_rtol: float, displacement_atol: float, area_rtol: float, request: pytest.FixtureRequest
) -> None:
    """A cylinder pressed across the proximal rim, where the skin is clamped (x = -15 mm): the batched path
    keeps the fixed vertices in place, so the indenter meets them as the one-trajectory stepper does (the warm
    start once pushed them out of the indenter, and the solve, which moves only free DOFs, left them there);
    once the indenter squeezes a clamped vertex's skin below the admissible stretch (onto the rigid base), both
    report the increment not converged, naming the clamped vertex."""
    model: BioTacModel = request.getfixturevalue(fixture)
    name, point = "cylinder_short_small", np.array([-12.5e-3, 0.0, -8e-3])
    travels = np.array([-0.2e-3, 0.0, 0.1e-3, 0.3e-3, 0.5e-3, 0.7e-3])  # admissible to ~0.6 mm here
    path = model.plan_trajectory(get_indenter(name), point, 0.0, 0.0, 1e-3, 1e-3)
    tips = path.touch_point + travels[:, None] * path.direction
    stepper, cpu = model.stepper(name), []
    for tip in tips:
        cpu.append(stepper.step(path.rotation, tip))
        if not cpu[-1].converged:
            break
    trajectory = PoseTrajectory(name, np.repeat(path.rotation[None], len(tips), 0), tips)
    skin = model.inflated_skin()
    batched = run_trajectories(skin, [trajectory], "cpu", slots=1, max_cuts=0).results[0]
    for run in (cpu, batched):
        assert not run[-1].converged and "clamped vertex" in run[-1].message, run[-1].message
    assert len(batched) == len(cpu) >= 4
    fixed = np.asarray(skin.fixed).reshape(len(skin.vertices), -1).all(axis=1)
    depth = get_indenter(name).sdf((skin.reference[fixed] - tips[len(batched) - 2]) @ path.rotation)
    assert depth.min() < 0.5 * model.params.thickness  # an accepted increment reaches into the clamped skin
    assert not np.any(batched[-2].displacement[fixed])
    _assert_agree(cpu[:-1], batched[:-1], force_rtol, displacement_atol, area_rtol)


def test_systems_of_one_batch_take_their_own_parameters(frictionless_biotac: BioTacModel) -> None:
    """A batch of two skins of one mesh, one twice as stiff and relaxing, one with trapped air and friction, each
    inflated on its own: every system reaches what it reaches alone (B = 1), and the stiffer skin pushes back
    harder at the same depth."""
    stiff = inflated_biotac(friction=0.0, mu_nh=5.6e5, relaxation_fraction=0.3)
    soft = inflated_biotac(friction=0.3, air_volume_fraction=0.1)
    path = _paths(frictionless_biotac)[0]
    skins = [stiff.inflated_skin(), soft.inflated_skin()]
    assert skins[1].air_boyle > 0.0 and skins[0].params.mu_nh == 2 * skins[1].params.mu_nh
    tips = [path.touch_point + s * path.direction for s in STEPS]
    together = BatchedStepper(skins, ["sphere_medium", "sphere_medium"], "cpu")
    alone = [BatchedStepper(skin, ["sphere_medium"], "cpu") for skin in skins]
    rotation = np.stack([path.rotation, path.rotation])
    for k, tip in enumerate(tips):
        both = together.step(rotation, np.stack([tip, tip]), times=np.full(2, 0.5 * k))
        for i, stepper in enumerate(alone):
            single = stepper.step(path.rotation[None], tip[None], times=np.array([0.5 * k]))[0]
            _assert_agree([single], [both[i]], 1e-3, 1e-6, 1e-4)  # friction tolerances (module docstring)
    assert np.linalg.norm(both[0].force) > 1.5 * np.linalg.norm(both[1].force)
    with pytest.raises(ValueError, match="share mesh"):
        moved = dataclasses.replace(skins[1], vertices=skins[1].vertices + 1e-3)
        BatchedStepper([skins[0], moved], ["sphere_medium"] * 2)


def test_a_slot_takes_the_next_trajectory_whatever_its_skin(frictionless_biotac: BioTacModel) -> None:
    """Trajectories of three skins of one mesh (the plain one, a stiffer relaxing one, one with trapped air and
    friction) on two slots, which change skin and indenter as they take the next trajectory (in the order
    given, the relaxing skin's first trajectory queued last so that a slot built without relaxation takes it):
    each trajectory's increments are those it gets alone on a batch of its own skin (B = 1), bit for bit (the
    CPU's direct solve is per system, so the systems of a batch do not touch each other)."""
    plain = frictionless_biotac.inflated_skin()
    stiff = inflated_biotac(friction=0.0, mu_nh=5.6e5, relaxation_fraction=0.3).inflated_skin()
    soft = inflated_biotac(friction=0.3, air_volume_fraction=0.1).inflated_skin()
    paths = _paths(frictionless_biotac)
    base = [_pose_trajectory(name, p) for (name, *_), p in zip(PATHS, paths, strict=True)]
    timed = [dataclasses.replace(t, times=0.5 * np.arange(len(STEPS))) for t in base]
    trajectories = [timed[0], timed[2], timed[1], timed[0], timed[2]]
    skins = [plain, soft, soft, plain, stiff]
    run = run_trajectories(skins, trajectories, "cpu", slots=2)
    assert run.complete
    for skin, trajectory, together in zip(skins, trajectories, run.results, strict=True):
        alone = run_trajectories(skin, [trajectory], "cpu", slots=1).results[0]
        assert len(together) == len(alone) == len(STEPS)
        for a, b in zip(alone, together, strict=True):
            assert a.converged and b.converged, b.message
            np.testing.assert_array_equal(a.force, b.force)
            np.testing.assert_array_equal(a.displacement, b.displacement)
            assert a.pressure == b.pressure
    stiff_force = np.linalg.norm(run.results[4][-1].force)
    assert stiff_force > 1.5 * np.linalg.norm(run.results[3][-1].force)  # its own skin, not the slot's last one
    with pytest.raises(ValueError, match="share mesh"):
        moved = dataclasses.replace(soft, vertices=soft.vertices + 1e-3)
        run_trajectories([plain, moved], timed[:2], "cpu", slots=1)


def test_a_batch_keeps_every_feature_a_later_skin_needs() -> None:
    """Skins without bending, with bending, and relaxing without bending: the batch is built for every skin of the
    run, so on three slots (the first three trajectories' skins without relaxation) and on one slot every
    trajectory gets what it gets alone (to round-off: zero bending blocks in the batch's matrix)."""
    flat = inflated_biotac(friction=0.0, bending=False).inflated_skin()
    bent = inflated_biotac(friction=0.0).inflated_skin()
    relaxing = inflated_biotac(friction=0.0, bending=False, relaxation_fraction=0.3).inflated_skin()
    assert bent.params.bending and not flat.params.bending
    model = inflated_biotac(friction=0.0)
    paths = _paths(model)
    timed = [
        dataclasses.replace(_pose_trajectory(name, p), times=0.5 * np.arange(len(STEPS)))
        for (name, *_), p in zip(PATHS, paths, strict=True)
    ]
    skins, trajectories = [flat, flat, bent, relaxing], [timed[0], timed[1], timed[0], timed[2]]
    for slots in (3, 1):
        run = run_trajectories(skins, trajectories, "cpu", slots=slots)
        for skin, trajectory, together in zip(skins, trajectories, run.results, strict=True):
            alone = run_trajectories(skin, [trajectory], "cpu", slots=1).results[0]
            assert len(together) == len(alone) == len(STEPS)
            for a, b in zip(alone, together, strict=True):  # to round-off: the batch's matrix has bending blocks
                np.testing.assert_allclose(b.force, a.force, rtol=1e-9, atol=1e-15)


def test_the_adaptive_forcing_asks_no_tighter_than_its_floor(frictionless_biotac: BioTacModel) -> None:
    """Newton converging fast (the residual falling 1000x) makes Eisenstat and Walker's choice ask a CG tolerance
    of ~1e-6; the adaptive forcing stops at `NewtonSettings.min_forcing`, and without the floor follows the choice
    down to half the Newton tolerance."""
    skin = frictionless_biotac.inflated_skin()
    lin = BatchLinearization(np.zeros(1), np.zeros(1), np.array([1e-3]), np.array([1e-3]), np.array([1.0]))
    for floor, expected in ((0.03, 0.03), (0.0, 0.5 * skin.newton.relative_force_tolerance / 1e-3)):
        settings = dataclasses.replace(skin.newton, min_forcing=floor)
        shell = BatchedStepper(dataclasses.replace(skin, newton=settings), ["sphere_medium"]).shell
        state = NewtonBatch.idle(1, 0.0)
        state.last_residual[:], state.last_eta[:] = 1.0, 0.1
        assert shell._forcing(state, lin)[0] == pytest.approx(expected)


def test_a_slot_changing_skin_on_the_gpu_algebra(frictionless_biotac: BioTacModel) -> None:
    """With the GPU's algebra (batched CG, its warm columns carried from one trajectory to the next), a slot that
    changes between skins of different thickness (other half-layers and admissibility floors) gives each
    trajectory what it gets alone, to the Newton tolerance; and the thicker skin's contact starts earlier."""
    plain = frictionless_biotac.inflated_skin()
    thick = inflated_biotac(friction=0.0, thickness=1.25 * plain.params.thickness).inflated_skin()
    paths = _paths(frictionless_biotac)
    trajectories = [_pose_trajectory(PATHS[0][0], paths[0])] * 3
    skins = [plain, thick, plain]
    run = run_trajectories(skins, trajectories, "cpu", slots=1, linear="cg")
    for skin, trajectory, together in zip(skins, trajectories, run.results, strict=True):
        alone = run_trajectories(skin, [trajectory], "cpu", slots=1, linear="cg").results[0]
        _assert_agree(alone, together, 1e-5, 1e-8, 1e-5)
    assert np.linalg.norm(run.results[1][1].force) > np.linalg.norm(run.results[0][1].force)


def test_rows_move_between_host_and_device_in_any_order() -> None:
    """`get_rows` / `put_rows` (one copy per run of consecutive systems) read and write exactly the rows asked
    for, in the order asked for, whatever runs they form (unsorted, repeated, single)."""
    values = np.arange(10 * 4 * 3, dtype=np.float64).reshape(10, 4, 3)
    array = wp.array(values, dtype=wp.vec3d, device="cpu")
    for rows in ([0, 1, 2, 5, 3, 4, 9], [7], [9, 8, 7], [2, 2, 3], list(range(10))):
        rows = np.array(rows)
        np.testing.assert_array_equal(get_rows(array, rows), values[rows])
    rows = np.array([4, 5, 6, 0, 8, 9])
    new = -np.arange(len(rows) * 4 * 3, dtype=np.float64).reshape(len(rows), 4, 3)
    put_rows(array, rows, new)
    expected = values.copy()
    expected[rows] = new
    np.testing.assert_array_equal(array.numpy(), expected)
    got = get_rows(array, np.array([4]))
    got[:] = 0.0  # a copy, not a view of the device array
    np.testing.assert_array_equal(array.numpy(), expected)
