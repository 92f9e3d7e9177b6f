"""Shared CLI helpers: number parsing, bad-input guarding, warnings about NaN forces, SIGTERM as Ctrl-C, progress
bars (stderr), consoles, the fe model and warp device of the `twin fe` commands, the predictor (and its warp device),
model and datasets of the analysis commands, the campaign options and config of `twin campaign` and `twin devices`."""

from __future__ import annotations

import json
import os
import signal
import sys
import tempfile
import time
from collections.abc import Callable, Iterator
from contextlib import contextmanager
from dataclasses import replace
from pathlib import Path
from typing import TYPE_CHECKING, Annotated, TypeVar

import typer
from rich.console import Console
from rich.markup import escape
from rich.progress import BarColumn, Progress, TextColumn, TimeElapsedColumn, TimeRemainingColumn

if TYPE_CHECKING:
    from assets.refine import Refinement
    from fe.params import SkinParameters
    from fe.sensor import BioTacModel, InflationResult
    from twin.analysis.data import CampaignData
    from twin.analysis.predict import Predictor, TwinModel
    from twin.campaign import CampaignConfig

err_console = Console(stderr=True)
out_console = Console()
T = TypeVar("T")


def parse_floats(text: str, count: int | None, name: str) -> list[float]:
    """Parse comma-separated numbers of an option called `name`; `count` fixes how many (None: any)."""
    try:
        values = [float(v) for v in text.split(",") if v.strip()]
    except ValueError as exc:
        raise typer.BadParameter(f"{name} must be comma-separated numbers, got {text!r}") from exc
    if count is not None and len(values) != count:
        raise typer.BadParameter(f"{name} needs {count} comma-separated numbers, got {text!r}")
    return values


def guarded(action: Callable[[], T]) -> T:
    """Run `action`, turning bad-input errors (ValueError) into a one-line message and exit code 2."""
    try:
        return action()
    except ValueError as exc:
        err_console.print(f"[red]error:[/red] {escape(str(exc))}", soft_wrap=True)
        raise typer.Exit(code=2) from exc


def warn_nonfinite_forces(paths: list[Path]) -> None:
    """A warning on stderr, with the count, for each file whose measured forces have NaN or infinite rows, so
    that no command leaves them out of (or lets them spoil) its force errors in silence."""
    import h5py

    from twin.dataset import nonfinite_rows

    for path in paths:
        bad, total = nonfinite_rows(path) if h5py.is_hdf5(path) else (0, 0)
        if bad:
            err_console.print(
                f"[yellow]warning:[/yellow] {escape(str(path))}: {bad} of {total} rows have NaN or infinite "
                "forces; force errors cannot use them",
                soft_wrap=True,
            )


@contextmanager
def sigterm_as_interrupt() -> Iterator[None]:
    """Within the block SIGTERM raises KeyboardInterrupt, like Ctrl-C, so that a terminated command cleans up
    (ends its workers, removes temporary files) and says so (main thread only)."""
    previous = signal.signal(signal.SIGTERM, signal.default_int_handler)
    try:
        yield
    finally:
        signal.signal(signal.SIGTERM, previous)


PLAIN_PROGRESS_INTERVAL_S = 15.0
"""Where stderr is not a terminal (a log file, a batch job), the progress is a plain line at most this often (s)."""


class LoggedProgress(Progress):
    """A rich progress bar that, where its console is not a terminal (so rich draws nothing), writes a plain line
    "description done/total (elapsed s)" instead: once the work has run `interval_s`, then whenever a task's
    description changes or it finishes, and at most every `interval_s` otherwise. Short runs stay silent."""

    def __init__(self, *columns, interval_s: float = PLAIN_PROGRESS_INTERVAL_S, **kwargs) -> None:
        super().__init__(*columns, **kwargs)
        self.interval_s = interval_s
        self._started = time.monotonic()
        self._last_line = float("-inf")
        self._last_description: dict[int, str] = {}

    def update(self, task_id, *args, **kwargs) -> None:  # noqa: D102 (rich's)
        super().update(task_id, *args, **kwargs)
        self._log(task_id)

    def advance(self, task_id, advance: float = 1) -> None:  # noqa: D102 (rich's)
        super().advance(task_id, advance)
        self._log(task_id)

    def _log(self, task_id) -> None:
        if self.console.is_terminal:
            return
        with self._lock:  # rich's own (re-entrant) lock: the campaign's stages are told from several threads
            self._log_line(task_id)

    def _log_line(self, task_id) -> None:
        now = time.monotonic()
        task = next(t for t in self.tasks if t.id == task_id)
        changed = self._last_description.get(task_id) not in (None, task.description)
        self._last_description[task_id] = task.description
        finished = task.total is not None and task.completed >= task.total
        due = changed or finished or now - self._last_line >= self.interval_s
        if now - self._started < self.interval_s or not due:
            return
        self._last_line = now
        total = "?" if task.total is None else f"{task.total:g}"
        line = f"{task.description} {task.completed:g}/{total} ({now - self._started:.0f} s)"
        self.console.print(line, markup=False, highlight=False)


