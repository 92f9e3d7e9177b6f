"""Fit of the parametric BioTac skin to the public unpressurised FE mesh, and its error.

Usage: python benchmarks/geometry_fit.py [--reference DIR] [--max-edge M]

Prints (mm): the file->biotac frame check, the least-squares fit of the skin cylinder + hemisphere
over the free skin, the RMS / max distance between the parametric OUTER skin surface and the
reference outer surface over the ventral region (both directions), thicknesses, the core against the
electrode table, and the unpressurised cavity volumes. Needs ../shared/reference (not shipped).
"""

from __future__ import annotations

import argparse
from pathlib import Path

import numpy as np
import trimesh
from scipy.optimize import least_squares

from assets.biotac import (
    BEVEL_NORMAL,
    BEVEL_OFFSET,
    DEFAULT_DIMENSIONS,
    BioTacDimensions,
    electrode_table,
    make_biotac,
    outer_surface,
)
from assets.reference_mesh import (
    FILE_TO_BIOTAC_X,
    file_to_biotac,
    load_reference_biotac,
    load_reference_core,
    load_tet_mesh,
    point_mesh_distance,
    split_components,
    tet_boundary,
    to_biotac_frame,
)

MM = 1e-3
DEFAULT_REFERENCE = Path(__file__).resolve().parents[2] / "shared" / "reference" / "biotac_sim" / "meshes" / "biotac"


def skin_radial_residual(points: np.ndarray, axis_z: float, radius: float, tip_x: float) -> np.ndarray:
    """Signed distance (m) of points to a cylinder (axis y = 0, z = axis_z) + hemisphere at tip_x."""
    q = points - np.array([tip_x, 0.0, axis_z])
    q[:, 0] = np.maximum(q[:, 0], 0.0)
    return np.linalg.norm(q, axis=1) - radius


def fit_skin(outer: np.ndarray, inner: np.ndarray, d: BioTacDimensions) -> dict[str, float]:
    """Least-squares axis_z, tip_center_x, outer and inner radius over the free skin (m)."""

    def free(p: np.ndarray) -> np.ndarray:
        return p[(p[:, 0] >= d.proximal_x) & (p[:, 2] <= d.dorsal_anchor_z)]

    po, pi = free(outer), free(inner)

    def residual(c: np.ndarray) -> np.ndarray:
        return np.concatenate([skin_radial_residual(po, c[0], c[2], c[1]), skin_radial_residual(pi, c[0], c[3], c[1])])

    fit = least_squares(residual, [d.axis_z, d.tip_center_x, d.skin_outer_radius, d.skin_inner_radius])
    axis_z, tip_x, r_out, r_in = fit.x
    return {
        "axis_z": axis_z,
        "tip_center_x": tip_x,
        "skin_outer_radius": r_out,
        "skin_thickness": r_out - r_in,
    }


def bevel_shift(core_vertices_file: np.ndarray, core_triangles: np.ndarray, radius_excess: float) -> float:
    """x shift (m) putting the file core's tip bevel on n.p = BEVEL_OFFSET + radius_excess (biotac frame)."""
    p = (core_vertices_file @ file_to_biotac()[:3, :3].T)[core_triangles]
    normal = np.cross(p[:, 1] - p[:, 0], p[:, 2] - p[:, 0])
    normal /= np.linalg.norm(normal, axis=1, keepdims=True)
    on_bevel = normal @ BEVEL_NORMAL > 0.995
    offset = float(np.mean(p[on_bevel].mean(axis=1) @ BEVEL_NORMAL))
    return (BEVEL_OFFSET + radius_excess - offset) / BEVEL_NORMAL[0]


def core_radius_fit(core_vertices: np.ndarray) -> float:
    """Mean distance (m) from the x axis of the core vertices on its ventral cylinder."""
    p = core_vertices[(core_vertices[:, 0] > -12 * MM) & (core_vertices[:, 0] < -1 * MM)]
    p = p[p[:, 2] < 0.0]
    return float(np.hypot(p[:, 1], p[:, 2]).mean())


