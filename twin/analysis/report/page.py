"""The report page: summary tables and the figures inlined as base64 PNGs, in one self-contained HTML."""

from __future__ import annotations

import base64
import html
import json
from pathlib import Path

from twin.analysis.report.figures import FIGURES
from twin.analysis.report.stats import ROW_CHANNELS

_STYLE = (
    "body{font-family:sans-serif;max-width:1300px;margin:auto}table{border-collapse:collapse}"
    "td,th{border:1px solid #ccc;padding:2px 6px;text-align:right}img{max-width:100%}"
)


def _cell(stats: dict) -> str:
    if stats["rms"] is None:
        return "-"
    return f"{stats['rms']:.3g} <small>({stats['mean']:+.2g})</small>"


def _html_table(channels: dict[str, dict[str, dict]], first_column: str) -> str:
    """A table with one row per group and one column per channel: RMS (mean)."""
    groups = list(next(iter(channels.values()), {}))
    head = "".join(f"<th>{html.escape(c)}</th>" for c in channels)
    body = ""
    for g in groups:
        n = next(iter(channels.values()))[g]["n"]
        cells = "".join(f"<td>{_cell(channels[c][g])}</td>" for c in channels)
        body += f"<tr><th>{html.escape(g)}</th><td>{n}</td>{cells}</tr>"
    return f"<table><tr><th>{html.escape(first_column)}</th><th>n</th>{head}</tr>{body}</table>"


def _overall_rows(summary: dict) -> dict[str, dict[str, dict]]:
    """The overall table of the ROW_CHANNELS as {channel: {"all": stats}} for `_html_table`."""
    return {c: {"all": summary["overall"][c]} for c in ROW_CHANNELS if c in summary["overall"]}


def render_html(summary: dict, figures: dict[str, Path]) -> str:
    """The report page: provenance, noise, overall and per-covariate tables, inlined figures."""
    noise = "".join(
        f"<tr><th>{html.escape(c)}</th><td>{v['fullrate']:.3g}</td><td>{v['rows']:.3g}</td></tr>"
        for c, v in summary["noise"].items()
    )
    sections = [
        f"<h1>{html.escape(summary['title'])}</h1>",
        f"<p>model {summary['model']['key']}: <code>{html.escape(json.dumps(summary['model']))}</code></p>",
        "<p>datasets: " + ", ".join(f"<code>{html.escape(d)}</code>" for d in summary["datasets"]) + "</p>",
        f"<p>samples: <code>{html.escape(json.dumps(summary['samples']))}</code></p>",
        "<p>Cells: RMS of measured - predicted (mean in brackets); force in N, pdc and electrodes in counts. "
        "<i>force</i> is the norm of the force residual vector, <i>electrodes</i> the RMS over the 19.</p>",
        "<h2>Noise sigma</h2><table><tr><th>channel</th><th>full rate</th><th>rows</th></tr>" + noise + "</table>",
        "<h2>Overall (rows)</h2>" + _html_table(_overall_rows(summary), "samples"),
    ]
    for by, channels in summary["by"].items():
        source = "full rate" if by == "phase" else "rows"
        sections.append(f"<h2>By {html.escape(by)} ({source})</h2>" + _html_table(channels, by))
    for name, caption, _ in FIGURES:
        data = base64.b64encode(figures[name].read_bytes()).decode()
        sections.append(
            f"<h2>{name.replace('_', ' ')}</h2><p>{html.escape(caption)}</p>"
            f'<img alt="{name}" src="data:image/png;base64,{data}">'
        )
    title = html.escape(summary["title"])
    head = f"<meta charset='utf-8'><title>{title}</title><style>{_STYLE}</style>"
    return f"<!doctype html><html><head>{head}</head><body>{''.join(sections)}</body></html>"