def progress_bar() -> Progress:
    """A rich progress bar on stderr with elapsed time and ETA (stdout stays clean for JSON); plain lines where
    stderr is not a terminal (`LoggedProgress`)."""
    return LoggedProgress(
        TextColumn("{task.description}"),
        BarColumn(),
        TextColumn("{task.completed}/{task.total}"),
        TimeElapsedColumn(),
        TimeRemainingColumn(),
        console=err_console,
        transient=True,
    )


FE_MESH_MM = 0.5
"""Maximum skin edge length (mm) of the `twin fe` indentations given neither --mesh-mm nor --model."""
FE_MESH_HELP = (
    f"Maximum skin edge length (mm); default the --model's mesh_max_edge, {FE_MESH_MM:g} without --model; "
    "given with --model it overrides the model's."
)
FE_MODEL_HELP = (
    "TwinModel JSON (TwinModel.to_dict(), as the analysis writes it): skin parameters with its effects applied, "
    "mesh size and inflation rule; default the nominal model."
)
"""Help of the --mesh-mm and --model options of `twin fe indent` and `twin fe batch` (`inflated_twin_model`)."""


def inflated_twin_model(
    model_path: Path | None, mesh_mm: float | None, refinement: Refinement | None = None
) -> tuple[TwinModel, BioTacModel, InflationResult]:
    """The `--model` TwinModel JSON (None: the nominal model) with its mesh size overridden by `mesh_mm` (mm;
    None: the model's, `FE_MESH_MM` without a model), and its fe model: skin with the effects applied, meshed
    finer about a press point with a `refinement`, inflated by the model's rule
    (`twin.fe_models.inflated_fe_model`), with the InflationResult. Bad input
    (unreadable or invalid model, bad mesh size): one-line message and exit code 2."""
    from twin.effects import apply_skin
    from twin.fe_models import inflated_fe_model

    def load() -> tuple[TwinModel, SkinParameters]:
        try:
            loaded = model_or_nominal(model_path, FE_MESH_MM * 1e-3)
            return loaded, apply_skin(loaded.skin, loaded.effects)
        except ValueError as exc:
            raise ValueError(f"--model: {exc}") from exc

    twin_model, skin = guarded(load)
    if mesh_mm is not None:
        twin_model = replace(twin_model, mesh_max_edge=mesh_mm * 1e-3)
    err_console.print(
        f"model: {escape(str(model_path or 'nominal'))}; skin mesh {twin_model.mesh_max_edge * 1e3:g} mm; "
        f"inflating ({twin_model.inflation} rule) ..."
    )
    model, inflation = guarded(
        lambda: inflated_fe_model(skin, twin_model.mesh_max_edge, twin_model.inflation, refinement)
    )
    return twin_model, model, inflation


@contextmanager
def native_stderr_captured() -> Iterator[list[str]]:
    """Within the block, what is written to file descriptor 2 (native libraries print there, past sys.stderr)
    is captured; the yielded list holds its lines after the block."""
    lines: list[str] = []
    sys.stderr.flush()
    saved = os.dup(2)
    with tempfile.TemporaryFile() as captured:
        os.dup2(captured.fileno(), 2)
        try:
            yield lines
        finally:
            sys.stderr.flush()
            os.dup2(saved, 2)
            os.close(saved)
            captured.seek(0)
            lines.extend(captured.read().decode(errors="replace").splitlines(keepends=True))


def check_device(device: str) -> None:
    """A ValueError naming the device when warp cannot use it here. What warp's native library prints while
    it finds out (e.g. "Warp CUDA error ..." lines for cuda on a machine without a usable GPU) is dropped
    when the device is refused, so the refusal is one line."""
    import warp as wp

    import fe.wptypes  # noqa: F401  (warp initialised without the no-driver line)

    with native_stderr_captured() as printed:
        try:
            wp.get_device(device)
            refusal = None
        except (RuntimeError, ValueError) as exc:
            refusal = exc
    if refusal is not None:
        raise ValueError(f"warp device {device!r} is not available here: {refusal}") from refusal
    sys.stderr.write("".join(printed))


