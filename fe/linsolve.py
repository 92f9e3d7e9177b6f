"""Sparse direct factorisation of the symmetric (possibly indefinite) Newton matrices on the CPU.

The matrices of one model share a sparsity pattern (fixed by `fe.assembly.BlockAssembler`), so the
symbolic analysis is done once per pattern and only the numeric factorisation is repeated.

Backends: Intel MKL PARDISO (symmetric indefinite LDL^T with Bunch-Kaufman pivoting) through the
optional `pypardiso` package when it is importable, else SciPy's SuperLU (LU in symmetric mode,
minimum-degree ordering of A^T + A), which is about four times slower on the BioTac meshes.
"""

import ctypes
import os
import weakref

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
    """MKL PARDISO called directly (the library that `pypardiso` loads): real symmetric indefinite LDL^T of
    the upper triangle with Bunch-Kaufman pivoting and 1e-8 pivot perturbation, METIS ordering, zero-based
    indices, and no iterative refinement of the solves (their relative residual is ~1e-12 without it,
    far below what a Newton step needs; pypardiso's defaults refine twice, doubling the solve cost)."""

    name = "pardiso"

    def __init__(self) -> None:
        import pypardiso

        self._pardiso = pypardiso.PyPardisoSolver()._mkl_pardiso
        self._handle = np.zeros(64, dtype=np.int64)
        self._iparm = np.zeros(64, dtype=np.int32)
        self._iparm[0] = 1  # parameters supplied here, the rest at their zero defaults
        self._iparm[1] = 2  # METIS nested dissection
        self._iparm[9] = 8  # pivot perturbation 1e-8
        self._iparm[17] = -1  # report the factor's non-zeros
        self._iparm[20] = 1  # Bunch-Kaufman 1x1 and 2x2 pivoting
        self._iparm[34] = 1  # zero-based indices
        self._n = 0
        self._data = np.zeros(0)
        self._select = self._indptr = self._indices = np.zeros(0, dtype=np.int64)
        self._upper_indptr = self._upper_indices = np.zeros(0, dtype=np.int32)
        self._release: weakref.finalize | None = None

    def factorize(self, matrix: sp.csr_matrix) -> None:
        if not matrix.has_sorted_indices:
            matrix.sort_indices()
        if not (
            self._n and np.array_equal(self._indptr, matrix.indptr) and np.array_equal(self._indices, matrix.indices)
        ):
            self._analyse(matrix)
        self._data = np.ascontiguousarray(matrix.data[self._select], dtype=np.float64)
        self._call(22, np.zeros((self._n, 1), order="F"))

    def _analyse(self, matrix: sp.csr_matrix) -> None:
        """Symbolic analysis (fill-reducing ordering) of the upper triangle's pattern."""
        if self._n:
            _release_pardiso(self._pardiso, self._handle, self._iparm)
        n = matrix.shape[0]
        rows = np.repeat(np.arange(n), np.diff(matrix.indptr))
        self._select = np.flatnonzero(matrix.indices >= rows)
        counts = np.bincount(rows[self._select], minlength=n)
        if not counts.all():
            raise SingularMatrixError("the matrix has an empty row")
        self._upper_indptr = np.concatenate([[0], np.cumsum(counts)]).astype(np.int32)
        self._upper_indices = matrix.indices[self._select].astype(np.int32)
        self._indptr, self._indices = matrix.indptr.copy(), matrix.indices.copy()
        self._data = np.ascontiguousarray(matrix.data[self._select], dtype=np.float64)
        self._n = n
        self._call(11, np.zeros((n, 1), order="F"))
        if self._release is None:
            self._release = weakref.finalize(self, _release_pardiso, self._pardiso, self._handle, self._iparm)

    def _call(self, phase: int, rhs: np.ndarray) -> np.ndarray:
        """One PARDISO phase (11 analysis, 22 factorisation, 33 solve) on the stored upper triangle."""
        int_p, double_p = ctypes.POINTER(ctypes.c_int32), ctypes.POINTER(ctypes.c_double)
        out = np.zeros_like(rhs, order="F")
        error = ctypes.c_int32(0)
        self._pardiso(
            self._handle.ctypes.data_as(ctypes.POINTER(ctypes.c_int64)),
            ctypes.byref(ctypes.c_int32(1)),  # maxfct
            ctypes.byref(ctypes.c_int32(1)),  # mnum
            ctypes.byref(ctypes.c_int32(-2)),  # real symmetric indefinite
            ctypes.byref(ctypes.c_int32(phase)),
            ctypes.byref(ctypes.c_int32(self._n)),
            self._data.ctypes.data_as(double_p),
            self._upper_indptr.ctypes.data_as(int_p),
            self._upper_indices.ctypes.data_as(int_p),
            None,  # perm
            ctypes.byref(ctypes.c_int32(rhs.shape[1])),
            self._iparm.ctypes.data_as(int_p),
            ctypes.byref(ctypes.c_int32(0)),  # msglvl
            rhs.ctypes.data_as(double_p),
            out.ctypes.data_as(double_p),
            ctypes.byref(error),
        )
        if error.value != 0:
            raise SingularMatrixError(f"PARDISO phase {phase} failed with error {error.value}")
        return out

    def solve(self, rhs: np.ndarray) -> np.ndarray:
        columns = np.asfortranarray(rhs.reshape(self._n, -1), dtype=np.float64)
        return np.ascontiguousarray(self._call(33, columns)).reshape(rhs.shape)


def _release_pardiso(pardiso: ctypes.CDLL, handle: np.ndarray, iparm: np.ndarray) -> None:
    """Free the memory PARDISO holds for `handle` (phase -1)."""
    int_p = ctypes.POINTER(ctypes.c_int32)
    one, zero, phase, mtype = ctypes.c_int32(1), ctypes.c_int32(0), ctypes.c_int32(-1), ctypes.c_int32(-2)
    dummy = np.zeros(1)
    pardiso(
        handle.ctypes.data_as(ctypes.POINTER(ctypes.c_int64)),
        *(ctypes.byref(v) for v in (one, one, mtype, phase, zero)),
        dummy.ctypes.data_as(ctypes.POINTER(ctypes.c_double)),
        None,
        None,
        None,
        ctypes.byref(one),
        iparm.ctypes.data_as(int_p),
        ctypes.byref(zero),
        dummy.ctypes.data_as(ctypes.POINTER(ctypes.c_double)),
        dummy.ctypes.data_as(ctypes.POINTER(ctypes.c_double)),
        ctypes.byref(ctypes.c_int32(0)),
    )


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
