"""Warp kernels of the batched Newton solver (`fe.batched`): reductions, residuals, vector updates and the
friction lagging, all over a leading batch axis b (positions m, forces N, pressures Pa)."""

import warp as wp

wp.set_module_options({"enable_backward": False})  # no adjoint kernels: nothing differentiates them


@wp.func
def _add_entry(a: wp.array2d(dtype=wp.float64), b: int, i: int, out: wp.array2d(dtype=wp.float64), column: int):
    if i < a.shape[1]:
        wp.atomic_add(out, b, column, a[b, i])


@wp.kernel
def totals(
    volume: wp.array2d(dtype=wp.float64),
    membrane_energy: wp.array2d(dtype=wp.float64),
    bending_energy: wp.array2d(dtype=wp.float64),
    core_energy: wp.array2d(dtype=wp.float64),
    indenter_energy: wp.array2d(dtype=wp.float64),
    indenter_face_energy: wp.array2d(dtype=wp.float64),
    out: wp.array2d(dtype=wp.float64),
    active: wp.array(dtype=wp.int32),
):
    """out[b] += (enclosed volume, total energy) of the active systems b: one thread per element index i
    adds entry i of every per-element array long enough to have one (launch over the longest)."""
    b, i = wp.tid()
    if active[b] == 0:
        return
    _add_entry(volume, b, i, out, 0)
    _add_entry(membrane_energy, b, i, out, 1)
    _add_entry(bending_energy, b, i, out, 1)
    _add_entry(core_energy, b, i, out, 1)
    _add_entry(indenter_energy, b, i, out, 1)
    _add_entry(indenter_face_energy, b, i, out, 1)


@wp.kernel
def two_dots(
    x: wp.array2d(dtype=wp.vec3d),
    a: wp.array2d(dtype=wp.vec3d),
    b: wp.array2d(dtype=wp.vec3d),
    out: wp.array2d(dtype=wp.float64),
):
    """out[s] += (x[s] . a[s], x[s] . b[s]) per system s over its nodes."""
    s, v = wp.tid()
    wp.atomic_add(out, s, 0, wp.dot(x[s, v], a[s, v]))
    wp.atomic_add(out, s, 1, wp.dot(x[s, v], b[s, v]))


@wp.kernel
def free_residual(
    gradients: wp.array3d(dtype=wp.vec3d),
    volume_gradient: wp.array2d(dtype=wp.vec3d),
    pressure: wp.array(dtype=wp.float64),
    free: wp.array(dtype=wp.vec3d),
    residual: wp.array2d(dtype=wp.vec3d),
    gradient: wp.array2d(dtype=wp.vec3d),
    bvec: wp.array2d(dtype=wp.vec3d),
    stats: wp.array2d(dtype=wp.float64),
    active: wp.array(dtype=wp.int32),
):
    """Free-DOF residual r = grad E - p grad V, grad E and b = grad V; stats[b] = (max|r|, sum r^2, max load)."""
    b, v = wp.tid()
    if active[b] == 0:  # a system left out of this evaluation: nothing is written for it
        return
    f = free[v]
    g = gradients[0, b, v] + gradients[1, b, v] + gradients[2, b, v]
    gv = volume_gradient[b, v]
    r = wp.cw_mul(g - pressure[b] * gv, f)
    residual[b, v] = r
    gradient[b, v] = wp.cw_mul(g, f)
    bvec[b, v] = wp.cw_mul(gv, f)
    load = wp.max(wp.max(wp.abs(wp.cw_mul(g, f))), wp.max(wp.abs(wp.cw_mul(gv, f) * pressure[b])))
    wp.atomic_max(stats, b, 0, wp.max(wp.abs(r)))
    wp.atomic_add(stats, b, 1, wp.dot(r, r))
    wp.atomic_max(stats, b, 2, load)


@wp.kernel
def axpy(
    x: wp.array2d(dtype=wp.vec3d),
    step: wp.array(dtype=wp.float64),
    d: wp.array2d(dtype=wp.vec3d),
    out: wp.array2d(dtype=wp.vec3d),
):
    """out[b] = x[b] + step[b] d[b]; rows with step 0 are copied from x (whatever d holds, NaN included)."""
    b, v = wp.tid()
    if step[b] == wp.float64(0.0):
        out[b, v] = x[b, v]
    else:
        out[b, v] = x[b, v] + step[b] * d[b, v]


@wp.kernel
def newton_rhs(residual: wp.array2d(dtype=wp.vec3d), bvec: wp.array2d(dtype=wp.vec3d), rhs: wp.array2d(dtype=wp.vec3d)):
    """Columns 0..B-1: -r; B..2B-1: b."""
    b, v = wp.tid()
    n = residual.shape[0]
    rhs[b, v] = -residual[b, v]
    rhs[n + b, v] = bvec[b, v]


@wp.kernel
def combine(
    u: wp.array2d(dtype=wp.vec3d),
    dp: wp.array(dtype=wp.float64),
    active: wp.array(dtype=wp.int32),
    dq: wp.array2d(dtype=wp.vec3d),
):
    """dq = u1 + dp u2 with u1 = u[b], u2 = u[B + b], for the active systems."""
    b, v = wp.tid()
    if active[b] != 0:
        dq[b, v] = u[b, v] + dp[b] * u[dq.shape[0] + b, v]


@wp.kernel
def lag_apply(
    changed: wp.array(dtype=wp.int32),
    candidate: wp.array2d(dtype=wp.float64),
    candidate_normal: wp.array2d(dtype=wp.vec3d),
    lagged_force: wp.array2d(dtype=wp.float64),
    lagged_normal: wp.array2d(dtype=wp.vec3d),
):
    b, v = wp.tid()
    if changed[b] != 0:
        lagged_force[b, v] = candidate[b, v]
        lagged_normal[b, v] = candidate_normal[b, v]
