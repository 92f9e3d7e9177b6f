"""The comparison report: error tables, plots, a JSON summary and the residual field on the skin.

`write_report(comparison, out_dir)` writes into `out_dir`:
- `summary.json`: the error tables (shape in docs/analysis.md; `summary.SCHEMA_VERSION` changes when it does);
- `report.html`: the same tables plus matplotlib figures, self-contained (PNGs inlined as base64);
- `figures/*.png`: the figures as files;
- `residual_field.npz`: the RMS force error interpolated onto the skin mesh, for a rerun viewer.

The jobs are modules of this package: `stats` (residual statistics), `field` (the residual field on the
skin), `summary` (summary.json), `figures` and `page` (the HTML); this module writes the files.
"""

from __future__ import annotations

import json
from dataclasses import dataclass
from pathlib import Path

from twin.analysis.compare import Comparison
from twin.analysis.report.field import skin_residual_field
from twin.analysis.report.figures import FIGURES, ReportInputs
from twin.analysis.report.page import render_html
from twin.analysis.report.summary import summarize

DEFAULT_TITLE = "biotac-twin: measured vs predicted"


@dataclass(frozen=True)
class ReportFiles:
    """Paths of what `write_report` wrote."""

    html: Path
    summary: Path
    residual_field: Path
    figures: dict[str, Path]


def write_report(comparison: Comparison, out_dir: Path, title: str = DEFAULT_TITLE) -> ReportFiles:
    """Write summary.json, report.html, figures/*.png and residual_field.npz into `out_dir` (created)."""
    out_dir = Path(out_dir)
    (out_dir / "figures").mkdir(parents=True, exist_ok=True)
    field = skin_residual_field(comparison)
    field.save(out_dir / "residual_field.npz")
    summary = summarize(comparison, title, field)
    (out_dir / "summary.json").write_text(json.dumps(summary, indent=1))
    inputs = ReportInputs(comparison, summary["noise"], field)
    figures = {name: out_dir / "figures" / f"{name}.png" for name, _, _ in FIGURES}
    for name, _, draw in FIGURES:
        draw(inputs).savefig(figures[name], dpi=90)
    (out_dir / "report.html").write_text(render_html(summary, figures))
    return ReportFiles(out_dir / "report.html", out_dir / "summary.json", out_dir / "residual_field.npz", figures)
