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
    """Scatters element blocks into a CSR matrix over free DOFs with a pattern computed once.

    `connectivities` lists node-index arrays (E_k, n_k) of each element family; `dof_map` maps every
    global DOF (3 * node + axis) to its free index or -1 when fixed.
    """

    connectivities: list[np.ndarray]
    dof_map: np.ndarray

    def __post_init__(self) -> None:
        self.n_free = int(self.dof_map.max()) + 1 if self.dof_map.size else 0
        keys, self._selectors = [], []
        for nodes in self.connectivities:
            dofs = (3 * nodes[:, :, None] + np.arange(3)).reshape(len(nodes), 3 * nodes.shape[1])
            free = self.dof_map[dofs]
            rows = np.broadcast_to(free[:, :, None], (*free.shape, free.shape[1]))
            cols = np.broadcast_to(free[:, None, :], rows.shape)
            keep = ((rows >= 0) & (cols >= 0)).ravel()
            keys.append(rows.ravel()[keep].astype(np.int64) * self.n_free + cols.ravel()[keep])
            self._selectors.append(np.flatnonzero(keep))
        all_keys = np.concatenate(keys) if keys else np.zeros(0, dtype=np.int64)
        unique, inverse = np.unique(all_keys, return_inverse=True)
        self._rows = unique // max(self.n_free, 1)
        self._cols = unique % max(self.n_free, 1)
        self._indptr = np.searchsorted(self._rows, np.arange(self.n_free + 1))
        # One 0/1 scatter matrix per family maps its flattened blocks onto the CSR data array.
        self._scatter, start = [], 0
        for nodes, selector in zip(self.connectivities, self._selectors, strict=True):
            size = len(nodes) * (3 * nodes.shape[1]) ** 2
            target = inverse[start : start + len(selector)]
            ones = np.ones(len(selector))
            self._scatter.append(sp.csr_matrix((ones, (target, selector)), shape=(len(unique), size)))
            start += len(selector)

    def assemble(self, blocks: list[np.ndarray]) -> sp.csr_matrix:
        """Sum blocks (one (E_k, 3 n_k, 3 n_k) array per family, in order) into an (n_free, n_free) CSR matrix."""
        data = sum(s @ b.reshape(-1) for s, b in zip(self._scatter, blocks, strict=True))
        return sp.csr_matrix((data, self._cols.copy(), self._indptr.copy()), shape=(self.n_free, self.n_free))
