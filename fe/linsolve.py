"""Sparse direct factorisation of the symmetric (possibly indefinite) Newton matrices on the CPU.

The matrices of one model share a sparsity pattern (fixed by `fe.assembly.BlockAssembler`), so the
symbolic analysis is done once per pattern and only the numeric factorisation is repeated.

Backends: Intel MKL PARDISO (symmetric indefinite LDL^T with Bunch-Kaufman pivoting) through the
optional `pypardiso` package when it is installed (MKL found), else SciPy's SuperLU (LU in symmetric mode,
minimum-degree ordering of A^T + A), which is about four times slower on the BioTac meshes.
"""

import ctypes
import functools
import importlib.metadata
import importlib.util
import os
import weakref
from collections import defaultdict
from collections.abc import Callable

import numpy as np
import scipy.sparse as sp
import scipy.sparse.linalg as spla
import warp as wp

from fe.device_solver import CG_CONVERGED, CG_NEGATIVE_CURVATURE, BlockPattern, HessianTerms


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


class _PardisoFactor:
    """One MKL PARDISO factorisation (the library that `pypardiso` loads) of a symmetric matrix's upper
    triangle in CSR, double or single precision: real symmetric indefinite LDL^T with Bunch-Kaufman
    pivoting and 1e-8 pivot perturbation, METIS ordering, zero-based indices, no iterative refinement."""

    def __init__(self, pardiso: ctypes.CDLL, indptr: np.ndarray, indices: np.ndarray, single: bool) -> None:
        self._pardiso = pardiso
        self._dtype = np.float32 if single else np.float64
        self._n = len(indptr) - 1
        self._indptr, self._indices = indptr.astype(np.int32), indices.astype(np.int32)
        self._data = np.zeros(len(indices), dtype=self._dtype)
        self._handle = np.zeros(64, dtype=np.int64)
        self._iparm = np.zeros(64, dtype=np.int32)
        self._iparm[0] = 1  # parameters supplied here, the rest at their zero defaults
        self._iparm[1] = 2  # METIS nested dissection
        self._iparm[9] = 8  # pivot perturbation 1e-8
        self._iparm[17] = -1  # report the factor's non-zeros
        self._iparm[20] = 1  # Bunch-Kaufman 1x1 and 2x2 pivoting
        self._iparm[27] = 1 if single else 0
        self._iparm[34] = 1  # zero-based indices
        self._call(11, np.zeros((self._n, 1)))
        release = (-1, np.zeros(1, dtype=self._dtype), self._indptr, self._indices, np.zeros((1, 1)))
        weakref.finalize(self, _pardiso_phase, pardiso, self._handle, self._iparm, *release)

    def factorize(self, data: np.ndarray) -> None:
        """Numeric factorisation of the upper-triangle values `data` (in the analysed pattern)."""
        self._data = np.ascontiguousarray(data, dtype=self._dtype)
        self._call(22, np.zeros((self._n, 1)))

    def solve(self, rhs: np.ndarray) -> np.ndarray:
        """Solutions (n, k) in double precision for right-hand sides (n, k)."""
        return self._call(33, rhs).astype(np.float64)

    def _call(self, phase: int, rhs: np.ndarray) -> np.ndarray:
        return _pardiso_phase(
            self._pardiso, self._handle, self._iparm, phase, self._data, self._indptr, self._indices, rhs
        )


