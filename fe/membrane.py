"""Incompressible Neo-Hookean membrane energy of a triangle shell, in warp.

Per unit reference area the energy density is (mu t / 2)(tr C + 1/det C - 3), where C = F^T F is the
2x2 right Cauchy-Green tensor of the in-plane deformation gradient F (3x2) and the thickness stretch
follows from incompressibility (lambda_3 = 1/sqrt(det C)). Positions in metres, energy in joules.
"""

import numpy as np
import warp as wp

from fe.wptypes import mat32d, mat99d

_ZERO = wp.float64(0.0)


@wp.func
def _edge_gradient(a: int, dm_inv: wp.mat22d) -> wp.vec2d:
    """Row a of dF/dx for node a of the triangle: F = sum_a x_a (x) g_a."""
    g1 = wp.vec2d(dm_inv[0, 0], dm_inv[0, 1])
    g2 = wp.vec2d(dm_inv[1, 0], dm_inv[1, 1])
    if a == 1:
        return g1
    if a == 2:
        return g2
    return -(g1 + g2)


@wp.func
def _stress_variation(F: mat32d, c_inv: wp.mat22d, det_c: wp.float64, dF: mat32d, coeff: wp.float64) -> mat32d:
    """Directional derivative of the first Piola-Kirchhoff stress P(F) along dF."""
    dC = wp.transpose(dF) @ F + wp.transpose(F) @ dF
    d_det = det_c * wp.trace(c_inv @ dC)
    d_c_inv = -(c_inv @ dC @ c_inv)
    inv_det = wp.float64(1.0) / det_c
    return coeff * (dF - (dF @ c_inv + F @ d_c_inv) * inv_det + F @ c_inv * (d_det * inv_det * inv_det))


@wp.kernel
def membrane_kernel(
    x: wp.array2d(dtype=wp.vec3d),
    triangles: wp.array(dtype=wp.vec3i),
    dm_inv: wp.array(dtype=wp.mat22d),
    rest_area: wp.array(dtype=wp.float64),
    mu_t: wp.array(dtype=wp.float64),
    want_hessian: int,
    energy: wp.array2d(dtype=wp.float64),
    gradient: wp.array2d(dtype=wp.vec3d),
    hessian: wp.array2d(dtype=mat99d),
):
    """Energy, gradient (atomically scattered to nodes) and 9x9 Hessian per (batch, triangle)."""
    b, t = wp.tid()
    tri = triangles[t]
    x0 = x[b, tri[0]]
    ds = mat32d()
    e1 = x[b, tri[1]] - x0
    e2 = x[b, tri[2]] - x0
    for i in range(3):
        ds[i, 0] = e1[i]
        ds[i, 1] = e2[i]
    Dinv = dm_inv[t]
    F = ds @ Dinv
    C = wp.transpose(F) @ F
    det_c = wp.determinant(C)
    c_inv = wp.inverse(C)
    area = rest_area[t]
    half = wp.float64(0.5)
    energy[b, t] = area * half * mu_t[b] * (wp.trace(C) + wp.float64(1.0) / det_c - wp.float64(3.0))
    coeff = area * mu_t[b]
    P = coeff * (F - F @ c_inv / det_c)
    for a in range(3):
        ga = _edge_gradient(a, Dinv)
        wp.atomic_add(gradient, b, tri[a], P @ ga)
    if want_hessian != 0:
        H = mat99d()
        for nb in range(3):
            gb = _edge_gradient(nb, Dinv)
            for j in range(3):
                dF = mat32d()
                dF[j, 0] = gb[0]
                dF[j, 1] = gb[1]
                dP = _stress_variation(F, c_inv, det_c, dF, coeff)
                for na in range(3):
                    col = dP @ _edge_gradient(na, Dinv)
                    for i in range(3):
                        H[3 * na + i, 3 * nb + j] = col[i]
        hessian[b, t] = H


def reference_frames(vertices: np.ndarray, triangles: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Inverse reference edge matrices (T,2,2) and reference areas (T,) in m^2 of a triangle mesh.

    Each triangle gets an orthonormal in-plane basis (e1 along edge 0-1), so F maps reference
    in-plane coordinates (m) to deformed positions (m).
    """
    p0, p1, p2 = (vertices[triangles[:, k]] for k in range(3))
    d1, d2 = p1 - p0, p2 - p0
    normal = np.cross(d1, d2)
    double_area = np.linalg.norm(normal, axis=1)
    if np.any(double_area <= 1e-18):
        raise ValueError("mesh has degenerate (zero-area) triangles")
    e1 = d1 / np.linalg.norm(d1, axis=1)[:, None]
    e2 = np.cross(normal / double_area[:, None], e1)
    dm = np.empty((len(triangles), 2, 2))
    dm[:, 0, 0] = np.einsum("ij,ij->i", e1, d1)
    dm[:, 0, 1] = np.einsum("ij,ij->i", e1, d2)
    dm[:, 1, 0] = np.einsum("ij,ij->i", e2, d1)
    dm[:, 1, 1] = np.einsum("ij,ij->i", e2, d2)
    return np.linalg.inv(dm), 0.5 * double_area
