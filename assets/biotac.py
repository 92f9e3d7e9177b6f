"""Parametric BioTac geometry for the shell finite-element model.

Everything here is in SI units (metres) and in the ``biotac`` frame of the BioTac Product Manual:
x points distal (toward the tip), y lateral, -z is the ventral pad, +z the fingernail side; the
origin is the centre of the electrode pairs and the x axis is the axis of the core's electrode
cylinder (side and ventral electrodes sit 5.08 mm from it).

The skin is a hemisphere cap (centre ``tip_center_x``) joined to a cylinder along -x, both of radius
``skin_outer_radius`` about the line (y = 0, z = ``axis_z``). Only the free skin plus an anchored band is
meshed: the skin is free for x > ``proximal_x`` and z < ``dorsal_anchor_z`` and glued to the core
elsewhere. The rigid core is a separate convex body: a cylinder + hemisphere of ``core_radius`` about
the x axis, cut by the flat dorsal top, the 30-degree electrode bevel at the tip and the proximal face.
The defaults are a fit to the public unpressurised FE mesh (see ``docs/geometry.md`` and
``benchmarks/geometry_fit.py``).
"""

from __future__ import annotations

from dataclasses import dataclass, field, fields

import numpy as np
from scipy.spatial import ConvexHull, cKDTree

from assets.refine import Refinement, refine_near

MM = 1e-3

# Electrode table of the BioTac Product Manual: x, y, z (mm), nx, ny, nz.
_ELECTRODES_MM = np.array(
    [
        [0.993, -4.855, -1.116, 0.196, -0.956, -0.220],
        [-2.700, -3.513, -3.670, 0.0, -0.692, -0.722],
        [-6.200, -3.513, -3.670, 0.0, -0.692, -0.722],
        [-8.000, -4.956, -1.116, 0.0, -0.976, -0.220],
        [-10.500, -3.513, -3.670, 0.0, -0.692, -0.722],
        [-13.400, -4.956, -1.116, 0.0, -0.976, -0.220],
        [4.763, 0.000, -2.330, 0.5, 0.0, -0.866],
        [3.031, -1.950, -3.330, 0.5, 0.0, -0.866],
        [3.031, 1.950, -3.330, 0.5, 0.0, -0.866],
        [1.299, 0.000, -4.330, 0.5, 0.0, -0.866],
        [0.993, 4.855, -1.116, 0.196, 0.956, -0.220],
        [-2.700, 3.513, -3.670, 0.0, 0.692, -0.722],
        [-6.200, 3.513, -3.670, 0.0, 0.692, -0.722],
        [-8.000, 4.956, -1.116, 0.0, 0.976, -0.220],
        [-10.500, 3.513, -3.670, 0.0, 0.692, -0.722],
        [-13.400, 4.956, -1.116, 0.0, 0.976, -0.220],
        [-2.800, 0.000, -5.080, 0.0, 0.0, -1.0],
        [-9.800, 0.000, -5.080, 0.0, 0.0, -1.0],
        [-13.600, 0.000, -5.080, 0.0, 0.0, -1.0],
    ]
)

#: Unit normal of the tilted tip facet carrying E7-E10 (biotac frame) and its offset n.p (m).
BEVEL_NORMAL = np.array([0.5, 0.0, -np.sqrt(3.0) / 2.0])
BEVEL_OFFSET = 4.40 * MM


