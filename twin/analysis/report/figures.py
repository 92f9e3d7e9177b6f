"""The report's figures (matplotlib, no pyplot state): what each draws is in its docstring and caption.

Lengths are m in the data, mm on the axes; forces N, pdc and electrodes counts; the biotac frame.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass

import numpy as np
from matplotlib.axes import Axes
from matplotlib.figure import Figure
from matplotlib.lines import Line2D

from twin.analysis.compare import FORCE_CHANNELS, PHASES, Comparison
from twin.analysis.report.field import ResidualField
from twin.analysis.report.stats import error_stats, residuals, trajectories

PHASE_COLOURS = ("tab:blue", "tab:green", "tab:orange")


@dataclass(frozen=True)
class ReportInputs:
    """What the figures draw from: the comparison, `noise_levels` of it and the skin residual field."""

    comparison: Comparison
    noise: dict[str, dict[str, float]]
    field: ResidualField


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
        members = [i for i in trajectories(rows) if rows.labels["indenter"][i[0]] == indenter]
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
