"""Sparse assembly of per-element Hessian blocks onto the free degrees of freedom, and PSD projection."""

from dataclasses import dataclass

import numpy as np
import scipy.sparse as sp


def project_psd(blocks: np.ndarray, floor: float = 0.0) -> np.ndarray:
    """Clamp the eigenvalues of each symmetric block (E, n, n) to at least `floor`."""
    if blocks.size == 0:
        return blocks
    sym = 0.5 * (blocks + np.swapaxes(blocks, 1, 2))
    values, vectors = np.linalg.eigh(sym)
    if np.all(values >= floor):
        return sym
    values = np.maximum(values, floor)
    return np.einsum("eij,ej,ekj->eik", vectors, values, vectors)


@dataclass
class BlockAssembler:
    """Scatters symmetric element blocks into a CSR matrix over free DOFs with a pattern computed once.

    `connectivities` lists node-index arrays (E_k, n_k) of each element family; `dof_map` maps every
    global DOF (3 * node + axis) to its free index or -1 when fixed. Only the block entries that land on
    or above the diagonal are summed (the ones a symmetric factorisation reads); the lower triangle is
    their mirror image.
    """

    connectivities: list[np.ndarray]
    dof_map: np.ndarray

    def __post_init__(self) -> None:
        self.n_free = int(self.dof_map.max()) + 1 if self.dof_map.size else 0
        n = max(self.n_free, 1)
        keys, upper_keys, self._selectors = [], [], []
        for nodes in self.connectivities:
            dofs = (3 * nodes[:, :, None] + np.arange(3)).reshape(len(nodes), 3 * nodes.shape[1])
            free = self.dof_map[dofs]
            rows = np.broadcast_to(free[:, :, None], (*free.shape, free.shape[1])).ravel()
            cols = np.broadcast_to(free[:, None, :], (*free.shape, free.shape[1])).ravel()
            keep = (rows >= 0) & (cols >= 0)
            keys.append(rows[keep].astype(np.int64) * n + cols[keep])
            upper = np.flatnonzero(keep & (rows <= cols))
            upper_keys.append(rows[upper].astype(np.int64) * n + cols[upper])
            self._selectors.append(upper)
        all_keys = np.unique(np.concatenate(keys)) if keys else np.zeros(0, dtype=np.int64)
        self._rows = all_keys // n
        self._cols = all_keys % n
        self._indptr = np.searchsorted(self._rows, np.arange(self.n_free + 1))
        upper_pattern = all_keys[self._rows <= self._cols]
        # Each stored entry (i, j) takes its value from the upper-triangle entry (min(i, j), max(i, j)).
        mirrored = np.minimum(self._rows, self._cols) * n + np.maximum(self._rows, self._cols)
        self._source = np.searchsorted(upper_pattern, mirrored)
        # One 0/1 scatter matrix per family maps its flattened blocks onto the upper-triangle values; stored
        # by columns where a family has fewer block entries than the triangle has values (cheaper product).
        self._scatter = []
        for nodes, selector, family_keys in zip(self.connectivities, self._selectors, upper_keys, strict=True):
            size = len(nodes) * (3 * nodes.shape[1]) ** 2
            target = np.searchsorted(upper_pattern, family_keys)
            scatter = sp.coo_matrix((np.ones(len(selector)), (target, selector)), shape=(len(upper_pattern), size))
            self._scatter.append(scatter.tocsc() if size < len(upper_pattern) else scatter.tocsr())

    def assemble(self, blocks: list[np.ndarray]) -> sp.csr_matrix:
        """Sum symmetric blocks (one (E_k, 3 n_k, 3 n_k) array per family, in order) into an (n_free, n_free)
        symmetric CSR matrix."""
        upper = sum(s @ b.reshape(-1) for s, b in zip(self._scatter, blocks, strict=True))
        data = upper[self._source] if len(self._source) else np.zeros(0)
        return sp.csr_matrix((data, self._cols.copy(), self._indptr.copy()), shape=(self.n_free, self.n_free))
