"""Importer for the public BioTac FE meshes (NVlabs/biotac_sim, MIT) into the project's description.

Optional: the product never needs these files; this module lets a user who has them build a
``BioTacGeometry`` from the published unpressurised skin tet mesh and core boundary mesh, and lets the
benchmarks check the parametric model against them.

File frame -> biotac frame. In the files (metres) the indenter approaches along +y, the sensor tip
is at -x, and z is lateral. The biotac frame (x distal, -z ventral) is
``p_biotac = R p_file + t`` with ``R = [[-1, 0, 0], [0, 0, 1], [0, 1, 0]]`` (a proper rotation, det +1)
and ``t = (FILE_TO_BIOTAC_X, 0, 0)``: the core mesh's cylinder axis is already at file y = z = 0 (the
manual's x axis), and the x shift puts the core's 30-degree tip bevel on the manual's electrode plane
n.p = 4.40 mm shifted outward by the 0.26 mm by which the file's core (radius 5.34 mm) exceeds the
electrode radius (5.08 mm). ``benchmarks/geometry_fit.py`` re-derives the shift.
"""

from __future__ import annotations

from os import PathLike

import numpy as np
import trimesh
from scipy.sparse import coo_matrix
from scipy.sparse.csgraph import connected_components
from scipy.spatial import cKDTree

from assets.biotac import (
    DEFAULT_DIMENSIONS,
    BioTacDimensions,
    BioTacGeometry,
    CoreMesh,
    SkinMesh,
    electrode_table,
    region_flags,
    signed_volume,
    skin_cut_z,
    vertex_normals,
)

#: x translation (m) from the public files' frame to the biotac frame (see module docstring).
FILE_TO_BIOTAC_X = -12.27e-3
_FILE_TO_BIOTAC_ROTATION = np.array([[-1.0, 0.0, 0.0], [0.0, 0.0, 1.0], [0.0, 1.0, 0.0]])


def file_to_biotac() -> np.ndarray:
    """4x4 homogeneous transform from the public meshes' frame to the biotac frame (m)."""
    transform = np.eye(4)
    transform[:3, :3] = _FILE_TO_BIOTAC_ROTATION
    transform[0, 3] = FILE_TO_BIOTAC_X
    return transform


def to_biotac_frame(points: np.ndarray) -> np.ndarray:
    """(N, 3) points (m) of the public meshes' frame expressed in the biotac frame."""
    transform = file_to_biotac()
    return points @ transform[:3, :3].T + transform[:3, 3]


def load_tet_mesh(path: str | PathLike) -> tuple[np.ndarray, np.ndarray]:
    """Read a ``.tet`` text mesh: lines ``v x y z w`` (metres) and ``t i j k l`` (0-based).

    Returns vertices (N, 3) float64 m in the file's frame and tets (M, 4) int64.
    """
    vertices, tets = [], []
    with open(path) as handle:
        for line in handle:
            parts = line.split()
            if parts and parts[0] == "v":
                vertices.append([float(p) for p in parts[1:4]])
            elif parts and parts[0] == "t":
                tets.append([int(p) for p in parts[1:5]])
    if not vertices or not tets:
        raise ValueError(f"load_tet_mesh: {path} has no 'v' or no 't' lines")
    v, t = np.asarray(vertices, dtype=np.float64), np.asarray(tets, dtype=np.int64)
    if t.min() < 0 or t.max() >= len(v):
        raise ValueError(f"load_tet_mesh: {path} has tet indices outside 0..{len(v) - 1}")
    return v, t


def tet_boundary(vertices: np.ndarray, tets: np.ndarray) -> np.ndarray:
    """(F, 3) boundary faces of a tet mesh, oriented with normals pointing out of the solid."""
    local = np.array([[1, 2, 3, 0], [0, 3, 2, 1], [0, 1, 3, 2], [0, 2, 1, 3]])  # face + opposite vertex
    faces = tets[:, local].reshape(-1, 4)
    key = np.sort(faces[:, :3], axis=1)
    _, inverse, counts = np.unique(key, axis=0, return_inverse=True, return_counts=True)
    faces = faces[counts[inverse.ravel()] == 1]
    p = vertices[faces]
    normal = np.cross(p[:, 1] - p[:, 0], p[:, 2] - p[:, 0])
    inward = np.einsum("ij,ij->i", normal, p[:, 3] - p[:, 0]) > 0.0
    tris = faces[:, :3].copy()
    tris[inward] = tris[inward][:, ::-1]
    return tris