@dataclass(frozen=True)
class BioTacDimensions:
    """BioTac dimensions in metres, biotac frame. Defaults: fit to the public unpressurised FE mesh.

    Skin (unpressurised, as moulded):
        skin_outer_radius: outer skin radius of the cylinder and of the tip hemisphere.
        skin_thickness: CAD skin thickness; mid-surface radius = skin_outer_radius - skin_thickness / 2.
        axis_z: z of the skin's cylinder axis (the axis lies at y = 0, parallel to x).
        tip_center_x: x of the centre of the skin's hemispherical tip cap.
        proximal_x: the skin is free for x > proximal_x and anchored (glued to the core) for x <= it.
        dorsal_anchor_z: the skin is anchored for z >= dorsal_anchor_z (the dorsal, nail-side skin).
        anchor_band: width (surface distance) of anchored skin kept in the mesh beyond the free
            region, at the proximal and at the dorsal anchor.
        dorsal_top_z: z of the top of the fixed dorsal outer surface; the unpressurised sensor
            thickness is dorsal_top_z - (axis_z - skin_outer_radius).
    Rigid core (a convex body about the x axis, y = z = 0, which carries the electrodes):
        core_radius: radius of the core's ventral cylinder and of its tip hemisphere.
        core_tip_center_x: x of the centre of the core's tip hemisphere.
        core_top_z: z of the core's flat dorsal face.
        core_proximal_x: x of the core's flat proximal face.
    The core is also cut by the electrode bevel plane ``BEVEL_NORMAL . p = BEVEL_OFFSET``.
    """

    core_radius: float = 5.08 * MM
    skin_outer_radius: float = 7.11 * MM
    axis_z: float = -0.97 * MM
    tip_center_x: float = 1.79 * MM
    proximal_x: float = -14.0 * MM
    dorsal_anchor_z: float = 1.0 * MM
    dorsal_top_z: float = 5.33 * MM
    anchor_band: float = 1.0 * MM
    skin_thickness: float = 1.58 * MM
    core_tip_center_x: float = 2.00 * MM
    core_top_z: float = 1.91 * MM
    core_proximal_x: float = -17.33 * MM

    def __post_init__(self) -> None:
        _validate_dimensions(self)

    @property
    def skin_mid_radius(self) -> float:
        """Radius of the unpressurised skin mid-surface (m)."""
        return self.skin_outer_radius - 0.5 * self.skin_thickness

    @property
    def skin_inner_radius(self) -> float:
        """Radius of the unpressurised inner skin surface (m)."""
        return self.skin_outer_radius - self.skin_thickness


def _require(condition: bool, message: str) -> None:
    if not condition:
        raise ValueError(f"BioTacDimensions: {message}")


def _validate_dimensions(d: BioTacDimensions) -> None:
    """Raise ValueError with a clear message for non-physical dimensions."""
    for f in fields(d):
        value = getattr(d, f.name)
        _require(np.isfinite(value), f"{f.name} must be finite, got {value!r}")
    for name in ("core_radius", "skin_outer_radius", "skin_thickness", "anchor_band"):
        _require(getattr(d, name) > 0.0, f"{name} must be > 0 (metres), got {getattr(d, name)!r}")
    _require(d.skin_outer_radius < 0.1, f"skin_outer_radius {d.skin_outer_radius!r} m is not a BioTac (metres?)")
    _require(d.skin_thickness < d.skin_outer_radius, "skin_thickness must be smaller than skin_outer_radius")
    _require(d.core_radius < d.skin_outer_radius, "core_radius must be smaller than skin_outer_radius")
    _require(
        d.proximal_x - d.anchor_band > d.core_proximal_x - d.skin_outer_radius,
        "proximal_x - anchor_band lies far behind the core's proximal face",
    )
    _require(d.proximal_x < d.tip_center_x, "proximal_x must be < tip_center_x")
    _require(d.core_proximal_x < d.core_tip_center_x, "core_proximal_x must be < core_tip_center_x")
    _require(-d.core_radius < d.core_top_z, "core_top_z must be above the core's ventral side")
    r_mid = d.skin_mid_radius
    _require(
        abs(d.dorsal_anchor_z - d.axis_z) < r_mid,
        "dorsal_anchor_z must cut the skin cylinder (|dorsal_anchor_z - axis_z| < mid-surface radius)",
    )
    _require(
        _dorsal_cut_angle(d) < np.pi - 1e-6,
        "dorsal_anchor_z + anchor_band reaches the top of the skin; lower dorsal_anchor_z or anchor_band",
    )
    _require(d.dorsal_top_z > d.dorsal_anchor_z, "dorsal_top_z must be above dorsal_anchor_z")


def _anchor_angle(d: BioTacDimensions) -> float:
    """Angle (rad) from the ventral bottom line of the mid-surface cylinder to the dorsal anchor line."""
    return float(np.arccos((d.axis_z - d.dorsal_anchor_z) / d.skin_mid_radius))


def _dorsal_cut_angle(d: BioTacDimensions) -> float:
    """Angle (rad) from the ventral bottom line to the meshed dorsal edge (anchor line + anchor band)."""
    return _anchor_angle(d) + d.anchor_band / d.skin_mid_radius


#: The fitted default dimensions.
DEFAULT_DIMENSIONS = BioTacDimensions()


def skin_cut_z(d: BioTacDimensions) -> float:
    """z (m) of the plane bounding the meshed skin dorsally (anchor line + band, mid-surface)."""
    return float(d.axis_z - d.skin_mid_radius * np.cos(_dorsal_cut_angle(d)))


