"""Batched block-sparse symmetric matrices and a batched preconditioned conjugate-gradient solver, in warp.

A batch holds B independent systems over the same V nodes (3 DOFs each) and the same sparsity pattern of
3x3 blocks (CSR of blocks, shared), with values (B, nnzb). Element Hessian blocks are scattered into it by
a precomputed map, fixed DOFs are eliminated by zeroing their rows and columns (unit diagonal), and
C right-hand sides, at most two per system (column c uses system `system_of[c]`), are solved together by block-Jacobi
preconditioned CG with per-column step lengths, stopping rules and negative-curvature detection. Every
kernel runs on the CPU or a CUDA device; on CUDA the CG iterations are replayed as a captured graph.
Units follow the caller (here N/m for stiffness blocks, m for solutions, N for right-hand sides).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import warp as wp

from fe.wptypes import launch

wp.set_module_options({"enable_backward": False})  # no adjoint kernels: nothing differentiates them

CG_RUNNING, CG_CONVERGED, CG_NEGATIVE_CURVATURE, CG_ITERATION_LIMIT = 1, 0, -1, -2
"""Per-column states of `BatchedCG.solve` (CG_NEGATIVE_CURVATURE also marks a non-finite curvature or
right-hand side: no usable solution)."""


@wp.kernel
def _scatter_blocks(
    blocks: wp.array3d(dtype=wp.float64),
    nodes_per_element: int,
    block_of: wp.array2d(dtype=wp.int32),
    scale: wp.array(dtype=wp.float64),
    active: wp.array(dtype=wp.int32),
    values: wp.array2d(dtype=wp.mat33d),
):
    """Add scale[b] x the (i, j) 3x3 sub-block of element e's Hessian (3k x 3k, row-major in blocks[b, e])
    to its matrix block, for the active systems."""
    b, e, ij = wp.tid()
    if active[b] == 0:
        return
    i = ij // nodes_per_element
    j = ij % nodes_per_element
    n = 3 * nodes_per_element
    s = scale[b]
    m = wp.mat33d()
    for r in range(3):
        for c in range(3):
            m[r, c] = blocks[b, e, (3 * i + r) * n + 3 * j + c] * s
    wp.atomic_add(values, b, block_of[e, ij], m)


def scalar_view(blocks: wp.array) -> wp.array:
    """The (B, E) matrix array `blocks` seen as (B, E, rows x cols) float64, without a copy."""
    size = wp.types.type_size(blocks.dtype)
    return wp.array(ptr=blocks.ptr, dtype=wp.float64, shape=(*blocks.shape, size), device=blocks.device, copy=False)


@wp.kernel
def _constrain(
    values: wp.array2d(dtype=wp.mat33d),
    block_row: wp.array(dtype=wp.int32),
    columns: wp.array(dtype=wp.int32),
    free: wp.array(dtype=wp.vec3d),
    shift: wp.array(dtype=wp.float64),
    active: wp.array(dtype=wp.int32),
):
    """Zero the rows and columns of fixed DOFs (free = 0) with a unit diagonal; add shift[b] tr(D)/3 to the
    free diagonal entries (relative Levenberg damping); active systems only."""
    b, k = wp.tid()
    if active[b] == 0:
        return
    row = block_row[k]
    col = columns[k]
    fr = free[row]
    fc = free[col]
    m = values[b, k]
    out = wp.mat33d()
    for r in range(3):
        for c in range(3):
            out[r, c] = m[r, c] * fr[r] * fc[c]
    if row == col:
        damping = shift[b] * wp.trace(m) / wp.float64(3.0)
        for r in range(3):
            out[r, r] = out[r, r] + (wp.float64(1.0) - fr[r]) + damping * fr[r]
    values[b, k] = out


@wp.kernel
def _invert_diagonal(
    values: wp.array2d(dtype=wp.mat33d),
    diagonal: wp.array(dtype=wp.int32),
    active: wp.array(dtype=wp.int32),
    preconditioner: wp.array2d(dtype=wp.mat33d),
):
    """Block-Jacobi preconditioner: the inverse of each node's 3x3 diagonal block (identity if singular),
    for the active systems."""
    b, v = wp.tid()
    if active[b] == 0:
        return
    d = values[b, diagonal[v]]
    if wp.abs(wp.determinant(d)) > wp.float64(0.0):
        preconditioner[b, v] = wp.inverse(d)
    else:
        preconditioner[b, v] = wp.identity(n=3, dtype=wp.float64)


@wp.kernel
def _multiply(
    values: wp.array2d(dtype=wp.mat33d),
    offsets: wp.array(dtype=wp.int32),
    columns: wp.array(dtype=wp.int32),
    system_of: wp.array(dtype=wp.int32),
    x: wp.array2d(dtype=wp.vec3d),
    y: wp.array2d(dtype=wp.vec3d),
):
    """y[c] = A[system_of[c]] x[c]."""
    c, row = wp.tid()
    s = system_of[c]
    out = wp.vec3d()
    for k in range(offsets[row], offsets[row + 1]):
        out += values[s, k] @ x[c, columns[k]]
    y[c, row] = out


@wp.kernel
def _cg_residual(
    rhs: wp.array2d(dtype=wp.vec3d),
    ax: wp.array2d(dtype=wp.vec3d),
    rr: wp.array(dtype=wp.float64),
    bb: wp.array(dtype=wp.float64),
):
    """Per column rr = |b - A x0|^2 (A x0 in `ax`) and bb = |b|^2."""
    c, v = wp.tid()
    b = rhs[c, v]
    wp.atomic_add(rr, c, wp.dot(b - ax[c, v], b - ax[c, v]))
    wp.atomic_add(bb, c, wp.dot(b, b))


@wp.kernel
def _cg_start(
    preconditioner: wp.array2d(dtype=wp.mat33d),
    system_of: wp.array(dtype=wp.int32),
    state: wp.array(dtype=wp.int32),
    warm: wp.array(dtype=wp.int32),
    rr: wp.array(dtype=wp.float64),
    bb: wp.array(dtype=wp.float64),
    last: wp.array2d(dtype=wp.vec3d),
    rhs: wp.array2d(dtype=wp.vec3d),
    ax: wp.array2d(dtype=wp.vec3d),
    x: wp.array2d(dtype=wp.vec3d),
    r: wp.array2d(dtype=wp.vec3d),
    p: wp.array2d(dtype=wp.vec3d),
    rz: wp.array(dtype=wp.float64),
):
    """x = x0, r = b - A x0, p = z = M^-1 r and rz = r.z per column, x0 the column's last solution where it is
    warm and that leaves a smaller residual than 0 does (rr < bb), else 0."""
    c, v = wp.tid()
    if state[c] != 1:
        return
    b = rhs[c, v]
    if warm[c] == 1 and rr[c] < bb[c]:
        x[c, v] = last[c, v]
        b = b - ax[c, v]
    z = preconditioner[system_of[c], v] @ b
    r[c, v] = b
    p[c, v] = z
    wp.atomic_add(rz, c, wp.dot(b, z))


@wp.kernel
def _cg_keep(
    warm: wp.array(dtype=wp.int32),
    state: wp.array(dtype=wp.int32),
    iterations: wp.array(dtype=wp.int32),
    x: wp.array2d(dtype=wp.vec3d),
    last: wp.array2d(dtype=wp.vec3d),
):
    """last = x for the warm columns that iterated and converged."""
    c, v = wp.tid()
    if warm[c] == 1 and state[c] == 0 and iterations[c] > 0:
        last[c, v] = x[c, v]


@wp.kernel
def _to_single(
    values: wp.array2d(dtype=wp.mat33d), active: wp.array(dtype=wp.int32), single: wp.array2d(dtype=wp.mat33f)
):
    """The active systems' blocks rounded to float32 (the CG's products read half the bytes)."""
    b, k = wp.tid()
    if active[b] == 0:
        return
    single[b, k] = wp.mat33f(values[b, k])


@wp.func
def _single_times(a: wp.mat33f, x: wp.vec3d) -> wp.vec3d:
    """a x in float64 arithmetic for a float32 block a."""
    y = wp.vec3d()
    for r in range(3):
        y[r] = wp.float64(a[r, 0]) * x[0] + wp.float64(a[r, 1]) * x[1] + wp.float64(a[r, 2]) * x[2]
    return y


@wp.kernel
def _cg_product(
    values: wp.array2d(dtype=wp.mat33f),
    offsets: wp.array(dtype=wp.int32),
    columns: wp.array(dtype=wp.int32),
    columns_of: wp.array2d(dtype=wp.int32),
    state: wp.array(dtype=wp.int32),
    p: wp.array2d(dtype=wp.vec3d),
    ap: wp.array2d(dtype=wp.vec3d),
    pap: wp.array(dtype=wp.float64),
):
    """ap = A p and pap = p.Ap for the running columns of system s (at most two, `columns_of[s]`, -1 for
    none), reading each matrix block once for both, in float32 (`BatchedBlockMatrix.single`)."""
    s, row = wp.tid()
    c0 = columns_of[s, 0]
    c1 = columns_of[s, 1]
    run0 = c0 >= 0
    run1 = c1 >= 0
    if run0:
        run0 = state[c0] == 1
    if run1:
        run1 = state[c1] == 1
    if not (run0 or run1):
        return
    y0 = wp.vec3d()
    y1 = wp.vec3d()
    for k in range(offsets[row], offsets[row + 1]):
        a = values[s, k]
        col = columns[k]
        if run0:
            y0 += _single_times(a, p[c0, col])
        if run1:
            y1 += _single_times(a, p[c1, col])
    if run0:
        ap[c0, row] = y0
        wp.atomic_add(pap, c0, wp.dot(p[c0, row], y0))
    if run1:
        ap[c1, row] = y1
        wp.atomic_add(pap, c1, wp.dot(p[c1, row], y1))


@wp.kernel
def _cg_update(
    preconditioner: wp.array2d(dtype=wp.mat33d),
    system_of: wp.array(dtype=wp.int32),
    state: wp.array(dtype=wp.int32),
    rz: wp.array(dtype=wp.float64),
    pap: wp.array(dtype=wp.float64),
    p: wp.array2d(dtype=wp.vec3d),
    ap: wp.array2d(dtype=wp.vec3d),
    x: wp.array2d(dtype=wp.vec3d),
    r: wp.array2d(dtype=wp.vec3d),
    z: wp.array2d(dtype=wp.vec3d),
    rz_new: wp.array(dtype=wp.float64),
    rr_new: wp.array(dtype=wp.float64),
):
    """x += alpha p, r -= alpha Ap, z = M^-1 r with alpha = rz / pAp (skipped on non-positive curvature)."""
    c, v = wp.tid()
    if state[c] != 1 or not (pap[c] > wp.float64(0.0)):
        return
    alpha = rz[c] / pap[c]
    x[c, v] = x[c, v] + alpha * p[c, v]
    rv = r[c, v] - alpha * ap[c, v]
    r[c, v] = rv
    zv = preconditioner[system_of[c], v] @ rv
    z[c, v] = zv
    wp.atomic_add(rz_new, c, wp.dot(rv, zv))
    wp.atomic_add(rr_new, c, wp.dot(rv, rv))


@wp.kernel
def _cg_scalars(
    tolerance: wp.array(dtype=wp.float64),
    max_iterations: int,
    bb: wp.array(dtype=wp.float64),
    state: wp.array(dtype=wp.int32),
    iterations: wp.array(dtype=wp.int32),
    rz: wp.array(dtype=wp.float64),
    pap: wp.array(dtype=wp.float64),
    rz_new: wp.array(dtype=wp.float64),
    rr_new: wp.array(dtype=wp.float64),
    beta: wp.array(dtype=wp.float64),
):
    """Per column: stop on non-positive curvature, on |r| <= tol |b| or at the iteration cap; else beta."""
    c = wp.tid()
    if state[c] != 1:
        return
    iterations[c] = iterations[c] + 1
    if not (pap[c] > wp.float64(0.0)):  # non-positive curvature, or NaN
        state[c] = -1
    elif rr_new[c] <= tolerance[c] * tolerance[c] * bb[c]:
        state[c] = 0
    elif iterations[c] >= max_iterations:
        state[c] = -2
    else:
        beta[c] = rz_new[c] / rz[c]
        rz[c] = rz_new[c]
    pap[c] = wp.float64(0.0)
    rz_new[c] = wp.float64(0.0)
    rr_new[c] = wp.float64(0.0)


@wp.kernel
def _cg_direction(
    state: wp.array(dtype=wp.int32),
    beta: wp.array(dtype=wp.float64),
    z: wp.array2d(dtype=wp.vec3d),
    p: wp.array2d(dtype=wp.vec3d),
):
    c, v = wp.tid()
    if state[c] != 1:
        return
    p[c, v] = z[c, v] + beta[c] * p[c, v]


HessianTerms = list[tuple[int, wp.array, np.ndarray | None]]
"""Element Hessians to assemble: per term its element family (index into `BlockPattern.block_of`), the (B, E_f)
matrices of that family and a per-system scale (B,) or None (1)."""


@dataclass
class BlockPattern:
    """3x3-block CSR pattern over `n_nodes` nodes, shared by a batch; `block_of[f]` (E_f, k_f^2) is the
    block receiving sub-block (i, j) (index i k_f + j) of element e of family f."""

    n_nodes: int
    offsets: np.ndarray
    columns: np.ndarray
    block_row: np.ndarray
    diagonal: np.ndarray
    block_of: list[np.ndarray]

    @classmethod
    def from_connectivities(cls, connectivities: list[np.ndarray], n_nodes: int) -> BlockPattern:
        """The pattern of all node pairs sharing an element of any family (E_f, k_f) node arrays, plus the diagonal."""
        keys = [np.arange(n_nodes, dtype=np.int64) * (n_nodes + 1)]
        for nodes in connectivities:
            nodes = np.asarray(nodes, dtype=np.int64)
            keys.append((nodes[:, :, None] * n_nodes + nodes[:, None, :]).ravel())
        unique, inverse = np.unique(np.concatenate(keys), return_inverse=True)
        rows, cols = unique // n_nodes, unique % n_nodes
        block_of, start = [], n_nodes
        for nodes in connectivities:
            size = len(nodes) * nodes.shape[1] ** 2
            block_of.append(inverse[start : start + size].reshape(len(nodes), nodes.shape[1] ** 2).astype(np.int32))
            start += size
        return cls(
            n_nodes=n_nodes,
            offsets=np.searchsorted(rows, np.arange(n_nodes + 1)).astype(np.int32),
            columns=cols.astype(np.int32),
            block_row=rows.astype(np.int32),
            diagonal=inverse[:n_nodes].astype(np.int32),
            block_of=block_of,
        )


class BatchedBlockMatrix:
    """B symmetric matrices of one `BlockPattern` on a warp device, assembled from element Hessian blocks."""

    def __init__(self, pattern: BlockPattern, batch: int, free: np.ndarray, device: str) -> None:
        """`free` (V,3): 1 for free DOFs, 0 for fixed ones (eliminated)."""
        self.pattern, self.batch, self.device = pattern, batch, device
        arr = lambda a, dtype: wp.array(a, dtype=dtype, device=device)  # noqa: E731
        self.offsets = arr(pattern.offsets, wp.int32)
        self.columns = arr(pattern.columns, wp.int32)
        self.block_row = arr(pattern.block_row, wp.int32)
        self.diagonal = arr(pattern.diagonal, wp.int32)
        self.block_of = [arr(m, wp.int32) for m in pattern.block_of]
        self.free = arr(np.asarray(free, dtype=np.float64), wp.vec3d)
        self.values = wp.zeros((batch, len(pattern.columns)), dtype=wp.mat33d, device=device)
        self.single = wp.zeros((batch, len(pattern.columns)), dtype=wp.mat33f, device=device)
        """The assembled blocks rounded to float32, which the CG's products read: the CG is bound by reading
        the matrix (about 1.3 GB for 256 systems of the 0.5 mm BioTac); the products are summed in float64,
        and an error of the matrix's 1e-7 relative rounding only loosens the Newton step (the residual,
        which decides convergence, is evaluated in float64)."""
        self.preconditioner = wp.zeros((batch, pattern.n_nodes), dtype=wp.mat33d, device=device)
        self._ones = arr(np.ones(batch), wp.float64)

    def assemble(self, terms: HessianTerms, shift: np.ndarray, active: np.ndarray | None = None) -> None:
        """Sum element Hessians, each term (family index, (B, E_f) matrices, per-system scale (B,) or None),
        eliminate fixed DOFs, add the relative damping `shift` (B,) to the diagonal, and refresh the
        block-Jacobi preconditioner, for the `active` systems ((B,) bool; all by default; the others' matrices
        are left zero)."""
        flags = np.ones(self.batch, dtype=np.int32) if active is None else np.asarray(active, dtype=np.int32)
        values = {**vars(self), "active": wp.array(flags, dtype=wp.int32, device=self.device)}
        values["shift"] = wp.array(np.asarray(shift, dtype=np.float64), dtype=wp.float64, device=self.device)
        self.values.zero_()
        for family, blocks, scale in terms:
            block_of = self.block_of[family]
            if blocks.shape[1] == 0:
                continue
            k = int(round(np.sqrt(block_of.shape[1])))
            weights = self._ones if scale is None else wp.array(np.asarray(scale, dtype=np.float64), device=self.device)
            element = {"blocks": scalar_view(blocks), "nodes_per_element": k, "block_of": block_of, "scale": weights}
            launch(_scatter_blocks, (self.batch, blocks.shape[1], k * k), values | element, self.device)
        launch(_constrain, self.values.shape, values, self.device)
        launch(_to_single, self.values.shape, values, self.device)
        launch(_invert_diagonal, (self.batch, self.pattern.n_nodes), values, self.device)

    def multiply(self, x: wp.array, y: wp.array, system_of: wp.array) -> None:
        """y[c] = A[system_of[c]] x[c] for (C, V) vec3d arrays."""
        wp.launch(_multiply, x.shape, [self.values, self.offsets, self.columns, system_of, x, y], device=self.device)


def _columns_of(system_of: np.ndarray, batch: int) -> np.ndarray:
    """(batch, 2) the columns of each system, in column order (-1: none), from each column's system (C,)."""
    order = np.argsort(system_of, kind="stable")
    systems = system_of[order]
    rank = np.arange(len(systems)) - np.searchsorted(systems, systems)  # 0: a system's first column, 1: its second
    if np.any(rank > 1):
        raise ValueError("at most two right-hand sides per system")
    columns_of = np.full((batch, 2), -1, dtype=np.int32)
    columns_of[systems, rank] = order
    return columns_of


