"""Discrete Kirchhoff-Love bending from per-triangle shape operators built on edge dihedral angles, in warp.

Each triangle T with edges e_i (i = 0, 1, 2, opposite its vertex i) estimates the change of its second
fundamental form from the changes of the dihedral angles across its edges,
dS = sum_i (theta_i - theta0_i) |e0_i| / (2 A0) t_i t_i^T, with t_i the rest in-plane unit normal of
edge i and |e0_i|, A0 rest lengths and areas (m, m^2); edges without a neighbour contribute nothing.
The energy is the plate energy of an incompressible sheet (nu = 1/2, D = mu t^3 / 3 in J):
E_T = (D / 2) A0 [nu (tr dS)^2 + (1 - nu) |dS|_F^2] = (D A0 / 2) dtheta^T M dtheta with the constant
M_ij = c_i c_j [nu + (1 - nu) (t_i . t_j)^2], c_i = |e0_i| / (2 A0). Unlike a sum of squared hinge
angles, which is exact for isotropic curvature only (and about 3x too stiff for cylindrical bending on
an equilateral mesh), the shape operator is exact for any uniform curvature on such meshes.
The gradient of theta is analytic; its Hessian is the forward difference of that analytic gradient
(step 1e-7 of the edge length), accurate to ~1e-7 relative: plenty for Newton.
"""

import numpy as np
import warp as wp

from fe.wptypes import mat1818d, vec6i, vec12d

wp.set_module_options({"enable_backward": False})  # no adjoint kernels: nothing differentiates them

mat318d = wp.types.matrix(shape=(3, 18), dtype=wp.float64)
"""d theta_i / d (18 stencil coordinates) of a triangle's three hinge angles."""

POISSON = 0.5
"""Poisson's ratio of the incompressible skin."""


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
def _corner(xs: vec12d, k: int) -> wp.vec3d:
    return wp.vec3d(xs[3 * k], xs[3 * k + 1], xs[3 * k + 2])


@wp.func
def _edge_slots(i: int) -> wp.vec4i:
    """Stencil slots (0-2 triangle vertices, 3-5 far vertices) of the hinge across edge i: (x0, x1, x2, x3)."""
    return wp.vec4i((i + 1) % 3, (i + 2) % 3, i, 3 + i)


@wp.func
def _hinge_coordinates(x: wp.array2d(dtype=wp.vec3d), b: int, nodes: vec6i, i: int) -> vec12d:
    """Stacked (x0, x1, x2, x3) of the hinge across edge i of the stencil `nodes`, batch b."""
    s = _edge_slots(i)
    xs = vec12d()
    for c in range(4):
        p = x[b, nodes[s[c]]]
        for d in range(3):
            xs[3 * c + d] = p[d]
    return xs


@wp.func
def _angle(xs: vec12d) -> wp.float64:
    return dihedral_angle(_corner(xs, 0), _corner(xs, 1), _corner(xs, 2), _corner(xs, 3))


@wp.func
def _angle_gradient(xs: vec12d) -> vec12d:
    return dihedral_gradient(_corner(xs, 0), _corner(xs, 1), _corner(xs, 2), _corner(xs, 3))


