"""Shared CLI helpers: number parsing, bad-input guarding, progress bars (stderr), consoles."""

from collections.abc import Callable
from typing import TypeVar

import typer
from rich.console import Console
from rich.markup import escape
from rich.progress import BarColumn, Progress, TextColumn, TimeElapsedColumn, TimeRemainingColumn

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
        err_console.print(f"[red]error:[/red] {escape(str(exc))}")
        raise typer.Exit(code=2) from exc


def progress_bar() -> Progress:
    """A rich progress bar on stderr with elapsed time and ETA (stdout stays clean for JSON)."""
    return Progress(
        TextColumn("{task.description}"),
        BarColumn(),
        TextColumn("{task.completed}/{task.total}"),
        TimeElapsedColumn(),
        TimeRemainingColumn(),
        console=err_console,
        transient=True,
    )
