"""Contact energies in warp: rigid core (frictionless, per skin vertex) and rigid indenter (normal contact
integrated over the skin triangles, friction per vertex).

Normal contact is the through-thickness compression of the skin. The shell's mid-surface carries half the
thickness, h (m), on each side (the indenter's side: `InflatedSkin.indenter_offset`, default t/2; the core's:
`InflatedSkin.core_offset`); with d (m) the signed distance of a mid-surface point to the body and
g = d - h its gap, a closing gap squeezes that half-layer to the stretch lam = d / h = 1 + g / h. The layer is
incompressible Neo-Hookean, compressed with free lateral expansion (Ogden, Non-linear Elastic Deformations,
1984, sec. 7.2: uniaxial nominal stress mu (lam - lam^-2)), so a reference area A (m^2) stores
E_n = A h (mu / 2)(lam^2 + 2 / lam - 3) for lam < 1 and nothing above: C1 at lam = 1 (the stress
vanishes there), stiffening as lam^-3 towards lam = 0. Below `ContactSettings.min_stretch` the energy goes on
as its second-order Taylor expansion there (finite and convex for any gap, so Newton never meets a
non-finite energy), and `fe.batched_stepper.BatchedStepper` refuses any converged state that reaches it.
h = 0 (a zero-thickness membrane, e.g. `fe.dome`) keeps the one-sided quadratic penalty kappa A g^2 / 2
(kappa in Pa/m). mu (Pa) is each system's long-term modulus (1 - g) mu_NH (`layer_mu`): the layer keeps no
viscoelastic branch of its own, so a relaxing skin ends exactly as the long-term elastic one.

The core's contact is lumped per skin vertex (A = the vertex's lumped reference area, 3x3 Hessian blocks).
The indenter's is integrated over each skin triangle f (`indenter_surface_kernel`): E = sum_f sum_q
psi(g(x_q); w_q A_f), x_q = sum_i N_i(q) x_i at the quadrature points of `fe.surface_quadrature` (reference-area
weights w_q A_f, barycentric shape functions N_i), so an indenter smaller than a triangle meets the skin
between its vertices and the force grows smoothly as the contact edge crosses a triangle, not in a jump per
ring of nodes; its Hessian is a 9x9 block per triangle (the pattern the membrane already has).

Friction is lagged Coulomb with IPC smoothing, per skin vertex: E_f = mu_fr lambda f0(|u_T|), lambda the
normal force (N) and n the normal of the last lagging pass (the surface contact's quadrature forces lumped to
the vertex with the weights N_i: lambda their magnitude, n their direction, `lag_candidates`), u_T the slip
over the increment projected on the plane normal to n, and f0 the C1 smoothing of |u| over the slip length
eps (m). The indenter moves rigidly from pose (R0, t0) to (R, t); the slip of a skin vertex at p relative to
the indenter material point it sticks to is u = R0 R^T (p - t) + t0 - x_start, i.e. its motion seen from the
indenter's body frame, x_start being that point at the start pose: the vertex's stick anchor, carried from
increment to increment by a return mapping (`fe.batched_stepper.BatchedStepper._stick`), or its last equilibrium
where it has none. Its SDF is evaluated in its own frame (tip at the origin, body along +z) and covers
the whole body, head and shank (`fe.indenter_sdf.body_sdf_and_grad`), so the skin cannot slip past the
head's back.
"""

import warp as wp

from fe.indenter_sdf import body_sdf_and_grad
from fe.wptypes import add_block, mat99d

wp.set_module_options({"enable_backward": False})  # no adjoint kernels: nothing differentiates them

_TINY = wp.constant(wp.float64(1e-30))
_UNBOUNDED = wp.constant(wp.float32(1.0e6))  # m: a search radius beyond any mesh


