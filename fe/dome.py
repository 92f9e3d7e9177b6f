"""Dome benchmark: a hemispherical membrane pinned to a rigid base, fluid-filled, indented at the apex.

Close to the BioTac's own situation (a fluid-backed skin anchored along its edge) yet simple enough
for an independent axisymmetric solution (`fe.axisymmetric`). Lengths in metres, pressures in Pa.
"""

from dataclasses import dataclass, replace

import numpy as np

from assets.indenters import KIND_SPHERE, Indenter
from assets.refine import refine_near
from fe.batched import InflatedSkin
from fe.batched_stepper import BatchedStepper
from fe.indentation import IncrementResult, IndentationStepper, Trajectory, drive
from fe.params import ContactSettings, SkinParameters
from fe.shell import ShellMesh
from fe.surface_quadrature import rule


def _zip_rings(lower: np.ndarray, upper: np.ndarray, lower_angles: np.ndarray, upper_angles: np.ndarray) -> list:
    """Triangulate the band between two closed vertex rings (indices, azimuths in [0, 2 pi))."""
    tris, i, j, n, m = [], 0, 0, len(lower), len(upper)
    while i < n or j < m:
        next_lower = lower_angles[i + 1] if i + 1 < n else 2 * np.pi + lower_angles[0]
        next_upper = upper_angles[j + 1] if j + 1 < m else 2 * np.pi + upper_angles[0]
        if j >= m or (i < n and next_lower <= next_upper):
            tris.append((lower[i % n], lower[(i + 1) % n], upper[j % m]))
            i += 1
        else:
            tris.append((lower[i % n], upper[(j + 1) % m], upper[j % m]))
            j += 1
    return tris


def hemisphere_mesh(radius: float, max_edge: float) -> ShellMesh:
    """Hemisphere z >= 0 (m) from latitude rings, apex vertex first, rim ring at z = 0 held fixed.

    Triangles are oriented with outward normals (away from the base centre).
    """
    if radius <= 0 or max_edge <= 0:
        raise ValueError("radius and max_edge must be positive")
    n_rings = max(2, int(np.ceil(0.5 * np.pi * radius / max_edge)))
    vertices, rings, angles = [np.array([0.0, 0.0, radius])], [np.array([0])], [np.array([0.0])]
    for k in range(1, n_rings + 1):
        polar = 0.5 * np.pi * k / n_rings
        count = max(6, int(np.ceil(2 * np.pi * radius * np.sin(polar) / max_edge)))
        phase = 0.5 * (k % 2) * 2 * np.pi / count
        az = (np.arange(count) * 2 * np.pi / count + phase) % (2 * np.pi)
        order = np.argsort(az)
        az = az[order]
        ring_xyz = radius * np.column_stack(
            [np.sin(polar) * np.cos(az), np.sin(polar) * np.sin(az), np.full(count, np.cos(polar))]
        )
        if k == n_rings:
            ring_xyz[:, 2] = 0.0
        start = sum(len(r) for r in rings)
        rings.append(np.arange(start, start + count))
        angles.append(az)
        vertices.append(ring_xyz)
    tris = []
    for k in range(1, len(rings)):
        # Outer ring k (larger polar angle) is "lower"; zip it with the ring above, apex fan included.
        tris.extend(_zip_rings(rings[k], rings[k - 1], angles[k], angles[k - 1]))
    v = np.vstack(vertices)
    t = np.asarray([tri for tri in tris if len(set(tri)) == 3], dtype=np.int32)
    normals = np.cross(v[t[:, 1]] - v[t[:, 0]], v[t[:, 2]] - v[t[:, 0]])
    flip = np.einsum("ij,ij->i", normals, v[t].mean(axis=1)) < 0
    t[flip] = t[flip][:, ::-1]
    fixed = np.zeros(len(v), dtype=bool)
    fixed[rings[-1]] = True
    return ShellMesh(v, t, fixed)


