"""Volume enclosed by an oriented triangle surface (and its derivatives), in warp.

V = sum over triangles of (x0 - o) . ((x1 - o) x (x2 - o)) / 6 for a fixed origin o. For a skin whose
boundary is anchored, the closing part of the cavity wall (core, anchors) never moves, so changes of V
are exactly changes of the fluid volume. Lengths in metres, volume in m^3.
"""

import warp as wp

from fe.wptypes import add_block, mat99d

wp.set_module_options({"enable_backward": False})  # no adjoint kernels: nothing differentiates them


@wp.func
def _skew(v: wp.vec3d) -> wp.mat33d:
    zero = wp.float64(0.0)
    return wp.mat33d(zero, -v[2], v[1], v[2], zero, -v[0], -v[1], v[0], zero)


@wp.kernel
def volume_kernel(
    x: wp.array2d(dtype=wp.vec3d),
    triangles: wp.array(dtype=wp.vec3i),
    origin: wp.vec3d,
    want_hessian: int,
    volume: wp.array2d(dtype=wp.float64),
    volume_gradient: wp.array2d(dtype=wp.vec3d),
    volume_hessian: wp.array2d(dtype=mat99d),
    active: wp.array(dtype=wp.int32),
):
    """Per (batch, triangle): signed tetra volume to `origin`, its node gradients and 9x9 Hessian."""
    b, t = wp.tid()
    if active[b] == 0:  # a system left out of this evaluation: nothing is written for it
        return
    tri = triangles[t]
    x0 = x[b, tri[0]] - origin
    x1 = x[b, tri[1]] - origin
    x2 = x[b, tri[2]] - origin
    xs = wp.matrix_from_rows(x0, x1, x2)
    sixth = wp.float64(1.0) / wp.float64(6.0)
    volume[b, t] = wp.dot(x0, wp.cross(x1, x2)) * sixth
    for i in range(3):  # node i's gradient x_j x x_k, (i, j, k) cyclic
        wp.atomic_add(volume_gradient, b, tri[i], wp.cross(xs[(i + 1) % 3], xs[(i + 2) % 3]) * sixth)
    if want_hessian != 0:
        H = mat99d()
        # d/dx_j of (x_j x x_k) = -[x_k]x, d/dx_k of (x_j x x_k) = [x_j]x, (i, j, k) cyclic.
        for i in range(3):
            H = add_block(H, i, (i + 1) % 3, -_skew(xs[(i + 2) % 3]) * sixth)
            H = add_block(H, i, (i + 2) % 3, _skew(xs[(i + 1) % 3]) * sixth)
        volume_hessian[b, t] = H