@dataclass(frozen=True)
class SkinMesh:
    """Unpressurised skin mid-surface, biotac frame.

    vertices: (V, 3) float64, m. triangles: (T, 3) int32 whose right-hand normals point out of the
    fluid cavity (away from the core). anchored: (V,) bool, vertices glued to the core (proximal and
    dorsal anchors; includes every boundary vertex). ventral: (V,) bool, free vertices at least one
    ``anchor_band`` away from the anchors, where indentation points may be sampled.
    """

    vertices: np.ndarray
    triangles: np.ndarray
    anchored: np.ndarray
    ventral: np.ndarray


@dataclass(frozen=True)
class CoreMesh:
    """Closed (watertight) triangle surface of the rigid core, outward normals; (Vc, 3) m, (Tc, 3) int32."""

    vertices: np.ndarray
    triangles: np.ndarray


@dataclass(frozen=True)
class Electrodes:
    """The 19 electrodes: positions (19, 3) m on the core surface, unit outward normals (19, 3)."""

    positions: np.ndarray
    normals: np.ndarray


@dataclass(frozen=True)
class BioTacGeometry:
    """Everything the skin solver needs, biotac frame, SI units.

    dorsal_top_z: z (m) of the top of the fixed dorsal outer surface; sensor thickness =
        dorsal_top_z - min z of the outer skin surface.
    core_gap: half the CAD skin thickness (m): the skin-core contact offset of the mid-surface.
    cavity_volume_reference: unpressurised fluid volume (m^3) between the inner skin surface and the
        core over the free skin (x >= proximal_x, z <= dorsal_anchor_z).
    dims: the dimensions the geometry was made from (None for an imported mesh).
    """

    skin: SkinMesh
    core: CoreMesh
    electrodes: Electrodes
    dorsal_top_z: float
    core_gap: float
    cavity_volume_reference: float
    dims: BioTacDimensions | None = field(default=None)


def electrode_table() -> Electrodes:
    """The 19 electrodes of the BioTac Product Manual in the biotac frame (m), normals normalised."""
    positions = _ELECTRODES_MM[:, :3] * MM
    normals = _ELECTRODES_MM[:, 3:]
    return Electrodes(positions=positions.copy(), normals=normals / np.linalg.norm(normals, axis=1)[:, None])


# ----------------------------------------------------------------------------------------- skin mesh


def _strip_triangles(row_a: np.ndarray, s_a: np.ndarray, row_b: np.ndarray, s_b: np.ndarray) -> list:
    """Triangulate the strip between two rows of vertex ids sorted by arc coordinate s (zipper that
    always adds the shorter diagonal)."""
    tris = []
    i = j = 0
    while i < len(row_a) - 1 or j < len(row_b) - 1:
        advance_a = j == len(row_b) - 1 or (i < len(row_a) - 1 and abs(s_a[i + 1] - s_b[j]) <= abs(s_b[j + 1] - s_a[i]))
        if advance_a:
            tris.append((row_a[i], row_a[i + 1], row_b[j]))
            i += 1
        else:
            tris.append((row_a[i], row_b[j + 1], row_b[j]))
            j += 1
    return tris


def _cylinder_part(d: BioTacDimensions, h: float) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Staggered (equilateral) lattice on the meshed part of the mid-surface cylinder.

    Returns vertices (N, 3) m, triangles (T, 3) and the vertex ids of the seam ring x = tip_center_x,
    ordered from one dorsal edge around the ventral side to the other.
    """
    r, a = d.skin_mid_radius, d.axis_z
    half_arc = r * _dorsal_cut_angle(d)
    n_s = int(np.ceil(2.0 * half_arc / h))
    ds = 2.0 * half_arc / n_s
    x0 = d.proximal_x - d.anchor_band
    n_x = max(1, int(np.ceil((d.tip_center_x - x0) / (ds * np.sqrt(3.0) / 2.0))))
    even = -half_arc + ds * np.arange(n_s + 1)
    odd = np.concatenate([[-half_arc], -half_arc + ds * (np.arange(n_s) + 0.5), [half_arc]])
    verts, rows, arcs = [], [], []
    count = 0
    for k, x in enumerate(np.linspace(x0, d.tip_center_x, n_x + 1)):
        s = even if k % 2 == 0 else odd
        phi = s / r
        verts.append(np.column_stack([np.full_like(s, x), r * np.sin(phi), a - r * np.cos(phi)]))
        rows.append(np.arange(count, count + len(s)))
        arcs.append(s)
        count += len(s)
    tris = []
    for k in range(n_x):
        tris += _strip_triangles(rows[k], arcs[k], rows[k + 1], arcs[k + 1])
    return np.concatenate(verts), np.asarray(tris), rows[-1]


def _cap_boundary_arc(d: BioTacDimensions, h: float) -> np.ndarray:
    """Points strictly between the two corners on the cap's dorsal edge (plane z = dorsal cut), m."""
    r, phi_cut = d.skin_mid_radius, _dorsal_cut_angle(d)
    rho = r * np.sin(phi_cut)
    z_cut = skin_cut_z(d)
    n = max(2, int(np.ceil(np.pi * rho / h)))
    t = np.linspace(-np.pi / 2.0, np.pi / 2.0, n + 1)[1:-1]
    return np.column_stack([d.tip_center_x + rho * np.cos(t), rho * np.sin(t), np.full_like(t, z_cut)])


