"""The engine's CPU speed-ups change no answer (accuracy only, no timing): the sparse direct solver
(`fe.linsolve.BatchedDirectSolver`: mixed-precision PARDISO or SuperLU, factorisation reused) against a dense
numpy solve, chord Newton steps against Newton that refactorises every iteration, and the direct linear
algebra against the batched CG, on the coarse inflated BioTac."""

import dataclasses

import numpy as np
import pytest
import warp as wp

from assets.indenters import get_indenter
from fe.batched_stepper import BatchedStepper
from fe.device_solver import CG_CONVERGED, BatchedBlockMatrix, BatchedCG, BlockPattern
from fe.indentation import IndentationStepper, drive
from fe.linsolve import BatchedDirectSolver
from fe.sensor import BioTacModel

MIDLINE_POINT = np.array([-6e-3, 0.0, -9e-3])


def _dense(linear: BatchedDirectSolver, system: int, n_nodes: int) -> np.ndarray:
    """System `system`'s assembled matrix as a dense (3V, 3V) array, read column by column through `multiply`."""
    unit = np.eye(3 * n_nodes).reshape(3 * n_nodes, n_nodes, 3)
    out = wp.zeros((3 * n_nodes, n_nodes), dtype=wp.vec3d)
    system_of = wp.array(np.full(3 * n_nodes, system, dtype=np.int32), dtype=wp.int32)
    linear.multiply(wp.array(unit, dtype=wp.vec3d), out, system_of)
    return out.numpy().reshape(3 * n_nodes, 3 * n_nodes).T


def _enclosed_volume(model: BioTacModel, x: np.ndarray) -> float:
    """Signed volume (m^3) of the cones from the core's centroid to the skin triangles (numpy, independent of fe/)."""
    origin = model.geometry.core.vertices.mean(axis=0)
    a, b, c = (x[model.geometry.skin.triangles[:, k]] - origin for k in range(3))
    return float(np.einsum("ij,ij->", a, np.cross(b, c)) / 6.0)


def test_direct_solver_matches_a_dense_solve_of_the_summed_element_blocks() -> None:
    """Random symmetric indefinite element blocks (triangles and pairs), fixed DOFs eliminated: the batched
    direct solves (and their repeats with the held factorisation, as chord steps do) against numpy's dense
    solve of the matrix summed here from the blocks."""
    rng = np.random.default_rng(3)
    n_nodes, batch = 14, 2
    families = [
        np.array([rng.choice(n_nodes, k, replace=False) for _ in range(count)]) for k, count in ((3, 20), (2, 15))
    ]
    free = np.ones((n_nodes, 3))
    free[0] = 0.0  # node 0 held
    free[[3, 7], [2, 0]] = 0.0  # two single coordinates held
    keep = free.ravel() > 0
    terms, dense = _random_element_terms(rng, families, batch, n_nodes, None)
    solver = BatchedDirectSolver(BlockPattern.from_connectivities(families, n_nodes), batch, free)
    solver.assemble(terms, np.zeros(batch))
    reduced = [dense[b][np.ix_(keep, keep)] for b in range(batch)]
    eigenvalues = np.concatenate([np.linalg.eigvalsh(r) for r in reduced])
    assert eigenvalues.min() < 0 < eigenvalues.max()  # indefinite, as Newton matrices under pressure can be
    assert all(np.linalg.cond(r) < 1e6 for r in reduced)
    system_of = np.array([0, 1, 0, 1])
    for attempt in range(2):
        rhs = rng.standard_normal((4, n_nodes, 3)) * free
        rhs_w = wp.array(rhs, dtype=wp.vec3d)
        if attempt == 0:
            x, _, state = solver.solve(rhs_w, system_of, np.ones(4, dtype=bool), np.full(4, 1e-12), 1)
        else:
            x, _, state = solver.resolve(rhs_w, system_of, np.ones(4, dtype=bool))
        assert np.all(state == CG_CONVERGED)
        for c, b in enumerate(system_of):
            expected = np.zeros(3 * n_nodes)
            expected[keep] = np.linalg.solve(reduced[b], rhs[c].ravel()[keep])
            solution = x.numpy()[c].ravel()
            assert np.all(solution[~keep] == 0.0)
            assert np.allclose(solution, expected, rtol=0, atol=1e-5 * np.abs(expected).max())