def disk_mesh(radius: float, max_edge: float, clamp_rings: int = 2) -> ShellMesh:
    """Flat disk z = 0 (m) of concentric rings, normals +z, centre vertex first; the ring at `radius` and
    `clamp_rings` rings beyond it are held fixed, so the plate edge is clamped (no deflection, no slope)."""
    if radius <= 0 or max_edge <= 0 or clamp_rings < 1:
        raise ValueError("radius and max_edge must be positive and clamp_rings at least 1")
    n_rings = max(2, int(np.ceil(radius / max_edge)))
    step = radius / n_rings
    vertices, rings, angles = [np.zeros((1, 3))], [np.array([0])], [np.array([0.0])]
    for k in range(1, n_rings + clamp_rings + 1):
        count = max(6, int(np.ceil(2 * np.pi * k * step / max_edge)))
        az = np.sort((np.arange(count) * 2 * np.pi / count + 0.5 * (k % 2) * 2 * np.pi / count) % (2 * np.pi))
        start = sum(len(r) for r in rings)
        rings.append(np.arange(start, start + count))
        angles.append(az)
        vertices.append(np.column_stack([k * step * np.cos(az), k * step * np.sin(az), np.zeros(count)]))
    tris = [tri for k in range(1, len(rings)) for tri in _zip_rings(rings[k], rings[k - 1], angles[k], angles[k - 1])]
    v = np.vstack(vertices)
    t = np.asarray([tri for tri in tris if len(set(tri)) == 3], dtype=np.int32)
    flip = np.cross(v[t[:, 1]] - v[t[:, 0]], v[t[:, 2]] - v[t[:, 0]])[:, 2] < 0
    t[flip] = t[flip][:, ::-1]
    fixed = np.linalg.norm(v[:, :2], axis=1) >= radius * (1 - 1e-9)
    return ShellMesh(v, t, fixed)


def refined_at_apex(mesh: ShellMesh, radius: float, levels: int) -> ShellMesh:
    """`mesh` (a hemisphere about the origin, apex on +z) with its edges halved `levels` times within
    `radius` (m) of the apex (`assets.refine.refine_near`); new vertices on the sphere, held where both
    vertices of their edge are."""
    apex = mesh.vertices[np.argmax(mesh.vertices[:, 2])]
    sphere = np.linalg.norm(apex)

    def onto_sphere(p: np.ndarray) -> np.ndarray:
        return sphere * p / np.linalg.norm(p, axis=1, keepdims=True)

    refined = refine_near(mesh.vertices, mesh.triangles, apex, radius, levels, onto_sphere)
    fixed = np.concatenate([mesh.fixed, np.zeros(len(refined.parents), dtype=bool)])
    for i, (a, b) in enumerate(refined.parents, start=len(mesh.vertices)):  # a level's parents may be new ones
        fixed[i] = fixed[a] and fixed[b]
    return ShellMesh(refined.vertices, refined.triangles, fixed)


def _contact_radius(x: np.ndarray, triangles: np.ndarray, centre: np.ndarray, radius: float, rule_name: str) -> float:
    """Largest distance (m) from the z axis of the contact quadrature points (the surface rule `rule_name`) of
    the skin at x (V, 3) m that lie inside the sphere (centre (3,) m, radius m): where the contact acts."""
    q = np.einsum("qk,tkd->tqd", rule(rule_name)[:, :3], x[triangles]).reshape(-1, 3)
    inside = np.linalg.norm(q - centre, axis=1) < radius
    return float(np.linalg.norm(q[inside, :2], axis=1).max(initial=0.0))


def contact_refinement(max_edge: float, indenter_radius: float) -> tuple[int, float]:
    """(levels, radius m) that resolve a sphere's contact patch at the apex of a mesh of `max_edge` (m): the
    finest edge at most a tenth of the indenter radius, and at least one level (1-3), within three coarse edges
    of the apex. Measured (docs/fe.md, session 35): within 1.8 % of the axisymmetric reference at every depth
    0.25 ... 1.5 mm for spheres of 1.5-10 mm on the 0.5 mm mesh, V/V0 1.1-1.5 (uniform: up to 7.1 %)."""
    return int(np.clip(np.ceil(np.log2(10.0 * max_edge / indenter_radius)), 1, 3)), 3.0 * max_edge


