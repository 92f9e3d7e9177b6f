"""docs/tutorial.ipynb runs end to end (issue 22): executed with nbclient in a fresh kernel, in a temporary folder,
and its outputs checked: the files each step writes, finite report figures, a diagnosis verdict."""

import json
import math
import os
from pathlib import Path

import pytest

nbclient = pytest.importorskip("nbclient", reason="the [dev] extra installs nbclient")
nbformat = pytest.importorskip("nbformat")

NOTEBOOK = Path(__file__).resolve().parents[1] / "docs" / "tutorial.ipynb"


def _stdout(cell: dict) -> str:
    return "".join(o.get("text", "") for o in cell.get("outputs", []) if o.get("output_type") == "stream")


def test_the_tutorial_runs_and_writes_what_it_says(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    root = str(NOTEBOOK.parents[1])
    monkeypatch.setenv("TUTORIAL_DIR", str(tmp_path))
    monkeypatch.setenv("PYTHONPATH", os.pathsep.join(filter(None, [root, os.environ.get("PYTHONPATH")])))
    notebook = nbformat.read(NOTEBOOK, as_version=4)
    client = nbclient.NotebookClient(
        notebook, timeout=600, kernel_name="python3", resources={"metadata": {"path": root}}
    )
    client.execute()
    for name in (
        "campaign/biotac2.hdf5",
        "report_before/report.html",
        "report_after/report.html",
        "model_improved.json",
        "tutorial.rrd",
    ):
        assert (tmp_path / name).is_file() and (tmp_path / name).stat().st_size > 0, name
    for report in ("report_before", "report_after"):
        summary = json.loads((tmp_path / report / "summary.json").read_text())
        assert math.isfinite(summary["overall"]["force"]["rms"]) and summary["overall"]["force"]["rms"] > 0
    text = "\n".join(_stdout(c) for c in notebook.cells if c.cell_type == "code")
    verdict = next(line for line in text.splitlines() if line.startswith("verdict: "))
    assert verdict.removeprefix("verdict: ").strip()
    effects = json.loads((tmp_path / "model_improved.json").read_text())["effects"]
    assert len(effects) == 1  # improve added the best-ranked candidate
