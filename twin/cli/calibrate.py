"""`twin calibrate`, `twin validate`: fit the skin like the paper, then check it on every trajectory."""

from __future__ import annotations

import json
from pathlib import Path
from typing import Annotated

import numpy as np
import typer
from rich.table import Table

from twin.cli.common import DeviceOption, analysis_inputs, err_console, guarded, out_console, progress_bar

calibrate_app = typer.Typer()

Datasets = Annotated[list[Path], typer.Argument(help="Campaign HDF5 files (one per sensor).")]
ModelOption = Annotated[
    Path | None, typer.Option("--model", help="Model JSON (TwinModel.to_dict()); default: nominal at the data's mesh.")
]


def _trajectory_choice(data: list, choice: str | None, indenter: str) -> list:
    """The trajectories to calibrate on: "SENSOR:ID" pairs (comma-separated), or the paper's default."""
    from twin.analysis.calibrate import default_trajectories

    if choice is None:
        return default_trajectories(data, indenter)
    by_key = {(t.sensor_id, t.trajectory_id): t for d in data for t in d.trajectories}
    chosen = []
    for item in choice.split(","):
        try:
            sensor, trajectory = (int(v) for v in item.split(":"))
        except ValueError as exc:
            raise ValueError(f"--trajectory takes SENSOR:ID pairs, got {item!r}") from exc
        if (sensor, trajectory) not in by_key:
            raise ValueError(f"no trajectory {trajectory} of sensor {sensor} in the datasets")
        chosen.append(by_key[(sensor, trajectory)])
    return chosen


@calibrate_app.command()
def calibrate(
    datasets: Datasets,
    model: ModelOption = None,
    trajectory: Annotated[
        str | None, typer.Option(help="SENSOR:ID[,SENSOR:ID...]; default: per sensor its first angled --indenter one.")
    ] = None,
    indenter: Annotated[str, typer.Option(help="Indenter of the default trajectory.")] = "sphere_medium",
    max_iter: Annotated[int, typer.Option(min=1, help="SLSQP iterations at most.")] = 20,
    out: Annotated[Path | None, typer.Option(help="Write the calibrated model JSON here (for --model).")] = None,
    as_json: Annotated[bool, typer.Option("--json", help="Print the result as JSON.")] = False,
    device: DeviceOption = "cpu",
) -> None:
    """The paper's SLSQP over t_s, mu_NH, mu_fr, T_fl on one angled trajectory, with uncertainty."""
    from twin.analysis.calibrate import CalibrationSettings
    from twin.analysis.calibrate import calibrate as run_calibration

    predictor, data, base = analysis_inputs(datasets, model, device)
    chosen = guarded(lambda: _trajectory_choice(data, trajectory, indenter))
    err_console.print(f"calibrating on {[(t.sensor_id, t.trajectory_id) for t in chosen]} (sensor, trajectory) ...")
    with progress_bar() as progress:
        task = progress.add_task("cost evaluations", total=None)

        def advance(evaluation: int, cost: float) -> None:
            progress.update(task, completed=evaluation, description=f"cost {cost:.4g}")

        result = guarded(
            lambda: run_calibration(
                chosen, base, predictor, CalibrationSettings(max_iterations=max_iter), progress=advance
            )
        )
    if out is not None:
        out.parent.mkdir(parents=True, exist_ok=True)
        out.write_text(json.dumps(result.model(base).to_dict(), indent=2))
    if as_json:
        print(json.dumps(result.to_dict()))
        return
    table = Table("parameter", "start", "optimum", "95 % interval", title="calibration (SLSQP)")
    for name, value in result.parameters.items():
        low, high = result.intervals[name]
        table.add_row(name, f"{result.start[name]:.4g}", f"{value:.4g}", f"[{low:.4g}, {high:.4g}]")
    out_console.print(table)
    out_console.print(
        f"cost {result.cost:.4f} = force {result.force_cost:.4f} N + thickness {result.thickness_cost:.4f} "
        f"(sensor {result.thickness * 1e3:.3f} mm); {result.evaluations} evaluations; {result.message}"
    )
    for warning in result.warnings:
        out_console.print(f"[yellow]warning:[/yellow] {warning}")
    if out is not None:
        out_console.print(f"model: {out}")


@calibrate_app.command()
def validate(
    datasets: Datasets,
    model: ModelOption = None,
    out: Annotated[Path | None, typer.Option(help="Folder for validation.json and the plots.")] = None,
    as_json: Annotated[bool, typer.Option("--json", help="Print the result as JSON.")] = False,
    device: DeviceOption = "cpu",
) -> None:
    """The model on every trajectory: mean RMS force error per indenter, as in the paper."""
    from twin.analysis.validate import plot_validation
    from twin.analysis.validate import validate as run_validation

    predictor, data, twin_model = analysis_inputs(datasets, model, device)
    with progress_bar() as progress:
        task = progress.add_task(f"replaying on {device}", total=sum(len(d.trajectories) for d in data))
        result = guarded(
            lambda: run_validation(
                data, twin_model, predictor, progress=lambda done, _: progress.update(task, completed=done)
            )
        )
    summary = result.to_dict()
    if out is not None:
        out.mkdir(parents=True, exist_ok=True)
        (out / "validation.json").write_text(json.dumps(summary, indent=2))
        plot_validation(result, data, out)
    if as_json:
        print(json.dumps(summary))
        return
    table = Table("indenter", "trajectories", "mean RMS (N)", "median RMS (N)", "force range (N)", "normalised")
    for i in result.indenters:
        table.add_row(
            i.indenter,
            str(i.trajectories),
            *(
                f"{v:.3f}" if np.isfinite(v) else "-"
                for v in (i.mean_rms_n, i.median_rms_n, i.force_range_n, i.normalised)
            ),
        )
    out_console.print(table)
    if out is not None:
        out_console.print(f"plots and validation.json: {out}")
