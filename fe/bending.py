"""Discrete-shell bending energy on interior edges (hinges), in warp.

Per hinge: E = (D / 2) * 3 |e0|^2 / (A0_A + A0_B) * (theta - theta0)^2, with theta the signed dihedral
angle, theta0 its rest value, |e0| and A0 the rest edge length and triangle areas (m, m^2) and
D = mu t^3 / 3 the plate bending stiffness of an incompressible sheet (J). The hinge sum
sum 3 |e|^2 / (A_A + A_B) theta^2 approximates the integral of (2H)^2 = (k1 + k2)^2 over the surface
(exactly so for isotropic curvature), so E approximates the plate energy (D / 2) int (k1 + k2)^2 dA
(Gaussian-curvature term omitted, as for clamped or closed shells). The hinge energy is anisotropic:
curvature fields that vary across an irregular mesh come out stiffer than the plate (see docs/fe.md).
The gradient of theta is analytic; the Hessian is the forward difference of that analytic gradient
(step 1e-7 of the edge length, then symmetrised), accurate to ~1e-7 relative: plenty for Newton.
"""

import numpy as np
import warp as wp

from fe.wptypes import mat1212d, vec12d


@wp.func
def dihedral_angle(x0: wp.vec3d, x1: wp.vec3d, x2: wp.vec3d, x3: wp.vec3d) -> wp.float64:
    """Signed angle (rad) between triangles (x0, x1, x2) and (x1, x0, x3) across edge x0-x1."""
    e = x1 - x0
    na = wp.cross(e, x2 - x0)
    nb = wp.cross(x3 - x1, e)
    s = wp.dot(wp.cross(na, nb), e) / wp.length(e)
    return wp.atan2(s, wp.dot(na, nb))


@wp.func
def dihedral_gradient(x0: wp.vec3d, x1: wp.vec3d, x2: wp.vec3d, x3: wp.vec3d) -> vec12d:
    """Gradient of `dihedral_angle` with respect to (x0, x1, x2, x3), stacked (12,)."""
    e = x1 - x0
    len_e = wp.length(e)
    na = wp.cross(e, x2 - x0)
    nb = wp.cross(x3 - x1, e)
    na2 = wp.dot(na, na)
    nb2 = wp.dot(nb, nb)
    ga = na * (len_e / na2)  # = n_A / h_A for the far vertex x2
    gb = nb * (len_e / nb2)
    ta = wp.dot(x2 - x0, e) / (len_e * len_e)
    tb = wp.dot(x3 - x0, e) / (len_e * len_e)
    one = wp.float64(1.0)
    g2 = -ga
    g3 = -gb
    g0 = ga * (one - ta) + gb * (one - tb)
    g1 = ga * ta + gb * tb
    out = vec12d()
    for i in range(3):
        out[i] = g0[i]
        out[3 + i] = g1[i]
        out[6 + i] = g2[i]
        out[9 + i] = g3[i]
    return out


@wp.func
def _hinge_energy_gradient(
    x0: wp.vec3d, x1: wp.vec3d, x2: wp.vec3d, x3: wp.vec3d, stiffness: wp.float64, theta0: wp.float64
) -> vec12d:
    theta = dihedral_angle(x0, x1, x2, x3)
    return dihedral_gradient(x0, x1, x2, x3) * (wp.float64(2.0) * stiffness * (theta - theta0))


@wp.func
def _corner(xs: vec12d, k: int) -> wp.vec3d:
    return wp.vec3d(xs[3 * k], xs[3 * k + 1], xs[3 * k + 2])


@wp.kernel
def bending_kernel(
    x: wp.array2d(dtype=wp.vec3d),
    hinges: wp.array(dtype=wp.vec4i),
    rest_angle: wp.array(dtype=wp.float64),
    rest_weight: wp.array(dtype=wp.float64),
    bending_stiffness: wp.array(dtype=wp.float64),
    want_hessian: int,
    energy: wp.array2d(dtype=wp.float64),
    gradient: wp.array2d(dtype=wp.vec3d),
    hessian: wp.array2d(dtype=mat1212d),
):
    """Energy, gradient (scattered to nodes) and 12x12 Hessian per (batch, hinge)."""
    b, h = wp.tid()
    idx = hinges[h]
    k = rest_weight[h] * bending_stiffness[b]
    xs = vec12d()
    for c in range(4):
        p = x[b, idx[c]]
        for i in range(3):
            xs[3 * c + i] = p[i]
    theta = dihedral_angle(_corner(xs, 0), _corner(xs, 1), _corner(xs, 2), _corner(xs, 3))
    d = theta - rest_angle[h]
    energy[b, h] = k * d * d
    g = _hinge_energy_gradient(_corner(xs, 0), _corner(xs, 1), _corner(xs, 2), _corner(xs, 3), k, rest_angle[h])
    for c in range(4):
        wp.atomic_add(gradient, b, idx[c], _corner(g, c))
    if want_hessian != 0:
        step = wp.float64(1e-7) * wp.length(_corner(xs, 1) - _corner(xs, 0))
        H = mat1212d()
        for j in range(12):
            xp = xs
            xp[j] = xs[j] + step
            gp = _hinge_energy_gradient(
                _corner(xp, 0), _corner(xp, 1), _corner(xp, 2), _corner(xp, 3), k, rest_angle[h]
            )
            for i in range(12):
                H[i, j] = (gp[i] - g[i]) / step
        for i in range(12):
            for j in range(i + 1, 12):
                s = wp.float64(0.5) * (H[i, j] + H[j, i])
                H[i, j] = s
                H[j, i] = s
        hessian[b, h] = H


def build_hinges(triangles: np.ndarray) -> np.ndarray:
    """Interior edges as (v0, v1, v2, v3).

    Edge v0-v1 is ordered as in triangle (v0, v1, v2); (v1, v0, v3) is its neighbour.
    """
    directed = {}
    for tri in triangles:
        for k in range(3):
            a, b, c = tri[k], tri[(k + 1) % 3], tri[(k + 2) % 3]
            directed[(int(a), int(b))] = int(c)
    hinges = [(a, b, c, directed[(b, a)]) for (a, b), c in directed.items() if a < b and (b, a) in directed]
    return np.asarray(hinges, dtype=np.int32).reshape(-1, 4)


def hinge_rest_state(vertices: np.ndarray, triangles: np.ndarray, hinges: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Rest dihedral angles (rad) and weights (1/2) 3|e0|^2/(A0_A + A0_B) (dimensionless) of each hinge,
    so that the hinge energy is D * weight * (theta - theta0)^2."""
    x0, x1, x2, x3 = (vertices[hinges[:, k]] for k in range(4))
    e = x1 - x0
    na = np.cross(e, x2 - x0)
    nb = np.cross(x3 - x1, e)
    len_e = np.linalg.norm(e, axis=1)
    s = np.einsum("ij,ij->i", np.cross(na, nb), e) / len_e
    angle = np.arctan2(s, np.einsum("ij,ij->i", na, nb))
    areas = 0.5 * (np.linalg.norm(na, axis=1) + np.linalg.norm(nb, axis=1))
    return angle, 1.5 * len_e**2 / areas
