"""The paper's nine rigid indenters: analytic signed-distance functions (numpy) and triangle meshes.

Frame (the ``indenter`` frame, the contract shared with ``fe.indenter_sdf``): the tip, the first point
to touch in a normal press, is at the origin; the indenter's body lies in z >= 0 with its shank along +z;
the indenter presses along -z. Units: metres. The ring's "tip" is the centre of its lip plane (on the
axis); the texture's is the apex of its central bump.

The public meshes (NVlabs/biotac_sim, ``meshes/indenters/*.obj``) have the tip at y = 0 and the shank
along -y; in this frame a public vertex (x, y, z) is (x, z, -y). Measured from them (docs/indenters.md):
the mm number in each public name is a *diameter* (spheres, cylinders) or a full side (cube), every
cylinder presses with its curved side (axis along x), the ring is a 7 mm deep tube of inner radius 3.5 mm
and outer radius 7 mm, and every sharp edge of the pressing head is rounded with a 1 mm radius.

The signed distance (negative inside) is exact near the pressing head; the shank and the mount are not
part of it (they are in ``Indenter.mesh``). ``fe.indenter_sdf`` evaluates the same functions in warp.
"""

from dataclasses import dataclass

import numpy as np
import trimesh

KIND_SPHERE = 0
KIND_CYLINDER_FLAT = 1
KIND_CYLINDER_SIDE = 2
KIND_BOX = 3
KIND_TORUS = 4
KIND_TEXTURE = 5

#: Concave fillet radius where a texture bump meets the plate, m: at least the skin's half-layer (0.5-1 mm over
#: the paper's 1-2 mm skins), so that the distance's kinks (medial surfaces of the concave foot, which start
#: this far from the texture) lie beyond the reach of the FE contact layer (docs/indenters.md).
TEXTURE_FILLET = 1.0e-3
#: Rounding radius of the texture plate's rim and vertical corners, m.
TEXTURE_RIM = 0.5e-3
#: Integer hash constants of the texture's bump jitter (MINSTD Lehmer generator), shared with warp.
HASH_MODULUS = 2147483647
HASH_MULTIPLIER = 48271
HASH_OFFSET = 1000
#: Tip-to-end length of every indenter including its shank, m (the public meshes: 17.86 mm).
TOTAL_LENGTH = 17.86e-3
#: Shank radius used by ``Indenter.mesh`` (capped at the head's own radius), m.
SHANK_RADIUS = 3.6e-3
#: The shank post of each kind, a round post on the z axis from z = base up: base (m) = sum_k c_k dims[k]
#: + offset with the row (c_0, c_1, c_2, c_3, offset) here (the head's mid-height for spheres, cylinders and
#: the box; the top of the ring's tube; 1 mm below the texture plate's top, its face rb plus 2 mm), its radius
#: SHANK_RADIUS, capped at dims[0] (the head's radius) where the row's last entry is 1. One rule for
#: ``Indenter.mesh``'s solid and the contact SDF (`fe.indenter_sdf.body_sdf_and_grad`, which reads this table).
SHANK_POSTS: tuple[tuple[float, float, float, float, float, float], ...] = (
    (1.0, 0.0, 0.0, 0.0, 0.0, 1.0),  # KIND_SPHERE: the centre, z = R
    (0.0, 0.5, 0.0, 0.0, 0.0, 1.0),  # KIND_CYLINDER_FLAT: z = H / 2
    (1.0, 0.0, 0.0, 0.0, 0.0, 1.0),  # KIND_CYLINDER_SIDE: the axis, z = R
    (0.0, 0.0, 0.5, 0.0, 0.0, 0.0),  # KIND_BOX: z = H / 2
    (0.0, 0.0, 1.0, 0.0, 0.0, 0.0),  # KIND_TORUS: the top of the tube, z = H
    (1.0, 0.0, 0.0, 0.0, 1.0e-3, 0.0),  # KIND_TEXTURE: z = rb + 1 mm
)


def shank_post(kind: int, dims: tuple[float, float, float, float]) -> tuple[float, float]:
    """(radius, base height) in m of indenter ``kind``'s shank post (`SHANK_POSTS`), indenter frame."""
    *c, offset, capped = SHANK_POSTS[kind]
    base = c[0] * dims[0] + c[1] * dims[1] + c[2] * dims[2] + c[3] * dims[3] + offset
    return (min(SHANK_RADIUS, dims[0]) if capped else SHANK_RADIUS), base


