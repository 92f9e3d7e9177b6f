"""Analytic indenter signed-distance functions for warp kernels (twins of ``assets.indenters``).

``indenter_sdf_and_grad(kind, dims, p)`` (the head) and ``body_sdf_and_grad(kind, dims, p)`` (head and
shank) take the integer kind code and the four dims of ``assets.indenters.Indenter`` (metres, meaning per
kind in its docstring) and a point p in the indenter frame (tip at the origin, body in z >= 0, shank along
+z, pressing along -z), metres. They return the signed distance (negative inside), m, and its unit outward
gradient, as (distance, gradient x, y, z).

Both are overloaded: (int, wp.vec4, wp.vec3) -> wp.vec4 (float32), and (int, wp.vec4d, wp.vec3d) ->
wp.vec4d (float64). The float64 overload agrees with the numpy twin to rounding (~1e-16 m); the float32
one to float32 rounding (~1e-9 m at centimetre coordinates). An unknown kind returns +1 m (no contact)
and gradient (0, 0, -1).

Gradients are continuous within the skin's reach except where the distance itself has a kink, at points
at least one edge radius (1 mm) inside the head, on a sphere's centre, a cylinder's axis, the ring's axis
(3.6 mm from the ring) or, for the texture, on the medial surfaces of the bumps' concave feet (from
TEXTURE_FILLET, 1 mm, out: beyond the skin's contact layer); there a sensible one-sided choice is returned.
"""

import numpy as np
import warp as wp

from assets.indenters import (
    HASH_MODULUS,
    HASH_MULTIPLIER,
    HASH_OFFSET,
    KIND_BOX,
    KIND_CYLINDER_FLAT,
    KIND_CYLINDER_SIDE,
    KIND_SPHERE,
    KIND_TEXTURE,
    KIND_TORUS,
    SHANK_POSTS,
    SHANK_RADIUS,
    TEXTURE_FILLET,
    TEXTURE_RIM,
    head_extent,
)

_KS = wp.constant(KIND_SPHERE)
_KCF = wp.constant(KIND_CYLINDER_FLAT)
_KCS = wp.constant(KIND_CYLINDER_SIDE)
_KB = wp.constant(KIND_BOX)
_KT = wp.constant(KIND_TORUS)
_KX = wp.constant(KIND_TEXTURE)
_HM = wp.constant(wp.int64(HASH_MODULUS))
_HA = wp.constant(wp.int64(HASH_MULTIPLIER))
_HO = wp.constant(wp.int64(HASH_OFFSET))
_SHANK = wp.constant(wp.types.matrix(shape=(len(SHANK_POSTS), 6), dtype=wp.float64)(*sum(SHANK_POSTS, ())))
"""`assets.indenters.SHANK_POSTS`, a row per kind code."""
_N_SHANK = wp.constant(len(SHANK_POSTS))


