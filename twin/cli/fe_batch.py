"""`twin fe batch`: many indentation trajectories through the batched FE solver on a warp device (CPU or GPU).

The trajectories are random straight presses at ventral points (`fe.trajectory_sets.random_paths`) or read
from a poses file; they run continuously batched on `--slots` systems (`fe.batched_runner`). The results
file (`twin.fe_batch_results`) holds per trajectory and pose the force, depth, pressure, contact area,
Newton iterations and convergence, with the poses asked for (so a results file runs again with --poses).
During a run it is rewritten every minute with the trajectories ended so far, so a crash loses at most a
minute of work, and `--resume` keeps the trajectories that ended in an earlier file of the same poses and
options (model, mesh, force limit, cut-backs, speed; another is refused, naming what differs).
"""

from __future__ import annotations

import json
import time
from collections.abc import Callable
from pathlib import Path
from typing import TYPE_CHECKING, Annotated

import numpy as np
import typer
from rich.table import Table

from twin.cli.common import FE_MESH_HELP as MESH_HELP
from twin.cli.common import FE_MODEL_HELP as MODEL_HELP
from twin.cli.common import check_device as _check_device
from twin.cli.common import err_console as _err
from twin.cli.common import guarded as _guarded
from twin.cli.common import inflated_twin_model as _inflated_twin_model
from twin.cli.common import out_console as _out
from twin.cli.common import progress_bar as _progress

if TYPE_CHECKING:
    from twin.fe_batch_results import BatchResults

FLUSH_S = 60.0
"""Seconds between the writes of the trajectories ended so far during a run."""


