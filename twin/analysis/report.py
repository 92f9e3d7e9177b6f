"""The comparison report: error tables, plots, a JSON summary and the residual field on the skin.

`write_report(comparison, out_dir)` writes into `out_dir`:
- `summary.json`: the error tables (shape in docs/analysis.md; `SCHEMA_VERSION` changes when it does);
- `report.html`: the same tables plus matplotlib figures, self-contained (PNGs inlined as base64);
- `figures/*.png`: the figures as files;
- `residual_field.npz`: the RMS force error interpolated onto the skin mesh, for a rerun viewer.

Errors are residuals measured - predicted. Channels are those of `twin.analysis.compare` plus two
derived per-sample magnitudes: `force` (N, Euclidean norm of the force residual vector, biotac frame)
and `electrodes` (counts, RMS over the 19 electrodes). The RMS of `force` over samples is
sqrt(sum of the per-axis mean squares); the RMS of `electrodes` is the pooled electrode RMS; their
`mean` is the mean magnitude, not a bias. Samples whose prediction did not converge are NaN and are
left out of every statistic (`n` counts what was used). Lengths are m inside, mm in labels and keys.
"""

from __future__ import annotations

import base64
import html
import json
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path

import numpy as np
from matplotlib.axes import Axes
from matplotlib.figure import Figure
from matplotlib.lines import Line2D
from scipy.spatial import cKDTree

from assets.biotac import make_biotac
from twin.analysis.compare import FORCE_CHANNELS, PHASES, Comparison, SampleTable
from twin.processing import lowpass

SCHEMA_VERSION = 1
DEFAULT_TITLE = "biotac-twin: measured vs predicted"
ROW_CHANNELS = (*FORCE_CHANNELS, "force", "pdc", "electrodes")
"""Channels of the per-covariate breakdowns of the rows table."""
FULLRATE_CHANNELS = (*FORCE_CHANNELS, "force")
"""Channels of the per-phase breakdown of the full-rate table."""
UNITS = {"force": "N", "pdc": "counts", "electrode": "counts", "depth": "mm"}
DEPTH_STEPS_MM = (0.1, 0.2, 0.25, 0.5, 1.0, 2.0, 5.0)
MAX_DEPTH_BINS = 6
MIN_BANDWIDTH = 1e-3
"""Smallest kernel bandwidth (m) of the residual field; the mesh edge length when larger."""
KERNEL_REACH = 2.5
"""Kernel cut-off in bandwidths: vertices farther than this from every contact get no value."""
PHASE_COLOURS = ("tab:blue", "tab:green", "tab:orange")


@dataclass(frozen=True)
class ErrorStats:
    """Residual statistics of one channel over a set of samples (units of the channel)."""

    rms: float
    mean: float
    n: int

    def to_json(self) -> dict:
        """JSON-ready dict; NaN (no samples) becomes null."""
        return {"rms": _json_float(self.rms), "mean": _json_float(self.mean), "n": self.n}


@dataclass(frozen=True)
class ResidualField:
    """RMS force error on the skin mesh (unpressurised mid-surface, biotac frame).

    values[v] = sqrt(sum_i w_iv |r_i|^2 / sum_i w_iv): the root of a Gaussian-kernel (Nadaraya-Watson)
    estimate of the mean squared force residual |r_i| (N) of the rows near vertex v, each row placed at the
    skin vertex nearest its contact location; NaN where no row lies within KERNEL_REACH bandwidths.
    support[v] = sum_i w_iv, the effective number of rows behind values[v].
    """

    vertices: np.ndarray  # (V, 3) m
    triangles: np.ndarray  # (T, 3) vertex indices
    values: np.ndarray  # (V,) N
    support: np.ndarray  # (V,)
    bandwidth: float  # m

    def save(self, path: Path) -> None:
        """Write the arrays (and the bandwidth in m) to an .npz file."""
        np.savez(path, **{k: getattr(self, k) for k in ("vertices", "triangles", "values", "support", "bandwidth")})


@dataclass(frozen=True)
class ReportFiles:
    """Paths of what `write_report` wrote."""

    html: Path
    summary: Path
    residual_field: Path
    figures: dict[str, Path]


@dataclass(frozen=True)
class ReportInputs:
    """What the figures draw from: the comparison, `noise_levels` of it and the skin residual field."""

    comparison: Comparison
    noise: dict[str, dict[str, float]]
    field: ResidualField