class _Pardiso:
    """Mixed precision MKL PARDISO: the factorisation in single precision (about 35% cheaper), solves
    refined in double precision against the full matrix until every column's residual is below
    `REFINED_RESIDUAL` of its right-hand side (usually one step; a Newton step needs no more, its
    error then shrinks the nonlinear residual by that factor at worst); a matrix for which that takes
    more than `MAX_REFINEMENTS` steps is factorised again in double precision (relative residual
    ~1e-12 without refinement).

    PARDISO runs on one MKL thread unless MKL_NUM_THREADS or MKL_DOMAIN_NUM_THREADS say otherwise: a
    second thread makes the factorisation about 1.6x faster on an idle 2-core machine but costs about 25%
    more CPU time, a poor trade on a shared one.
    """

    name = "pardiso"
    REFINED_RESIDUAL = 1e-6
    MAX_REFINEMENTS = 3

    def __init__(self) -> None:
        self._pardiso = _mkl_pardiso()
        self._matrix: sp.csr_matrix | None = None
        self._single: _PardisoFactor | None = None
        self._double: _PardisoFactor | None = None
        self._use_double = False
        self._select = self._indptr = self._indices = np.zeros(0, dtype=np.int64)
        self._upper_indptr = self._upper_indices = np.zeros(0, dtype=np.int64)

    def factorize(self, matrix: sp.csr_matrix) -> None:
        if not matrix.has_sorted_indices:
            matrix.sort_indices()
        if not (
            self._single is not None
            and np.array_equal(self._indptr, matrix.indptr)
            and np.array_equal(self._indices, matrix.indices)
        ):
            self._analyse(matrix)
        self._matrix = matrix
        self._use_double = False
        self._single.factorize(matrix.data[self._select])

    def _analyse(self, matrix: sp.csr_matrix) -> None:
        """Symbolic analysis (fill-reducing ordering) of the upper triangle's pattern."""
        n = matrix.shape[0]
        rows = np.repeat(np.arange(n), np.diff(matrix.indptr))
        self._select = np.flatnonzero(matrix.indices >= rows)
        counts = np.bincount(rows[self._select], minlength=n)
        if not counts.all():
            raise SingularMatrixError("the matrix has an empty row")
        self._upper_indptr = np.concatenate([[0], np.cumsum(counts)])
        self._upper_indices = matrix.indices[self._select]
        self._indptr, self._indices = matrix.indptr.copy(), matrix.indices.copy()
        self._double = None
        self._single = _PardisoFactor(self._pardiso, self._upper_indptr, self._upper_indices, single=True)

    def solve(self, rhs: np.ndarray) -> np.ndarray:
        columns = rhs.reshape(len(rhs), -1)
        if not self._use_double:
            x = self._single.solve(columns)
            scale = np.max(np.abs(columns), axis=0)
            for _ in range(self.MAX_REFINEMENTS + 1):
                residual = columns - self._matrix @ x
                if np.all(np.max(np.abs(residual), axis=0) <= self.REFINED_RESIDUAL * scale):
                    return x.reshape(rhs.shape)
                x += self._single.solve(residual)
            self._use_double = True
            if self._double is None:
                self._double = _PardisoFactor(self._pardiso, self._upper_indptr, self._upper_indices, single=False)
            self._double.factorize(self._matrix.data[self._select])
        return self._double.solve(columns).reshape(rhs.shape)


def _pardiso_phase(
    pardiso: ctypes.CDLL,
    handle: np.ndarray,
    iparm: np.ndarray,
    phase: int,
    data: np.ndarray,
    indptr: np.ndarray,
    indices: np.ndarray,
    rhs: np.ndarray,
) -> np.ndarray:
    """One PARDISO call for `handle` (real symmetric indefinite, one matrix, quiet): `phase` on the matrix
    of upper-triangle CSR (`data` in the factor's precision, int32 `indptr`, `indices`) with right-hand
    sides `rhs` (n, k); returns the solutions (n, k) in `data`'s precision (phase -1 frees the handle's
    memory, whatever the matrix)."""
    pointer = ctypes.POINTER(ctypes.c_float if data.dtype == np.float32 else ctypes.c_double)
    columns = np.asfortranarray(rhs, dtype=data.dtype)
    out = np.zeros_like(columns)
    int_p = ctypes.POINTER(ctypes.c_int32)
    error = ctypes.c_int32(0)
    pardiso(
        handle.ctypes.data_as(ctypes.POINTER(ctypes.c_int64)),
        ctypes.byref(ctypes.c_int32(1)),  # maxfct
        ctypes.byref(ctypes.c_int32(1)),  # mnum
        ctypes.byref(ctypes.c_int32(-2)),  # real symmetric indefinite
        ctypes.byref(ctypes.c_int32(phase)),
        ctypes.byref(ctypes.c_int32(len(indptr) - 1)),
        data.ctypes.data_as(pointer),
        indptr.ctypes.data_as(int_p),
        indices.ctypes.data_as(int_p),
        None,  # perm
        ctypes.byref(ctypes.c_int32(columns.shape[1])),
        iparm.ctypes.data_as(int_p),
        ctypes.byref(ctypes.c_int32(0)),  # msglvl
        columns.ctypes.data_as(pointer),
        out.ctypes.data_as(pointer),
        ctypes.byref(error),
    )
    if error.value != 0:
        raise SingularMatrixError(f"PARDISO phase {phase} failed with error {error.value}")
    return out