def head_extent(kind: int, dims: tuple[float, float, float, float]) -> tuple[float, float]:
    """(radius, height) in m of indenter ``kind``'s pressing head, indenter frame: the largest distance of a
    head point from the z axis and the head's z extent above the tip (the texture's up to the top of its
    2 mm plate, face at rb); (0, 0) for an unknown kind. One rule for ``Indenter.head_height`` and the
    sweep's ball about the tip (`fe.indenter_sdf.head_radius`)."""
    a, b, c, e = dims
    return {
        KIND_SPHERE: (a, 2.0 * a),
        KIND_CYLINDER_FLAT: (a, b),
        KIND_CYLINDER_SIDE: (max(0.5 * b, a), 2.0 * a),
        KIND_BOX: (float(np.hypot(a, b)), c),
        KIND_TORUS: (b, c),
        KIND_TEXTURE: (float(np.sqrt(2.0)) * e, a + 2.0e-3),
    }.get(kind, (0.0, 0.0))


def _safe_unit(v: np.ndarray, fallback: np.ndarray) -> np.ndarray:
    """Normalise the rows of ``v`` (N, k); rows of zero length become ``fallback`` (k,)."""
    n = np.linalg.norm(v, axis=1, keepdims=True)
    out = np.broadcast_to(fallback, v.shape).astype(float)
    ok = n[:, 0] > 0.0
    out[ok] = v[ok] / n[ok]
    return out


def _sign(u: np.ndarray) -> np.ndarray:
    """Sign with sign(0) = +1, as in the warp twin."""
    return np.where(u < 0.0, -1.0, 1.0)


def _rounded_rect(qx: np.ndarray, qy: np.ndarray, r: float) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """2D rounded-rectangle SDF from the folded, shrunk coordinates q = |p| - (half - r).

    Returns (distance, d/dqx, d/dqy); exact everywhere, gradient continuous outside the inner rectangle.
    """
    mx, my = np.maximum(qx, 0.0), np.maximum(qy, 0.0)
    length = np.sqrt(mx * mx + my * my)
    outside = length > 0.0
    safe = np.where(outside, length, 1.0)
    x_wins = qx > qy
    d = np.where(outside, length - r, np.where(x_wins, qx, qy) - r)
    gx = np.where(outside, mx / safe, np.where(x_wins, 1.0, 0.0))
    gy = np.where(outside, my / safe, np.where(x_wins, 0.0, 1.0))
    return d, gx, gy