def _cap_interior_seed(d: BioTacDimensions, h: float, boundary: np.ndarray) -> np.ndarray:
    """Ring-based seed points strictly inside the cap region, at least ~0.6 h from its boundary."""
    r, c = d.skin_mid_radius, np.array([d.tip_center_x, 0.0, d.axis_z])
    z_cut = skin_cut_z(d)
    n_rings = int(np.ceil(0.5 * np.pi * r / (h * np.sqrt(3.0) / 2.0)))
    pts = [c + [r, 0.0, 0.0]]
    for k in range(1, n_rings):
        theta = 0.5 * np.pi * k / n_rings
        m = max(3, int(round(2.0 * np.pi * r * np.sin(theta) / h)))
        psi = 2.0 * np.pi * (np.arange(m) + 0.5 * (k % 2)) / m
        ring = np.column_stack([np.full(m, np.cos(theta)), np.sin(theta) * np.sin(psi), -np.sin(theta) * np.cos(psi)])
        pts.append(c + r * ring)
    pts = np.vstack(pts)
    pts = pts[pts[:, 2] < z_cut]
    far = cKDTree(boundary).query(pts)[0] > 0.6 * h
    return pts[far]


def _hull_triangles(points: np.ndarray, on_plane: list[np.ndarray]) -> np.ndarray:
    """Triangles of the convex hull of points on a sphere, minus the flat lids spanning the cut planes.

    on_plane: boolean masks of the points lying on each cutting plane; a hull facet whose three
    vertices all lie on one cutting plane is a lid, not surface.
    """
    simplices = ConvexHull(points).simplices
    keep = np.ones(len(simplices), dtype=bool)
    for mask in on_plane:
        keep &= ~mask[simplices].all(axis=1)
    return simplices[keep]