def _random_element_terms(
    rng: np.random.Generator, families: list[np.ndarray], batch: int, n_nodes: int, scale: np.ndarray | None
) -> tuple[list[tuple[int, wp.array, np.ndarray | None]], np.ndarray]:
    """Random symmetric element Hessians of each family (the last scaled per system by `scale`), as assembly
    terms, and their sum (batch, 3V, 3V) done here densely."""
    terms, dense = [], np.zeros((batch, 3 * n_nodes, 3 * n_nodes))
    for k, family in enumerate(families):
        size = 3 * family.shape[1]
        raw = rng.normal(size=(batch, len(family), size, size))
        sym = raw + np.swapaxes(raw, 2, 3)
        weight = scale if scale is not None and k == len(families) - 1 else np.ones(batch)
        dofs = (3 * family[:, :, None] + np.arange(3)).reshape(len(family), -1)
        for b in range(batch):
            for d, block in zip(dofs, sym[b], strict=True):
                dense[b][np.ix_(d, d)] += weight[b] * block
        mat = wp.types.matrix(shape=(size, size), dtype=wp.float64)
        terms.append((k, wp.array(sym, dtype=mat), None if weight is not scale else scale))
    return terms, dense


def test_both_linear_solvers_assemble_scaled_damped_matrices_as_a_dense_sum() -> None:
    """The CG's block matrix and the direct solver's host assembly against a dense sum done here: a
    per-system scale on one family, fixed DOFs eliminated (unit diagonal), relative damping shift x the trace
    of the node's unconstrained diagonal block / 3 on the free diagonal, one system left out."""
    rng = np.random.default_rng(11)
    n_nodes, batch = 12, 3
    families = [np.array([rng.choice(n_nodes, k, replace=False) for _ in range(14)]) for k in (3, 2)]
    free = np.ones((n_nodes, 3))
    free[2] = 0.0
    free[5, 1] = 0.0
    scale, shift = np.array([1.0, -2.5, 0.7]), np.array([0.0, 0.3, 10.0])
    terms, dense = _random_element_terms(rng, families, batch, n_nodes, scale)
    keep = free.ravel()
    expected = dense * keep[None, :, None] * keep[None, None, :]
    for b in range(batch):
        trace = np.einsum(
            "vii->v", dense[b].reshape(n_nodes, 3, n_nodes, 3).transpose(0, 2, 1, 3)[range(n_nodes), range(n_nodes)]
        )
        expected[b][np.diag_indices(3 * n_nodes)] += (1.0 - keep) + shift[b] * np.repeat(trace, 3) / 3.0 * keep
    pattern = BlockPattern.from_connectivities(families, n_nodes)
    active = np.array([True, True, False])
    x = rng.standard_normal((batch, n_nodes, 3))
    for linear in (
        BatchedCG(BatchedBlockMatrix(pattern, batch, free, "cpu"), batch),
        BatchedDirectSolver(pattern, batch, free),
    ):
        linear.assemble(terms, shift, active)
        y = wp.zeros((batch, n_nodes), dtype=wp.vec3d)
        linear.multiply(wp.array(x, dtype=wp.vec3d), y, wp.array(np.arange(batch, dtype=np.int32), dtype=wp.int32))
        for b in np.flatnonzero(active):
            want = expected[b] @ x[b].ravel()
            assert np.allclose(y.numpy()[b].ravel(), want, rtol=0, atol=1e-12 * np.abs(want).max()), type(linear)


def test_direct_solver_solves_the_biotac_newton_matrix(frictional_biotac: BioTacModel) -> None:
    """The Newton matrix the engine left after an angled press (mixed precision with refinement on PARDISO):
    solves to a 1e-6 relative residual of the matrix read back densely, and agree with numpy's dense solve."""
    model = frictional_biotac
    path = model.plan_trajectory(get_indenter("sphere_medium"), MIDLINE_POINT, 30.0, 0.0, 0.4e-3, 0.2e-3)
    stepper = IndentationStepper(model.inflated_skin(), "sphere_medium", path.touch_point)
    assert all(inc.converged for inc in drive(stepper, path))
    shell = stepper.engine.shell
    dense = _dense(shell.linear, 0, shell.n_vertices)
    assert np.allclose(dense, dense.T, rtol=0, atol=1e-9 * np.abs(dense).max())
    free = shell.free.ravel() > 0
    rng = np.random.default_rng(5)
    rhs = rng.standard_normal((2, *shell.free.shape)) * shell.free
    rhs[1] = shell.bvec.numpy()[0] * shell.free  # the volume gradient, the Schur complement's column
    x, _, state = shell.linear.solve(
        wp.array(rhs, dtype=wp.vec3d), np.array([0, 0]), np.ones(2, dtype=bool), np.zeros(2), 1
    )
    assert np.all(state == CG_CONVERGED)
    for c in range(2):
        solution, b = x.numpy()[c].ravel(), rhs[c].ravel()
        assert np.abs(dense @ solution - b).max() <= 1e-6 * np.abs(b).max()
        expected = np.linalg.solve(dense[np.ix_(free, free)], b[free])
        assert np.allclose(solution[free], expected, rtol=0, atol=1e-5 * np.abs(expected).max())


