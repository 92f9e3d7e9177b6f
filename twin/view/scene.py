"""Log one BioTac's state to rerun: skin coloured by displacement, indenter pose, force, electrodes, series.

Entity layout (under the `root`, default `biotac`), all in the biotac frame, metres:
- `{root}/skin`: Mesh3D of the deformed skin mid-surface, vertex colours = |displacement| (viridis,
  0 to `displacement_scale_m`);
- `{root}/indenter`: Transform3D (rotation body->biotac, tip position); `{root}/indenter/shape`: the
  indenter's Mesh3D in its own frame (logged when the indenter changes);
- `{root}/force`: Arrows3D from the tip along the force of the indenter on the skin, `FORCE_ARROW_M_PER_N`;
- `{root}/electrodes`: Points3D at the 19 electrode centres, colours = tared counts (coolwarm, +-
  `electrode_scale_counts`);
- `series/{root}/force` (3 scalars, N), `series/{root}/pressure` (Pa), `series/{root}/pdc` (counts),
  `series/{root}/electrodes` (19 scalars, tared counts): time series.
"""

from __future__ import annotations

from functools import lru_cache
from pathlib import Path

import numpy as np
import rerun as rr
from matplotlib import colormaps

from assets.indenters import get_indenter

FORCE_ARROW_M_PER_N = 5e-3
"""Length of the force arrow per newton (m/N)."""
INDENTER_MESH_EDGE = 1e-3
"""Largest edge (m) of the indenter meshes drawn."""
NAN_COLOUR = np.array([128, 128, 128, 255], dtype=np.uint8)


def open_recording(application_id: str, save: Path | None = None, spawn: bool = False) -> rr.RecordingStream:
    """A new recording that streams to the .rrd file `save` and/or a spawned rerun viewer."""
    if save is None and not spawn:
        raise ValueError("a recording needs a place to go: a file to save or a viewer to spawn")
    recording = rr.RecordingStream(application_id)
    if save is not None:
        Path(save).parent.mkdir(parents=True, exist_ok=True)
        recording.save(str(save))
    if spawn:
        recording.spawn()
    return recording


def colours(values: np.ndarray, low: float, high: float, cmap: str = "viridis") -> np.ndarray:
    """(N, 4) uint8 RGBA of `values` mapped linearly from [low, high] through a matplotlib colormap;
    NaN values are grey."""
    if not high > low:
        raise ValueError(f"colour range needs high > low, got [{low}, {high}]")
    values = np.asarray(values, dtype=float)
    scaled = np.clip((values - low) / (high - low), 0.0, 1.0)
    rgba = (colormaps[cmap](np.nan_to_num(scaled)) * 255).astype(np.uint8)
    rgba[~np.isfinite(values)] = NAN_COLOUR
    return rgba


@lru_cache(maxsize=16)
def _indenter_mesh(name: str) -> tuple[np.ndarray, np.ndarray]:
    mesh = get_indenter(name).mesh(INDENTER_MESH_EDGE)
    return np.asarray(mesh.vertices), np.asarray(mesh.faces)