def _json_float(value: float) -> float | None:
    return float(value) if np.isfinite(value) else None


# --- tables ---------------------------------------------------------------------------------------


def residuals(table: SampleTable) -> dict[str, np.ndarray]:
    """measured - predicted of every channel of `table`, plus the derived `force` and `electrodes`."""
    out = {c: table.residual(c) for c in table.measured}
    if all(c in out for c in FORCE_CHANNELS):
        out["force"] = np.linalg.norm(np.column_stack([out[c] for c in FORCE_CHANNELS]), axis=1)
    electrodes = [c for c in out if c.startswith("electrode_")]
    if electrodes:
        out["electrodes"] = np.sqrt(np.mean(np.column_stack([out[c] for c in electrodes]) ** 2, axis=1))
    return out


def _trajectories(table: SampleTable) -> list[np.ndarray]:
    """Sample indices of each (sensor, trajectory), in table order."""
    keys = np.column_stack([table.labels["sensor"], table.labels["trajectory"]])
    _, inverse = np.unique(keys, axis=0, return_inverse=True)
    return [np.flatnonzero(inverse.ravel() == k) for k in range(inverse.max() + 1)] if len(keys) else []


def error_stats(residual: np.ndarray) -> ErrorStats:
    """RMS, mean and count of the finite entries of `residual` (NaN statistics when none)."""
    finite = residual[np.isfinite(residual)]
    if not len(finite):
        return ErrorStats(float("nan"), float("nan"), 0)
    return ErrorStats(float(np.sqrt(np.mean(finite**2))), float(np.mean(finite)), len(finite))


def grouped_stats(residual: np.ndarray, groups: np.ndarray, name: Callable = str) -> dict[str, ErrorStats]:
    """`error_stats` per distinct value of `groups` (sorted), keyed by `name(value)`."""
    return {name(g): error_stats(residual[groups == g]) for g in np.unique(groups)}


def depth_step_mm(max_depth: float) -> float:
    """Bin width (mm) for depths up to `max_depth` (m): the finest step giving at most MAX_DEPTH_BINS bins."""
    needed = max(max_depth * 1e3, DEPTH_STEPS_MM[0]) / MAX_DEPTH_BINS
    return next((s for s in DEPTH_STEPS_MM if s >= needed - 1e-9), DEPTH_STEPS_MM[-1])


def depth_bins(depth: np.ndarray) -> tuple[np.ndarray, Callable[[int], str]]:
    """Bin index of each depth (m) and the bins' names (mm).

    Bin k >= 0 holds depths in (k w, (k+1) w] mm, named "lo-hi"; bin -1, named "<=0", holds the samples
    with no commanded indentation (first contact and the retract). w is `depth_step_mm` of the deepest sample.
    """
    finite = depth[np.isfinite(depth)]
    step = depth_step_mm(float(finite.max()) if len(finite) else 0.0)
    index = np.maximum(np.ceil(np.round(depth * 1e3 / step, 6)) - 1, -1).astype(int)
    return index, lambda k: "<=0" if k < 0 else f"{k * step:g}-{(k + 1) * step:g}"


def row_groupings(rows: SampleTable) -> dict[str, tuple[np.ndarray, Callable]]:
    """The covariates the rows table is broken down by: (group of each sample, group naming)."""
    labels = rows.labels
    return {
        "indenter": (labels["indenter"], str),
        "sensor": (labels["sensor"], str),
        "normal": (labels["normal"], lambda normal: "normal" if normal else "angled"),
        "depth_mm": depth_bins(labels["depth"]),
    }


def breakdowns(comparison: Comparison) -> dict[str, dict[str, dict[str, ErrorStats]]]:
    """{covariate: {channel: {group: stats}}}: rows by `row_groupings`, the full-rate table by phase."""
    rows_res, full_res = residuals(comparison.rows), residuals(comparison.fullrate)
    out = {
        by: {c: grouped_stats(rows_res[c], groups, name) for c in ROW_CHANNELS if c in rows_res}
        for by, (groups, name) in row_groupings(comparison.rows).items()
    }
    phase = comparison.fullrate.labels["phase"]
    out["phase"] = {c: grouped_stats(full_res[c], phase, PHASES.__getitem__) for c in FULLRATE_CHANNELS}
    return out