def batch(
    out: Annotated[Path, typer.Option(help="Results file (.npz).")],
    trajectories: Annotated[int, typer.Option(help="Random trajectories to run (without --poses).")] = 16,
    indenters: Annotated[str, typer.Option(help="Comma-separated indenter names, or 'all' (cycled).")] = "all",
    seed: Annotated[int, typer.Option(help="Seed of the random trajectories.")] = 0,
    depth_mm: Annotated[float, typer.Option(help="Depth past first contact of the random ones (mm).")] = 3.0,
    step_mm: Annotated[float, typer.Option(help="Increment of the random ones (mm).")] = 0.1,
    poses: Annotated[
        Path | None, typer.Option(help="Poses file (.npz with names, rotations, translations in m) to run instead.")
    ] = None,
    mesh_mm: Annotated[float | None, typer.Option(help=MESH_HELP)] = None,
    model_json: Annotated[Path | None, typer.Option("--model", help=MODEL_HELP)] = None,
    device: Annotated[str, typer.Option(help="Warp device: cpu, cuda, cuda:0, ...")] = "cpu",
    slots: Annotated[int, typer.Option(help="Trajectories solved together.")] = 256,
    force_limit: Annotated[float, typer.Option(help="A trajectory stops past this force (N).")] = 25.0,
    time_limit: Annotated[
        float, typer.Option(help="Stop after this many seconds (unfinished ones keep theirs).")
    ] = 1e9,
    max_cuts: Annotated[int, typer.Option(min=0, help="Halvings of a failed step before it ends the trajectory.")] = 3,
    speed_mm_s: Annotated[
        float, typer.Option(help="Tip speed (mm/s) timing the poses; only a relaxing skin feels it.")
    ] = 1.0,
    resume: Annotated[
        bool, typer.Option(help="Keep the trajectories that ended in an earlier --out of the same options.")
    ] = False,
    as_json: Annotated[bool, typer.Option("--json", help="Print the summary as JSON.")] = False,
) -> None:
    """Run many indentation trajectories batched on a warp device and write their forces and contact."""
    from assets.indenters import INDENTERS, indenter_name
    from fe.batched_runner import PoseTrajectory, run_trajectories
    from fe.trajectory_sets import press_travels, random_paths, round_robin, to_trajectories
    from twin.fe_batch_results import POSES_FILE_KEYS, BatchResults, read_poses

    if slots < 1 or trajectories < 1 or depth_mm < 0 or step_mm <= 0 or force_limit <= 0 or speed_mm_s <= 0:
        raise typer.BadParameter("--slots and --trajectories must be >= 1, --depth-mm >= 0, the rest > 0")
    names = (
        list(INDENTERS) if indenters == "all" else _guarded(lambda: [indenter_name(n) for n in indenters.split(",")])
    )
    _guarded(lambda: _check_device(device))
    asked = _guarded(lambda: read_poses(poses)) if poses is not None else None
    twin_model, model, inflation = _inflated_twin_model(model_json, mesh_mm)
    if not inflation.converged:
        _err.print(f"[red]error:[/red] the inflation did not converge ({inflation.message})")
        raise typer.Exit(code=1)
    if asked is None:
        paths = random_paths(model, trajectories, names, seed, depth_mm * 1e-3)
        paths = {k: v[round_robin(paths["names"])] for k, v in paths.items()}
        runs = to_trajectories(paths, press_travels(depth_mm * 1e-3, step_mm * 1e-3))
    else:
        runs = [PoseTrajectory(str(n), r, t) for n, r, t in zip(*(asked[k] for k in POSES_FILE_KEYS), strict=True)]
    made_with = {"model": twin_model.to_dict(), "vertices": len(model.reference), "force_limit_n": force_limit}
    made_with |= {"max_cuts": max_cuts, "speed_mm_s": speed_mm_s}
    results = BatchResults(out, runs, made_with)
    todo = _guarded(results.resume) if resume and out.exists() else np.ones(len(runs), dtype=bool)
    indices = np.flatnonzero(todo)
    start = time.perf_counter()
    with _progress() as progress:
        task = progress.add_task(f"trajectories on {device}", total=len(runs), completed=len(runs) - len(indices))
        writer = _PeriodicWriter(results, indices, lambda: progress.advance(task))
        run = None
        if len(indices):
            run = _guarded(
                lambda: run_trajectories(
                    model.inflated_skin(),
                    [runs[i].at_speed(speed_mm_s * 1e-3) for i in indices],
                    device,
                    slots,
                    force_limit,
                    writer.ended,
                    time_limit,
                    max_cuts=max_cuts,
                )
            )
    for j, i in enumerate(indices):
        if run is not None and not results.arrays["ended"][i]:  # stopped by --time-limit
            results.put(i, run.results[j], False)
    results.save()
    wall = time.perf_counter() - start
    summary = results.summary() | {"wall_s": wall, "run_now": len(indices), "device": device}
    summary |= {"mesh_mm": round(twin_model.mesh_max_edge * 1e3, 9), "model": model_json and str(model_json)}
    if run is not None:
        loaded = sum(r.message != "no contact" for t in run.results for r in t)
        summary |= {"increments_per_s": loaded / max(wall, 1e-12), "slots": run.slots}
        summary["cut_backs"] = run.counters["cut_backs"]
    if as_json:
        print(json.dumps(summary))
        return
    table = Table("quantity", "value")
    for key, value in summary.items():
        table.add_row(key, f"{value:.4g}" if isinstance(value, float) else str(value))
    _out.print(table)


class _PeriodicWriter:
    """Files the trajectories of a run (of `indices` into the results) as they end, calling `advance` for
    each (a progress bar), and saves the results every `FLUSH_S` s."""

    def __init__(self, results: BatchResults, indices: np.ndarray, advance: Callable[[], None]) -> None:
        self.results, self.indices, self.advance = results, indices, advance
        self.last = time.perf_counter()

    def ended(self, index: int, increments: list) -> None:
        self.advance()
        self.results.put(int(self.indices[index]), increments, True)
        if time.perf_counter() - self.last > FLUSH_S:
            self.results.save()
            self.last = time.perf_counter()
