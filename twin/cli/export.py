"""`twin export --format mjcf|urdf --out FILE [--testbed]`: the BioTac on its mount for other simulators (top level)."""

from __future__ import annotations

from pathlib import Path
from typing import Annotated

import typer

from twin.cli.common import err_console, guarded

export_app = typer.Typer()


@export_app.command("export")
def export_command(
    fmt: Annotated[str, typer.Option("--format", help="mjcf or urdf.")],
    out: Annotated[Path, typer.Option(help="File to write; a URDF's STL meshes go to <stem>_meshes/ beside it.")],
    testbed: Annotated[
        bool, typer.Option("--testbed", help="The whole testbed: bench, both YuMi arms (no tool), mount, BioTac.")
    ] = False,
) -> None:
    """Write the BioTac (skin outer surface, core, base, the 19 electrode sites) on its mount with the F/T
    sensor, or the whole testbed, as MJCF (loads in MuJoCo) or URDF with STL meshes (m, rad)."""
    from twin.export import export

    guarded(lambda: export(fmt, out, testbed))
    err_console.print(f"wrote {out}")