@wp.func
def layer_response(
    g: wp.float64, h: wp.float64, mu: wp.float64, area: wp.float64, kappa: wp.float64, min_stretch: wp.float64
) -> wp.vec3d:
    """(energy J, dE/dg N, d2E/dg2 N/m) of one vertex's normal contact at gap g (m, negative when closing) for
    a half-layer of thickness h (m) and shear modulus mu (Pa), reference area `area` (m^2): the Neo-Hookean
    layer of the module docstring (continued quadratically below `min_stretch`), or for h = 0 the penalty
    kappa (Pa/m). -dE/dg >= 0 is the normal force."""
    zero = wp.float64(0.0)
    one = wp.float64(1.0)
    if g >= zero:
        return wp.vec3d(zero, zero, zero)
    if h <= zero:
        ka = kappa * area
        return wp.vec3d(wp.float64(0.5) * ka * g * g, ka * g, ka)
    lam = one + g / h
    c = wp.max(lam, min_stretch)
    s = (c - one) * h  # the gap at c, written so that nothing cancels near lam = 1
    e = wp.float64(0.5) * area * mu * s * s * (c + wp.float64(2.0)) / (h * c)
    f1 = area * mu * (s / h) * (c * c + c + one) / (c * c)
    f2 = area * mu * (one + wp.float64(2.0) / (c * c * c)) / h
    if lam < c:  # past the floor: the Taylor expansion at c
        dg = g - s
        e += f1 * dg + wp.float64(0.5) * f2 * dg * dg
        f1 += f2 * dg
    return wp.vec3d(e, f1, f2)


@wp.func
def closest_point_on_triangle(p: wp.vec3d, a: wp.vec3d, b: wp.vec3d, c: wp.vec3d) -> wp.vec3d:
    """Closest point (m) to p on triangle abc, in double precision (Ericson's region test)."""
    ab = b - a
    ac = c - a
    ap = p - a
    d1 = wp.dot(ab, ap)
    d2 = wp.dot(ac, ap)
    zero = wp.float64(0.0)
    if d1 <= zero and d2 <= zero:
        return a
    bp = p - b
    d3 = wp.dot(ab, bp)
    d4 = wp.dot(ac, bp)
    if d3 >= zero and d4 <= d3:
        return b
    vc = d1 * d4 - d3 * d2
    if vc <= zero and d1 >= zero and d3 <= zero:
        return a + ab * (d1 / (d1 - d3))
    cp = p - c
    d5 = wp.dot(ab, cp)
    d6 = wp.dot(ac, cp)
    if d6 >= zero and d5 <= d6:
        return c
    vb = d5 * d2 - d1 * d6
    if vb <= zero and d2 >= zero and d6 <= zero:
        return a + ac * (d2 / (d2 - d6))
    va = d3 * d6 - d5 * d4
    if va <= zero and (d4 - d3) >= zero and (d5 - d6) >= zero:
        return b + (c - b) * ((d4 - d3) / ((d4 - d3) + (d5 - d6)))
    denom = wp.float64(1.0) / (va + vb + vc)
    return a + ab * (vb * denom) + ac * (vc * denom)


@wp.func
def core_distance(
    core: wp.uint64,
    core_vertices: wp.array(dtype=wp.vec3d),
    core_triangles: wp.array(dtype=wp.vec3i),
    p: wp.vec3d,
    max_dist: wp.float32,
) -> wp.vec4d:
    """(signed distance m, unit gradient) of p to the core mesh: the float32 BVH search picks a face, and the
    distance is the float64 one to the nearest of the faces within that face's distance (over a nearly flat
    core edge float32 rounding picks either face, 0.2 nm apart: a gap that jumps stalls Newton, issue 17).
    The search first looks within `max_dist` (m), which
    prunes the BVH; a point with no face that close (far outside, or deep inside the core) is searched again
    without a bound, so its distance and side (angle-weighted pseudo-normal sign) are always the true ones."""
    q = wp.mesh_query_point_sign_normal(core, wp.vec3(p), max_dist)
    if not q.result:
        q = wp.mesh_query_point_sign_normal(core, wp.vec3(p), _UNBOUNDED)
    tri = core_triangles[q.face]
    diff = p - closest_point_on_triangle(p, core_vertices[tri[0]], core_vertices[tri[1]], core_vertices[tri[2]])
    dist = wp.length(diff)
    box = wp.vec3(wp.float32(dist) * wp.float32(1.001) + wp.float32(1e-9))
    near = wp.mesh_query_aabb(core, wp.vec3(p) - box, wp.vec3(p) + box)
    k = int(0)  # noqa: UP018 (a warp variable the query writes)
    while wp.mesh_query_aabb_next(near, k):
        tri = core_triangles[k]
        other = p - closest_point_on_triangle(p, core_vertices[tri[0]], core_vertices[tri[1]], core_vertices[tri[2]])
        if wp.length(other) < dist:
            diff, dist = other, wp.length(other)
    if dist < _TINY:
        return wp.vec4d(wp.float64(0.0), wp.float64(0.0), wp.float64(0.0), wp.float64(0.0))
    sign = wp.float64(q.sign)
    n = diff * (sign / dist)
    return wp.vec4d(sign * dist, n[0], n[1], n[2])


