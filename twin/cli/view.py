"""`twin view DATASET|REPORT ...`: rerun views of campaign files and `twin compare` reports (top level)."""

from __future__ import annotations

from pathlib import Path
from typing import Annotated

import typer

from twin.cli.common import err_console, guarded

view_app = typer.Typer()


def _check_save(save: Path | None) -> None:
    if save is not None and save.suffix != ".rrd":
        raise ValueError(f"--save needs a .rrd file name, got {save}")


@view_app.command("view")
def view_command(
    paths: Annotated[
        list[Path], typer.Argument(help="Campaign HDF5 files and/or `twin compare` report folders.", exists=True)
    ],
    save: Annotated[
        Path | None, typer.Option(help="Write the recording to this .rrd file instead of spawning the viewer.")
    ] = None,
    trajectory: Annotated[
        list[int] | None,
        typer.Option(help="Trajectory id of the datasets to log (repeatable; default: each file's first)."),
    ] = None,
) -> None:
    """Skin coloured by displacement, indenter pose, force arrows, electrodes, force/pressure/electrode
    series of dataset trajectories, and the residual field of reports on the skin (docs/view.md)."""
    from twin.view import log_path, open_recording

    guarded(lambda: _check_save(save))
    recording = open_recording("biotac-twin", save=save, spawn=save is None)
    for path in paths:
        kind = guarded(lambda p=path: log_path(recording, p, trajectory or None))
        err_console.print(f"logged {kind} {path}")
    recording.flush()
    recording.disconnect()
    if save is not None:
        err_console.print(f"recording: {save}")
