"""`twin dataset ...`: inspect campaign datasets (features, units, frames, trajectory counts, provenance)."""

import json
from pathlib import Path
from typing import Annotated

import typer
from rich.table import Table

from twin.cli.common import guarded, out_console

dataset_app = typer.Typer(help="Inspect campaign datasets (HDF5).", no_args_is_help=True)


@dataset_app.command("info")
def info(
    path: Annotated[Path, typer.Argument(help="A campaign HDF5 file.")],
    as_json: Annotated[bool, typer.Option("--json", help="Print JSON.")] = False,
) -> None:
    """Features with shapes and units, trajectory counts and provenance of a campaign file."""
    from twin.dataset import dataset_info

    summary = guarded(lambda: dataset_info(path))
    if as_json:
        print(json.dumps(summary))
        return
    table = Table("feature", "shape", "dtype", "units", "frame")
    for name, feature in summary["features"].items():
        table.add_row(name, str(tuple(feature["shape"])), feature["dtype"], feature["units"], feature["frame"] or "")
    out_console.print(table)
    if summary["simulation_only"]:
        out_console.print(
            f"simulation only (the plant's view; the analysis never reads it): {', '.join(summary['simulation_only'])}"
        )
    if "trajectories" in summary:
        out_console.print(f"trajectories: {summary['trajectories']}")
