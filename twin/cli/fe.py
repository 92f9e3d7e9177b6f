"""`twin fe ...`: finite-element physics checks and single indentations (lengths in mm on the CLI)."""

import json
import sys
from pathlib import Path
from typing import Annotated

import numpy as np
import typer
from rich.progress import Progress
from rich.table import Table

from twin.cli.common import FE_MESH_HELP, FE_MODEL_HELP
from twin.cli.common import check_device as _check_device
from twin.cli.common import err_console as _err
from twin.cli.common import guarded as _guarded
from twin.cli.common import inflated_twin_model as _inflated_twin_model
from twin.cli.common import out_console as _out
from twin.cli.common import parse_floats as _floats
from twin.cli.common import progress_bar as _progress
from twin.cli.fe_batch import batch

fe_app = typer.Typer(help="Finite-element skin model: physics checks and indentations.", no_args_is_help=True)
fe_app.command("batch")(batch)


@fe_app.command()
def balloon(
    radius_mm: Annotated[float, typer.Option(help="Sphere radius (mm).")] = 10.0,
    thickness_mm: Annotated[float, typer.Option(help="Membrane thickness (mm).")] = 0.1,
    mu_pa: Annotated[float, typer.Option(help="Neo-Hookean shear modulus (Pa).")] = 1e5,
    volume_ratios: Annotated[str, typer.Option(help="Comma-separated V/V0 values.")] = "1.2,1.5,2.0,2.63,3.375",
    subdivisions: Annotated[int, typer.Option(min=0, max=6, help="Icosphere subdivisions of the mesh.")] = 3,
    as_json: Annotated[bool, typer.Option("--json", help="Print JSON.")] = False,
) -> None:
    """Inflate a closed Neo-Hookean spherical membrane by volume control; compare with membrane theory."""
    from fe.balloon import check_balloon_input, inflate_balloon

    ratios = _floats(volume_ratios, None, "--volume-ratios")
    size = (radius_mm * 1e-3, thickness_mm * 1e-3, mu_pa)
    _guarded(lambda: check_balloon_input(*size, ratios))
    with _progress() as progress:
        task = progress.add_task("volume steps", total=None)
        points = inflate_balloon(
            *size, ratios, subdivisions, on_step=lambda done, total: progress.update(task, completed=done, total=total)
        )
    records = [
        {
            "volume_ratio": p.volume_ratio,
            "stretch": p.stretch,
            "pressure_pa": p.pressure_pa,
            "analytic_pressure_pa": p.analytic_pressure_pa,
            "converged": p.converged,
        }
        for p in points
    ]
    if as_json:
        print(json.dumps(records))
        return
    table = Table("V/V0", "stretch", "p FE (Pa)", "p theory (Pa)", "error")
    for r in records:
        err = r["pressure_pa"] / r["analytic_pressure_pa"] - 1
        table.add_row(
            f"{r['volume_ratio']:.3f}",
            f"{r['stretch']:.4f}",
            f"{r['pressure_pa']:.2f}",
            f"{r['analytic_pressure_pa']:.2f}",
            f"{err:+.2%}",
        )
    _out.print(table)


