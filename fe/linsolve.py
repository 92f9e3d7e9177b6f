"""Sparse direct factorisation of the symmetric (possibly indefinite) Newton matrices on the CPU.

The matrices of one model share a sparsity pattern (fixed by `fe.assembly.BlockAssembler`), so the
symbolic analysis is done once per pattern and only the numeric factorisation is repeated.

Backends: Intel MKL PARDISO (symmetric indefinite LDL^T with Bunch-Kaufman pivoting) through the
optional `pypardiso` package when it is importable, else SciPy's SuperLU (LU in symmetric mode,
minimum-degree ordering of A^T + A), which is about four times slower on the BioTac meshes.
"""

import os

import numpy as np
import scipy.sparse as sp
import scipy.sparse.linalg as spla


class SingularMatrixError(RuntimeError):
    """The matrix could not be factorised (numerically singular)."""


class _SuperLU:
    name = "superlu"

    def __init__(self) -> None:
        self._lu = None

    def factorize(self, matrix: sp.csr_matrix) -> None:
        try:
            self._lu = spla.splu(matrix.tocsc(), permc_spec="MMD_AT_PLUS_A", options={"SymmetricMode": True})
        except RuntimeError as error:
            raise SingularMatrixError(str(error)) from error

    def solve(self, rhs: np.ndarray) -> np.ndarray:
        return self._lu.solve(rhs)


class _Pardiso:
    name = "pardiso"

    def __init__(self) -> None:
        import pypardiso

        self._solver = pypardiso.PyPardisoSolver(mtype=-2)  # real symmetric indefinite
        self._upper: sp.csr_matrix | None = None
        self._select = self._indptr = self._indices = np.zeros(0, dtype=np.int64)

    def factorize(self, matrix: sp.csr_matrix) -> None:
        if not matrix.has_sorted_indices:
            matrix.sort_indices()
        if self._upper is None or not (
            np.array_equal(self._indptr, matrix.indptr) and np.array_equal(self._indices, matrix.indices)
        ):
            self._analyse(matrix)
        self._upper.data = matrix.data[self._select]
        self._call(22, np.zeros((matrix.shape[0], 1)))

    def _analyse(self, matrix: sp.csr_matrix) -> None:
        """Symbolic analysis (fill-reducing ordering) of the upper triangle's pattern."""
        n = matrix.shape[0]
        rows = np.repeat(np.arange(n), np.diff(matrix.indptr))
        self._select = np.flatnonzero(matrix.indices >= rows)
        indptr = np.concatenate([[0], np.cumsum(np.bincount(rows[self._select], minlength=n))])
        self._upper = sp.csr_matrix((matrix.data[self._select], matrix.indices[self._select], indptr), shape=(n, n))
        self._indptr, self._indices = matrix.indptr.copy(), matrix.indices.copy()
        self._solver._check_A(self._upper)
        self._call(11, np.zeros((n, 1)))

    def _call(self, phase: int, rhs: np.ndarray) -> np.ndarray:
        import pypardiso

        self._solver.set_phase(phase)
        try:
            return self._solver._call_pardiso(self._upper, np.asfortranarray(rhs))
        except pypardiso.pardiso_wrapper.PyPardisoError as error:
            raise SingularMatrixError(str(error)) from error

    def solve(self, rhs: np.ndarray) -> np.ndarray:
        return self._call(33, rhs)


def _pardiso_available() -> bool:
    if os.environ.get("BIOTAC_TWIN_SPARSE", "").lower() == "superlu":
        return False
    try:
        import pypardiso  # noqa: F401
    except ImportError:
        return False
    return True


class SymmetricSolver:
    """Factorise a symmetric sparse matrix (CSR, both triangles stored) and solve with it.

    The backend is PARDISO when `pypardiso` is installed (unless the environment variable
    BIOTAC_TWIN_SPARSE=superlu asks otherwise), SuperLU else.
    """

    def __init__(self) -> None:
        self._backend = _Pardiso() if _pardiso_available() else _SuperLU()

    @property
    def backend(self) -> str:
        """Name of the factorisation backend in use."""
        return self._backend.name

    def factorize(self, matrix: sp.csr_matrix) -> None:
        """Numeric factorisation (symbolic analysis reused while the pattern stays the same)."""
        self._backend.factorize(matrix)

    def solve(self, rhs: np.ndarray) -> np.ndarray:
        """Solutions for one (n,) or several (n,k) right-hand sides; non-finite results raise."""
        out = self._backend.solve(rhs)
        if not np.all(np.isfinite(out)):
            raise SingularMatrixError("non-finite solution")
        return out
