"""The improvement history: one JSON line per saved model, replayable in order.

Each entry records the model (skin parameters, effects, mesh), the datasets it was judged on (paths
and content hashes), the effect just added with its fitted values, and the errors before and after
(whitened RMS: 1 = the noise floor), so `twin history` can show how the error fell step by step.
"""

from __future__ import annotations

import json
import os
from datetime import UTC, datetime
from pathlib import Path

from twin.analysis.predict import TwinModel

HISTORY_NAME = "twin-history.jsonl"
"""File name of a history kept beside the data or the model it improves."""


def history_beside(datasets: list[Path], model: Path | None = None) -> Path:
    """Where a history goes when none is named: beside the model file when there is one (it continues
    that model's sequence), else beside the first dataset; never the folder the command runs in."""
    anchor = Path(model) if model is not None else Path(datasets[0])
    return anchor.resolve().parent / HISTORY_NAME


def append_entry(history: Path, entry: dict) -> dict:
    """Append `entry` (plus its step number and time) to the history file, durably; returns it."""
    history = Path(history)
    steps = read_history(history)
    record = {"step": len(steps) + 1, "time_utc": datetime.now(UTC).isoformat(timespec="seconds"), **entry}
    history.parent.mkdir(parents=True, exist_ok=True)
    with open(history, "a", encoding="utf-8") as handle:
        handle.write(json.dumps(record, sort_keys=True) + "\n")
        handle.flush()
        os.fsync(handle.fileno())
    return record


def read_history(history: Path) -> list[dict]:
    """Every entry of a history file (empty when it does not exist); a corrupt line is an error."""
    history = Path(history)
    if not history.exists():
        return []
    entries = []
    for number, line in enumerate(history.read_text(encoding="utf-8").splitlines(), start=1):
        if not line.strip():
            continue
        try:
            entries.append(json.loads(line))
        except json.JSONDecodeError as exc:
            raise ValueError(f"{history}:{number} is not a history entry ({exc.msg})") from exc
    return entries


def load_model(path: Path) -> TwinModel:
    """A TwinModel from a JSON file (`TwinModel.to_dict()` shape); clear error otherwise."""
    try:
        return TwinModel.from_dict(json.loads(Path(path).read_text(encoding="utf-8")))
    except (OSError, json.JSONDecodeError, KeyError, TypeError) as exc:
        raise ValueError(f"{path} is not a model file ({exc})") from exc