@wp.kernel
def core_contact_kernel(
    x: wp.array2d(dtype=wp.vec3d),
    core: wp.uint64,
    core_vertices: wp.array(dtype=wp.vec3d),
    core_triangles: wp.array(dtype=wp.vec3i),
    vertex_area: wp.array(dtype=wp.float64),
    core_offset: wp.float64,
    kappa: wp.float64,
    layer_mu: wp.array(dtype=wp.float64),
    min_stretch: wp.float64,
    core_energy: wp.array2d(dtype=wp.float64),
    core_gradient: wp.array2d(dtype=wp.vec3d),
    core_hessian: wp.array2d(dtype=wp.mat33d),
    core_gap: wp.array2d(dtype=wp.float64),
    queried_at: wp.array2d(dtype=wp.vec3d),
    queried_gap: wp.array2d(dtype=wp.float64),
    active: wp.array(dtype=wp.int32),
):
    """Frictionless contact of skin vertex v with the core mesh: the inner half-layer (thickness `core_offset` m)
    squeezed by the `layer_response` law (modulus layer_mu[b] Pa).

    The closest-face search looks within offset + 1 mm of the core first (a small radius prunes the BVH
    search: half the cost of 5 mm) and, where that finds nothing, without a bound (`core_distance`): a
    vertex deeper inside the core than that gets its true negative gap (squeezed past the floor, so the
    stepper refuses the state) instead of looking far outside. The search is skipped where it cannot find
    contact: the signed distance is 1-Lipschitz, so a vertex outside the core that has moved less than its
    gap at its last search (`queried_at`, `queried_gap`, kept per vertex between evaluations) is still out
    of contact, and its gap is reported as that lower bound (+inf for vertices never searched: the clamped
    ones). A vertex inside keeps a negative `queried_gap`: it is searched at every evaluation.
    The Hessian includes the curvature of the distance field (non-zero where the closest point is on a
    mesh edge or vertex) by central differences of its gradient.
    """
    b, v = wp.tid()
    if active[b] == 0:  # a system left out of this evaluation: nothing is written for it
        return
    p = x[b, v]
    zero = wp.float64(0.0)
    core_energy[b, v] = zero
    core_hessian[b, v] = wp.mat33d()
    bound = queried_gap[b, v] - wp.length(p - queried_at[b, v])
    if bound > zero:
        core_gap[b, v] = bound
        return
    reach = wp.float32(core_offset) + wp.float32(1.0e-3)
    dn = core_distance(core, core_vertices, core_triangles, p, reach)
    g = dn[0] - core_offset
    queried_at[b, v] = p
    queried_gap[b, v] = g  # exact: a bound for the skip only where positive (outside the core)
    core_gap[b, v] = g
    if g >= zero:
        return
    n = wp.vec3d(dn[1], dn[2], dn[3])
    law = layer_response(g, core_offset, layer_mu[b], vertex_area[v], kappa, min_stretch)
    core_energy[b, v] = law[0]
    wp.atomic_add(core_gradient, b, v, n * law[1])
    h = wp.float64(1e-9)
    curv = wp.mat33d()
    for j in range(3):
        dp = wp.vec3d()
        dp[j] = h
        plus = core_distance(core, core_vertices, core_triangles, p + dp, reach)
        minus = core_distance(core, core_vertices, core_triangles, p - dp, reach)
        for i in range(3):
            curv[i, j] = (plus[i + 1] - minus[i + 1]) / (wp.float64(2.0) * h)
    curv = wp.float64(0.5) * (curv + wp.transpose(curv))
    core_hessian[b, v] = law[2] * wp.outer(n, n) + law[1] * curv


