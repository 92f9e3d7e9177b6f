"""Contact refinement (`assets.refine`): force accuracy and cost of a mesh refined under the indenter against the
uniform mesh it refines, in one process.

    python benchmarks/refine_bench.py [--part dome|biotac|both] [--indenters sphere_small,sphere_medium]

dome: the membrane dome (R 10 mm, t 0.1 mm, mu 1e5 Pa) against the independent axisymmetric solution
(`fe.axisymmetric`) at 0.25 ... 1.5 mm past first touch, on the 0.5 mm mesh uniform and refined at the apex.
biotac: a normal press at `twin fe indent`'s default point to 3 mm on the nominal BioTac, 0.5 mm mesh uniform,
refined once within 3 mm of the point, and 0.25 mm uniform (no independent solution there: the finer mesh is the
yardstick). CPU seconds (`time.process_time`): of a dome run (inflation and indentation), of a press's loaded
increment; each with its ratio to the uniform 0.5 mm mesh.
"""

import argparse
import time

import numpy as np
from rich.console import Console
from rich.table import Table

from assets.biotac import make_biotac
from assets.refine import Refinement
from fe.axisymmetric import indent_dome
from fe.dome import run_dome
from fe.params import SkinParameters
from fe.sensor import SENSOR_THICKNESS, BioTacModel

DOME_CASES = [(1.5, 5e-3, 1), (1.5, 2.5e-3, 1), (1.2, 5e-3, 1), (1.2, 2.5e-3, 1), (1.5, 10e-3, 1), (1.1, 5e-3, 1)]
DOME_CASES += [(1.35, 1.5e-3, 2)]
"""(V/V0, indenter radius m, refinement levels): issue 17's grid, then other radii and inflations."""
DOME_DEPTHS = np.arange(7) * 0.25e-3  # m past first touch
POINT = np.array([-5e-3, 0.0, -9e-3])  # m, biotac frame: `twin fe indent`'s default point


def _dome(ratio: float, radius: float, levels: int, refine_radius: float) -> tuple[np.ndarray, float, int]:
    """(apex forces N at DOME_DEPTHS[1:], CPU s of the run (inflation and indentation), mesh vertices)."""
    start = time.process_time()
    result = run_dome(
        10e-3, 0.1e-3, 1e5, ratio, False, radius, DOME_DEPTHS, 0.5e-3, refine_levels=levels, refine_radius=refine_radius
    )
    if not all(inc.converged for inc in result.increments):
        raise RuntimeError(f"dome V/V0 {ratio}, r {radius}: an increment did not converge")
    cpu = time.process_time() - start
    return np.array([-inc.force[2] for inc in result.increments])[1:], cpu, result.vertices


def dome_table(console: Console, refine_radius: float) -> None:
    table = Table(
        "V/V0",
        "indenter (mm)",
        "mesh",
        "vertices",
        "force error at 0.25 ... 1.5 mm (%)",
        "max |error|",
        "CPU s / run",
        "ratio",
        title=f"dome, 0.5 mm mesh, refined within {refine_radius * 1e3:g} mm",
    )
    for ratio, radius, levels in DOME_CASES:
        reference = np.array([s.force for s in indent_dome(10e-3, 0.1e-3, 1e5, ratio, radius, list(DOME_DEPTHS))])[1:]
        base_cpu = None
        for lv in (0, levels):
            force, cpu, n = _dome(ratio, radius, lv, refine_radius)
            base_cpu = base_cpu or cpu
            error = 100.0 * (force / reference - 1.0)
            table.add_row(
                f"{ratio:g}",
                f"{radius * 1e3:g}",
                "uniform" if lv == 0 else f"{lv} level(s)",
                str(n),
                " ".join(f"{e:+.2f}" for e in error),
                f"{np.abs(error).max():.2f}",
                f"{cpu:.3f}",
                f"{cpu / base_cpu:.2f}",
            )
    console.print(table)


def _press(indenter: str, edge: float, refinement: Refinement | None) -> tuple[np.ndarray, float, int, int]:
    """(|force| N at 1, 2, 3 mm, CPU s per loaded increment, Newton iterations, skin vertices) of one press."""
    model = BioTacModel(make_biotac(edge, refinement=refinement), SkinParameters())
    if not model.inflate(SENSOR_THICKNESS).converged:
        raise RuntimeError("inflation did not converge")
    start = time.process_time()
    increments = list(model.indent(indenter, POINT, 3e-3, 0.25e-3))
    cpu = (time.process_time() - start) / (len(increments) - 1)
    if not all(inc.converged for inc in increments):
        raise RuntimeError(f"{indenter}: an increment did not converge")
    force = {round(inc.depth * 1e3, 3): float(np.linalg.norm(inc.force)) for inc in increments}
    iterations = sum(inc.newton_iterations for inc in increments)
    return np.array([force[1.0], force[2.0], force[3.0]]), cpu, iterations, len(model.geometry.skin.vertices)


def biotac_table(console: Console, indenters: list[str]) -> None:
    table = Table(
        "indenter",
        "mesh",
        "vertices",
        "|F| at 1, 2, 3 mm (N)",
        "against 0.25 mm (%)",
        "Newton its",
        "CPU s / increment",
        "ratio",
        title="BioTac normal press at (-5, 0, -9) mm",
    )
    meshes = [("0.5 mm", 0.5e-3, None), ("0.5 mm, 1 level within 3 mm", 0.5e-3, Refinement(tuple(POINT), 3e-3, 1))]
    meshes.append(("0.25 mm", 0.25e-3, None))
    for indenter in indenters:
        runs = [(label, *_press(indenter, edge, refinement)) for label, edge, refinement in meshes]
        fine, base_cpu = runs[-1][1], runs[0][2]
        for label, force, cpu, iterations, n in runs:
            table.add_row(
                indenter,
                label,
                str(n),
                " ".join(f"{f:.3f}" for f in force),
                " ".join(f"{e:+.2f}" for e in 100.0 * (force / fine - 1.0)),
                str(iterations),
                f"{cpu:.3f}",
                f"{cpu / base_cpu:.2f}",
            )
    console.print(table)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--part", choices=["dome", "biotac", "both"], default="both")
    parser.add_argument("--indenters", default="sphere_small,sphere_medium")
    parser.add_argument("--refine-radius-mm", type=float, default=1.5, help="the dome's refined zone (mm)")
    args = parser.parse_args()
    console = Console()
    if args.part in ("dome", "both"):
        dome_table(console, args.refine_radius_mm * 1e-3)
    if args.part in ("biotac", "both"):
        biotac_table(console, args.indenters.split(","))


if __name__ == "__main__":
    main()
