"""`twin campaign ...`: plan and run indentation campaigns, simulated or on hardware.

Also where a hardware campaign opens `hardware.backend.HardwareBackend` (`run_from_config`): the CLI
layer is the one place that joins `twin` and `hardware`.
"""

from __future__ import annotations

import json
import threading
from collections.abc import Callable
from dataclasses import asdict
from pathlib import Path
from typing import TYPE_CHECKING, Annotated

import typer
from rich.table import Table

from twin.cli.common import (
    Indenters,
    MeshMm,
    Quick,
    Seed,
    Sensors,
    campaign_config,
    check_device,
    err_console,
    guarded,
    out_console,
    progress_bar,
    sigterm_as_interrupt,
)

if TYPE_CHECKING:
    from twin.campaign import CampaignConfig
    from twin.campaign_hardware import HardwareCampaignResult

campaign_app = typer.Typer(help="Plan and run indentation campaigns (simulated or on hardware).", no_args_is_help=True)


@campaign_app.command("plan")
def plan(
    paper: Annotated[bool, typer.Option("--paper", help="The paper-size plan (the default).")] = False,
    quick: Quick = False,
    sensors: Sensors = None,
    indenters: Indenters = None,
    seed: Seed = 0,
    mesh_mm: MeshMm = None,
    as_json: Annotated[bool, typer.Option("--json", help="Print JSON.")] = False,
) -> None:
    """Sample points, register each sensor, plan joint paths; report kept and dropped trajectories."""
    from twin.campaign import plan_campaign

    if paper and quick:
        raise typer.BadParameter("--paper and --quick exclude each other")
    config = guarded(lambda: campaign_config(quick, sensors, indenters, seed, mesh_mm))
    err_console.print("planning (inflating the nominal model, registering, solving IK) ...")
    stats = guarded(lambda: plan_campaign(config)).statistics()
    if as_json:
        print(json.dumps(stats))
        return
    table = Table("indenter", "planned", "kept", "dropped")
    for name, entry in stats["indenters"].items():
        dropped = ", ".join(f"{k}: {v}" for k, v in entry["dropped"].items()) or "-"
        table.add_row(name, str(entry["planned"]), str(entry["kept"]), dropped)
    out_console.print(table)
    out_console.print(f"kept {stats['kept_total']} trajectories ({stats['kept_unique']} unique)")


def _executor(name: str, workers: int, address: str | None):
    """The campaign executor, with its errors (unknown name, Ray missing or unreachable) as usage errors."""
    from twin.executors import ExecutorUnavailable, make_executor

    try:
        return make_executor(name, workers, address)
    except (ValueError, ExecutorUnavailable) as error:
        raise typer.BadParameter(str(error)) from error


def _campaign_viewer(config, spawn: bool, save: Path | None):
    """A rerun CampaignViewer for --view / --view-save, or None when neither is asked for."""
    if not spawn and save is None:
        return None
    from assets.biotac import make_biotac
    from twin.view import CampaignViewer, open_recording

    recording = guarded(lambda: open_recording("biotac-twin-campaign", save=save, spawn=spawn))
    return CampaignViewer(recording, make_biotac(config.mesh_max_edge).skin.triangles)