@wp.func
def _body_world(kind: int, dims: wp.vec4d, rotation: wp.mat33d, translation: wp.vec3d, p: wp.vec3d) -> wp.vec4d:
    """(signed distance m, unit outward gradient in the world frame) of world point p to the indenter body
    (head and shank, `fe.indenter_sdf.body_sdf_and_grad` in the indenter frame) at pose (rotation, tip)."""
    local = body_sdf_and_grad(kind, dims, wp.transpose(rotation) @ (p - translation))
    n = rotation @ wp.vec3d(local[1], local[2], local[3])
    return wp.vec4d(local[0], n[0], n[1], n[2])


@wp.func
def indenter_gap_and_normal(
    kind: int, dims: wp.vec4d, rotation: wp.mat33d, translation: wp.vec3d, offset: wp.float64, p: wp.vec3d
) -> wp.vec4d:
    """(gap m, unit outward normal in the world frame) of mid-surface point p to the indenter body at pose
    (rotation, tip): `_body_world` minus the half-layer `offset` (m). The one gap rule of the skin vertices,
    the quadrature points and the step guard."""
    r = _body_world(kind, dims, rotation, translation, p)
    return wp.vec4d(r[0] - offset, r[1], r[2], r[3])


@wp.func
def _sdf_curvature_world(
    kind: int, dims: wp.vec4d, rotation: wp.mat33d, translation: wp.vec3d, p: wp.vec3d, n: wp.vec3d
) -> wp.mat33d:
    """Hessian (1/m, world frame, symmetrised) of the indenter SDF (`_body_world`) at p, where its gradient
    is n: forward differences of the analytic gradient over 1e-8 m (truncation ~1e-8 m |d3 SDF|, ~1e-5 of the
    curvature of a 1.75 mm ball; three gradients where central differences take six)."""
    h = wp.float64(1e-8)
    curv = wp.mat33d()
    for j in range(3):
        dp = wp.vec3d()
        dp[j] = h
        r = _body_world(kind, dims, rotation, translation, p + dp)
        curv[j] = (wp.vec3d(r[1], r[2], r[3]) - n) / h  # row j: d n / d p_j, transposed by the symmetrisation
    return wp.float64(0.5) * (curv + wp.transpose(curv))


@wp.func
def _triangle_bound(
    kind: int,
    dims: wp.vec4d,
    rotation: wp.mat33d,
    translation: wp.vec3d,
    offset: wp.float64,
    p0: wp.vec3d,
    p1: wp.vec3d,
    p2: wp.vec3d,
) -> wp.float64:
    """A lower bound (m) of the indenter SDF minus `offset` (m; the half-layer for a gap, 0 for the SDF itself)
    over triangle p0 p1 p2: its value at the centroid minus the centroid's distance to the farthest corner
    (the SDF is 1-Lipschitz). Where positive for the half-layer, no quadrature point of the triangle is in
    contact."""
    centre = (p0 + p1 + p2) / wp.float64(3.0)
    spread = wp.max(wp.length(p0 - centre), wp.max(wp.length(p1 - centre), wp.length(p2 - centre)))
    return _body_world(kind, dims, rotation, translation, centre)[0] - spread - offset


@wp.func
def _at(p0: wp.vec3d, p1: wp.vec3d, p2: wp.vec3d, q: wp.vec4d) -> wp.vec3d:
    """The point (m) of triangle p0 p1 p2 at the barycentric coordinates (q[0], q[1], q[2])."""
    return p0 * q[0] + p1 * q[1] + p2 * q[2]