def split_components(vertices: np.ndarray, triangles: np.ndarray) -> list[tuple[np.ndarray, np.ndarray]]:
    """Connected components of a triangle surface, each re-indexed, largest (most vertices) first."""
    n = len(vertices)
    rows = np.repeat(triangles, 3, axis=1).ravel()
    cols = np.tile(triangles, 3).ravel()
    graph = coo_matrix((np.ones(len(rows)), (rows, cols)), shape=(n, n))
    _, labels = connected_components(graph, directed=False)
    parts = []
    for label in np.unique(labels[triangles[:, 0]]):
        tris = triangles[labels[triangles[:, 0]] == label]
        used = np.unique(tris)
        remap = np.full(n, -1)
        remap[used] = np.arange(len(used))
        parts.append((vertices[used], remap[tris]))
    return sorted(parts, key=lambda part: -len(part[0]))


def point_mesh_distance(points: np.ndarray, vertices: np.ndarray, triangles: np.ndarray, k: int = 12) -> np.ndarray:
    """(N,) unsigned distance (m) from points to a triangle surface.

    Candidate triangles are those incident to the k nearest mesh vertices (exact for a reasonably
    uniform surface mesh closer than a few edge lengths; an upper bound otherwise).
    """
    k = min(k, len(vertices))
    _, near = cKDTree(vertices).query(points, k=k)
    near = near.reshape(len(points), k)
    incident = [[] for _ in range(len(vertices))]
    for f, tri in enumerate(triangles):
        for vid in tri:
            incident[vid].append(f)
    best = np.full(len(points), np.inf)
    for column in range(k):
        lists = [incident[v] for v in near[:, column]]
        counts = np.array([len(item) for item in lists])
        if counts.sum() == 0:
            continue
        faces = np.concatenate([np.asarray(item, dtype=np.int64) for item in lists])
        owner = np.repeat(np.arange(len(points)), counts)
        closest = trimesh.triangles.closest_point(vertices[triangles[faces]], points[owner])
        dist = np.linalg.norm(closest - points[owner], axis=1)
        np.minimum.at(best, owner, dist)
    return best


def _inside_closed_mesh(vertices: np.ndarray, triangles: np.ndarray, grid: list[np.ndarray]) -> np.ndarray:
    """(nx, ny, nz) bool: grid points inside a closed surface, by the parity of +x ray crossings."""
    xs, ys, zs = grid
    p = vertices[triangles]
    inside = np.zeros((len(xs), len(ys), len(zs)), dtype=bool)
    ymin, ymax = p[:, :, 1].min(axis=1), p[:, :, 1].max(axis=1)
    for j, y in enumerate(ys):
        rows = np.flatnonzero((ymin <= y) & (ymax >= y))
        if len(rows) == 0:
            continue
        a, b, c = p[rows, 0], p[rows, 1], p[rows, 2]
        det = (b[:, 1] - a[:, 1]) * (c[:, 2] - a[:, 2]) - (c[:, 1] - a[:, 1]) * (b[:, 2] - a[:, 2])
        ok = np.abs(det) > 1e-30
        a, b, c, det = a[ok], b[ok], c[ok], det[ok]
        dy, dz = y - a[:, 1], zs[:, None] - a[None, :, 2]
        u = (dy * (c[:, 2] - a[:, 2]) - dz * (c[:, 1] - a[:, 1])) / det
        v = (dz * (b[:, 1] - a[:, 1]) - dy * (b[:, 2] - a[:, 2])) / det
        hit = (u >= 0.0) & (v >= 0.0) & (u + v <= 1.0)
        x_hit = a[:, 0] + u * (b[:, 0] - a[:, 0]) + v * (c[:, 0] - a[:, 0])
        crossings = (hit[None] & (x_hit[None] > xs[:, None, None])).sum(axis=2)
        inside[:, j, :] = crossings % 2 == 1
    return inside


def _reference_cavity_volume(
    inner: tuple[np.ndarray, np.ndarray], core: CoreMesh, d: BioTacDimensions, spacing: float = 0.2e-3
) -> float:
    """Fluid volume (m^3) inside the reference inner skin surface and outside the core, over the free
    skin (x >= proximal_x, z <= dorsal_anchor_z); midpoint rule on a grid (offset to avoid edge hits)."""
    lo, hi = inner[0].min(axis=0), inner[0].max(axis=0)
    lo[0], hi[2] = max(lo[0], d.proximal_x), min(hi[2], d.dorsal_anchor_z)
    grid = [np.arange(lo[i], hi[i], spacing) + spacing * (0.5 + 0.0123 * (i + 1)) for i in range(3)]
    grid = [axis[axis < hi[i]] for i, axis in enumerate(grid)]
    fluid = _inside_closed_mesh(*inner, grid) & ~_inside_closed_mesh(core.vertices, core.triangles, grid)
    return float(np.count_nonzero(fluid) * spacing**3)


