"""The JSON report of a learn benchmark or study: one object whose "models" maps a model name to its figures.

Each model's entry is printed as one JSON line when it is done (progress on a long run); the whole
report is printed at the end, indented, and written to a file when one is asked for. Units are the
caller's (in the entries' keys).
"""

from __future__ import annotations

import json
from pathlib import Path


def add_model(report: dict, name: str, entry: dict) -> None:
    """Put `entry` under report["models"][name] and print `{name: entry}` as one JSON line at once."""
    report["models"][name] = entry
    print(json.dumps({name: entry}), flush=True)


def emit(report: dict, path: Path | None) -> None:
    """Print `report` as indented JSON and, when `path` is given, write the same text there."""
    text = json.dumps(report, indent=1)
    print(text)
    if path is not None:
        path.write_text(text)
