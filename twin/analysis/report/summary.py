"""The summary.json document of a comparison report (shape in docs/analysis.md)."""

from __future__ import annotations

import numpy as np

from twin.analysis.compare import Comparison
from twin.analysis.report.field import ResidualField
from twin.analysis.report.stats import breakdowns, error_stats, noise_levels, residuals, trajectories

SCHEMA_VERSION = 1
UNITS = {"force": "N", "pdc": "counts", "electrode": "counts", "depth": "mm"}


def _sample_counts(comparison: Comparison) -> dict[str, int]:
    rows, full = comparison.rows.labels, comparison.fullrate.labels
    runs = trajectories(comparison.fullrate)
    return {
        "trajectories": len(runs),
        "trajectories_not_converged": sum(not full["converged"][idx].all() for idx in runs),
        "rows": len(comparison.rows),
        "rows_converged": int(rows["converged"].sum()),
        "fullrate": len(comparison.fullrate),
        "fullrate_converged": int(full["converged"].sum()),
    }


def summarize(comparison: Comparison, title: str, field: ResidualField) -> dict:
    """The summary.json document (docs/analysis.md)."""
    by = breakdowns(comparison)
    rows_res = residuals(comparison.rows)
    return {
        "schema": SCHEMA_VERSION,
        "title": title,
        "model": {"key": comparison.model.key(), **comparison.model.to_dict()},
        "datasets": list(comparison.datasets),
        "units": UNITS,
        "samples": _sample_counts(comparison),
        "noise": noise_levels(comparison),
        "overall": {c: error_stats(r).to_json() for c, r in rows_res.items()},
        "by": {k: {c: {g: s.to_json() for g, s in groups.items()} for c, groups in v.items()} for k, v in by.items()},
        "residual_field": {
            "file": "residual_field.npz",
            "channel": "force",
            "bandwidth_mm": field.bandwidth * 1e3,
            "vertices": len(field.vertices),
            "vertices_with_data": int(np.isfinite(field.values).sum()),
        },
    }