CHORD_CASES = [
    ("frictionless_biotac", 0.0, 1e-6),
    ("frictionless_biotac", 30.0, 3e-6),
    ("frictional_biotac", 0.0, 1e-3),
    ("frictional_biotac", 30.0, 1e-2),
]
"""Fixture, indentation angle (deg) and force tolerance relative to |F|. Without friction both runs solve
the same equations to the Newton tolerance, 1e-6 of the largest nodal load (~0.13 N here) at every node,
so two converged states may differ by that summed over the vertices the contact loads: at 30 deg the
force is 0.22 N at 0.4 mm and, with the contact integrated over the triangles (more vertices loaded),
the runs differ by 1.02e-6 of it (session 11; the bound is several times that). With friction the
equilibrium also depends on the lagged normal
forces, refreshed at most `ContactSettings.friction_passes` times at iterates that differ between the runs:
at 30 deg the runs stop with lagged forces up to ~0.7% (plain) and ~0.1% (chord) off the final ones, which
moves the tangential force by that order."""


@pytest.mark.parametrize(("fixture", "angle_deg", "force_rtol"), CHORD_CASES)
def test_chord_steps_reach_the_same_equilibrium(
    request: pytest.FixtureRequest, fixture: str, angle_deg: float, force_rtol: float
) -> None:
    """Newton with chord steps (the last factorisation reused) against Newton whose chords are all rejected
    (chord_contraction 0: it refactorises every iteration): the same forces, the volume held (measured here
    from the positions), the forces balanced; the chords save factorisations."""
    model: BioTacModel = request.getfixturevalue(fixture)
    skin = model.inflated_skin()
    path = model.plan_trajectory(get_indenter("sphere_medium"), MIDLINE_POINT, angle_deg, 0.0, 0.4e-3, 0.1e-3)
    runs, solves = [], []
    for chord in (skin.newton.chord_contraction, 0.0):
        variant = dataclasses.replace(skin, newton=dataclasses.replace(skin.newton, chord_contraction=chord))
        stepper = IndentationStepper(variant, "sphere_medium", path.touch_point)
        runs.append(list(drive(stepper, path)))
        solves.append(stepper.engine.shell.counters["linear_solves"])
    assert skin.newton.chord_contraction > 0.0 and solves[0] < solves[1]
    v_ref = _enclosed_volume(model, model.reference)
    assert len(runs[0]) == len(runs[1]) == len(path.depths)
    for with_chord, plain in zip(*runs, strict=True):
        assert with_chord.converged and plain.converged
        scale = max(np.linalg.norm(plain.force), 1e-3)
        assert np.linalg.norm(with_chord.force - plain.force) <= force_rtol * scale
        assert with_chord.pressure == pytest.approx(plain.pressure, rel=max(force_rtol, 1e-6) / 10)
        for run in (with_chord, plain):
            assert run.volume == pytest.approx(model.target_volume, rel=1e-9)
            volume = _enclosed_volume(model, model.reference + run.displacement)
            assert abs(volume - v_ref) <= 1e-9 * abs(model.target_volume)
            assert run.equilibrium_error < 1e-6
    assert runs[0][-1].force[2] > 0.05


def test_direct_and_cg_linear_algebra_reach_the_same_equilibrium(frictionless_biotac: BioTacModel) -> None:
    """The CPU's sparse direct Newton against the GPU's batched CG (run on the CPU device), frictionless:
    the same equilibrium within the Newton tolerance, both balanced and holding the volume."""
    model = frictionless_biotac
    path = model.plan_trajectory(get_indenter("sphere_medium"), MIDLINE_POINT, 0.0, 0.0, 0.4e-3, 0.2e-3)
    runs = []
    for linear in ("direct", "cg"):
        stepper = BatchedStepper(model.inflated_skin(), ["sphere_medium"], "cpu", linear=linear)
        runs.append(
            [stepper.step(path.rotation[None], (path.touch_point + d * path.direction)[None])[0] for d in path.depths]
        )
    for direct, cg in zip(*runs, strict=True):
        assert direct.converged and cg.converged
        assert direct.equilibrium_error < 1e-6 and cg.equilibrium_error < 1e-6
        scale = max(np.linalg.norm(direct.force), 1e-3)
        assert np.linalg.norm(cg.force - direct.force) <= 1e-6 * scale
        assert cg.pressure == pytest.approx(direct.pressure, rel=1e-6)
        assert np.abs(cg.displacement - direct.displacement).max() <= 1e-9
    assert runs[0][-1].force[2] > 0.05