@fe_app.command()
def dome(
    radius_mm: Annotated[float, typer.Option(help="Hemisphere radius (mm).")] = 10.0,
    thickness_mm: Annotated[float, typer.Option(help="Membrane thickness (mm).")] = 0.1,
    mu_pa: Annotated[float, typer.Option(help="Neo-Hookean shear modulus (Pa).")] = 1e5,
    volume_ratio: Annotated[float, typer.Option(help="Inflated volume / initial volume.")] = 1.5,
    bending: Annotated[str, typer.Option(help="Discrete-shell bending: on or off.")] = "off",
    indenter_radius_mm: Annotated[float | None, typer.Option(help="Rigid sphere radius (mm).")] = None,
    depth_mm: Annotated[float, typer.Option(help="Depth past first touch (mm).")] = 0.0,
    step_mm: Annotated[float, typer.Option(help="Depth increment (mm).")] = 0.25,
    mesh_mm: Annotated[float | None, typer.Option(help="Maximum edge length (mm); default R/12.")] = None,
    refine_levels: Annotated[
        int | None,
        typer.Option(min=0, max=3, help="Halve the edges this many times at the apex (default: fe.dome's rule)."),
    ] = None,
    refine_radius_mm: Annotated[
        float | None, typer.Option(help="Reach of the finest level from the apex (mm; default: three edges).")
    ] = None,
    as_json: Annotated[bool, typer.Option("--json", help="Print JSON.")] = False,
) -> None:
    """Hemispherical membrane pinned to a flat base, fluid-filled, inflated, then indented at the apex; with an
    indenter the mesh is refined under it by default (`fe.dome.contact_refinement`, docs/fe.md)."""
    from fe.dome import run_dome

    if bending not in ("on", "off"):
        raise typer.BadParameter("--bending must be on or off")
    sizes = {"--radius-mm": radius_mm, "--thickness-mm": thickness_mm, "--mu-pa": mu_pa, "--volume-ratio": volume_ratio}
    sizes |= {"--depth-mm": depth_mm, "--step-mm": step_mm}
    optional = {"--indenter-radius-mm": indenter_radius_mm, "--mesh-mm": mesh_mm}
    optional["--refine-radius-mm"] = refine_radius_mm
    given = {name: v for name, v in optional.items() if v is not None}
    _guarded(lambda: _check_finite(sizes | given))
    if depth_mm < 0 or step_mm <= 0 or min(given.values(), default=1.0) <= 0:
        raise typer.BadParameter(
            "--depth-mm must be >= 0; --step-mm, --refine-radius-mm, --indenter-radius-mm and --mesh-mm > 0"
        )
    depths = np.arange(0, int(round(depth_mm / step_mm)) + 1) * step_mm * 1e-3
    result = _guarded(
        lambda: run_dome(
            radius_mm * 1e-3,
            thickness_mm * 1e-3,
            mu_pa,
            volume_ratio,
            bending == "on",
            None if indenter_radius_mm is None else indenter_radius_mm * 1e-3,
            depths if indenter_radius_mm is not None else None,
            None if mesh_mm is None else mesh_mm * 1e-3,
            refine_levels=refine_levels,
            refine_radius=None if refine_radius_mm is None else refine_radius_mm * 1e-3,
        )
    )
    _err.print(
        f"dome mesh: {result.vertices} vertices, edges halved {result.refine_levels} time(s) within "
        f"{result.refine_radius * 1e3:.3g} mm of the apex"
    )
    records = [
        {
            "depth_mm": 0.0,
            "force_n": 0.0,
            "pressure_pa": result.inflated_pressure,
            "volume_m3": result.inflated_volume,
            "contact_radius_mm": 0.0,
        }
    ]
    if result.increments:
        records = [
            {
                "depth_mm": inc.depth * 1e3,
                "force_n": float(0.0 - inc.force[2]),  # no -0.0 at first touch
                "pressure_pa": inc.pressure,
                "volume_m3": inc.volume,
                "contact_radius_mm": inc.contact_radius * 1e3,
                "converged": inc.converged,
            }
            for inc in result.increments
        ]
    if as_json:
        print(json.dumps(records))
        return
    table = Table("depth (mm)", "force (N)", "pressure (Pa)", "volume (m^3)", "contact radius (mm)")
    for r in records:
        table.add_row(
            f"{r['depth_mm']:.3f}",
            f"{r['force_n']:.5f}",
            f"{r['pressure_pa']:.2f}",
            f"{r['volume_m3']:.6e}",
            f"{r['contact_radius_mm']:.3f}",
        )
    _out.print(table)