@wp.kernel
def bending_kernel(
    x: wp.array2d(dtype=wp.vec3d),
    stencils: wp.array(dtype=vec6i),
    has_edge: wp.array(dtype=wp.vec3i),
    rest_angle: wp.array2d(dtype=wp.vec3d),
    bend_area: wp.array(dtype=wp.float64),
    coupling: wp.array(dtype=wp.mat33d),
    bending_stiffness: wp.array(dtype=wp.float64),
    want_hessian: int,
    bending_energy: wp.array2d(dtype=wp.float64),
    elastic_gradient: wp.array2d(dtype=wp.vec3d),
    bending_hessian: wp.array2d(dtype=mat1818d),
    active: wp.array(dtype=wp.int32),
):
    """Energy, gradient (scattered to the 6 stencil nodes) and 18x18 Hessian per (batch, triangle)."""
    b, t = wp.tid()
    if active[b] == 0:  # a system left out of this evaluation: nothing is written for it
        return
    nodes = stencils[t]
    present = has_edge[t]
    k = bending_stiffness[b] * bend_area[t]
    m = coupling[t]
    dtheta = wp.vec3d()
    jac = mat318d()
    for i in range(3):
        if present[i] != 0:
            xs = _hinge_coordinates(x, b, nodes, i)
            dtheta[i] = _angle(xs) - rest_angle[b, t][i]
            g = _angle_gradient(xs)
            s = _edge_slots(i)
            for j in range(12):
                jac[i, 3 * s[j // 3] + j % 3] = g[j]
    lam = (m @ dtheta) * k  # dE / dtheta_i
    bending_energy[b, t] = wp.float64(0.5) * wp.dot(dtheta, lam)
    for slot in range(6):
        f = wp.vec3d()
        for d in range(3):
            f[d] = lam[0] * jac[0, 3 * slot + d] + lam[1] * jac[1, 3 * slot + d] + lam[2] * jac[2, 3 * slot + d]
        wp.atomic_add(elastic_gradient, b, nodes[slot], f)
    if want_hessian != 0:
        # Gauss-Newton part k jac^T M jac, through w = k M jac (M symmetric).
        w = mat318d()
        for j in range(3):
            for r in range(18):
                w[j, r] = k * (m[0, j] * jac[0, r] + m[1, j] * jac[1, r] + m[2, j] * jac[2, r])
        H = mat1818d()
        for r in range(18):
            for c in range(r, 18):
                v = w[0, r] * jac[0, c] + w[1, r] * jac[1, c] + w[2, r] * jac[2, c]
                H[r, c] = v
                H[c, r] = v
        for i in range(3):
            if present[i] != 0:
                xs = _hinge_coordinates(x, b, nodes, i)
                g0 = _angle_gradient(xs)
                step = wp.float64(1e-7) * wp.length(_corner(xs, 1) - _corner(xs, 0))
                s = _edge_slots(i)
                for j in range(12):
                    xp = xs
                    xp[j] = xs[j] + step
                    gp = _angle_gradient(xp)
                    col = 3 * s[j // 3] + j % 3
                    for r in range(12):
                        row = 3 * s[r // 3] + r % 3
                        H[row, col] = H[row, col] + lam[i] * (gp[r] - g0[r]) / step
        for r in range(18):
            for c in range(r + 1, 18):
                avg = wp.float64(0.5) * (H[r, c] + H[c, r])
                H[r, c] = avg
                H[c, r] = avg
        bending_hessian[b, t] = H


def build_stencils(triangles: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Per triangle (a, b, c): its vertices then the far vertex across each edge i (opposite vertex i),
    (T, 6); and whether that neighbour exists, (T, 3). A missing far vertex repeats vertex i."""
    far = {}
    for tri in triangles:
        for k in range(3):
            far[(int(tri[k]), int(tri[(k + 1) % 3]))] = int(tri[(k + 2) % 3])
    stencils = np.zeros((len(triangles), 6), dtype=np.int32)
    present = np.zeros((len(triangles), 3), dtype=np.int32)
    for n, tri in enumerate(triangles):
        stencils[n, :3] = tri
        for i in range(3):
            # Edge i runs tri[i+1] -> tri[i+2] in this triangle; the neighbour holds it reversed.
            other = far.get((int(tri[(i + 2) % 3]), int(tri[(i + 1) % 3])))
            stencils[n, 3 + i] = tri[i] if other is None else other
            present[n, i] = other is not None
    return stencils, present


def stencil_rest_state(
    vertices: np.ndarray, stencils: np.ndarray, present: np.ndarray
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Rest dihedral angles (T,3) rad, rest areas (T,) m^2 and couplings M (T,3,3) 1/m^2 of each triangle."""
    tri = vertices[stencils[:, :3]]
    angles = np.zeros((len(stencils), 3))
    normals = np.zeros((len(stencils), 3, 3))
    lengths = np.zeros((len(stencils), 3))
    face = np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0])
    area = 0.5 * np.linalg.norm(face, axis=1)
    unit = face / (2.0 * area[:, None])
    for i in range(3):
        x0, x1, x2 = tri[:, (i + 1) % 3], tri[:, (i + 2) % 3], tri[:, i]
        x3 = vertices[stencils[:, 3 + i]]
        e = x1 - x0
        lengths[:, i] = np.linalg.norm(e, axis=1)
        na, nb = np.cross(e, x2 - x0), np.cross(x3 - x1, e)
        s = np.einsum("ij,ij->i", np.cross(na, nb), e) / lengths[:, i]
        angles[:, i] = np.where(present[:, i] != 0, np.arctan2(s, np.einsum("ij,ij->i", na, nb)), 0.0)
        normals[:, i] = np.cross(e / lengths[:, i, None], unit)  # in-plane, pointing away from vertex i
    c = np.where(present != 0, lengths / (2.0 * area[:, None]), 0.0)
    dots = np.einsum("tid,tjd->tij", normals, normals)
    coupling = c[:, :, None] * c[:, None, :] * (POISSON + (1.0 - POISSON) * dots**2)
    return angles, area, coupling