def _build(real, vec2, vec3, vec4, indenter_sdf_and_grad=None, body_sdf_and_grad=None):
    """Define the warp functions for one float type; passing the previous functions adds overloads."""
    fillet = real(TEXTURE_FILLET)
    rim = real(TEXTURE_RIM)

    @wp.func
    def sgn(u: real) -> real:
        if u < real(0.0):
            return real(-1.0)
        return real(1.0)

    @wp.func
    def rounded_rect(qx: real, qy: real, r: real) -> vec3:
        # (distance, d/dqx, d/dqy) of a 2D rounded rectangle from folded coordinates q = |p| - (half - r)
        mx = wp.max(qx, real(0.0))
        my = wp.max(qy, real(0.0))
        length = wp.sqrt(mx * mx + my * my)
        if length > real(0.0):
            return vec3(length - r, mx / length, my / length)
        if qx > qy:
            return vec3(qx - r, real(1.0), real(0.0))
        return vec3(qy - r, real(0.0), real(1.0))

    @wp.func
    def radial(x: real, y: real) -> vec3:
        # (rho, unit x, unit y); direction (1, 0) on the axis
        rho = wp.sqrt(x * x + y * y)
        if rho > real(0.0):
            return vec3(rho, x / rho, y / rho)
        return vec3(rho, real(1.0), real(0.0))

    @wp.func
    def rounded_box(q: vec3, s: vec3, r: real) -> vec4:
        # (distance, gradient) of a 3D rounded box from folded coordinates q and fold signs s
        m = vec3(wp.max(q[0], real(0.0)), wp.max(q[1], real(0.0)), wp.max(q[2], real(0.0)))
        length = wp.length(m)
        if length > real(0.0):
            return vec4(length - r, s[0] * m[0] / length, s[1] * m[1] / length, s[2] * m[2] / length)
        if q[0] >= q[1] and q[0] >= q[2]:
            return vec4(q[0] - r, s[0], real(0.0), real(0.0))
        if q[1] >= q[2]:
            return vec4(q[1] - r, real(0.0), s[1], real(0.0))
        return vec4(q[2] - r, real(0.0), real(0.0), s[2])

    @wp.func
    def imod(x: wp.int64) -> wp.int64:
        # x mod HASH_MODULUS for x >= 0, written without % (which has no adjoint for int64)
        return x - (x / _HM) * _HM

    @wp.func
    def jitter(i: int, j: int) -> vec2:
        # MINSTD hash of lattice cell (i, j) -> two numbers in [-1, 1); zero for the centre cell
        if i == 0 and j == 0:
            return vec2(real(0.0), real(0.0))
        seed = (wp.int64(i) + _HO) * wp.int64(7919) + (wp.int64(j) + _HO) * wp.int64(104729)
        h1 = imod(seed * _HA)
        h2 = imod(h1 * _HA)
        one = real(1.0)
        return vec2(
            real(2.0) * (real(wp.float64(h1) / wp.float64(_HM))) - one,
            real(2.0) * (real(wp.float64(h2) / wp.float64(_HM))) - one,
        )

    @wp.func
    def bump_profile(rho: real, z: real, rb: real) -> vec3:
        # (distance, d/drho, d/dz) of one filleted hemispherical bump on the plane z = rb
        rho_f = wp.sqrt(rb * rb + real(2.0) * rb * fillet)
        nx = -fillet / (rb + fillet)
        nz = -rho_f / (rb + fillet)
        vx = rho
        vz = z - rb
        below = vx * nx + vz * nz >= real(0.0)
        best = real(1.0e30)
        out = vec3(best, real(0.0), real(-1.0))
        if rho >= rho_f:
            best = rb - z
            out = vec3(best, real(0.0), real(-1.0))
        vlen = wp.sqrt(vx * vx + vz * vz)
        d_s = vlen - rb
        if below and wp.abs(d_s) < wp.abs(best):
            best = d_s
            if vlen > real(0.0):
                out = vec3(d_s, vx / vlen, vz / vlen)
            else:
                out = vec3(d_s, real(0.0), real(-1.0))
        wx = rho - rho_f
        wz = z - (rb - fillet)
        wlen = wp.sqrt(wx * wx + wz * wz)
        d_f = fillet - wlen
        if (not below) and rho <= rho_f and wp.abs(d_f) < wp.abs(best):
            if wlen > real(0.0):
                out = vec3(d_f, -wx / wlen, -wz / wlen)
            else:
                out = vec3(d_f, real(0.0), real(-1.0))
        return out

    @wp.func
    def texture(dims: vec4, p: vec3) -> vec4:
        rb = dims[0]
        a = dims[1]
        jit = dims[2]
        half = dims[3]
        n = int(wp.floor(half / a - real(0.5)))
        d_bump = rb - p[2]
        g_bump = vec3(real(0.0), real(0.0), real(-1.0))
        i0 = int(wp.round(p[0] / a))
        j0 = int(wp.round(p[1] / a))
        for di in range(-1, 2):
            for dj in range(-1, 2):
                i = i0 + di
                j = j0 + dj
                if wp.abs(i) <= n and wp.abs(j) <= n:
                    jj = jitter(i, j)
                    rad = radial(p[0] - (real(i) * a + jit * jj[0]), p[1] - (real(j) * a + jit * jj[1]))
                    prof = bump_profile(rad[0], p[2], rb)
                    if prof[0] < d_bump:
                        d_bump = prof[0]
                        g_bump = vec3(prof[1] * rad[1], prof[1] * rad[2], prof[2])
        q = vec3(wp.abs(p[0]) - (half - rim), wp.abs(p[1]) - (half - rim), d_bump + rim)
        w = rounded_box(q, vec3(real(1.0), real(1.0), real(1.0)), rim)
        g = w[3] * g_bump + vec3(w[1] * sgn(p[0]), w[2] * sgn(p[1]), real(0.0))
        return vec4(w[0], g[0], g[1], g[2])

    @wp.func
    def indenter_sdf_and_grad(kind: int, dims: vec4, p: vec3) -> vec4:  # noqa: F811
        """(signed distance, unit outward gradient) of indenter ``kind`` at p (indenter frame), m."""
        a = dims[0]
        b = dims[1]
        c = dims[2]
        e = dims[3]
        if kind == _KS:
            v = p - vec3(real(0.0), real(0.0), a)
            length = wp.length(v)
            if length > real(0.0):
                return vec4(length - a, v[0] / length, v[1] / length, v[2] / length)
            return vec4(-a, real(0.0), real(0.0), real(-1.0))
        if kind == _KCF:
            rad = radial(p[0], p[1])
            w = p[2] - real(0.5) * b
            r2 = rounded_rect(rad[0] - (a - c), wp.abs(w) - (real(0.5) * b - c), c)
            return vec4(r2[0], r2[1] * rad[1], r2[1] * rad[2], r2[2] * sgn(w))
        if kind == _KCS:
            zc = p[2] - a
            rad = radial(-zc, p[1])
            r2 = rounded_rect(rad[0] - (a - c), wp.abs(p[0]) - (real(0.5) * b - c), c)
            return vec4(r2[0], r2[2] * sgn(p[0]), r2[1] * rad[2], -r2[1] * rad[1])
        if kind == _KB:
            w = p[2] - real(0.5) * c
            q = vec3(wp.abs(p[0]) - (a - e), wp.abs(p[1]) - (b - e), wp.abs(w) - (real(0.5) * c - e))
            return rounded_box(q, vec3(sgn(p[0]), sgn(p[1]), sgn(w)), e)
        if kind == _KT:
            rad = radial(p[0], p[1])
            u = rad[0] - real(0.5) * (a + b)
            w = p[2] - real(0.5) * c
            r2 = rounded_rect(wp.abs(u) - (real(0.5) * (b - a) - e), wp.abs(w) - (real(0.5) * c - e), e)
            gr = r2[1] * sgn(u)
            return vec4(r2[0], gr * rad[1], gr * rad[2], r2[2] * sgn(w))
        if kind == _KX:
            return texture(dims, p)
        return vec4(real(1.0), real(0.0), real(0.0), real(-1.0))

    @wp.func
    def body_sdf_and_grad(kind: int, dims: vec4, p: vec3) -> vec4:  # noqa: F811
        """(signed distance, unit outward gradient) of indenter ``kind``'s head united with its shank, a
        semi-infinite round post on the z axis (radius and base of `assets.indenters.SHANK_POSTS`, the rule
        `assets.indenters.Indenter.mesh` builds the solid with): the body cannot be passed along its axis.
        Exact outside; inside, the nearer surface's distance."""
        head = indenter_sdf_and_grad(kind, dims, p)
        if kind < 0 or kind >= _N_SHANK:
            return head
        base = real(_SHANK[kind, 4])
        for k in range(4):
            base += real(_SHANK[kind, k]) * dims[k]
        shank = real(SHANK_RADIUS)
        if _SHANK[kind, 5] != wp.float64(0.0):
            shank = wp.min(shank, dims[0])
        rad = radial(p[0], p[1])
        post = rounded_rect(rad[0] - shank, base - p[2], real(0.0))
        if post[0] < head[0]:
            return vec4(post[0], post[1] * rad[1], post[1] * rad[2], -post[2])
        return head

    return indenter_sdf_and_grad, body_sdf_and_grad


indenter_sdf_and_grad, body_sdf_and_grad = _build(wp.float32, wp.vec2, wp.vec3, wp.vec4)
indenter_sdf_and_grad, body_sdf_and_grad = _build(
    wp.float64, wp.vec2d, wp.vec3d, wp.vec4d, indenter_sdf_and_grad, body_sdf_and_grad
)


def head_radius(kind: int, dims: tuple[float, float, float, float]) -> float:
    """Radius (m) of a ball about the tip holding indenter ``kind``'s pressing head (`assets.indenters.
    head_extent` of ``dims``): a rotation by theta about the tip moves no head point more than theta times it."""
    return float(np.hypot(*head_extent(kind, dims)))
