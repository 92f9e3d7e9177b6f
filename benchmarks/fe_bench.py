"""FE speed and mesh-convergence table: nodes, wall time and Newton iterations per 0.1 mm increment,
and the force change between a default and a finer mesh at the final depth.

    python benchmarks/fe_bench.py [--meshes-mm 0.5,0.35] [--depth-mm 3] [--indenter sphere_medium]

The issue's target on the 2-core CPU: at most 1 s per 0.1 mm increment at >= 4000 skin nodes.
s / increment is the median wall time of the loaded increments; Newton / incr. their mean iteration count.
"""

import argparse
import time

import numpy as np
from rich.console import Console
from rich.table import Table

from assets.biotac import make_biotac
from fe.sensor import BioTacModel


def run(mesh_mm: float, indenter: str, point_mm: list[float], depth_mm: float, step_mm: float) -> dict:
    """Inflate and indent once on a mesh of `mesh_mm` edges; return timings and the final force (N)."""
    start = time.perf_counter()
    model = BioTacModel(make_biotac(max_edge=mesh_mm * 1e-3))
    inflation = model.inflate()
    setup_s = time.perf_counter() - start
    increments = list(model.indent(indenter, np.array(point_mm) * 1e-3, depth_mm * 1e-3, step_mm * 1e-3))
    loaded = increments[1:]
    return {
        "mesh_mm": mesh_mm,
        "nodes": len(model.geometry.skin.vertices),
        "free_nodes": int((~model.geometry.skin.anchored).sum()),
        "setup_s": setup_s,
        "pressure_kpa": inflation.pressure / 1e3,
        "s_per_increment": float(np.median([inc.wall_s for inc in loaded])),
        "newton_per_increment": float(np.mean([inc.newton_iterations for inc in loaded])),
        "reached_mm": increments[-1].depth * 1e3,
        "converged": increments[-1].converged,
        "force": increments[-1].force,
        "backend": model.system.linear_solver.backend,
    }


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--meshes-mm", default="0.5,0.35")
    parser.add_argument("--depth-mm", type=float, default=3.0)
    parser.add_argument("--step-mm", type=float, default=0.1)
    parser.add_argument("--indenter", default="sphere_medium")
    parser.add_argument("--point-mm", default="-6,0,-9")
    args = parser.parse_args()
    point = [float(v) for v in args.point_mm.split(",")]
    rows = [run(float(h), args.indenter, point, args.depth_mm, args.step_mm) for h in args.meshes_mm.split(",")]
    table = Table(
        "mesh (mm)",
        "nodes",
        "free",
        "inflate (s)",
        "p (kPa)",
        "s / increment",
        "Newton / incr.",
        "depth reached (mm)",
        "F (N), biotac frame",
        "|dF| / |F| vs first",
    )
    reference = rows[0]["force"]
    for r in rows:
        change = np.linalg.norm(r["force"] - reference) / max(np.linalg.norm(reference), 1e-12)
        table.add_row(
            f"{r['mesh_mm']:.2f}",
            str(r["nodes"]),
            str(r["free_nodes"]),
            f"{r['setup_s']:.1f}",
            f"{r['pressure_kpa']:.2f}",
            f"{r['s_per_increment']:.2f}",
            f"{r['newton_per_increment']:.1f}",
            f"{r['reached_mm']:.2f}{'' if r['converged'] else ' (stopped)'}",
            "[" + ", ".join(f"{f:.3f}" for f in r["force"]) + "]",
            f"{change:.1%}",
        )
    console = Console(width=200)
    console.print(table)
    console.print(f"sparse factorisation: {rows[0]['backend']} (BIOTAC_TWIN_SPARSE=superlu forces SciPy's SuperLU)")


if __name__ == "__main__":
    main()