def _oriented_closed(vertices: np.ndarray, triangles: np.ndarray) -> CoreMesh:
    """A closed surface as a CoreMesh with outward normals (flipped if its signed volume is negative)."""
    if signed_volume(vertices, triangles, vertices.mean(axis=0)) < 0.0:
        triangles = triangles[:, ::-1]
    return CoreMesh(vertices=np.ascontiguousarray(vertices), triangles=np.ascontiguousarray(triangles, np.int32))


def load_reference_core(core_obj_path: str | PathLike) -> CoreMesh:
    """The core body of ``top_side_core_bc.obj`` in the biotac frame (m).

    The file also holds two small boxes (the nail plate and the proximal clamp used as boundary
    conditions); only the largest component, the core itself, is returned.
    """
    mesh = trimesh.load(core_obj_path, process=False, force="mesh")
    body_v, body_t = split_components(np.asarray(mesh.vertices), np.asarray(mesh.faces))[0]
    return _oriented_closed(to_biotac_frame(body_v), body_t)


def _clip_to_region(vertices: np.ndarray, triangles: np.ndarray, d: BioTacDimensions) -> tuple[np.ndarray, np.ndarray]:
    """Keep the largest connected piece of triangles inside x >= proximal_x - band, z <= skin_cut_z."""
    keep_v = (vertices[:, 0] >= d.proximal_x - d.anchor_band) & (vertices[:, 2] <= skin_cut_z(d))
    tris = triangles[keep_v[triangles].all(axis=1)]
    return split_components(vertices, tris)[0]


def load_reference_biotac(
    tet_path: str | PathLike,
    core_obj_path: str | PathLike | None = None,
    max_edge: float | None = None,
    dims: BioTacDimensions = DEFAULT_DIMENSIONS,
) -> BioTacGeometry:
    """Build a BioTacGeometry from the public unpressurised skin tet mesh (and core mesh).

    The tet mesh's boundary splits into an outer and an inner skin surface. The mid-surface is the
    outer surface moved inward along its vertex normals by half the local skin thickness (distance
    to the inner surface), clipped to the free region plus anchored band and flagged by the rules of
    ``dims`` (proximal_x, dorsal_anchor_z, anchor_band). The core is the core body of
    ``core_obj_path`` if given, else the closed inner skin surface (then the cavity volume is 0). If
    ``max_edge`` (m) is given, the mid-surface triangles are bisected until every edge is shorter.
    ``core_gap`` is half the median local thickness over the free skin; ``dorsal_top_z`` is the
    highest z of the outer surface; ``cavity_volume_reference`` as for the parametric model.
    """
    file_v, tets = load_tet_mesh(tet_path)
    vertices = to_biotac_frame(file_v)
    surfaces = split_components(vertices, tet_boundary(vertices, tets))
    if len(surfaces) != 2:
        raise ValueError(f"load_reference_biotac: expected 2 boundary surfaces, found {len(surfaces)}")
    outer, inner = surfaces
    thickness = point_mesh_distance(outer[0], *inner)
    mid = outer[0] - 0.5 * thickness[:, None] * vertex_normals(*outer)
    mid_v, mid_t = _clip_to_region(mid, outer[1], dims)
    if max_edge is not None:
        if not np.isfinite(max_edge) or max_edge <= 0.0:
            raise ValueError(f"load_reference_biotac: max_edge must be a positive length in m, got {max_edge!r}")
        mid_v, mid_t = trimesh.remesh.subdivide_to_size(mid_v, mid_t, max_edge, max_iter=20)
    mid_t = np.asarray(mid_t, dtype=np.int32)
    anchored, ventral = region_flags(mid_v, mid_t, dims)
    core = load_reference_core(core_obj_path) if core_obj_path is not None else _oriented_closed(*inner)
    free = (outer[0][:, 0] > dims.proximal_x) & (outer[0][:, 2] < dims.dorsal_anchor_z)
    return BioTacGeometry(
        skin=SkinMesh(vertices=mid_v, triangles=mid_t, anchored=anchored, ventral=ventral),
        core=core,
        electrodes=electrode_table(),
        dorsal_top_z=float(outer[0][:, 2].max()),
        core_gap=float(0.5 * np.median(thickness[free])),
        cavity_volume_reference=_reference_cavity_volume(inner, core, dims),
        dims=dims,
    )