@dataclass(frozen=True)
class DomeResult:
    """Inflated state and indentation increments of the dome benchmark; the mesh's vertex count and the levels
    and radius (m) of its refinement at the apex."""

    reference_volume: float
    inflated_volume: float
    inflated_pressure: float
    apex_height: float
    increments: list[IncrementResult]
    vertices: int
    refine_levels: int
    refine_radius: float


def run_dome(
    radius: float,
    thickness: float,
    mu: float,
    volume_ratio: float,
    bending: bool = False,
    indenter_radius: float | None = None,
    depths: np.ndarray | None = None,
    max_edge: float | None = None,
    contact: ContactSettings = ContactSettings(),
    refine_levels: int | None = None,
    refine_radius: float | None = None,
) -> DomeResult:
    """Inflate the dome to `volume_ratio` V0 with volume control, then optionally indent its apex.

    The indenter is a frictionless rigid sphere touching the skin mid-surface; depth 0 is first touch. An
    increment's contact radius is that of its contact quadrature points inside the sphere (`_contact_radius`).
    `refine_levels` halves the mesh's edges that many times within `refine_radius` (m) of the apex
    (`refined_at_apex`), where the contact patch is; None: `contact_refinement`'s with an indenter, none without.
    """
    if volume_ratio <= 0:
        raise ValueError("volume_ratio must be positive")
    edge = max_edge or radius / 12
    auto = contact_refinement(edge, indenter_radius) if indenter_radius is not None else (0, 3.0 * edge)
    levels = auto[0] if refine_levels is None else refine_levels
    reach = auto[1] if refine_radius is None else refine_radius
    mesh = refined_at_apex(hemisphere_mesh(radius, edge), reach, levels)
    params = SkinParameters(thickness=thickness, mu_nh=mu, friction=0.0, bending=bending)
    rest = InflatedSkin.at_rest(mesh.vertices, mesh.triangles, mesh.fixed, params, contact, indenter_offset=0.0)
    sphere = Indenter("dome_sphere", KIND_SPHERE, (indenter_radius or radius, 0.0, 0.0, 0.0), "frictionless sphere")
    engine = BatchedStepper(rest, [sphere])
    v0 = engine.rest_volumes[0]
    for target in np.linspace(1.0, volume_ratio, max(2, int(np.ceil(abs(volume_ratio - 1) / 0.05)) + 1))[1:]:
        converged, message = engine.hold_volume(np.array([target * v0]))
        if not converged[0]:
            raise RuntimeError(f"dome inflation did not converge at V/V0={target:.3f}: {message[0]}")
    x_ref, pressure = engine.x[0].copy(), float(engine.pressure[0])
    apex = x_ref[0].copy()
    increments = []
    if indenter_radius is not None and depths is not None:
        push = np.array([0.0, 0.0, -1.0])
        # Indenter frame: body along +z, presses along -z; pushing down needs no rotation.
        trajectory = Trajectory(apex, push, np.eye(3), np.asarray(depths, dtype=float))
        inflated = replace(rest, reference=x_ref, pressure=pressure, target_volume=volume_ratio * v0)
        for inc in drive(IndentationStepper(inflated, sphere, apex), trajectory):
            centre = apex + (inc.depth - indenter_radius) * push  # the sphere's centre, m
            x = x_ref + inc.displacement
            at = _contact_radius(x, mesh.triangles, centre, indenter_radius, contact.surface_rule)
            increments.append(replace(inc, contact_radius=at))
    return DomeResult(v0, volume_ratio * v0, pressure, float(apex[2]), increments, len(mesh.vertices), levels, reach)