@wp.kernel
def indenter_surface_kernel(
    x: wp.array2d(dtype=wp.vec3d),
    triangles: wp.array(dtype=wp.vec3i),
    rest_area: wp.array(dtype=wp.float64),
    quadrature: wp.array(dtype=wp.vec4d),
    kind: wp.array(dtype=wp.int32),
    dims: wp.array(dtype=wp.vec4d),
    rotation: wp.array(dtype=wp.mat33d),
    translation: wp.array(dtype=wp.vec3d),
    offset: wp.array(dtype=wp.float64),
    kappa: wp.float64,
    layer_mu: wp.array(dtype=wp.float64),
    min_stretch: wp.float64,
    want_hessian: int,
    indenter_face_energy: wp.array2d(dtype=wp.float64),
    indenter_gradient: wp.array2d(dtype=wp.vec3d),
    membrane_hessian: wp.array2d(dtype=mat99d),
    indenter_face_gap: wp.array2d(dtype=wp.float64),
    indenter_vertex_force: wp.array2d(dtype=wp.vec3d),
    active: wp.array(dtype=wp.int32),
):
    """Normal contact of skin triangle f with the indenter of batch b (the outer half-layer, thickness
    offset[b] m, squeezed by the `layer_response` law), integrated over the triangle: at each quadrature
    point q (barycentric N_i, weight w_q of the reference area A_f) the law of area w_q A_f at the point's
    gap, energy summed per face, gradient N_i psi' n to the nodes (and the force -N_i psi' n to
    `indenter_vertex_force`, for the friction lagging), 9x9 Hessian blocks N_i N_j (psi'' n n^T + psi' d2g/dx2)
    added to the triangle's block in `membrane_hessian` (the membrane's, written before: no block of its own to
    assemble, and nothing written for a triangle out of contact). A face whose SDF lower bound
    (`_triangle_bound`) clears the layer is skipped (its `indenter_face_gap` is that bound); otherwise that is its
    smallest gap (m) over the quadrature points."""
    b, f = wp.tid()
    if active[b] == 0:  # a system left out of this evaluation: nothing is written for it
        return
    tri = triangles[f]
    p0 = x[b, tri[0]]
    p1 = x[b, tri[1]]
    p2 = x[b, tri[2]]
    R = rotation[b]
    t = translation[b]
    shape = kind[b]
    size = dims[b]
    h = offset[b]
    zero = wp.float64(0.0)
    indenter_face_energy[b, f] = zero
    bound = _triangle_bound(shape, size, R, t, h, p0, p1, p2)
    if bound > zero:
        indenter_face_gap[b, f] = bound
        return
    H = mat99d()
    e = zero
    nodal = wp.mat33d()  # row i: the gradient on node i
    least = wp.float64(1.0e30)
    for k in range(quadrature.shape[0]):
        q = quadrature[k]
        p = _at(p0, p1, p2, q)
        gn = indenter_gap_and_normal(shape, size, R, t, h, p)
        g = gn[0]
        least = wp.min(least, g)
        if g < zero:
            n = wp.vec3d(gn[1], gn[2], gn[3])
            law = layer_response(g, h, layer_mu[b], q[3] * rest_area[f], kappa, min_stretch)
            e += law[0]
            nodal += wp.outer(wp.vec3d(q[0], q[1], q[2]), n * law[1])
            if want_hessian != 0:
                K = law[2] * wp.outer(n, n) + law[1] * _sdf_curvature_world(shape, size, R, t, p, n)
                for i in range(3):
                    for j in range(3):
                        H = add_block(H, i, j, q[i] * q[j] * K)
    indenter_face_energy[b, f] = e
    indenter_face_gap[b, f] = least
    if least < zero:
        if want_hessian != 0:
            membrane_hessian[b, f] = membrane_hessian[b, f] + H
        for i in range(3):
            wp.atomic_add(indenter_gradient, b, tri[i], nodal[i])
            wp.atomic_sub(indenter_vertex_force, b, tri[i], nodal[i])