_MKL_DOMAIN_PARDISO = 4
"""MKL's function domain of PARDISO, for MKL_Domain_Set_Num_Threads."""


def _pardiso_available() -> bool:
    """Whether PARDISO can be used: not refused by BIOTAC_TWIN_SPARSE=superlu, `pypardiso` installed and MKL's
    runtime found (`_mkl_runtime_path`, or else by importing pypardiso, which looks for it on import)."""
    if os.environ.get("BIOTAC_TWIN_SPARSE", "").lower() == "superlu":
        return False
    if importlib.util.find_spec("pypardiso") is None:
        return False
    if _mkl_runtime_path() is not None:
        return True
    try:
        import pypardiso  # noqa: F401
    except ImportError:
        return False
    return True


@functools.cache
def _mkl_runtime_path() -> str | None:
    """Where MKL's runtime library is: PYPARDISO_MKL_RT when set (pypardiso's own override), else the file
    that the `mkl` wheel's record lists (a look-up in its metadata, milliseconds), None when neither says."""
    if "PYPARDISO_MKL_RT" in os.environ:
        return os.environ["PYPARDISO_MKL_RT"]
    try:
        files = importlib.metadata.files("mkl") or []
    except importlib.metadata.PackageNotFoundError:
        return None
    return next((str(f.locate()) for f in files if f.name.startswith("libmkl_rt")), None)


@functools.cache
def _mkl_library() -> ctypes.CDLL:
    """MKL's runtime library, loaded once per process: from `_mkl_runtime_path`, else as pypardiso finds it
    (it searches the whole Python prefix with `glob`, seconds, on every solver construction)."""
    path = _mkl_runtime_path()
    if path is not None:
        return ctypes.CDLL(path)
    import pypardiso

    return pypardiso.PyPardisoSolver().libmkl


@functools.cache
def _mkl_pardiso() -> Callable[..., None]:
    """MKL's `pardiso` entry point (`_mkl_library`), its PARDISO domain set to one thread unless
    MKL_NUM_THREADS or MKL_DOMAIN_NUM_THREADS say otherwise (see `_Pardiso`)."""
    library = _mkl_library()
    if "MKL_NUM_THREADS" not in os.environ and "MKL_DOMAIN_NUM_THREADS" not in os.environ:
        library.MKL_Domain_Set_Num_Threads(ctypes.c_int(1), ctypes.c_int(_MKL_DOMAIN_PARDISO))
    pardiso = library.pardiso
    pardiso.restype = None
    return pardiso


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