@campaign_app.command("run")
def run(
    out: Annotated[Path, typer.Option(help="Output folder (one HDF5 per sensor); resumes if it has parts.")],
    quick: Quick = False,
    sensors: Sensors = None,
    indenters: Indenters = None,
    seed: Seed = 0,
    mesh_mm: MeshMm = None,
    workers: Annotated[
        int | None, typer.Option(help="Local worker processes, or CPUs of a locally started Ray (sim only; default 2).")
    ] = None,
    executor: Annotated[
        str, typer.Option(help="Where sim trajectories run: local (worker processes) or ray (docs/scale.md).")
    ] = "local",
    address: Annotated[
        str | None, typer.Option(help="Ray cluster address for --executor ray (default: start a local Ray).")
    ] = None,
    backend: Annotated[
        str, typer.Option(help="sim: the simulated testbed; hardware: the devices of --config, one robot.")
    ] = "sim",
    hardware_config: Annotated[
        Path | None, typer.Option("--config", help="Hardware config (.toml/.json) for --backend hardware.")
    ] = None,
    yes: Annotated[
        bool, typer.Option("--yes", help="Hardware: do not stop to have indenters mounted (e.g. simulated devices).")
    ] = False,
    view: Annotated[bool, typer.Option("--view", help="Sim: show each finished trajectory in a rerun viewer.")] = False,
    view_save: Annotated[
        Path | None, typer.Option("--view-save", help="Sim: record each finished trajectory to this .rrd file.")
    ] = None,
    restart: Annotated[
        bool,
        typer.Option("--restart", help="Sim: discard the parts in --out (made with other options) and start over."),
    ] = False,
    device: Annotated[
        str | None,
        typer.Option(
            "--device",
            help="Sim: solve the fe of all trajectories as one batch per sensor on this warp device (cpu, cuda, "
            "cuda:0, ...; docs/scale.md); default: one trajectory at a time on the workers.",
        ),
    ] = None,
    slots: Annotated[int, typer.Option(help="With --device: trajectories solved together (fe systems).")] = 256,
) -> None:
    """Run a campaign, simulated on local workers or on the testbed's devices; a killed run resumes where it stopped.

    With --device (sim) the protocol of every trajectory is first recorded on the workers, the fe of each
    sensor's trajectories is solved as one batch on that warp device, and the protocol is replayed from
    those solves into the same parts and files (docs/scale.md, "The campaign on the batched engine").

    With --backend hardware the same controller drives `HardwareBackend` (docs/hardware.md), one
    trajectory at a time, on the one mounted sensor (--sensors N), in real time.
    """
    from rich.markup import escape

    from twin.backend import BackendError
    from twin.campaign import prepare_out_dir

    if backend not in ("sim", "hardware"):
        raise typer.BadParameter(f"--backend must be sim or hardware, got {backend!r}")
    if backend == "sim" and hardware_config is not None:
        raise typer.BadParameter("--config is the hardware config; it needs --backend hardware")
    if backend == "hardware" and hardware_config is None:
        raise typer.BadParameter("--backend hardware needs --config FILE (see `twin devices config`)")
    if backend == "hardware" and workers not in (None, 1):
        raise typer.BadParameter("--workers: a hardware campaign runs on one robot, one trajectory at a time")
    if workers is not None and workers < 1:
        raise typer.BadParameter("--workers must be >= 1")
    if backend == "hardware" and (executor != "local" or address is not None):
        raise typer.BadParameter("--executor/--address: a hardware campaign runs on one robot, here")
    if backend == "hardware" and (view or view_save is not None):
        raise typer.BadParameter("--view/--view-save show simulated campaigns (hardware parts lack the fe fields)")
    if backend == "hardware" and restart:
        raise typer.BadParameter("--restart: a hardware campaign's parts are measurements; move them away yourself")
    if backend == "hardware" and device is not None:
        raise typer.BadParameter("--device: a hardware campaign measures, it solves no fe")
    if slots < 1:
        raise typer.BadParameter("--slots must be >= 1")
    if device is not None:
        guarded(lambda: check_device(device))
    guarded(lambda: prepare_out_dir(out))
    pool = _executor(executor, workers or 2, address) if backend == "sim" else None
    config = guarded(lambda: campaign_config(quick, sensors, indenters, seed, mesh_mm))
    viewer = _campaign_viewer(config, view, view_save) if backend == "sim" else None
    with progress_bar() as progress:
        task = progress.add_task("trajectories", total=None)

        def report(done: int, total: int) -> None:
            progress.update(task, completed=done, total=total)

        def mount(arm: str, indenter: str) -> None:
            progress.stop()
            typer.confirm(f"Mount the {indenter} indenter on the {arm} arm. Done?", abort=True, err=True)
            progress.start()

        stopped = None
        if backend == "sim":
            from twin.campaign import one_at_a_time, run_campaign
            from twin.campaign_batched import BatchedRunner

            stage_tasks: dict[str, int] = {}
            stage_lock = threading.Lock()

            def stage(name: str, done: int, total: int) -> None:
                """One bar per stage: the batched campaign's stages overlap (told from several threads)."""
                label = {"schedules": "fe schedules", "fe": f"fe batch on {device}"}.get(name, name)
                with stage_lock:
                    if label not in stage_tasks:
                        stage_tasks[label] = progress.add_task(label, total=total)
                    progress.update(stage_tasks[label], completed=done, total=total)

            runner = one_at_a_time if device is None else BatchedRunner(device, slots, stage)
            on_trajectory = viewer.log_trajectory if viewer else None
            try:
                with sigterm_as_interrupt():
                    result = guarded(
                        lambda: run_campaign(
                            config,
                            out,
                            on_progress=report,
                            executor=pool,
                            on_trajectory=on_trajectory,
                            restart=restart,
                            runner=runner,
                            on_plan=stage,
                        )
                    )
            except KeyboardInterrupt as exc:
                progress.stop()
                kept = escape(str(out / "parts"))
                err_console.print(
                    f"[yellow]interrupted:[/yellow] the finished trajectories are kept in {kept}; "
                    "run the same command again to resume"
                )
                raise typer.Exit(code=130) from exc
            finally:
                if viewer:
                    viewer.close()
            pool.close()  # the workers kept between the campaign's maps (an interrupt leaves them to die with us)
        else:
            try:
                result = guarded(lambda: run_from_config(config, hardware_config, out, None if yes else mount, report))
            except BackendError as exc:
                err_console.print(f"[red]error:[/red] {escape(str(exc))}")
                raise typer.Exit(code=1) from exc
            stopped = result.stopped
    for sid, path in result.files.items():
        out_console.print(f"sensor {sid}: {path}")
    out_console.print(f"ran {result.ran}, resumed past {result.skipped}, incomplete {result.incomplete}")
    if stopped:
        err_console.print(f"[red]stopped:[/red] {escape(stopped)}")
        raise typer.Exit(code=1)


def run_from_config(
    config: CampaignConfig,
    hardware_file: Path,
    out_dir: Path,
    on_tool_change: Callable[[str, str], None] | None = None,
    on_progress: Callable[[int, int], None] | None = None,
) -> HardwareCampaignResult:
    """Plan `config`, open `HardwareBackend` on the config file `hardware_file`, run the plan, close.

    Bad input (config file, several sensors) raises ValueError before anything is opened; a device
    that cannot be opened raises BackendError.
    """
    from hardware.backend import HardwareBackend
    from hardware.config import load_config
    from twin.campaign import plan_campaign
    from twin.campaign_hardware import mounted_sensor, run_hardware_campaign

    mounted_sensor(config)
    hardware = load_config(hardware_file)
    plan = plan_campaign(config)
    backend = HardwareBackend(hardware)
    try:
        return run_hardware_campaign(
            plan, out_dir, backend, {"hardware_config": asdict(hardware)}, on_tool_change, on_progress
        )
    finally:
        backend.close()