@wp.kernel
def indenter_face_gap_kernel(
    x: wp.array2d(dtype=wp.vec3d),
    triangles: wp.array(dtype=wp.vec3i),
    quadrature: wp.array(dtype=wp.vec4d),
    kind: wp.array(dtype=wp.int32),
    dims: wp.array(dtype=wp.vec4d),
    rotation: wp.array(dtype=wp.mat33d),
    translation: wp.array(dtype=wp.vec3d),
    rotation_start: wp.array(dtype=wp.mat33d),
    translation_start: wp.array(dtype=wp.vec3d),
    offset: wp.array(dtype=wp.float64),
    indenter_face_gap: wp.array2d(dtype=wp.float64),
    indenter_face_moved: wp.array2d(dtype=wp.float64),
):
    """indenter_face_gap[b, f] (m): the smallest gap over the quadrature points of skin triangle f to the
    indenter of batch b at its pose (rotation, translation), as `indenter_surface_kernel` reports it:
    `_triangle_bound` where that is positive. indenter_face_moved[b, f] (m): the largest change of a
    quadrature point's gap (`indenter_gap_and_normal`) on the triangle, fixed at x[b], as the indenter moves
    from pose (rotation_start, translation_start) to (rotation, translation), among the points in contact at
    either pose (0 where the triangle clears the layer at both, `_triangle_bound`)."""
    b, f = wp.tid()
    tri = triangles[f]
    p0 = x[b, tri[0]]
    p1 = x[b, tri[1]]
    p2 = x[b, tri[2]]
    shape = kind[b]
    size = dims[b]
    h = offset[b]
    R = rotation[b]
    t = translation[b]
    R0 = rotation_start[b]
    t0 = translation_start[b]
    zero = wp.float64(0.0)
    bound = _triangle_bound(shape, size, R, t, h, p0, p1, p2)
    least = bound
    largest = zero
    if bound <= zero or _triangle_bound(shape, size, R0, t0, h, p0, p1, p2) <= zero:
        nearest = wp.float64(1.0e30)
        for k in range(quadrature.shape[0]):
            p = _at(p0, p1, p2, quadrature[k])
            now = indenter_gap_and_normal(shape, size, R, t, h, p)[0]
            before = indenter_gap_and_normal(shape, size, R0, t0, h, p)[0]
            nearest = wp.min(nearest, now)
            if now < zero or before < zero:
                largest = wp.max(largest, wp.abs(now - before))
        if bound <= zero:
            least = nearest
    indenter_face_gap[b, f] = least
    indenter_face_moved[b, f] = largest


@wp.kernel
def indenter_friction_kernel(
    x: wp.array2d(dtype=wp.vec3d),
    x_start: wp.array2d(dtype=wp.vec3d),
    kind: wp.array(dtype=wp.int32),
    dims: wp.array(dtype=wp.vec4d),
    rotation: wp.array(dtype=wp.mat33d),
    translation: wp.array(dtype=wp.vec3d),
    rotation_start: wp.array(dtype=wp.mat33d),
    translation_start: wp.array(dtype=wp.vec3d),
    offset: wp.array(dtype=wp.float64),
    friction: wp.array(dtype=wp.float64),
    lagged_force: wp.array2d(dtype=wp.float64),
    lagged_normal: wp.array2d(dtype=wp.vec3d),
    slip_eps: wp.float64,
    want_hessian: int,
    indenter_energy: wp.array2d(dtype=wp.float64),
    indenter_gradient: wp.array2d(dtype=wp.vec3d),
    indenter_hessian: wp.array2d(dtype=wp.mat33d),
    indenter_gap: wp.array2d(dtype=wp.float64),
    indenter_normal: wp.array2d(dtype=wp.vec3d),
    active: wp.array(dtype=wp.int32),
):
    """Lagged smoothed Coulomb friction of skin vertex v with the indenter of batch b (its lagged normal
    force and normal: the surface contact's forces lumped to the vertex, `lag_candidates`), and the
    vertex's own gap (m; SDF of kind[b] with dims[b] of `fe.indenter_sdf` minus offset[b]) and unit
    normal."""
    b, v = wp.tid()
    if active[b] == 0:  # a system left out of this evaluation: nothing is written for it
        return
    p = x[b, v]
    R = rotation[b]
    t = translation[b]
    zero = wp.float64(0.0)
    gn = indenter_gap_and_normal(kind[b], dims[b], R, t, offset[b], p)
    indenter_gap[b, v] = gn[0]
    indenter_normal[b, v] = wp.vec3d(gn[1], gn[2], gn[3])
    e = zero
    grad = wp.vec3d()
    H = wp.mat33d()
    lam = lagged_force[b, v] * friction[b]
    if lam > zero:
        nl = lagged_normal[b, v]
        A = rotation_start[b] @ wp.transpose(R)
        u = A @ (p - t) + translation_start[b] - x_start[b, v]
        ut = u - nl * wp.dot(u, nl)
        y = wp.length(ut)
        eps = slip_eps
        one = wp.float64(1.0)
        cubed = y * y * y  # f0'' - f0' / y = -y / cubed on the slip's direction
        if y < eps:
            e = lam * (-y * y * y / (wp.float64(3.0) * eps * eps) + y * y / eps + eps / wp.float64(3.0))
            f1_over_y = wp.float64(2.0) / eps - y / (eps * eps)
            cubed = eps * eps * y
        else:
            e = lam * y
            f1_over_y = one / y
        grad = wp.transpose(A) @ (ut * (lam * f1_over_y))
        if want_hessian != 0:
            proj = wp.identity(n=3, dtype=wp.float64) - wp.outer(nl, nl)
            Hf = proj * f1_over_y
            if y > _TINY:
                Hf -= wp.outer(ut, ut) / cubed
            H = lam * (wp.transpose(A) @ Hf @ A)
    indenter_energy[b, v] = e
    wp.atomic_add(indenter_gradient, b, v, grad)
    indenter_hessian[b, v] = H