def _cap_part(d: BioTacDimensions, h: float, seam: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Mesh the hemispherical cap region given the seam-ring points (ordered), sharing them.

    Interior points are seeded on rings, then alternately smoothed (Laplacian, projected back onto
    the sphere) and refined (midpoints of edges longer than h inserted) on the spherical Delaunay
    triangulation (convex hull). Returns the new vertices (interior + dorsal arc, m) and triangles
    indexed as [seam points, new vertices].
    """
    r, c = d.skin_mid_radius, np.array([d.tip_center_x, 0.0, d.axis_z])
    boundary = np.vstack([seam, _cap_boundary_arc(d, h)])
    n_b = len(boundary)
    pts = np.vstack([boundary, _cap_interior_seed(d, 0.8 * h, boundary)])
    for k in range(_MAX_REFINE):
        tris = _smooth_on_sphere(pts, n_b, len(seam), c, r, n_iter=6 if k == 0 else 2)
        long_edges = _unique_edges(tris)
        long_edges = long_edges[np.linalg.norm(pts[long_edges[:, 0]] - pts[long_edges[:, 1]], axis=1) > h]
        if len(long_edges) == 0:
            return pts[len(seam) :], tris
        mid = c + r * _unit(pts[long_edges].mean(axis=1) - c)
        pts = np.vstack([pts, mid])
    raise RuntimeError("skin cap meshing did not reach the requested edge length")


_MAX_REFINE = 40


def _smooth_on_sphere(pts: np.ndarray, n_b: int, n_seam: int, c: np.ndarray, r: float, n_iter: int) -> np.ndarray:
    """Smooth the interior points pts[n_b:] in place on the sphere (c, r); return the final triangles."""
    on_seam = np.zeros(len(pts), dtype=bool)
    on_seam[:n_seam] = True
    on_arc = np.zeros(len(pts), dtype=bool)
    on_arc[n_seam:n_b] = True
    on_arc[[0, n_seam - 1]] = True  # the two corners lie on both cutting planes
    tris = _hull_triangles(pts, [on_seam, on_arc])
    for _ in range(n_iter):
        pts[n_b:] = c + r * _unit(_laplacian_step(pts, tris)[n_b:] - c)
        tris = _hull_triangles(pts, [on_seam, on_arc])
    return tris


def _unique_edges(triangles: np.ndarray) -> np.ndarray:
    """(E, 2) sorted unique vertex pairs of the triangles' edges."""
    edges = np.vstack([triangles[:, [0, 1]], triangles[:, [1, 2]], triangles[:, [2, 0]]])
    return np.unique(np.sort(edges, axis=1), axis=0)


def _laplacian_step(pts: np.ndarray, tris: np.ndarray) -> np.ndarray:
    """Each vertex moved to the mean of its edge neighbours (vertices in no triangle stay)."""
    edges = np.vstack([tris[:, [0, 1]], tris[:, [1, 2]], tris[:, [2, 0]]])
    edges = np.vstack([edges, edges[:, ::-1]])
    total = np.zeros_like(pts)
    np.add.at(total, edges[:, 0], pts[edges[:, 1]])
    count = np.bincount(edges[:, 0], minlength=len(pts)).astype(float)
    out = pts.copy()
    has = count > 0
    out[has] = total[has] / count[has, None]
    return out


def _unit(v: np.ndarray) -> np.ndarray:
    return v / np.linalg.norm(v, axis=-1, keepdims=True)


def _from_skin_axis(points: np.ndarray, d: BioTacDimensions) -> np.ndarray:
    """(N, 3) m: each point (N, 3) m less its nearest point of the skin's axis up to the cap centre (on the axis for
    x <= tip_center_x, the cap centre beyond): the skin's outward direction there, its length the radius."""
    q = points - np.array([d.tip_center_x, 0.0, d.axis_z])
    q[:, 0] = np.maximum(q[:, 0], 0.0)
    return q


def _orient_outward(vertices: np.ndarray, triangles: np.ndarray, d: BioTacDimensions) -> np.ndarray:
    """Reorder triangles so that right-hand normals point away from the skin axis / cap centre."""
    p = vertices[triangles]
    normal = np.cross(p[:, 1] - p[:, 0], p[:, 2] - p[:, 0])
    flip = np.einsum("ij,ij->i", normal, _from_skin_axis(p.mean(axis=1), d)) < 0.0
    out = triangles.copy()
    out[flip] = out[flip][:, ::-1]
    return out


def boundary_vertices(triangles: np.ndarray, n_vertices: int) -> np.ndarray:
    """(V,) bool: vertices on an edge used by exactly one triangle."""
    edges = np.sort(np.vstack([triangles[:, [0, 1]], triangles[:, [1, 2]], triangles[:, [2, 0]]]), axis=1)
    uniq, counts = np.unique(edges, axis=0, return_counts=True)
    flags = np.zeros(n_vertices, dtype=bool)
    flags[uniq[counts == 1].ravel()] = True
    return flags


def region_flags(vertices: np.ndarray, triangles: np.ndarray, d: BioTacDimensions) -> tuple[np.ndarray, np.ndarray]:
    """Anchored and ventral flags of skin vertices (m, biotac frame) by the rules of ``d``.

    anchored: x <= proximal_x, or z >= dorsal_anchor_z, or on the mesh boundary.
    ventral: not anchored, x >= proximal_x + anchor_band and z <= dorsal_anchor_z - anchor_band.
    """
    tol = 1e-9
    x, z = vertices[:, 0], vertices[:, 2]
    anchored = (x <= d.proximal_x + tol) | (z >= d.dorsal_anchor_z - tol) | boundary_vertices(triangles, len(x))
    ventral = ~anchored & (x >= d.proximal_x + d.anchor_band) & (z <= d.dorsal_anchor_z - d.anchor_band)
    return anchored, ventral


def make_skin(max_edge: float, d: BioTacDimensions) -> SkinMesh:
    """Mesh the unpressurised skin mid-surface (free region + anchored band); every edge <= max_edge (m)."""
    h = 0.98 * max_edge
    cyl_v, cyl_t, seam_ids = _cylinder_part(d, h)
    cap_v, cap_t = _cap_part(d, h, cyl_v[seam_ids])
    n_cyl = len(cyl_v)
    # cap triangles index [seam, new]; map seam to cylinder ids, new vertices after the cylinder's
    index = np.concatenate([seam_ids, n_cyl + np.arange(len(cap_v))])
    vertices = np.vstack([cyl_v, cap_v])
    triangles = np.vstack([cyl_t, index[cap_t]])
    triangles = _orient_outward(vertices, triangles, d).astype(np.int32)
    anchored, ventral = region_flags(vertices, triangles, d)
    return SkinMesh(vertices=vertices, triangles=triangles, anchored=anchored, ventral=ventral)


# ----------------------------------------------------------------------------------------- core mesh


def _core_cut_planes(d: BioTacDimensions) -> tuple[np.ndarray, np.ndarray]:
    """Half-spaces n.p <= off bounding the core besides its capsule: dorsal top, tip bevel, proximal face."""
    normals = np.array([[0.0, 0.0, 1.0], BEVEL_NORMAL, [-1.0, 0.0, 0.0]])
    offsets = np.array([d.core_top_z, BEVEL_OFFSET, -d.core_proximal_x])
    return normals, offsets


def inside_core(points: np.ndarray, d: BioTacDimensions, tol: float = 0.0) -> np.ndarray:
    """(N,) bool: points (m, biotac frame) inside the analytic rigid core grown by tol (m)."""
    q = points.copy()
    q[:, 0] = np.maximum(q[:, 0] - d.core_tip_center_x, 0.0)
    inside = np.linalg.norm(q, axis=1) <= d.core_radius + tol
    normals, offsets = _core_cut_planes(d)
    return inside & np.all(points @ normals.T <= offsets + tol, axis=1)


def _capsule_points(radius: float, x0: float, x1: float, h: float) -> np.ndarray:
    """Points with spacing ~h on a cylinder about the x axis (x0..x1) capped by a hemisphere at x1."""
    n_phi = max(8, int(np.ceil(2.0 * np.pi * radius / h)))
    phi = 2.0 * np.pi * np.arange(n_phi) / n_phi
    xs = np.linspace(x0, x1, max(2, int(np.ceil((x1 - x0) / h)) + 1))
    xx, pp = np.meshgrid(xs, phi, indexing="ij")
    cyl = np.column_stack([xx.ravel(), radius * np.sin(pp.ravel()), -radius * np.cos(pp.ravel())])
    n_sph = max(16, int(np.ceil(2.0 * np.pi * radius**2 / h**2)))
    k = np.arange(n_sph) + 0.5
    cos_t = k / n_sph  # uniform on the hemisphere x >= 0 (Fibonacci spiral)
    ang = np.pi * (1.0 + np.sqrt(5.0)) * k
    sin_t = np.sqrt(1.0 - cos_t**2)
    sph = np.column_stack([x1 + radius * cos_t, radius * sin_t * np.sin(ang), radius * sin_t * np.cos(ang)])
    return np.vstack([cyl, sph])


def _core_centre(d: BioTacDimensions) -> np.ndarray:
    """A point (m) well inside the core, the centre of the radial map onto its boundary."""
    return np.array([0.5 * (d.core_proximal_x + d.core_tip_center_x), 0.0, 0.5 * (d.core_top_z - d.core_radius)])


def _largest_root(a: np.ndarray, b: np.ndarray, c: np.ndarray) -> np.ndarray:
    """Larger root of a t^2 + b t + c = 0 (c < 0: the ray starts inside); inf where a == 0."""
    with np.errstate(divide="ignore", invalid="ignore"):
        return np.where(a > 0.0, (-b + np.sqrt(np.maximum(b * b - 4.0 * a * c, 0.0))) / (2.0 * a), np.inf)


def project_to_core(points: np.ndarray, d: BioTacDimensions) -> np.ndarray:
    """(N, 3) m: where the rays from the core centre through the points leave the analytic core."""
    c = _core_centre(d)
    u = points - c
    r2 = d.core_radius**2
    t = _largest_root(u[:, 1] ** 2 + u[:, 2] ** 2, 2.0 * c[2] * u[:, 2], np.full(len(u), c[2] ** 2 - r2))
    beyond = c[0] + t * u[:, 0] > d.core_tip_center_x
    cs = c - np.array([d.core_tip_center_x, 0.0, 0.0])
    t_sphere = _largest_root(np.einsum("ij,ij->i", u, u), 2.0 * u @ cs, np.full(len(u), cs @ cs - r2))
    t = np.where(beyond, t_sphere, t)
    normals, offsets = _core_cut_planes(d)
    along = u @ normals.T
    with np.errstate(divide="ignore", invalid="ignore"):
        t_plane = np.where(along > 0.0, (offsets - c @ normals.T) / along, np.inf)
    return c + np.minimum(t, t_plane.min(axis=1))[:, None] * u


def make_core(max_edge: float, d: BioTacDimensions) -> CoreMesh:
    """Closed outward-oriented triangle surface of the convex rigid core (m).

    Capsule sample points (spacing max(max_edge, 0.3 mm)) and the electrode positions are mapped
    radially onto the core boundary and triangulated by their convex hull: every vertex is on the
    analytic core, flat faces and the edges between faces are exact, curved parts are chords
    (sagitta <= spacing^2 / (8 core_radius)). Triangles on flat faces and along the straight
    cylinder generators are long and thin (fine for distance queries, not for FE on the core).
    """
    h = max(max_edge, 0.3 * MM)
    pts = _capsule_points(d.core_radius, d.core_proximal_x - 2.0 * d.core_radius, d.core_tip_center_x, h)
    electrodes = electrode_table().positions
    pts = np.vstack([project_to_core(pts, d), electrodes[inside_core(electrodes, d, tol=1e-6)]])
    hull = ConvexHull(pts)
    tris = hull.simplices.copy()
    p = pts[tris]
    normal = np.cross(p[:, 1] - p[:, 0], p[:, 2] - p[:, 0])
    flip = np.einsum("ij,ij->i", normal, hull.equations[:, :3]) < 0.0
    tris[flip] = tris[flip][:, ::-1]
    used = np.unique(tris)
    remap = np.full(len(pts), -1)
    remap[used] = np.arange(len(used))
    return CoreMesh(vertices=pts[used], triangles=remap[tris].astype(np.int32))


# ----------------------------------------------------------------------------------------- volumes


def inside_skin_inner(points: np.ndarray, d: BioTacDimensions) -> np.ndarray:
    """(N,) bool: points (m) inside the inner skin surface of the full (unclipped) parametric skin."""
    return np.linalg.norm(_from_skin_axis(points, d), axis=1) < d.skin_inner_radius


def cavity_volume(d: BioTacDimensions, spacing: float = 0.1 * MM) -> float:
    """Unpressurised fluid volume (m^3) between the inner skin surface and the core over the free skin.

    Region: inside the inner skin surface, x >= proximal_x, z <= dorsal_anchor_z, outside the core;
    integrated by the midpoint rule on a grid of the given spacing (relative error ~1e-3 at 0.1 mm).
    """
    r = d.skin_inner_radius
    axes = [
        np.arange(d.proximal_x, d.tip_center_x + r, spacing) + 0.5 * spacing,
        np.arange(-r, r, spacing) + 0.5 * spacing,
        np.arange(d.axis_z - r, d.dorsal_anchor_z, spacing) + 0.5 * spacing,
    ]
    axes[2] = axes[2][axes[2] <= d.dorsal_anchor_z]
    count = 0
    for x in axes[0]:
        yy, zz = np.meshgrid(axes[1], axes[2], indexing="ij")
        p = np.column_stack([np.full(yy.size, x), yy.ravel(), zz.ravel()])
        count += int(np.count_nonzero(inside_skin_inner(p, d) & ~inside_core(p, d)))
    return count * spacing**3


def signed_volume(vertices: np.ndarray, triangles: np.ndarray, apex: np.ndarray) -> float:
    """Sum of signed volumes (m^3) of the tetrahedra (apex, triangle): for an open surface, the volume
    of the cone from ``apex`` over it; positive when the normals point away from the apex."""
    p = vertices[triangles] - apex
    return float(np.einsum("ij,ij->i", p[:, 0], np.cross(p[:, 1], p[:, 2])).sum() / 6.0)


# ----------------------------------------------------------------------------------------- public API


def vertex_normals(vertices: np.ndarray, triangles: np.ndarray) -> np.ndarray:
    """(V, 3) unit area-weighted vertex normals (orientation of the triangles)."""
    p = vertices[triangles]
    face = np.cross(p[:, 1] - p[:, 0], p[:, 2] - p[:, 0])
    acc = np.zeros_like(vertices)
    for k in range(3):
        np.add.at(acc, triangles[:, k], face)
    return _unit(acc)


def outer_surface(skin: SkinMesh, thickness: float) -> np.ndarray:
    """(V, 3) m: the mid-surface vertices offset by thickness/2 (m) along area-weighted vertex normals."""
    if not np.isfinite(thickness) or thickness < 0.0:
        raise ValueError(f"outer_surface: thickness must be a finite non-negative length in m, got {thickness!r}")
    return skin.vertices + 0.5 * thickness * vertex_normals(skin.vertices, skin.triangles)


def project_to_skin(points: np.ndarray, d: BioTacDimensions) -> np.ndarray:
    """(N, 3) m: the closest points to `points` (N, 3) m, biotac frame, of the capsule the unpressurised skin
    mid-surface lies on (its cylinder for x <= tip_center_x, its tip sphere beyond; not cut where the mesh ends).
    A point on the skin's axis has no closest point (NaN)."""
    radial = _from_skin_axis(points, d)
    return points - radial + d.skin_mid_radius * _unit(radial)


def refine_skin(skin: SkinMesh, refinement: Refinement, d: BioTacDimensions) -> SkinMesh:
    """`skin` with its edges halved `refinement.levels` times about the skin point nearest `refinement.centre`
    (`assets.refine.refine_near`), new vertices on the mid-surface, regions flagged again by the rules of `d`."""
    centre = project_to_skin(np.asarray(refinement.centre, dtype=float)[None], d)[0]
    refined = refine_near(
        skin.vertices, skin.triangles, centre, refinement.radius, refinement.levels, lambda p: project_to_skin(p, d)
    )
    anchored, ventral = region_flags(refined.vertices, refined.triangles, d)
    return SkinMesh(refined.vertices, refined.triangles, anchored, ventral)


def make_biotac(
    max_edge: float = 0.5e-3, dims: BioTacDimensions = DEFAULT_DIMENSIONS, refinement: Refinement | None = None
) -> BioTacGeometry:
    """Parametric BioTac geometry: skin mid-surface mesh (edges <= max_edge, m; finer about a press point with
    a `refinement`), core mesh, electrodes."""
    d = dims
    if not np.isfinite(max_edge) or max_edge <= 0.0:
        raise ValueError(f"make_biotac: max_edge must be a positive length in metres, got {max_edge!r}")
    if max_edge > 0.5 * d.skin_mid_radius:
        raise ValueError(
            f"make_biotac: max_edge {max_edge!r} m is too coarse (limit {0.5 * d.skin_mid_radius:.4g} m); "
            "did you pass millimetres?"
        )
    skin = make_skin(max_edge, d)
    return BioTacGeometry(
        skin=skin if refinement is None else refine_skin(skin, refinement, d),
        core=make_core(max_edge, d),
        electrodes=electrode_table(),
        dorsal_top_z=d.dorsal_top_z,
        core_gap=0.5 * d.skin_thickness,
        cavity_volume_reference=cavity_volume(d),
        dims=d,
    )


def sample_ventral_points(geometry: BioTacGeometry, n: int, rng: np.random.Generator) -> tuple[np.ndarray, np.ndarray]:
    """Area-uniform random points on the OUTER unpressurised skin surface over the ventral region.

    The outer surface is the mid-surface offset by ``core_gap`` (half the skin thickness). Returns
    points (n, 3) m and outward unit normals (n, 3), biotac frame. Reproducible for a seeded rng.
    """
    if n < 0:
        raise ValueError(f"sample_ventral_points: n must be >= 0, got {n!r}")
    skin = geometry.skin
    tris = skin.triangles[skin.ventral[skin.triangles].all(axis=1)]
    if len(tris) == 0:
        raise ValueError("sample_ventral_points: the skin mesh has no ventral triangles")
    outer = outer_surface(skin, 2.0 * geometry.core_gap)
    normals = vertex_normals(skin.vertices, skin.triangles)
    p = outer[tris]
    area = 0.5 * np.linalg.norm(np.cross(p[:, 1] - p[:, 0], p[:, 2] - p[:, 0]), axis=1)
    pick = rng.choice(len(tris), size=n, p=area / area.sum())
    u, v = rng.random(n), rng.random(n)
    fold = u + v > 1.0
    u[fold], v[fold] = 1.0 - u[fold], 1.0 - v[fold]
    w = np.column_stack([1.0 - u - v, u, v])
    points = np.einsum("nk,nkj->nj", w, p[pick])
    return points, _unit(np.einsum("nk,nkj->nj", w, normals[tris[pick]]))