class BatchedDirectSolver:
    """The batched CG's interface (`fe.device_solver.BatchedCG`: `assemble`, `multiply`, `solve`) answered by
    one sparse direct factorisation per system: the CPU's linear algebra for the batched Newton.

    Element Hessians are summed on the host straight into each system's scalar CSR over the free DOFs (one
    precomputed sparse scatter matrix per element family, as a serial FE code assembles; no block matrix),
    factorised by the system's own `SymmetricSolver` (the symbolic analysis of the shared pattern is done once
    per system slot) and solved for its right-hand sides to round-off (fixed DOFs get 0); the factorisation
    is kept, so `resolve` repeats a solve with it (a chord step) without a new matrix.
    """

    holds_factorization = True

    def __init__(self, pattern: BlockPattern, batch: int, free: np.ndarray) -> None:
        """`pattern`: the 3x3-block pattern of the element families; `free` (V,3): 1 for free DOFs, 0 for fixed."""
        self.batch, n = batch, pattern.n_nodes
        self._free = np.flatnonzero(np.asarray(free).reshape(-1) > 0.0)
        # Number every block entry (1-based, so none is a structural zero) and keep the free part's CSR.
        numbers = np.arange(1, 9 * len(pattern.columns) + 1, dtype=np.float64).reshape(-1, 3, 3)
        blocks = sp.bsr_matrix((numbers, pattern.columns, pattern.offsets), shape=(3 * n, 3 * n)).tocsr()
        csr = blocks[self._free][:, self._free].tocsr()
        csr.sort_indices()
        self._indices, self._indptr = csr.indices.astype(np.int32), csr.indptr.astype(np.int32)
        position = np.full(9 * len(pattern.columns), -1, dtype=np.int64)  # block entry -> CSR value, -1: fixed
        position[csr.data.astype(np.int64) - 1] = np.arange(csr.nnz)
        self._diagonal = np.flatnonzero(np.repeat(np.arange(len(self._free)), np.diff(csr.indptr)) == csr.indices)
        # Both triangles are summed: a Newton matrix with lagged friction is not exactly symmetric, and the
        # refinement of the (symmetric, upper-triangle) factorisation's solves is against the whole matrix.
        self._scatter = [_family_scatter(pattern, f, position, csr.nnz) for f in range(len(pattern.block_of))]
        self._trace = [_family_trace(pattern, f) for f in range(len(pattern.block_of))]
        self._node_of_free = self._free // 3
        self._matrices: dict[int, sp.csr_matrix] = {}
        self._solvers: defaultdict[int, SymmetricSolver] = defaultdict(SymmetricSolver)
        """Each system slot's factorisation, made at its first solve (its symbolic analysis kept)."""
        self._factorized = np.zeros(batch, dtype=bool)
        self.x = None
        """(C, V) vec3d solutions of the last solve (a warp array on the matrix's device, owned here)."""

    def assemble(self, terms: HessianTerms, shift: np.ndarray, active: np.ndarray | None = None) -> None:
        """`fe.device_solver.BatchedBlockMatrix.assemble`: sum the element Hessians of each term (family, (B, E_f)
        matrices, per-system scale or None) over the free DOFs and add the relative damping `shift` (B,)
        (shift x the node's unconstrained diagonal-block trace / 3) to the free diagonal, for the `active`
        systems ((B,) bool, default all)."""
        active = np.ones(self.batch, dtype=bool) if active is None else np.asarray(active, dtype=bool)
        hessians = [(f, blocks.numpy().reshape(self.batch, -1), scale) for f, blocks, scale in terms if blocks.shape[1]]
        for b in np.flatnonzero(active):
            summed: dict[int, np.ndarray] = {}  # one element-Hessian sum per family, then one product each
            for f, values, scale in hessians:
                term = values[b] if scale is None else float(scale[b]) * values[b]
                summed[f] = term if f not in summed else summed[f] + term
            data = sum(self._scatter[f] @ values for f, values in summed.items())
            trace = sum(self._trace[f] @ values for f, values in summed.items()) if shift[b] != 0.0 else None
            if trace is not None:
                data[self._diagonal] += shift[b] * trace[self._node_of_free] / 3.0
            n = len(self._free)
            matrix = sp.csr_matrix((data, self._indices, self._indptr), shape=(n, n))
            matrix.has_sorted_indices = True  # the pattern's (saves the check in every factorisation)
            self._matrices[int(b)] = matrix

    def multiply(self, x: wp.array, y: wp.array, system_of: wp.array) -> None:
        """y[c] = A[system_of[c]] x[c] for (C, V) vec3d arrays (fixed DOFs: y = x, the unit diagonal)."""
        x_host, system_of = x.numpy().reshape(len(x.numpy()), -1), system_of.numpy()
        out = x_host.copy()
        for c, b in enumerate(system_of):
            if int(b) in self._matrices:
                out[c, self._free] = self._matrices[int(b)] @ x_host[c, self._free]
        y.assign(out.reshape(y.shape + (3,)))

    def solve(
        self, rhs: wp.array, system_of: np.ndarray, active: np.ndarray, tolerance: np.ndarray, max_iterations: int
    ) -> tuple[wp.array, np.ndarray, np.ndarray]:
        """Factorise the matrix (`assemble`) of every system with an active column, then solve (`BatchedCG.solve`'s
        arguments and results; `tolerance` and `max_iterations` are met by construction). A singular
        system's columns come back CG_NEGATIVE_CURVATURE (no usable solution)."""
        systems = np.unique(np.asarray(system_of)[np.asarray(active, dtype=bool)])
        for b in systems:
            self._factorized[b] = False
            try:
                self._solvers[int(b)].factorize(self._matrices[int(b)])
            except SingularMatrixError:
                continue
            self._factorized[b] = True
        return self.resolve(rhs, system_of, active)

    def resolve(
        self, rhs: wp.array, system_of: np.ndarray, active: np.ndarray
    ) -> tuple[wp.array, np.ndarray, np.ndarray]:
        """Solve the active columns with the factorisations held (of each system's last `solve`)."""
        system_of, active = np.asarray(system_of), np.asarray(active, dtype=bool)
        rhs_host = rhs.numpy().reshape(len(system_of), -1)
        out = np.zeros_like(rhs_host)
        state = np.full(len(system_of), CG_CONVERGED, dtype=np.int32)
        for b in np.unique(system_of[active]):
            columns = np.flatnonzero(active & (system_of == b))
            if not self._factorized[b]:
                state[columns] = CG_NEGATIVE_CURVATURE
                continue
            try:
                out[np.ix_(columns, self._free)] = self._solvers[int(b)].solve(rhs_host[columns][:, self._free].T).T
            except SingularMatrixError:
                state[columns] = CG_NEGATIVE_CURVATURE
        if self.x is None or self.x.shape != rhs.shape:
            self.x = wp.zeros(rhs.shape, dtype=wp.vec3d, device=rhs.device)
        self.x.assign(out.reshape(*rhs.shape, 3))
        return self.x, np.zeros(len(system_of), dtype=np.int32), state


