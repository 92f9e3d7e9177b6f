"""Log one BioTac's state to rerun: skin coloured by displacement, indenter pose, force, electrodes, series.

Entity layout (under the `root`, default `biotac`), all in the biotac frame, metres:
- `{root}/skin`: Mesh3D of the deformed skin mid-surface; its triangles are static (logged once), its
  vertex positions and colours (= |displacement|, viridis, 0 to `displacement_scale_m`) per state;
- `{root}/indenter`: Transform3D (rotation body->biotac, tip position); `{root}/indenter/shape`: the
  indenter's Mesh3D in its own frame (logged when the indenter changes, never per state);
- `{root}/force`: Arrows3D from the tip along the force of the indenter on the skin, `FORCE_ARROW_M_PER_N`
  (colour static);
- `{root}/electrodes`: Points3D at the 19 electrode centres (positions and radii static), colours = tared
  counts per state (coolwarm, +-`electrode_scale_counts`);
- `series/{root}/force` (3 scalars, N), `series/{root}/pressure` (Pa), `series/{root}/pdc` (counts),
  `series/{root}/electrodes` (19 scalars, tared counts): time series.

A state is logged with `SkinScene.log_state` at the recording's current time (rr.log; live views), a
trajectory of states with `SkinScene.log_states` as whole columns (rr.send_columns) on the `row` and
`time` timelines.
"""

from __future__ import annotations

from functools import lru_cache
from pathlib import Path

import numpy as np
import rerun as rr
from matplotlib import colormaps

from assets.indenters import get_indenter
from twin.view.layout import default_blueprint

FORCE_ARROW_M_PER_N = 5e-3
"""Length of the force arrow per newton (m/N)."""
INDENTER_MESH_EDGE = 1e-3
"""Largest edge (m) of the indenter meshes drawn."""
ELECTRODE_RADIUS_M = 4e-4
"""Radius (m) of the electrode points."""
NAN_COLOUR = np.array([128, 128, 128, 255], dtype=np.uint8)
FORCE_COLOUR = np.array([255, 60, 60, 255], dtype=np.uint8)
INDENTER_COLOUR = np.array([180, 180, 200, 255], dtype=np.uint8)

Fields = dict[str, np.ndarray]
"""An archetype's fields for N states: field name -> (N, L, ...) array, L instances per state."""
Stamps = tuple[np.ndarray, "np.ndarray | None"]
"""Where N states go: their `row` indices (N,) and `time` values (N,) s or None."""


def open_recording(
    application_id: str, save: Path | None = None, spawn: bool = False, roots: tuple[str, ...] = ("biotac",)
) -> rr.RecordingStream:
    """A new recording that streams to the .rrd file `save` and/or a spawned rerun viewer, with the
    default layout (`twin.view.layout.default_blueprint(roots)`) sent along."""
    if save is None and not spawn:
        raise ValueError("a recording needs a place to go: a file to save or a viewer to spawn")
    recording = rr.RecordingStream(application_id)
    blueprint = default_blueprint(roots)
    if save is not None:
        Path(save).parent.mkdir(parents=True, exist_ok=True)
        recording.save(str(save), default_blueprint=blueprint)
    if spawn:
        recording.spawn(default_blueprint=blueprint)
    return recording


def colours(values: np.ndarray, low: float, high: float, cmap: str = "viridis") -> np.ndarray:
    """(..., 4) uint8 RGBA of `values` (any shape) mapped linearly from [low, high] through a matplotlib
    colormap; NaN values are grey."""
    if not high > low:
        raise ValueError(f"colour range needs high > low, got [{low}, {high}]")
    values = np.asarray(values, dtype=float)
    scaled = np.clip((values - low) / (high - low), 0.0, 1.0)
    rgba = (colormaps[cmap](np.nan_to_num(scaled)) * 255).astype(np.uint8)
    rgba[~np.isfinite(values)] = NAN_COLOUR
    return rgba


def time_columns(rows: np.ndarray, times: np.ndarray | None) -> list[rr.TimeColumn]:
    """The `row` (sequence) and, when given, `time` (s, duration) index columns of N states."""
    indexes = [rr.TimeColumn("row", sequence=np.asarray(rows, dtype=np.int64))]
    if times is not None:
        indexes.append(rr.TimeColumn("time", duration=np.asarray(times, dtype=float)))
    return indexes


@lru_cache(maxsize=16)
def _indenter_mesh(name: str) -> tuple[np.ndarray, np.ndarray]:
    mesh = get_indenter(name).mesh(INDENTER_MESH_EDGE)
    return np.asarray(mesh.vertices), np.asarray(mesh.faces)