@wp.kernel
def indenter_gap_kernel(
    x: wp.array2d(dtype=wp.vec3d),
    kind: wp.array(dtype=wp.int32),
    dims: wp.array(dtype=wp.vec4d),
    rotation: wp.array(dtype=wp.mat33d),
    translation: wp.array(dtype=wp.vec3d),
    offset: wp.array(dtype=wp.float64),
    indenter_gap: wp.array2d(dtype=wp.float64),
    indenter_normal: wp.array2d(dtype=wp.vec3d),
):
    """Gap (m) of skin vertex v to the indenter of batch b (kind[b], dims[b]; SDF minus the mid-surface
    offset), unit normal."""
    b, v = wp.tid()
    gn = indenter_gap_and_normal(kind[b], dims[b], rotation[b], translation[b], offset[b], x[b, v])
    indenter_gap[b, v] = gn[0]
    indenter_normal[b, v] = wp.vec3d(gn[1], gn[2], gn[3])


@wp.kernel
def lag_candidates(
    vertex_force: wp.array2d(dtype=wp.vec3d),
    lagged_force: wp.array2d(dtype=wp.float64),
    candidate: wp.array2d(dtype=wp.float64),
    candidate_normal: wp.array2d(dtype=wp.vec3d),
    stats: wp.array2d(dtype=wp.float64),
):
    """Normal force (N) of each vertex on the indenter of batch b, the magnitude of the surface contact's
    forces lumped to it (`indenter_surface_kernel`'s `indenter_vertex_force`), and its direction (unit; 0 where no
    force); stats[b] = (largest change from the lagged force, largest force)."""
    b, v = wp.tid()
    force = vertex_force[b, v]
    f = wp.length(force)
    candidate[b, v] = f
    if f > _TINY:
        candidate_normal[b, v] = force / f
    else:
        candidate_normal[b, v] = wp.vec3d()
    wp.atomic_max(stats, b, 0, wp.abs(f - lagged_force[b, v]))
    wp.atomic_max(stats, b, 1, f)


_SPLIT = wp.constant(8)  # sub-triangles per edge screened by their own bound before sampling


@wp.func
def _triangle_clearance(
    kind: int,
    dims: wp.vec4d,
    rotation: wp.mat33d,
    translation: wp.vec3d,
    p0: wp.vec3d,
    p1: wp.vec3d,
    p2: wp.vec3d,
    parts: int,
    floor: wp.float64,
) -> wp.float64:
    """`_triangle_bound` where that is at least `floor` (m); else the smallest indenter SDF over the nodes
    of the triangle's regular subdivision into parts^2 pieces."""
    bound = _triangle_bound(kind, dims, rotation, translation, wp.float64(0.0), p0, p1, p2)
    if bound >= floor:
        return bound
    least = wp.float64(1.0e30)
    scale = wp.float64(1.0) / wp.float64(parts)
    for i in range(parts + 1):
        for j in range(parts + 1 - i):
            u = wp.float64(i) * scale
            v = wp.float64(j) * scale
            q = p0 * (wp.float64(1.0) - u - v) + p1 * u + p2 * v
            least = wp.min(least, _body_world(kind, dims, rotation, translation, q)[0])
    return least