def rms_max(values: np.ndarray) -> str:
    rms = np.sqrt(np.mean(values**2))
    return f"RMS {rms / MM:.3f} mm, max {np.abs(values).max() / MM:.3f} mm (n={len(values)})"


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--reference", type=Path, default=DEFAULT_REFERENCE)
    parser.add_argument("--max-edge", type=float, default=0.5e-3, help="parametric mesh edge (m)")
    args = parser.parse_args()
    tet_path = args.reference / "int_ext_skin" / "int_ext_skin_combined_ftw.tet"
    core_path = args.reference / "bc" / "top_side_core_bc.obj"
    d = DEFAULT_DIMENSIONS

    file_v, tets = load_tet_mesh(tet_path)
    outer, inner = split_components(to_biotac_frame(file_v), tet_boundary(file_v, tets))
    core = load_reference_core(core_path)
    r_core = core_radius_fit(core.vertices)
    raw = trimesh.load(core_path, process=False, force="mesh")
    raw_v, raw_t = split_components(np.asarray(raw.vertices), np.asarray(raw.faces))[0]
    shift = bevel_shift(raw_v, raw_t, r_core - 5.08 * MM)
    print("frame: p_biotac = [[-1,0,0],[0,0,1],[0,1,0]] p_file + (tx, 0, 0)")
    print(f"  tx from the core bevel: {shift / MM:.3f} mm (module constant {FILE_TO_BIOTAC_X / MM:.3f} mm)")
    print(f"  reference core radius {r_core / MM:.3f} mm vs electrode radius 5.080 mm")

    fit = fit_skin(outer[0], inner[0], d)
    print("least-squares skin fit over the free skin (x >= proximal_x, z <= dorsal_anchor_z):")
    for name, value in fit.items():
        print(f"  {name:18s} fit {value / MM:8.3f} mm   default {getattr(d, name) / MM:8.3f} mm")
    print("defaults (mm):", {k: round(v / MM, 3) for k, v in vars(d).items()})

    geo = make_biotac(args.max_edge, d)
    mine = outer_surface(geo.skin, 2.0 * geo.core_gap)
    ventral_ref = outer[0][
        (outer[0][:, 0] >= d.proximal_x + d.anchor_band) & (outer[0][:, 2] <= d.dorsal_anchor_z - d.anchor_band)
    ]
    ref_to_mine = point_mesh_distance(ventral_ref, mine, geo.skin.triangles)
    mine_to_ref = point_mesh_distance(mine[geo.skin.ventral], *outer)
    print(f"outer skin distance over the ventral region, parametric mesh max_edge {args.max_edge / MM:.2f} mm:")
    print("  reference -> parametric:", rms_max(ref_to_mine))
    print("  parametric -> reference:", rms_max(mine_to_ref))

    print("unpressurised sensor thickness (dorsal_top_z - min z of the outer skin):")
    print(
        f"  parametric {(geo.dorsal_top_z - mine[:, 2].min()) / MM:.3f} mm, "
        f"reference {np.ptp(outer[0][:, 2]) / MM:.3f} mm (inflated real sensor 15.1 mm)"
    )

    el = electrode_table()
    dist = point_mesh_distance(el.positions, core.vertices, core.triangles)
    print(f"electrodes to the reference core: mean {dist.mean() / MM:.3f} mm, max {dist.max() / MM:.3f} mm")
    ref = load_reference_biotac(tet_path, core_path)
    print(
        f"cavity volume (free skin): parametric {geo.cavity_volume_reference * 1e9:.1f} mm^3, "
        f"reference {ref.cavity_volume_reference * 1e9:.1f} mm^3"
    )
    print(f"core_gap: parametric {geo.core_gap / MM:.3f} mm, reference {ref.core_gap / MM:.3f} mm")


if __name__ == "__main__":
    main()