def _family_scatter(pattern: BlockPattern, family: int, position: np.ndarray, nnz: int) -> sp.spmatrix:
    """(nnz, E k^2 9) 0/1 matrix taking the flattened element Hessians (E, 3k x 3k, row-major) of element family
    `family` (k nodes each) to the free-DOF CSR values (`position`: block entry -> CSR value, -1 for fixed)."""
    entries = _block_entries(pattern, family)
    keep = position[entries] >= 0
    columns = np.flatnonzero(keep)
    scatter = sp.coo_matrix((np.ones(len(columns)), (position[entries[keep]], columns)), shape=(nnz, entries.size))
    return scatter.tocsc() if entries.size < nnz else scatter.tocsr()  # the cheaper product


def _family_trace(pattern: BlockPattern, family: int) -> sp.csr_matrix:
    """(V, E k^2 9) 0/1 matrix summing the flattened element Hessians of `family` into the trace of each node's
    unconstrained diagonal block."""
    entries = _block_entries(pattern, family)
    block, within = entries // 9, entries % 9
    on_diagonal = (pattern.block_row[block] == pattern.columns[block]) & (within % 4 == 0)
    columns = np.flatnonzero(on_diagonal)
    rows = pattern.block_row[block[on_diagonal]]
    return sp.csr_matrix((np.ones(len(columns)), (rows, columns)), shape=(pattern.n_nodes, entries.size))


def _block_entries(pattern: BlockPattern, family: int) -> np.ndarray:
    """Block-entry number (9 x block + 3 r + c) of each flattened element-Hessian entry of `family`: entry
    (3i + r) 3k + 3j + c of element e lands in row r, column c of block block_of[e, i k + j]."""
    block_of = np.asarray(pattern.block_of[family], dtype=np.int64)
    k = int(round(np.sqrt(block_of.shape[1])))
    i, r, j, c = np.meshgrid(np.arange(k), np.arange(3), np.arange(k), np.arange(3), indexing="ij")
    return (9 * block_of[:, (i * k + j).ravel()] + (3 * r + c).ravel()).reshape(len(block_of), 9 * k * k)
