"""Incompressible Neo-Hookean (optionally Gent) membrane energy of a triangle shell, in warp.

Per unit reference area the energy density is (mu t / 2)(I1 - 3), I1 = tr C + 1/det C, where C = F^T F is
the 2x2 right Cauchy-Green tensor of the in-plane deformation gradient F (3x2) and the thickness stretch
follows from incompressibility (lambda_3 = 1/sqrt(det C)). With Gent stiffening (beta = 1/J_m > 0) it is
-(mu t / 2)(1 / beta) ln(1 - beta (I1 - 3)), which tends to Neo-Hookean as beta -> 0 and stiffens without
bound as I1 -> 3 + J_m. Positions in metres, energy in joules, stress resultants in N/m.
"""

import numpy as np
import warp as wp

from fe.wptypes import mat32d, mat99d

wp.set_module_options({"enable_backward": False})  # no adjoint kernels: nothing differentiates them


@wp.func
def edge_gradient(a: int, dm_inv: wp.mat22d) -> wp.vec2d:
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


@wp.func
def _gent_log_ratio(z: wp.float64) -> wp.float64:
    """-ln(1 - z) / z (1 at z = 0): the Gent energy over its Neo-Hookean value, z = beta (I1 - 3); a series
    below z = 1e-4, where the logarithm would cancel. Beyond the Gent limit (z >= 1) it is inf or nan."""
    one = wp.float64(1.0)
    if z < wp.float64(1e-4):
        return one + z * (wp.float64(0.5) + z * (one / wp.float64(3.0) + z * wp.float64(0.25)))
    return -wp.log(one - z) / z


@wp.func
def deformation_gradient(x: wp.array2d(dtype=wp.vec3d), b: int, tri: wp.vec3i, dm_inv: wp.mat22d) -> mat32d:
    """In-plane deformation gradient F (3x2) of triangle `tri` in batch b."""
    x0 = x[b, tri[0]]
    ds = mat32d()
    e1 = x[b, tri[1]] - x0
    e2 = x[b, tri[2]] - x0
    for i in range(3):
        ds[i, 0] = e1[i]
        ds[i, 1] = e2[i]
    return ds @ dm_inv


@wp.kernel
def membrane_kernel(
    x: wp.array2d(dtype=wp.vec3d),
    triangles: wp.array(dtype=wp.vec3i),
    dm_inv: wp.array(dtype=wp.mat22d),
    rest_area: wp.array(dtype=wp.float64),
    mu_t: wp.array(dtype=wp.float64),
    gent_beta: wp.array(dtype=wp.float64),
    frozen_stress: wp.array2d(dtype=wp.mat22d),
    want_hessian: int,
    membrane_energy: wp.array2d(dtype=wp.float64),
    elastic_gradient: wp.array2d(dtype=wp.vec3d),
    membrane_hessian: wp.array2d(dtype=mat99d),
    active: wp.array(dtype=wp.int32),
):
    """Energy, gradient (atomically scattered to nodes) and 9x9 Hessian per (batch, triangle).

    `gent_beta` (per batch) is 1/J_m; 0 gives Neo-Hookean. Beyond the Gent limit the energy is +inf or nan.
    `frozen_stress` a (N/m, symmetric, per batch and triangle; zero for an elastic skin) adds the
    viscoelastic term (1/2) A0 a : (C - I) of `fe.viscoelastic`: P += A0 F a, dP += A0 dF a.
    """
    b, t = wp.tid()
    if active[b] == 0:  # a system left out of this evaluation: nothing is written for it
        return
    tri = triangles[t]
    Dinv = dm_inv[t]
    F = deformation_gradient(x, b, tri, Dinv)
    C = wp.transpose(F) @ F
    det_c = wp.determinant(C)
    c_inv = wp.inverse(C)
    area = rest_area[t]
    half = wp.float64(0.5)
    one = wp.float64(1.0)
    beta = gent_beta[b]
    i1_excess = wp.trace(C) + one / det_c - wp.float64(3.0)
    z = beta * i1_excess
    held = frozen_stress[b, t]
    frozen = half * area * wp.trace(held @ (C - wp.identity(n=2, dtype=wp.float64)))
    membrane_energy[b, t] = area * half * mu_t[b] * i1_excess * _gent_log_ratio(z) + frozen
    stiffening = one / (one - z)  # d(energy density)/d(I1) over its Neo-Hookean value mu t / 2
    coeff = area * mu_t[b] * stiffening
    P_unit = F - F @ c_inv / det_c  # half of dI1/dF
    P = coeff * P_unit + area * (F @ held)
    for a in range(3):
        ga = edge_gradient(a, Dinv)
        wp.atomic_add(elastic_gradient, b, tri[a], P @ ga)
    if want_hessian != 0:
        H = mat99d()
        for nb in range(3):
            gb = edge_gradient(nb, Dinv)
            for j in range(3):
                dF = mat32d()
                dF[j, 0] = gb[0]
                dF[j, 1] = gb[1]
                dP = _stress_variation(F, c_inv, det_c, dF, coeff) + area * (dF @ held)
                for na in range(3):
                    col = dP @ edge_gradient(na, Dinv)
                    for i in range(3):
                        H[3 * na + i, 3 * nb + j] = col[i]
        if beta > wp.float64(0.0):
            # d(stiffening)/dI1 = beta stiffening^2 times (dI1/dx)(dI1/dx)^T, dI1/dx_a = 2 P_unit g_a.
            k = wp.float64(2.0) * area * mu_t[b] * beta * stiffening * stiffening
            for na in range(3):
                ra = P_unit @ edge_gradient(na, Dinv)
                for nb in range(3):
                    rb = P_unit @ edge_gradient(nb, Dinv)
                    for i in range(3):
                        for j in range(3):
                            H[3 * na + i, 3 * nb + j] = H[3 * na + i, 3 * nb + j] + k * ra[i] * rb[j]
        membrane_hessian[b, t] = H


def membrane_stress(
    x: np.ndarray, triangles: np.ndarray, dm_inv: np.ndarray, mu_t: float, gent_inverse_jm: float
) -> np.ndarray:
    """Second Piola-Kirchhoff membrane stress resultants N = 2 dW/dC (T,2,2) in N/m, in each triangle's
    reference in-plane frame, at positions x (V,3) m: N = s mu t (I - C^-1 / det C), s the Gent factor."""
    d1 = x[triangles[:, 1]] - x[triangles[:, 0]]
    d2 = x[triangles[:, 2]] - x[triangles[:, 0]]
    F = np.stack([d1, d2], axis=2) @ dm_inv
    C = np.transpose(F, (0, 2, 1)) @ F
    det_c = np.linalg.det(C)
    stiffening = 1.0 / (1.0 - gent_inverse_jm * (np.trace(C, axis1=1, axis2=2) + 1.0 / det_c - 3.0))
    return (stiffening * mu_t)[:, None, None] * (np.eye(2) - np.linalg.inv(C) / det_c[:, None, None])


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
