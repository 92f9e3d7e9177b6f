"""`twin compare ...`: model-vs-measurement commands (registered at the top level of `twin`)."""

from __future__ import annotations

import json
from pathlib import Path
from typing import Annotated

import typer
from rich.table import Table

from twin.cli.common import DeviceOption, analysis_inputs, err_console, out_console, progress_bar

analysis_app = typer.Typer()


def _print_overall(summary: dict, out: Path) -> None:
    table = Table("channel", "RMS error", "mean", "n", "noise sigma (rows)", title="measured - predicted (rows)")
    for channel in ("force_x", "force_y", "force_z", "force", "pdc", "electrodes"):
        stats = summary["overall"].get(channel)
        if stats is None or stats["rms"] is None:
            continue
        noise = summary["noise"].get(channel, {}).get("rows")
        table.add_row(
            channel,
            f"{stats['rms']:.4g}",
            f"{stats['mean']:+.3g}",
            str(stats["n"]),
            "-" if noise is None else f"{noise:.3g}",
        )
    out_console.print(table)
    out_console.print(f"report: {out / 'report.html'}")


@analysis_app.command("compare")
def compare_command(
    datasets: Annotated[list[Path], typer.Argument(help="Campaign HDF5 files (one per sensor).")],
    out: Annotated[Path, typer.Option(help="Report folder (created): report.html, summary.json, ...")],
    model: Annotated[
        Path | None, typer.Option(help="Model JSON (TwinModel.to_dict()); default: nominal at the data's mesh size.")
    ] = None,
    title: Annotated[str | None, typer.Option(help="Report title.")] = None,
    as_json: Annotated[bool, typer.Option("--json", help="Print summary.json.")] = False,
    device: DeviceOption = "cpu",
) -> None:
    """Measured vs predicted on every channel: error tables, plots, residual field on the skin."""
    from twin.analysis.compare import compare
    from twin.analysis.report import DEFAULT_TITLE, write_report

    predictor, data, twin_model = analysis_inputs(datasets, model, device)
    total = sum(len(d.trajectories) for d in data)
    with progress_bar() as progress:
        task = progress.add_task(f"replaying on {device}", total=total)
        comparison = compare(
            data, twin_model, predictor, progress=lambda done, _: progress.update(task, completed=done)
        )
    err_console.print("writing the report ...")
    files = write_report(comparison, out, title or DEFAULT_TITLE)
    if as_json:
        print(files.summary.read_text())
        return
    _print_overall(json.loads(files.summary.read_text()), out)
