"""The learn scripts' JSON report: one progress line per model, then the whole object, printed and written."""

from __future__ import annotations

import json
from pathlib import Path

import pytest

from learn.report import add_model, emit


def test_progress_lines_then_the_whole_report_printed_and_written(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    report: dict = {"samples": 10, "models": {}}
    add_model(report, "mlp", {"wall_s": 1.5})
    add_model(report, "pointnet", {"wall_s": 2.0, "epochs": 3})
    emit(report, tmp_path / "report.json")
    first, second, *rest = capsys.readouterr().out.splitlines()
    assert json.loads(first) == {"mlp": {"wall_s": 1.5}}
    assert json.loads(second) == {"pointnet": {"wall_s": 2.0, "epochs": 3}}
    whole = "\n".join(rest)
    assert json.loads(whole) == {
        "samples": 10,
        "models": {"mlp": {"wall_s": 1.5}, "pointnet": {"wall_s": 2.0, "epochs": 3}},
    }
    assert (tmp_path / "report.json").read_text() == whole
    emit(report, None)  # printing only
    assert json.loads(capsys.readouterr().out) == report