class BatchedCG:
    """Preconditioned CG for `columns` right-hand sides of a `BatchedBlockMatrix`, buffers kept between solves.

    On CUDA, `check_every` iterations are captured once as a graph and replayed; the host checks whether
    any column still runs after each replay.
    """

    holds_factorization = False
    """CG keeps no factorisation: no chord steps (`fe.linsolve.BatchedDirectSolver` does)."""

    def __init__(
        self,
        matrix: BatchedBlockMatrix,
        columns: int,
        check_every: int = 25,
        use_graph: bool | None = None,
        warm: np.ndarray | None = None,
    ) -> None:
        """`use_graph`: replay the iterations as a CUDA graph (None: on CUDA devices); `warm` (columns,) bool:
        columns that start from their last converged solution where it leaves a smaller residual than 0 (for a
        right-hand side that changes little from one solve to the next; None: none)."""
        self.matrix, self.columns, self.check_every = matrix, columns, check_every
        self.use_graph = wp.get_device(matrix.device).is_cuda if use_graph is None else use_graph
        device, n = matrix.device, matrix.pattern.n_nodes
        vec = lambda: wp.zeros((columns, n), dtype=wp.vec3d, device=device)  # noqa: E731
        scalar = lambda dtype=wp.float64: wp.zeros(columns, dtype=dtype, device=device)  # noqa: E731
        self.x, self.r, self.z, self.p, self.ap = vec(), vec(), vec(), vec(), vec()
        self.rz, self.pap, self.rz_new, self.rr_new, self.beta, self.bb = (scalar() for _ in range(6))
        self.tolerance, self.rr, self.last = scalar(), scalar(), vec()
        warm = np.zeros(columns, dtype=bool) if warm is None else np.asarray(warm, dtype=bool)
        if warm.shape != (columns,):
            raise ValueError(f"warm needs one flag per column ({columns}), got shape {warm.shape}")
        self.warm_columns = warm
        self.warm = wp.array(warm.astype(np.int32), dtype=wp.int32, device=device)
        self.state, self.iterations = scalar(wp.int32), scalar(wp.int32)
        self.system_of = scalar(wp.int32)
        self.columns_of = wp.zeros((matrix.batch, 2), dtype=wp.int32, device=device)
        self._max_iterations = -1
        self._graph = None

    def assemble(self, terms: HessianTerms, shift: np.ndarray, active: np.ndarray | None = None) -> None:
        """`BatchedBlockMatrix.assemble` of the solver's matrix."""
        self.matrix.assemble(terms, shift, active)

    def multiply(self, x: wp.array, y: wp.array, system_of: wp.array) -> None:
        """`BatchedBlockMatrix.multiply` of the solver's matrix."""
        self.matrix.multiply(x, y, system_of)

    def _iterate(self) -> None:
        m, shape = self.matrix, (self.columns, self.matrix.pattern.n_nodes)
        values = {**vars(self), "values": m.single, "offsets": m.offsets, "columns": m.columns}
        values |= {"preconditioner": m.preconditioner, "max_iterations": self._max_iterations}
        for _ in range(self.check_every):
            launch(_cg_product, (m.batch, m.pattern.n_nodes), values, m.device)
            launch(_cg_update, shape, values, m.device)
            launch(_cg_scalars, self.columns, values, m.device)
            launch(_cg_direction, shape, values, m.device)

    def solve(
        self, rhs: wp.array, system_of: np.ndarray, active: np.ndarray, tolerance: np.ndarray, max_iterations: int
    ) -> tuple[wp.array, np.ndarray, np.ndarray]:
        """Solve A[system_of[c]] x[c] = rhs[c] (fixed DOFs of rhs must be 0) for the `active` columns to
        |r| <= tolerance[c] |rhs[c]| (2-norms). Returns the solutions (C, V) (device array, owned by the
        solver), iteration counts and final states (CG_* constants; inactive columns CG_CONVERGED with 0
        iterations and x = 0)."""
        device = self.matrix.device
        system_of = np.asarray(system_of, dtype=np.int32)
        self.system_of.assign(system_of)
        self.columns_of.assign(_columns_of(system_of, self.matrix.batch))
        self.state.assign(np.where(active, CG_RUNNING, CG_CONVERGED).astype(np.int32))
        self.tolerance.assign(np.asarray(tolerance, dtype=np.float64))
        for a in (self.iterations, self.rz, self.pap, self.rz_new, self.rr_new, self.bb, self.rr, self.x):
            a.zero_()
        shape = (self.columns, self.matrix.pattern.n_nodes)
        values = {**vars(self), "preconditioner": self.matrix.preconditioner, "rhs": rhs, "ax": self.ap}
        self.matrix.multiply(self.last, self.ap, self.system_of)
        launch(_cg_residual, shape, values, device)
        launch(_cg_start, shape, values, device)
        bb, rr = self.bb.numpy(), self.rr.numpy()
        active = np.asarray(active, dtype=bool)
        met = self.warm_columns & (rr < bb) & (rr <= np.asarray(tolerance) ** 2 * bb)  # by its start
        state = np.where(active & (bb > 0.0) & ~met, CG_RUNNING, CG_CONVERGED)
        state = np.where(active & ~np.isfinite(bb), CG_NEGATIVE_CURVATURE, state)  # a non-finite right-hand side
        self.state.assign(state.astype(np.int32))
        use_graph = self.use_graph
        if use_graph and (self._graph is None or self._max_iterations != max_iterations):
            self._max_iterations = max_iterations
            with wp.ScopedCapture(device=device) as capture:
                self._iterate()
            self._graph = capture.graph
        self._max_iterations = max_iterations
        while np.any(self.state.numpy() == CG_RUNNING):
            if use_graph:
                wp.capture_launch(self._graph)
            else:
                self._iterate()
        launch(_cg_keep, shape, values, device)
        return self.x, self.iterations.numpy(), self.state.numpy()