def _radial(x: np.ndarray, y: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Radius and unit radial direction in a plane; direction (1, 0) on the axis."""
    rho = np.sqrt(x * x + y * y)
    ok = rho > 0.0
    safe = np.where(ok, rho, 1.0)
    return rho, np.where(ok, x / safe, 1.0), np.where(ok, y / safe, 0.0)


def texture_jitter(i: np.ndarray, j: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Deterministic jitter in [-1, 1) of the texture bump in lattice cell (i, j); zero for cell (0, 0).

    Two steps of the MINSTD generator seeded with a pairing of (i + 1000, j + 1000), in int64; the
    warp twin uses the same integer arithmetic, so both agree to rounding.
    """
    i = np.asarray(i, dtype=np.int64)
    j = np.asarray(j, dtype=np.int64)
    seed = (i + HASH_OFFSET) * 7919 + (j + HASH_OFFSET) * 104729
    h1 = (seed * HASH_MULTIPLIER) % HASH_MODULUS
    h2 = (h1 * HASH_MULTIPLIER) % HASH_MODULUS
    centre = (i == 0) & (j == 0)
    jx = np.where(centre, 0.0, 2.0 * (h1.astype(float) / HASH_MODULUS) - 1.0)
    jy = np.where(centre, 0.0, 2.0 * (h2.astype(float) / HASH_MODULUS) - 1.0)
    return jx, jy


def _bump_profile(rho: np.ndarray, z: np.ndarray, rb: float) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Exact 2D SDF of one filleted hemispherical bump on the plate plane z = rb, in (rho, z).

    Pieces: sphere arc (centre (0, rb), radius rb), concave fillet arc (radius TEXTURE_FILLET, tangent to
    sphere and plane), plane z = rb for rho >= rho_f. Returns (distance, d/drho, d/dz).
    """
    f = TEXTURE_FILLET
    rho_f = np.sqrt(rb * rb + 2.0 * rb * f)
    nx, nz = -f / (rb + f), -rho_f / (rb + f)  # normal of line sphere-centre -> fillet-centre, apex side
    vx, vz = rho, z - rb
    below = vx * nx + vz * nz >= 0.0
    # plane piece
    best = np.where(rho >= rho_f, rb - z, np.inf)
    g_r = np.zeros_like(rho)
    g_z = np.full_like(rho, -1.0)
    # sphere piece
    vlen = np.sqrt(vx * vx + vz * vz)
    vsafe = np.where(vlen > 0.0, vlen, 1.0)
    d_s = vlen - rb
    take = below & (np.abs(d_s) < np.abs(best))
    best = np.where(take, d_s, best)
    g_r = np.where(take, np.where(vlen > 0.0, vx / vsafe, 0.0), g_r)
    g_z = np.where(take, np.where(vlen > 0.0, vz / vsafe, -1.0), g_z)
    # fillet piece
    wx, wz = rho - rho_f, z - (rb - f)
    wlen = np.sqrt(wx * wx + wz * wz)
    wsafe = np.where(wlen > 0.0, wlen, 1.0)
    d_f = f - wlen
    take = ~below & (rho <= rho_f) & (np.abs(d_f) < np.abs(best))
    best = np.where(take, d_f, best)
    g_r = np.where(take, np.where(wlen > 0.0, -wx / wsafe, 0.0), g_r)
    g_z = np.where(take, np.where(wlen > 0.0, -wz / wsafe, -1.0), g_z)
    return best, g_r, g_z


Dims = tuple[float, float, float, float]


def _sdf_and_grad(kind: int, dims: Dims, p: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Signed distance (N,) and unit outward gradient (N, 3) of one analytic indenter head."""
    x, y, z = p[:, 0], p[:, 1], p[:, 2]
    a, b, c, e = dims
    if kind == KIND_SPHERE:
        v = p - np.array([0.0, 0.0, a])
        return np.linalg.norm(v, axis=1) - a, _safe_unit(v, np.array([0.0, 0.0, -1.0]))
    if kind == KIND_CYLINDER_FLAT:
        rho, ux, uy = _radial(x, y)
        w = z - 0.5 * b
        d, gx, gy = _rounded_rect(rho - (a - c), np.abs(w) - (0.5 * b - c), c)
        return d, np.stack([gx * ux, gx * uy, gy * _sign(w)], axis=1)
    if kind == KIND_TORUS:
        rho, ux, uy = _radial(x, y)
        u = rho - 0.5 * (a + b)
        w = z - 0.5 * c
        d, gx, gy = _rounded_rect(np.abs(u) - (0.5 * (b - a) - e), np.abs(w) - (0.5 * c - e), e)
        gr = gx * _sign(u)
        return d, np.stack([gr * ux, gr * uy, gy * _sign(w)], axis=1)
    if kind == KIND_CYLINDER_SIDE:
        zc = z - a
        rho, uz, uy = _radial(-zc, y)  # radial direction (0, 0, -1), towards the tip, on the axis
        d, gx, gy = _rounded_rect(rho - (a - c), np.abs(x) - (0.5 * b - c), c)
        return d, np.stack([gy * _sign(x), gx * uy, -gx * uz], axis=1)
    if kind == KIND_BOX:
        w = z - 0.5 * c
        q = np.stack([np.abs(x) - (a - e), np.abs(y) - (b - e), np.abs(w) - (0.5 * c - e)], axis=1)
        s = np.stack([_sign(x), _sign(y), _sign(w)], axis=1)
        return _rounded_box_3d(q, s, e)
    if kind == KIND_TEXTURE:
        return _texture(p, dims)
    raise ValueError(f"unknown indenter kind {kind}")


def _rounded_box_3d(q: np.ndarray, s: np.ndarray, r: float) -> tuple[np.ndarray, np.ndarray]:
    """3D rounded-box SDF from folded, shrunk coordinates q (N, 3) with fold signs s (N, 3)."""
    m = np.maximum(q, 0.0)
    length = np.linalg.norm(m, axis=1)
    outside = length > 0.0
    qmax = q.max(axis=1)
    d = np.where(outside, length - r, qmax - r)
    g = np.zeros_like(q)
    g[outside] = m[outside] / length[outside, None]
    inner = ~outside
    g[inner, np.argmax(q[inner], axis=1)] = 1.0
    return d, g * s


def texture_bump_centres(dims: tuple[float, float, float, float]) -> np.ndarray:
    """(M, 2) x, y centres of the texture's bumps, m: lattice cells |i|, |j| <= floor(W / a - 1/2)."""
    _, a, jit, half = dims
    n = int(np.floor(half / a - 0.5))
    i, j = np.meshgrid(np.arange(-n, n + 1), np.arange(-n, n + 1), indexing="ij")
    jx, jy = texture_jitter(i.ravel(), j.ravel())
    return np.stack([i.ravel() * a + jit * jx, j.ravel() * a + jit * jy], axis=1)


def _texture(p: np.ndarray, dims: tuple[float, float, float, float]) -> tuple[np.ndarray, np.ndarray]:
    """Texture SDF: plate face z = rb with filleted hemispherical bumps, rounded rim; plate top ignored."""
    rb, a, jit, half = dims
    x, y, z = p[:, 0], p[:, 1], p[:, 2]
    n = int(np.floor(half / a - 0.5))
    d_bump = rb - z
    g_bump = np.tile([0.0, 0.0, -1.0], (len(p), 1))
    i0 = np.round(x / a).astype(np.int64)
    j0 = np.round(y / a).astype(np.int64)
    for di in (-1, 0, 1):
        for dj in (-1, 0, 1):
            i, j = i0 + di, j0 + dj
            valid = (np.abs(i) <= n) & (np.abs(j) <= n)
            jx, jy = texture_jitter(i, j)
            rho, ux, uy = _radial(x - (i * a + jit * jx), y - (j * a + jit * jy))
            d, gr, gz = _bump_profile(rho, z, rb)
            take = valid & (d < d_bump)
            d_bump = np.where(take, d, d_bump)
            g_bump[take] = np.stack([gr * ux, gr * uy, gz], axis=1)[take]
    r = TEXTURE_RIM
    q = np.stack([np.abs(x) - (half - r), np.abs(y) - (half - r), d_bump + r], axis=1)
    m = np.maximum(q, 0.0)
    length = np.linalg.norm(m, axis=1)
    outside = length > 0.0
    d = np.where(outside, length - r, q.max(axis=1) - r)
    # chain rule: d/dq3 multiplies the bump-surface gradient; d/dq1, d/dq2 the lateral folds
    w = np.zeros_like(q)
    w[outside] = m[outside] / length[outside, None]
    inner = ~outside
    w[inner, np.argmax(q[inner], axis=1)] = 1.0
    g = w[:, 2:3] * g_bump
    g[:, 0] += w[:, 0] * _sign(x)
    g[:, 1] += w[:, 1] * _sign(y)
    return d, g


@dataclass(frozen=True)
class Indenter:
    """One rigid indenter as an analytic head (for contact) plus a shank (for meshes).

    ``dims`` (metres) by ``kind``, all in the indenter frame (tip at the origin, body in z >= 0):

    - KIND_SPHERE: (R, 0, 0, 0); sphere of radius R centred at (0, 0, R).
    - KIND_CYLINDER_FLAT: (R, H, e, 0); cylinder of radius R on the z axis, z in [0, H], flat face down,
      edges rounded with radius e.
    - KIND_CYLINDER_SIDE: (R, L, e, 0); cylinder of radius R and length L, axis along x through
      (0, 0, R), pressing with its curved side; end edges rounded with radius e.
    - KIND_BOX: (hx, hy, H, e); box |x| <= hx, |y| <= hy, z in [0, H], every edge rounded with radius e.
    - KIND_TORUS: (r_in, r_out, H, e); tube r_in <= rho <= r_out, z in [0, H] (a revolved rounded
      rectangle), edges rounded with radius e; with e = (r_out - r_in) / 2 its lip is an exact torus.
    - KIND_TEXTURE: (rb, a, J, W); plate face at z = rb covering |x|, |y| <= W with hemispherical bumps of
      radius rb (apex at z = 0) on a square lattice of spacing a, each jittered by up to +-J per axis
      (``texture_jitter``), bump cells |i|, |j| <= floor(W / a - 1/2); bump-plate fillet TEXTURE_FILLET,
      rim rounding TEXTURE_RIM. The plate is unbounded upwards in the SDF.
    """

    name: str
    kind: int
    dims: tuple[float, float, float, float]
    description: str

    def sdf(self, points: np.ndarray) -> np.ndarray:
        """Signed distance (N,) of points (N, 3) in the indenter frame, m; negative inside."""
        return _sdf_and_grad(self.kind, self.dims, np.atleast_2d(np.asarray(points, dtype=float)))[0]

    def sdf_gradient(self, points: np.ndarray) -> np.ndarray:
        """Unit outward gradient (N, 3) of ``sdf`` at points (N, 3) in the indenter frame."""
        return _sdf_and_grad(self.kind, self.dims, np.atleast_2d(np.asarray(points, dtype=float)))[1]

    def head_height(self) -> float:
        """Height (z extent) of the analytic head above the tip, m (`head_extent`)."""
        return head_extent(self.kind, self.dims)[1]

    def _solid_sdf(self, p: np.ndarray) -> np.ndarray:
        """SDF-like field of the closed solid (head, closed back, shank) used only for meshing."""
        d = self.sdf(p)
        a, b, _, _ = self.dims
        top = self.head_height()
        rho = np.sqrt(p[:, 0] ** 2 + p[:, 1] ** 2)
        if self.kind == KIND_TEXTURE:  # 2 mm plate
            d = np.maximum(d, p[:, 2] - top)
        if self.kind == KIND_TORUS:  # the public ring is a cup: closed 1 mm above its 7 mm deep hole
            cap = np.maximum(rho - b, np.abs(p[:, 2] - (top + 0.5e-3)) - 0.5e-3)
            d = np.minimum(d, cap)
            top += 1.0e-3
        rs, z0 = shank_post(self.kind, self.dims)
        shank = np.maximum(rho - rs, np.maximum(z0 - p[:, 2], p[:, 2] - TOTAL_LENGTH))
        return np.minimum(d, shank)

    def mesh(self, max_edge: float = 0.5e-3) -> trimesh.Trimesh:
        """Watertight triangle mesh of head plus a round shank to z = TOTAL_LENGTH, indenter frame, m.

        Marching tetrahedra on a grid of spacing max_edge / 2, vertices projected onto the surface. The
        shank is a simplified round post (radius min(3.6 mm, head radius)); the public meshes end in
        tapered mount adapters. Non-convex (ring, texture): MuJoCo collides with a mesh's convex hull.
        """
        return _mesh_from_field(self._solid_sdf, self._mesh_bounds(), 0.5 * max_edge)

    def _mesh_bounds(self) -> np.ndarray:
        """(2, 3) axis-aligned bounds of the solid, m, padded by one millimetre."""
        a, b, _, _ = self.dims
        half = {
            KIND_SPHERE: (a, a),
            KIND_CYLINDER_FLAT: (a, a),
            KIND_CYLINDER_SIDE: (0.5 * b, a),
            KIND_BOX: (a, b),
            KIND_TORUS: (b, b),
            KIND_TEXTURE: (self.dims[3], self.dims[3]),
        }[self.kind]
        hx, hy = max(half[0], SHANK_RADIUS), max(half[1], SHANK_RADIUS)
        pad = 1.0e-3
        return np.array([[-hx - pad, -hy - pad, -pad], [hx + pad, hy + pad, TOTAL_LENGTH + pad]])


# Kuhn triangulation of the unit cube: six tetrahedra along the main diagonal, conforming across cubes.
_CUBE_CORNERS = np.array([[i, j, k] for i in (0, 1) for j in (0, 1) for k in (0, 1)])
_KUHN_TETS = np.array(
    [
        [0, int(np.dot(e1, [4, 2, 1])), int(np.dot(e1 + e2, [4, 2, 1])), 7]
        for e1, e2 in (
            (np.eye(3, dtype=int)[a], np.eye(3, dtype=int)[b])
            for a, b in ((0, 1), (0, 2), (1, 0), (1, 2), (2, 0), (2, 1))
        )
    ]
)


def _mesh_from_field(field, bounds: np.ndarray, h: float) -> trimesh.Trimesh:
    """Watertight, outward-oriented triangle mesh of {field < 0} by marching tetrahedra, spacing h."""
    shape = np.ceil((bounds[1] - bounds[0]) / h).astype(int) + 1
    axes = [bounds[0, k] + h * np.arange(shape[k]) for k in range(3)]
    nodes = np.stack(np.meshgrid(*axes, indexing="ij"), axis=-1).reshape(-1, 3)
    s = field(nodes)
    s = np.where(s == 0.0, 1e-15, s)  # no vertex exactly on the surface: no degenerate triangles
    node_id = np.arange(len(nodes)).reshape(shape)
    n0, n1, n2 = shape - 1
    corner_ids = np.stack(
        [node_id[i : n0 + i, j : n1 + j, k : n2 + k].ravel() for i, j, k in _CUBE_CORNERS],
        axis=1,
    )
    cs = s[corner_ids]
    active = (cs.min(axis=1) < 0.0) & (cs.max(axis=1) > 0.0)
    tets = corner_ids[active][:, _KUHN_TETS].reshape(-1, 4)
    ts = s[tets]
    inside = ts < 0.0
    count = inside.sum(axis=1)
    tris = []  # each triangle as three (node_a, node_b) edges
    for c in (1, 3):
        sel = count == c
        lone_mask = inside[sel] if c == 1 else ~inside[sel]
        order = np.argsort(~lone_mask, axis=1, kind="stable")  # lone vertex first
        t = np.take_along_axis(tets[sel], order, axis=1)
        tris.append(np.stack([t[:, [0, k]] for k in (1, 2, 3)], axis=1))
    sel = count == 2
    order = np.argsort(~inside[sel], axis=1, kind="stable")  # two inside first
    t = np.take_along_axis(tets[sel], order, axis=1)
    a, b, c, d = t[:, 0], t[:, 1], t[:, 2], t[:, 3]
    quad = [np.stack([a, c], 1), np.stack([a, d], 1), np.stack([b, d], 1), np.stack([b, c], 1)]
    tris.append(np.stack([quad[0], quad[1], quad[2]], axis=1))
    tris.append(np.stack([quad[0], quad[2], quad[3]], axis=1))
    edges = np.concatenate(tris, axis=0)  # (T, 3, 2)
    lo, hi = edges.min(axis=2), edges.max(axis=2)
    keys, faces = np.unique((lo * len(nodes) + hi).ravel(), return_inverse=True)
    faces = faces.reshape(-1, 3)
    e0, e1 = keys // len(nodes), keys % len(nodes)
    t_par = s[e0] / (s[e0] - s[e1])
    verts = nodes[e0] + t_par[:, None] * (nodes[e1] - nodes[e0])
    # orient every triangle so its normal points from the inside node to the outside node of its first
    # edge; judged on the edge midpoints, whose triangles are never degenerate and orient alike
    first = edges[:, 0, :]
    outward = np.where((s[first[:, 0]] < 0.0)[:, None], 1.0, -1.0) * (nodes[first[:, 1]] - nodes[first[:, 0]])
    mid = 0.5 * (nodes[edges[:, :, 0]] + nodes[edges[:, :, 1]])
    normal = np.cross(mid[:, 1] - mid[:, 0], mid[:, 2] - mid[:, 0])
    flip = np.einsum("ij,ij->i", normal, outward) < 0.0
    faces[flip] = faces[flip][:, ::-1]
    verts = _project(field, verts, h)
    return trimesh.Trimesh(vertices=verts, faces=faces, process=False)


def _project(field, verts: np.ndarray, h: float, steps: int = 3) -> np.ndarray:
    """Move vertices onto the zero level set by Newton steps along a central-difference gradient."""
    eps = 1e-3 * h
    for _ in range(steps):
        grad = np.stack([(field(verts + eps * e) - field(verts - eps * e)) / (2.0 * eps) for e in np.eye(3)], axis=1)
        norm2 = np.maximum((grad * grad).sum(axis=1), 1e-12)
        step = (field(verts) / norm2)[:, None] * grad
        verts = verts - np.clip(step, -0.5 * h, 0.5 * h)
    return verts


_MM = 1e-3
INDENTERS: dict[str, Indenter] = {
    ind.name: ind
    for ind in (
        Indenter(
            "sphere_small",
            KIND_SPHERE,
            (1.75 * _MM, 0.0, 0.0, 0.0),
            "sphere of 3.5 mm diameter (public sphere_3-5mm)",
        ),
        Indenter(
            "sphere_medium",
            KIND_SPHERE,
            (3.5 * _MM, 0.0, 0.0, 0.0),
            "sphere of 7 mm diameter (public sphere_7mm)",
        ),
        Indenter(
            "sphere_large",
            KIND_SPHERE,
            (7.0 * _MM, 0.0, 0.0, 0.0),
            "sphere of 14 mm diameter (public sphere_14mm)",
        ),
        Indenter(
            "cylinder_short_small",
            KIND_CYLINDER_SIDE,
            (1.75 * _MM, 7.0 * _MM, 1.0 * _MM, 0.0),
            "cylinder of 3.5 mm diameter, 7 mm long, pressed on its side (public cylinder_short_3-5mm)",
        ),
        Indenter(
            "cylinder_short_medium",
            KIND_CYLINDER_SIDE,
            (3.5 * _MM, 7.0 * _MM, 1.0 * _MM, 0.0),
            "cylinder of 7 mm diameter, 7 mm long, pressed on its side (public cylinder_short_7mm)",
        ),
        Indenter(
            "cylinder_long",
            KIND_CYLINDER_SIDE,
            (3.5 * _MM, 28.0 * _MM, 1.0 * _MM, 0.0),
            "cylinder of 7 mm diameter, 28 mm long, pressed on its side: a table edge (public cylinder_long_7mm)",
        ),
        Indenter(
            "cube",
            KIND_BOX,
            (7.0 * _MM, 7.0 * _MM, 7.0 * _MM, 1.0 * _MM),
            "block with a 14 x 14 mm pressing face, 7 mm deep, 1 mm edge radius (public cube_14mm)",
        ),
        Indenter(
            "ring",
            KIND_TORUS,
            (3.5 * _MM, 7.0 * _MM, 7.0 * _MM, 1.0 * _MM),
            "tube of 14 mm outer / 7 mm inner diameter, 7 mm deep, 1 mm lip fillets: a bottle opening "
            "(public ring_7mm)",
        ),
        Indenter(
            "texture",
            KIND_TEXTURE,
            (1.0 * _MM, 4.0 * _MM, 0.25 * _MM, 11.0 * _MM),
            "22 x 22 mm plate with 25 hemispherical bumps of 1 mm radius on a jittered 4 mm lattice: "
            "scattered debris (no public mesh; designed here)",
        ),
    )
}


#: The public meshes' names (NVlabs/biotac_sim ``meshes/indenters/*.obj``) and our names of the same indenters.
PUBLIC_NAMES: dict[str, str] = {
    "sphere_3-5mm": "sphere_small",
    "sphere_7mm": "sphere_medium",
    "sphere_14mm": "sphere_large",
    "cylinder_short_3-5mm": "cylinder_short_small",
    "cylinder_short_7mm": "cylinder_short_medium",
    "cylinder_long_7mm": "cylinder_long",
    "cube_14mm": "cube",
    "ring_7mm": "ring",
}


def indenter_name(name: str) -> str:
    """Our name of the indenter called ``name`` (ours or its public mesh name); ValueError for an unknown one."""
    canonical = PUBLIC_NAMES.get(name, name)
    if canonical not in INDENTERS:
        raise ValueError(
            f"unknown indenter {name!r}; valid names: {', '.join(INDENTERS)} "
            f"(or the public mesh names {', '.join(PUBLIC_NAMES)})"
        )
    return canonical


def get_indenter(name: str) -> Indenter:
    """The indenter called ``name`` (ours or its public mesh name); ValueError listing the valid names."""
    return INDENTERS[indenter_name(name)]