DeviceOption = Annotated[
    str,
    typer.Option(
        "--device",
        help="Warp device of the fe replays: cpu, cuda, cuda:0, ...; the trajectories of each model are solved "
        "as the systems of one batch.",
    ),
]
"""The --device option of compare, validate, calibrate, diagnose and improve (`analysis_predictor`)."""


def analysis_predictor(device: str, electrodes: bool = True) -> Predictor:
    """A `twin.analysis.predict.Predictor` replaying on the warp `device`, reading the electrodes unless told not to
    (the residual's analyses); a device warp cannot use here is a one-line message and exit code 2."""
    from twin.analysis.predict import Predictor

    guarded(lambda: check_device(device))
    return Predictor(device, electrodes=electrodes)


@contextmanager
def replay_progress(predictor: Predictor) -> Iterator[Progress]:
    """A progress bar (`progress_bar`) with an "fe replays" line that `predictor` advances as it solves the
    replays of a batch; more lines may be added to it."""
    with progress_bar() as progress:
        task = progress.add_task("fe replays", total=None)
        predictor.on_replays = lambda done, total: progress.update(task, completed=done, total=total)
        try:
            yield progress
        finally:
            predictor.on_replays = None


def model_or_nominal(path: Path | None, mesh_max_edge: float) -> TwinModel:
    """The TwinModel of a `TwinModel.to_dict()` JSON file, or the nominal model at `mesh_max_edge` (m)."""
    from twin.analysis.predict import TwinModel

    if path is None:
        return TwinModel(mesh_max_edge=mesh_max_edge)
    try:
        return TwinModel.from_dict(json.loads(path.read_text()))
    except OSError as exc:
        raise ValueError(f"cannot read the model {path}: {exc}") from exc
    except (json.JSONDecodeError, KeyError, TypeError, AttributeError) as exc:
        raise ValueError(f"{path} is not a model JSON (TwinModel.to_dict()): {exc!r}") from exc


def load_datasets(paths: list[Path]) -> list[CampaignData]:
    """The campaign files (warning about NaN forces; one stderr line per row-only file, naming what it cannot
    identify); ValueError when they disagree on the mesh size the default model needs."""
    from twin.analysis.data import load_campaign
    from twin.analysis.rows_only import rows_only_note

    datasets = [load_campaign(p) for p in paths]
    for d in datasets:
        if d.rows_only:
            err_console.print(rows_only_note(d.path), soft_wrap=True, markup=False, highlight=False)
    warn_nonfinite_forces(paths)
    if len({d.mesh_max_edge for d in datasets}) > 1:
        raise ValueError("the datasets were made with different mesh sizes: pass --model")
    return datasets


def analysis_inputs(
    datasets: list[Path], model_path: Path | None, device: str
) -> tuple[Predictor, list[CampaignData], TwinModel]:
    """What compare, calibrate and validate start from: the predictor on the warp `device` (checked first), the
    campaign files (`load_datasets`) and the `--model` JSON or the nominal model at the data's mesh size. Bad
    input: one-line message and exit code 2."""
    predictor = analysis_predictor(device)
    data = guarded(lambda: load_datasets(datasets))
    model = guarded(lambda: model_or_nominal(model_path, data[0].mesh_max_edge))
    return predictor, data, model


def campaign_config(
    quick: bool, sensors: str | None, indenters: str | None, seed: int, mesh_mm: float | None
) -> CampaignConfig:
    """The campaign of the `--quick/--sensors/--indenters/--seed/--mesh-mm` options (`twin campaign plan|run`,
    `twin devices serve --twin`): the paper plan or `QUICK_CONFIG`, with comma-separated sensor ids and indenter
    names, and the skin mesh max edge given in mm (stored in m)."""
    from twin.campaign import QUICK_CONFIG, CampaignConfig

    config = QUICK_CONFIG if quick else CampaignConfig()
    changes: dict = {"seed": seed}
    if sensors:
        changes["sensors"] = tuple(int(s) for s in sensors.split(",") if s.strip())
    if indenters:
        changes["indenters"] = tuple(s.strip() for s in indenters.split(",") if s.strip())
    if mesh_mm is not None:
        changes["mesh_max_edge"] = mesh_mm * 1e-3
    return replace(config, **changes)


Quick = Annotated[bool, typer.Option("--quick", help="A small campaign: coarse mesh, few trajectories.")]
Sensors = Annotated[str | None, typer.Option(help="Comma-separated sensor ids (default 1,2,3).")]
Indenters = Annotated[str | None, typer.Option(help="Comma-separated indenter names (default all nine).")]
Seed = Annotated[int, typer.Option(help="Seed of every random draw.")]
MeshMm = Annotated[float | None, typer.Option(help="Skin mesh max edge (mm); default 0.5, quick 2.")]
"""The campaign options of `campaign_config`."""