class SkinScene:
    """Logs states of one BioTac (skin mesh with `reference` (V, 3) m and `triangles` (T, 3), electrode
    centres (19, 3) m) into `recording` under `root`; see the module docstring for the entities. The
    topology (triangles, electrode positions, colours that never change) is logged once, static."""

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
        recording.log(f"{root}/skin", rr.Mesh3D.from_fields(triangle_indices=self.triangles), static=True)
        electrodes = rr.Points3D(self.electrode_positions, radii=ELECTRODE_RADIUS_M)
        recording.log(f"{root}/electrodes", electrodes, static=True)
        recording.log(f"{root}/force", rr.Arrows3D.from_fields(colors=FORCE_COLOUR), static=True)
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

        def one(value: np.ndarray | float | None) -> np.ndarray | None:
            return None if value is None else np.asarray(value, dtype=float)[None]

        state = (one(displacement), one(rotation), one(tip), one(force), one(electrodes), one(pressure), one(pdc))
        self._log(None, *state)

    def log_states(
        self,
        rows: np.ndarray,
        times: np.ndarray | None,
        displacement: np.ndarray,
        rotation: np.ndarray | None = None,
        tip: np.ndarray | None = None,
        force: np.ndarray | None = None,
        electrodes: np.ndarray | None = None,
        pressure: np.ndarray | None = None,
        pdc: np.ndarray | None = None,
    ) -> None:
        """Log N states as whole columns (rr.send_columns) at `row` indices `rows` (N,) and, when given,
        `time` `times` (N,) s: displacement (N, V, 3) m; rotation (3, 3) body->biotac for all states or
        (N, 3, 3); tip (N, 3) m; force (N, 3) N; electrodes (N, 19) counts; pressure (N,) Pa; pdc (N,)
        counts. Whatever is None is left out."""
        n = len(rows)
        if rotation is not None and np.ndim(rotation) == 2:
            rotation = np.broadcast_to(rotation, (n, 3, 3))
        at = (np.asarray(rows), None if times is None else np.asarray(times))
        self._log(at, displacement, rotation, tip, force, electrodes, pressure, pdc)

    def _log(
        self,
        at: Stamps | None,
        displacement: np.ndarray,
        rotation: np.ndarray | None,
        tip: np.ndarray | None,
        force: np.ndarray | None,
        electrodes: np.ndarray | None,
        pressure: np.ndarray | None,
        pdc: np.ndarray | None,
    ) -> None:
        """Log N states (arrays with a leading state axis) with rr.log at the current time (`at` None,
        N = 1) or with rr.send_columns at the stamps `at`."""
        root, series = self.root, self.series
        displacement = np.asarray(displacement, dtype=float)
        if displacement.shape[1:] != self.reference.shape:
            raise ValueError(f"displacement must be {self.reference.shape} m per state, got {displacement.shape[1:]}")
        magnitude = np.linalg.norm(displacement, axis=2)
        skin = {
            "vertex_positions": self.reference + displacement,
            "vertex_colors": colours(magnitude, 0.0, self.displacement_scale_m),
        }
        self._send(at, f"{root}/skin", rr.Mesh3D, skin)
        if rotation is not None and tip is not None:
            tip = np.asarray(tip, dtype=float)
            pose = {"translation": tip[:, None], "mat3x3": np.asarray(rotation, dtype=float)[:, None]}
            self._send(at, f"{root}/indenter", rr.Transform3D, pose)
            if self._indenter is not None and self._indenter != self._drawn:
                vertices, faces = _indenter_mesh(self._indenter)
                shape = {"vertex_positions": vertices[None], "triangle_indices": faces[None]}
                shape["albedo_factor"] = INDENTER_COLOUR[None, None]
                first = None if at is None else (at[0][:1], None if at[1] is None else at[1][:1])
                self._send(first, f"{root}/indenter/shape", rr.Mesh3D, shape)
                self._drawn = self._indenter
            if force is not None:
                arrows = {"origins": tip[:, None], "vectors": np.asarray(force)[:, None] * FORCE_ARROW_M_PER_N}
                self._send(at, f"{root}/force", rr.Arrows3D, arrows)
        if force is not None:
            self._send(at, f"{series}/force", rr.Scalars, {"scalars": np.asarray(force, dtype=float)})
        if electrodes is not None:
            electrodes = np.asarray(electrodes, dtype=float)
            scale = self.electrode_scale_counts
            points = {"colors": colours(electrodes, -scale, scale, "coolwarm")}
            self._send(at, f"{root}/electrodes", rr.Points3D, points)
            self._send(at, f"{series}/electrodes", rr.Scalars, {"scalars": electrodes})
        if pressure is not None:
            self._send(at, f"{series}/pressure", rr.Scalars, {"scalars": np.asarray(pressure, dtype=float)[:, None]})
        if pdc is not None:
            self._send(at, f"{series}/pdc", rr.Scalars, {"scalars": np.asarray(pdc, dtype=float)[:, None]})

    def _send(self, at: Stamps | None, entity: str, archetype: type, fields: Fields) -> None:
        """Log `fields` (each (N, L, ...): L instances per state) of `archetype` at `entity`: one rr.log
        of the partial archetype when `at` is None (N = 1), else one rr.send_columns of N rows."""
        if at is None:
            self.recording.log(entity, archetype.from_fields(**{name: value[0] for name, value in fields.items()}))
            return
        columns = []
        for name, value in fields.items():
            column = archetype.columns(**{name: value.reshape(-1, *value.shape[2:])})
            columns += column.partition(np.full(len(value), value.shape[1]))
        rr.send_columns(entity, time_columns(*at), columns, recording=self.recording)


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