def filtered_noise_gain(rate_hz: float) -> float:
    """Standard deviation of unit white noise after the rows' force filter (exact: impulse response norm)."""
    impulse = np.zeros(int(20 * rate_hz) + 1)
    impulse[len(impulse) // 2] = 1.0
    return float(np.linalg.norm(lowpass(impulse, rate_hz)))


def noise_levels(comparison: Comparison) -> dict[str, dict[str, float]]:
    """Per channel, the noise sigma of full-rate samples and of rows (forces in rows are low-passed)."""
    time = comparison.fullrate.labels["time"]
    gain = filtered_noise_gain(float(1.0 / np.median(np.diff(time))))
    return {
        c: {"fullrate": sigma, "rows": sigma * gain if c in FORCE_CHANNELS else sigma}
        for c, sigma in comparison.noise.items()
    }


def _sample_counts(comparison: Comparison) -> dict[str, int]:
    rows, full = comparison.rows.labels, comparison.fullrate.labels
    trajectories = _trajectories(comparison.fullrate)
    return {
        "trajectories": len(trajectories),
        "trajectories_not_converged": sum(not full["converged"][idx].all() for idx in trajectories),
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


# --- residual field on the skin -------------------------------------------------------------------


def residual_field(
    vertices: np.ndarray, triangles: np.ndarray, points: np.ndarray, residual: np.ndarray, bandwidth: float
) -> ResidualField:
    """Interpolate per-sample residual magnitudes at `points` (m) onto the mesh (see `ResidualField`)."""
    keep = np.isfinite(residual) & np.isfinite(points).all(axis=1)
    tree = cKDTree(vertices)
    _, anchor = tree.query(points[keep])
    squares = np.bincount(anchor, weights=residual[keep] ** 2, minlength=len(vertices))
    counts = np.bincount(anchor, minlength=len(vertices)).astype(float)
    used = np.flatnonzero(counts)
    neighbours = tree.query_ball_point(vertices[used], KERNEL_REACH * bandwidth)
    source = np.repeat(used, [len(n) for n in neighbours])
    target = np.concatenate([np.asarray(n, dtype=int) for n in neighbours]) if len(used) else np.zeros(0, int)
    weight = np.exp(-0.5 * (np.linalg.norm(vertices[target] - vertices[source], axis=1) / bandwidth) ** 2)
    numerator = np.bincount(target, weights=weight * squares[source], minlength=len(vertices))
    support = np.bincount(target, weights=weight * counts[source], minlength=len(vertices))
    with np.errstate(invalid="ignore", divide="ignore"):
        values = np.where(support > 0, np.sqrt(numerator / support), np.nan)
    return ResidualField(vertices, triangles, values, support, bandwidth)


def skin_residual_field(comparison: Comparison) -> ResidualField:
    """The rows' force residual magnitude on the skin mesh of the comparison's model mesh size."""
    edge = comparison.model.mesh_max_edge
    skin = make_biotac(edge).skin
    rows = comparison.rows
    points = np.column_stack([rows.labels[f"contact_{a}"] for a in "xyz"])
    return residual_field(skin.vertices, skin.triangles, points, residuals(rows)["force"], max(MIN_BANDWIDTH, edge))


# --- figures --------------------------------------------------------------------------------------


def _force_norm(forces: dict[str, np.ndarray]) -> np.ndarray:
    return np.linalg.norm(np.column_stack([forces[c] for c in FORCE_CHANNELS]), axis=1)


def _noise_band(ax: Axes, sigma: float, label: str = "noise sigma") -> None:
    ax.axhline(sigma, color="k", ls=":", lw=1, label=label)
    ax.axhline(-sigma, color="k", ls=":", lw=1)
    ax.axhline(0.0, color="grey", lw=0.5)


def _axes(n: int, width: float = 4.0, height: float = 3.2) -> tuple[Figure, list[Axes]]:
    cols = min(n, 3)
    rows = -(-n // cols)
    fig = Figure(figsize=(width * cols, height * rows), layout="constrained")
    axes = list(fig.subplots(rows, cols, squeeze=False).ravel())
    for spare in axes[n:]:
        fig.delaxes(spare)
    return fig, axes[:n]


def plot_force_depth(inputs: ReportInputs) -> Figure:
    """Measured (solid) and predicted (dashed) force magnitude vs depth >= 0, per indenter and trajectory."""
    rows = inputs.comparison.rows
    indenters = list(np.unique(rows.labels["indenter"]))
    fig, axes = _axes(len(indenters))
    measured, predicted = _force_norm(rows.measured), _force_norm(rows.predicted)
    depth = rows.labels["depth"] * 1e3
    for ax, indenter in zip(axes, indenters, strict=True):
        members = [i for i in _trajectories(rows) if rows.labels["indenter"][i[0]] == indenter]
        for k, idx in enumerate(members):
            idx = idx[np.argsort(rows.labels["time"][idx])]
            idx = idx[depth[idx] >= 0]
            ax.plot(depth[idx], measured[idx], color=f"C{k}", lw=1.2)
            ax.plot(depth[idx], predicted[idx], color=f"C{k}", lw=1.2, ls="--")
        ax.set(title=indenter, xlabel="depth (mm)", ylabel="|force| (N)")
    axes[0].legend([Line2D([], [], color="k"), Line2D([], [], color="k", ls="--")], ["measured", "predicted"])
    return fig


def plot_residual_vs_depth(inputs: ReportInputs) -> Figure:
    """Force residual per axis vs depth (rows), loading and unloading, with the rows' noise sigma."""
    rows = inputs.comparison.rows
    fig, axes = _axes(len(FORCE_CHANNELS))
    depth, phase = rows.labels["depth"] * 1e3, rows.labels["phase"]
    for ax, channel in zip(axes, FORCE_CHANNELS, strict=True):
        for p in (0, 2):
            mask = phase == p
            ax.scatter(depth[mask], rows.residual(channel)[mask], s=6, color=PHASE_COLOURS[p], label=PHASES[p])
        _noise_band(ax, inputs.noise[channel]["rows"])
        ax.set(title=channel, xlabel="depth (mm)", ylabel="residual (N)")
    axes[0].legend(fontsize="small")
    return fig


def plot_residual_vs_time_in_increment(inputs: ReportInputs) -> Figure:
    """Full-rate force residual vs time since the increment's command (pause effects), with binned RMS."""
    full = inputs.comparison.fullrate
    fig, axes = _axes(len(FORCE_CHANNELS))
    t, phase = full.labels["time_in_increment"], full.labels["phase"]
    edges = np.linspace(0.0, float(np.nanmax(t)) if len(t) else 1.0, 21)
    bin_of = np.clip(np.digitize(t, edges) - 1, 0, len(edges) - 2)
    centres = 0.5 * (edges[1:] + edges[:-1])
    for ax, channel in zip(axes, FORCE_CHANNELS, strict=True):
        residual = full.residual(channel)
        for p, name in enumerate(PHASES):
            mask = phase == p
            ax.scatter(t[mask], residual[mask], s=2, alpha=0.3, color=PHASE_COLOURS[p], label=name)
        binned = [error_stats(residual[bin_of == k]).rms for k in range(len(centres))]
        ax.plot(centres, binned, color="k", lw=1.5, label="binned RMS")
        _noise_band(ax, inputs.noise[channel]["fullrate"])
        ax.set(title=channel, xlabel="time in increment (s)", ylabel="residual (N)")
    axes[0].legend(fontsize="small", markerscale=3)
    return fig


def _histogram(ax: Axes, residual: np.ndarray, sigma: float, title: str, unit: str) -> None:
    finite = residual[np.isfinite(residual)]
    ax.hist(finite, bins=40, density=True, color="tab:blue", alpha=0.7, label="residual")
    if sigma > 0:
        x = np.linspace(*ax.get_xlim(), 200)
        ax.plot(x, np.exp(-0.5 * (x / sigma) ** 2) / (sigma * np.sqrt(2 * np.pi)), "k:", label="noise N(0, sigma)")
    ax.set(title=title, xlabel=f"residual ({unit})", ylabel="density")


def plot_histograms(inputs: ReportInputs) -> Figure:
    """Residual histograms against the noise density: full-rate forces and the rows' pdc."""
    comparison, noise = inputs.comparison, inputs.noise
    fig, axes = _axes(len(FORCE_CHANNELS) + 1)
    for ax, channel in zip(axes, FORCE_CHANNELS, strict=False):
        _histogram(ax, comparison.fullrate.residual(channel), noise[channel]["fullrate"], f"{channel} (full rate)", "N")
    _histogram(axes[-1], comparison.rows.residual("pdc"), noise["pdc"]["rows"], "pdc (rows)", "counts")
    axes[0].legend(fontsize="small")
    return fig


def _identity_scatter(ax: Axes, measured: np.ndarray, predicted: np.ndarray, title: str) -> None:
    ax.scatter(measured, predicted, s=4, alpha=0.5)
    both = np.concatenate([measured, predicted])
    both = both[np.isfinite(both)]
    if len(both):
        ax.plot([both.min(), both.max()], [both.min(), both.max()], "k:", lw=1)
    ax.set(title=title, xlabel="measured (counts)", ylabel="predicted (counts)")


def plot_electrodes(inputs: ReportInputs) -> Figure:
    """Per-electrode RMS residual (after the per-sensor affine read-out fit), electrode and pdc scatter."""
    rows = inputs.comparison.rows
    names = sorted((c for c in rows.measured if c.startswith("electrode_")), key=lambda c: int(c.split("_")[1]))
    fig, axes = _axes(3)
    axes[0].bar([c.split("_")[1] for c in names], [error_stats(rows.residual(c)).rms for c in names])
    axes[0].set(title="electrode RMS residual", xlabel="electrode", ylabel="RMS (counts)")
    pooled = [np.concatenate([part[c] for c in names]) for part in (rows.measured, rows.predicted)]
    _identity_scatter(axes[1], *pooled, "electrodes (tared)")
    _identity_scatter(axes[2], rows.measured["pdc"], rows.predicted["pdc"], "pdc")
    sigma = inputs.noise["pdc"]["rows"]
    axes[2].text(0.02, 0.95, f"noise sigma {sigma:.3g} counts", transform=axes[2].transAxes, va="top")
    return fig


def plot_skin_map(inputs: ReportInputs) -> Figure:
    """Force error on the finger, seen from below (ventral side): per-row scatter and the skin field."""
    rows, field = inputs.comparison.rows, inputs.field
    magnitude = residuals(rows)["force"]
    top = max(float(np.nanmax(magnitude)) if np.isfinite(magnitude).any() else 0.0, 1e-12)
    fig, axes = _axes(2, width=5.0)
    v = field.vertices * 1e3
    for ax in axes:
        ax.scatter(v[:, 0], v[:, 1], s=1, color="0.85")
        ax.set(xlabel="x (mm)", ylabel="y (mm)", aspect="equal")
    x, y = rows.labels["contact_x"] * 1e3, rows.labels["contact_y"] * 1e3
    scatter = axes[0].scatter(x, y, c=magnitude, s=10, vmin=0, vmax=top)
    axes[0].set_title("|force residual| at each row's contact")
    corner = v[field.triangles]
    facing_down = np.cross(corner[:, 1] - corner[:, 0], corner[:, 2] - corner[:, 0])[:, 2] < 0
    shown = field.triangles[facing_down & np.isfinite(field.values[field.triangles]).all(axis=1)]
    if len(shown):
        axes[1].tripcolor(v[:, 0], v[:, 1], shown, facecolors=field.values[shown].mean(axis=1), vmin=0, vmax=top)
    axes[1].set_title(f"RMS force error on the skin (kernel {field.bandwidth * 1e3:g} mm)")
    fig.colorbar(scatter, ax=axes, label="force error (N)")
    return fig


FIGURES: tuple[tuple[str, str, Callable[[ReportInputs], Figure]], ...] = (
    (
        "force_depth",
        "Measured (solid) vs predicted (dashed) force magnitude against depth, per indenter.",
        plot_force_depth,
    ),
    (
        "residual_vs_depth",
        "Force residual against depth (rows); dotted: the rows' noise sigma.",
        plot_residual_vs_depth,
    ),
    (
        "residual_vs_time_in_increment",
        "Full-rate force residual against time since each increment's command: a trend in the pause is "
        "relaxation or drift; dotted: full-rate noise sigma.",
        plot_residual_vs_time_in_increment,
    ),
    ("histograms", "Residual distributions against the noise density (dotted).", plot_histograms),
    (
        "electrodes",
        "Electrodes (after a per-sensor affine read-out fit) and pdc: measured vs predicted.",
        plot_electrodes,
    ),
    (
        "skin_map",
        "Where on the finger the force error is: rows at their contact, and the field on the skin.",
        plot_skin_map,
    ),
)
"""(name, caption, drawing) of every figure, in report order."""


# --- html -----------------------------------------------------------------------------------------


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


# --- entry point ----------------------------------------------------------------------------------


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