class SkinScene:
    """Logs states of one BioTac (skin mesh with `reference` (V, 3) m and `triangles` (T, 3), electrode
    centres (19, 3) m) into `recording` under `root`; see the module docstring for the entities."""

    def __init__(
        self,
        recording: rr.RecordingStream,
        reference: np.ndarray,
        triangles: np.ndarray,
        electrode_positions: np.ndarray,
        root: str = "biotac",
        displacement_scale_m: float = 1.5e-3,
        electrode_scale_counts: float = 300.0,
    ) -> None:
        self.recording = recording
        self.reference = np.asarray(reference, dtype=float)
        self.triangles = np.asarray(triangles)
        self.electrode_positions = np.asarray(electrode_positions, dtype=float)
        if self.reference.ndim != 2 or self.reference.shape[1] != 3 or self.triangles.max() >= len(self.reference):
            raise ValueError("SkinScene needs reference vertices (V, 3) and triangles (T, 3) indexing them")
        if self.electrode_positions.shape != (19, 3):
            raise ValueError(f"electrode_positions must be (19, 3) m, got {self.electrode_positions.shape}")
        self.root = root
        self.displacement_scale_m = float(displacement_scale_m)
        self.electrode_scale_counts = float(electrode_scale_counts)
        self.series = f"series/{root}"
        self._indenter: str | None = None
        self._drawn: str | None = None
        recording.log(root, rr.ViewCoordinates.RIGHT_HAND_Z_UP, static=True)
        recording.log(f"{self.series}/force", rr.SeriesLines(names=["x", "y", "z"]), static=True)
        names = [f"E{k}" for k in range(1, 20)]
        recording.log(f"{self.series}/electrodes", rr.SeriesLines(names=names), static=True)

    def set_indenter(self, name: str) -> None:
        """Draw indenter `name` from the next logged state on (its mesh, in its own frame, is logged at
        that state's time whenever the indenter changes)."""
        get_indenter(name)  # a clear error for an unknown name
        self._indenter = name

    def log_state(
        self,
        displacement: np.ndarray,
        rotation: np.ndarray | None = None,
        tip: np.ndarray | None = None,
        force: np.ndarray | None = None,
        electrodes: np.ndarray | None = None,
        pressure: float | None = None,
        pdc: float | None = None,
    ) -> None:
        """Log one state at the recording's current time: skin displacement (V, 3) m; indenter rotation
        (3, 3) body->biotac and tip (3,) m; force (3,) N on the skin; tared electrodes (19,) counts;
        fluid pressure (Pa); PDC (counts). Whatever is None is left out."""
        rec, root = self.recording, self.root
        displacement = np.asarray(displacement, dtype=float)
        if displacement.shape != self.reference.shape:
            raise ValueError(f"displacement must be {self.reference.shape} m, got {displacement.shape}")
        magnitude = np.linalg.norm(displacement, axis=1)
        rec.log(
            f"{root}/skin",
            rr.Mesh3D(
                vertex_positions=self.reference + displacement,
                triangle_indices=self.triangles,
                vertex_colors=colours(magnitude, 0.0, self.displacement_scale_m),
            ),
        )
        if rotation is not None and tip is not None:
            rec.log(f"{root}/indenter", rr.Transform3D(translation=tip, mat3x3=rotation))
            if self._indenter is not None and self._indenter != self._drawn:
                vertices, faces = _indenter_mesh(self._indenter)
                shape = rr.Mesh3D(vertex_positions=vertices, triangle_indices=faces, albedo_factor=[180, 180, 200, 255])
                rec.log(f"{root}/indenter/shape", shape)
                self._drawn = self._indenter
            if force is not None:
                rec.log(
                    f"{root}/force",
                    rr.Arrows3D(origins=[tip], vectors=[np.asarray(force) * FORCE_ARROW_M_PER_N], colors=[255, 60, 60]),
                )
        if force is not None:
            rec.log(f"{self.series}/force", rr.Scalars(np.asarray(force, dtype=float)))
        if electrodes is not None:
            electrodes = np.asarray(electrodes, dtype=float)
            scale = self.electrode_scale_counts
            rec.log(
                f"{root}/electrodes",
                rr.Points3D(
                    self.electrode_positions, colors=colours(electrodes, -scale, scale, "coolwarm"), radii=4e-4
                ),
            )
            rec.log(f"{self.series}/electrodes", rr.Scalars(electrodes))
        if pressure is not None:
            rec.log(f"{self.series}/pressure", rr.Scalars([float(pressure)]))
        if pdc is not None:
            rec.log(f"{self.series}/pdc", rr.Scalars([float(pdc)]))


def log_residual_field(
    recording: rr.RecordingStream, vertices: np.ndarray, triangles: np.ndarray, values: np.ndarray, path: str
) -> None:
    """Log a per-vertex residual field (values (V,) N, NaN where unknown) on the mesh (V, 3) m as a static
    Mesh3D coloured from 0 to the largest finite value (inferno; NaN grey)."""
    values = np.asarray(values, dtype=float)
    if values.shape != (len(vertices),):
        raise ValueError(f"residual field needs one value per vertex ({len(vertices)}), got {values.shape}")
    finite = values[np.isfinite(values)]
    high = float(finite.max()) if len(finite) and finite.max() > 0 else 1.0
    recording.log(
        path,
        rr.Mesh3D(
            vertex_positions=vertices, triangle_indices=triangles, vertex_colors=colours(values, 0.0, high, "inferno")
        ),
        static=True,
    )