@wp.func
def _split_clearance(
    kind: int,
    dims: wp.vec4d,
    rotation: wp.mat33d,
    tip: wp.vec3d,
    p0: wp.vec3d,
    e1: wp.vec3d,
    e2: wp.vec3d,
    parts: int,
    floor: wp.float64,
) -> wp.float64:
    """The indenter SDF's minimum (m) over triangle (p0, p0 + e1, p0 + e2) to the sampling of
    `_triangle_clearance` with nodes `parts` to an edge where below `floor` (m): the whole triangle's bound
    where that is at least `floor`, else its 8^2 (at most) similar pieces each bounded or sampled."""
    whole = _triangle_bound(kind, dims, rotation, tip, wp.float64(0.0), p0, p0 + e1, p0 + e2)
    if whole >= floor:
        return whole
    k = wp.min(parts, _SPLIT)
    n = (parts + k - 1) / k
    d1 = e1 / wp.float64(k)
    d2 = e2 / wp.float64(k)
    least = wp.float64(1.0e30)
    for i in range(k):
        for j in range(k - i):
            a = p0 + d1 * wp.float64(i) + d2 * wp.float64(j)
            up = _triangle_clearance(kind, dims, rotation, tip, a, a + d1, a + d2, n, floor)
            least = wp.min(least, up)
            if i + j < k - 1:
                down = _triangle_clearance(kind, dims, rotation, tip, a + d1, a + d2, a + d1 + d2, n, floor)
                least = wp.min(least, down)
    return least


@wp.kernel
def indenter_clearance_kernel(
    core_vertices: wp.array(dtype=wp.vec3d),
    core_triangles: wp.array(dtype=wp.vec3i),
    parts: wp.array(dtype=wp.int32),
    floor: wp.array(dtype=wp.float64),
    kind: wp.array(dtype=wp.int32),
    dims: wp.array(dtype=wp.vec4d),
    rotation: wp.array(dtype=wp.mat33d),
    translation: wp.array(dtype=wp.vec3d),
    active: wp.array(dtype=wp.int32),
    clearance: wp.array(dtype=wp.float64),
):
    """clearance[b] = min over core triangles t of the indenter body's SDF there (m), to the sampling of
    `_split_clearance` with nodes parts[t] to an edge (clearance must start at +inf; systems with
    active[b] = 0 are left as they are)."""
    b, t = wp.tid()
    if active[b] == 0:
        return
    tri = core_triangles[t]
    p0 = core_vertices[tri[0]]
    e1 = core_vertices[tri[1]] - p0
    e2 = core_vertices[tri[2]] - p0
    least = _split_clearance(kind[b], dims[b], rotation[b], translation[b], p0, e1, e2, parts[t], floor[b])
    wp.atomic_min(clearance, b, least)


@wp.kernel
def indenter_skin_clearance_kernel(
    x: wp.array2d(dtype=wp.vec3d),
    triangles: wp.array(dtype=wp.vec3i),
    spacing: wp.array(dtype=wp.float64),
    floor: wp.array(dtype=wp.float64),
    kind: wp.array(dtype=wp.int32),
    dims: wp.array(dtype=wp.vec4d),
    rotation: wp.array(dtype=wp.mat33d),
    translation: wp.array(dtype=wp.vec3d),
    active: wp.array(dtype=wp.int32),
    clearance: wp.array2d(dtype=wp.float64),
):
    """clearance[b, f] = min over skin mid-surface triangle f at positions x[b] of the indenter body's SDF
    (m), to the sampling of `_split_clearance` with nodes at most spacing[b] m apart along the triangle's
    longest edge where below floor[b] m (systems with active[b] = 0 are left as they are)."""
    b, f = wp.tid()
    if active[b] == 0:
        return
    tri = triangles[f]
    p0 = x[b, tri[0]]
    e1 = x[b, tri[1]] - p0
    e2 = x[b, tri[2]] - p0
    longest = wp.max(wp.length(e1), wp.max(wp.length(e2), wp.length(e2 - e1)))
    parts = wp.max(int(wp.ceil(longest / spacing[b])), 1)
    clearance[b, f] = _split_clearance(kind[b], dims[b], rotation[b], translation[b], p0, e1, e2, parts, floor[b])