@fe_app.command()
def indent(
    indenter: Annotated[str, typer.Option(help="Indenter name (see `twin fe indenters`).")] = "sphere_medium",
    point_mm: Annotated[str, typer.Option(help="Target point x,y,z (mm, biotac frame).")] = "-5,0,-9",
    angle_deg: Annotated[float, typer.Option(help="Tilt from the inward surface normal (deg).")] = 0.0,
    azimuth_deg: Annotated[
        float, typer.Option(help="Direction of the tilt around the normal (deg, 0 = distal).")
    ] = 0.0,
    depth_mm: Annotated[float, typer.Option(help="Depth past first contact (mm).")] = 3.0,
    step_mm: Annotated[float, typer.Option(help="Increment (mm).")] = 0.1,
    speed_mm_s: Annotated[
        float, typer.Option(help="Indentation speed (mm/s) timing the increments; only a relaxing skin feels it.")
    ] = 1.0,
    mesh_mm: Annotated[float | None, typer.Option(help=FE_MESH_HELP)] = None,
    refine_levels: Annotated[
        int, typer.Option(min=0, max=3, help="Halve the skin's edges this many times about the point (docs/fe.md).")
    ] = 0,
    refine_radius_mm: Annotated[
        float, typer.Option(help="Reach of the finest --refine-levels level from the press point (mm).")
    ] = 1.5,
    model_json: Annotated[Path | None, typer.Option("--model", help=FE_MODEL_HELP)] = None,
    device: Annotated[str, typer.Option(help="Warp device of the indentation: cpu, cuda, cuda:0, ...")] = "cpu",
    as_json: Annotated[bool, typer.Option("--json", help="Print JSON records.")] = False,
) -> None:
    """Inflate the BioTac (nominal or a --model), then indent it at a point and print the force-depth table."""
    from assets.indenters import get_indenter
    from assets.refine import Refinement

    point = np.array(_floats(point_mm, 3, "--point-mm")) * 1e-3
    _guarded(lambda: get_indenter(indenter))
    numbers = {"--point-mm": point * 1e3, "--angle-deg": angle_deg, "--azimuth-deg": azimuth_deg}
    numbers |= {"--depth-mm": depth_mm, "--step-mm": step_mm, "--speed-mm-s": speed_mm_s}
    _guarded(lambda: _check_finite(numbers | {"--refine-radius-mm": refine_radius_mm}))
    if depth_mm < 0 or step_mm <= 0 or speed_mm_s <= 0 or refine_radius_mm <= 0:
        raise typer.BadParameter("--depth-mm must be >= 0, --step-mm, --speed-mm-s and --refine-radius-mm > 0")
    _guarded(lambda: _check_device(device))
    refinement = Refinement(tuple(point), refine_radius_mm * 1e-3, refine_levels) if refine_levels else None
    _, model, inflation = _inflated_twin_model(model_json, mesh_mm, refinement)
    _err.print(
        f"inflated {len(model.geometry.skin.vertices)} skin vertices: "
        f"+{inflation.volume_change * 1e9:.1f} mm^3, p = {inflation.pressure / 1e3:.2f} kPa, "
        f"thickness {inflation.thickness * 1e3:.3f} mm ({inflation.message})"
    )
    n_steps = int(round(depth_mm / step_mm)) + 1
    records = []
    with _progress() as progress:
        task = progress.add_task("indenting", total=n_steps)
        increments = _guarded(
            lambda: model.indent(
                indenter,
                point,
                depth_mm * 1e-3,
                step_mm * 1e-3,
                angle_deg,
                azimuth_deg,
                speed=speed_mm_s * 1e-3,
                device=device,
            )
        )
        for inc in _guarded(lambda: list(_advance(increments, progress, task))):
            records.append(
                {
                    "depth_mm": inc.depth * 1e3,
                    "force_n": [float(f) for f in inc.force],
                    "pressure_pa": inc.pressure,
                    "volume_m3": inc.volume,
                    "contact_area_mm2": inc.contact_area * 1e6,
                    "newton_iters": inc.newton_iterations,
                    "converged": inc.converged,
                    "wall_s": inc.wall_s,
                }
            )
    if as_json:
        print(json.dumps(records))
    else:
        _print_indentation(records)
    if records and not records[-1]["converged"]:
        _err.print("[yellow]the last increment did not converge; the trajectory stopped there[/yellow]")
        sys.exit(1)


def _check_finite(options: dict[str, object]) -> None:
    """ValueError naming the first option whose value is NaN or infinite."""
    for name, value in options.items():
        if not np.all(np.isfinite(value)):
            raise ValueError(f"{name} must be finite, got {value}")


def _print_indentation(records: list[dict]) -> None:
    """The `twin fe indent` table of its JSON records."""
    table = Table("depth (mm)", "Fx (N)", "Fy (N)", "Fz (N)", "p (kPa)", "contact (mm^2)", "Newton", "ok", "s")
    for r in records:
        fx, fy, fz = r["force_n"]
        table.add_row(
            f"{r['depth_mm']:.2f}",
            f"{fx:.4f}",
            f"{fy:.4f}",
            f"{fz:.4f}",
            f"{r['pressure_pa'] / 1e3:.3f}",
            f"{r['contact_area_mm2']:.2f}",
            str(r["newton_iters"]),
            "yes" if r["converged"] else "NO",
            f"{r['wall_s']:.2f}",
        )
    _out.print(table)


def _advance(increments, progress: Progress, task) -> object:
    for inc in increments:
        progress.advance(task)
        yield inc


@fe_app.command("indenters")
def list_indenters() -> None:
    """List the nine indenters and what their size means."""
    from assets.indenters import INDENTERS

    table = Table("name", "dims (mm)", "description")
    for name, ind in INDENTERS.items():
        table.add_row(name, ", ".join(f"{d * 1e3:g}" for d in ind.dims), ind.description)
    _out.print(table)
