"""The FE speed-ups change no answer: upper-triangle assembly, mixed-precision PARDISO solves and chord
Newton steps against their plain counterparts (accuracy only, no timing)."""

import dataclasses

import numpy as np
import pytest
import scipy.sparse.linalg as spla

from fe.assembly import BlockAssembler
from fe.linsolve import SymmetricSolver
from fe.sensor import BioTacModel

MIDLINE_POINT = np.array([-6e-3, 0.0, -9e-3])


def test_assembly_equals_the_dense_sum_of_symmetric_blocks() -> None:
    rng = np.random.default_rng(3)
    nodes = 12
    triangles = rng.integers(0, nodes, size=(20, 3))
    pairs = rng.integers(0, nodes, size=(15, 2))
    dof_map = np.arange(3 * nodes)
    dof_map[[0, 1, 2, 10, 20]] = -1  # node 0 and two single coordinates held
    free = dof_map >= 0
    dof_map[free] = np.arange(free.sum())
    blocks = []
    for family in (triangles, pairs):
        size = 3 * family.shape[1]
        raw = rng.normal(size=(len(family), size, size))
        blocks.append(raw + np.swapaxes(raw, 1, 2))
    matrix = BlockAssembler([triangles, pairs], dof_map).assemble(blocks)
    dense = np.zeros((3 * nodes, 3 * nodes))
    for family, block in zip((triangles, pairs), blocks, strict=True):
        dofs = (3 * family[:, :, None] + np.arange(3)).reshape(len(family), -1)
        for d, b in zip(dofs, block, strict=True):
            np.add.at(dense, (d[:, None], d[None, :]), b)
    expected = dense[np.ix_(free, free)]
    assert np.allclose(matrix.toarray(), expected, rtol=1e-13, atol=1e-12)
    assert np.array_equal(matrix.toarray(), matrix.toarray().T)


def test_mixed_precision_solves_match_superlu(frictional_biotac: BioTacModel) -> None:
    model = frictional_biotac
    system = model.system
    lin = system.linearize(system.free_coordinates(model.reference), model.pressure, want_matrix=True)
    rhs = np.column_stack([-lin.gradient, lin.volume_gradient])
    solver = SymmetricSolver()
    solver.factorize(lin.matrix)
    solution = solver.solve(rhs)
    single = solver.solve(rhs[:, 1])
    residual = np.abs(lin.matrix @ solution - rhs).max(axis=0) / np.abs(rhs).max(axis=0)
    assert np.all(residual <= 1e-6)
    reference = spla.splu(lin.matrix.tocsc()).solve(rhs)
    assert np.allclose(solution, reference, rtol=0, atol=1e-5 * np.abs(reference).max())
    assert np.allclose(single, solution[:, 1], rtol=0, atol=1e-5 * np.abs(reference[:, 1]).max())


@pytest.mark.parametrize("angle_deg", [0.0, 30.0])
def test_chord_steps_reach_the_same_equilibrium(frictional_biotac: BioTacModel, angle_deg: float) -> None:
    """Newton with chord steps against Newton that refactorises every iteration (chord_contraction 0):
    the same forces within the friction lagging tolerance, the volume held, the forces balanced."""
    model = frictional_biotac
    settings = model.newton
    runs = []
    try:
        for chord in (settings.chord_contraction, 0.0):
            model.newton = dataclasses.replace(settings, chord_contraction=chord)
            runs.append(list(model.indent("sphere_medium", MIDLINE_POINT, 0.4e-3, 0.1e-3, angle_deg=angle_deg)))
    finally:
        model.newton = settings
    for with_chord, plain in zip(*runs, strict=True):
        assert with_chord.converged and plain.converged
        scale = max(np.linalg.norm(plain.force), 1e-3)
        assert np.linalg.norm(with_chord.force - plain.force) <= 1e-3 * scale
        assert with_chord.pressure == pytest.approx(plain.pressure, rel=1e-4)
        assert with_chord.volume == pytest.approx(model.target_volume, rel=1e-6)
        assert with_chord.equilibrium_error < 1e-6
