"""What `twin view` logs: campaign datasets (HDF5), `twin compare` reports, trajectories of a live campaign.

A trajectory is logged as whole columns (rr.send_columns; the dataset's subsampled rows: one per depth
increment) on the timelines `row` (sequence, running on across trajectories) and `time` (the backend
clock, s). The skin
displacement is the file's `nodal_res` where it has it (simulated campaigns); otherwise the trajectory's
planned path (touch point + depth * direction) is replayed through the nominal FE model of the file's
mesh size (nominal skin parameters, as `twin compare`'s default model).
"""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import rerun as rr

from assets.biotac import electrode_table
from assets.indenters import INDENTERS
from fe.indentation import step_through
from twin.dataset import open_dataset
from twin.fe_models import shared_model
from twin.view.layout import default_blueprint
from twin.view.scene import SkinScene, log_residual_field

ROW_FEATURES = ("time", "depth", "contact_loc", "force", "electrode_vals", "pdc", "fe_pressure", "nodal_res")
"""The subsampled features a logged trajectory uses (those a file lacks are left out, except `nodal_res`)."""
REPORT_FIELD = "residual_field.npz"


def log_rows(scene: SkinScene, rows: dict[str, np.ndarray], rotation: np.ndarray, indenter: str, first_row: int) -> int:
    """Log one trajectory's rows (features as in docs/dataset.md, `nodal_res` (N, V, 3) m required) with
    the indenter's rotation (3, 3) body->biotac as whole columns at `row` first_row.. (and `time`);
    returns the next free `row` index. Rows without a finite displacement (after an FE failure in a
    replay) are left out."""
    displacement = rows["nodal_res"]
    scene.set_indenter(indenter)
    kept = np.flatnonzero(np.all(np.isfinite(displacement.reshape(len(displacement), -1)), axis=1))
    if len(kept):
        column = {name: rows[name][kept] if name in rows else None for name in ROW_FEATURES}
        scene.log_states(
            first_row + kept,
            column["time"],
            column["nodal_res"],
            rotation=rotation,
            tip=column["contact_loc"],
            force=column["force"],
            electrodes=column["electrode_vals"],
            pressure=column["fe_pressure"],
            pdc=column["pdc"],
        )
    return first_row + len(displacement)


def _replayed_displacement(
    mesh_max_edge: float, indenter: str, rotation: np.ndarray, tips: np.ndarray
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """FE replay of tip positions (N, 3) m: (N, V, 3) displacement (NaN after a failed increment),
    reference (V, 3) m and triangles of the nominal model with `mesh_max_edge` (m)."""
    model = shared_model(mesh_max_edge * 1e3)
    out = np.full((len(tips), *model.reference.shape), np.nan)
    for k, result in enumerate(step_through(model.stepper(indenter), rotation, tips)):
        if result.converged:
            out[k] = result.displacement
    return out, model.reference, model.geometry.skin.triangles


def log_dataset(
    recording: rr.RecordingStream, path: Path, trajectory_ids: list[int] | None = None, root: str = "biotac"
) -> list[int]:
    """Log trajectories of a campaign file (default: its first); returns the ids logged."""
    with open_dataset(path) as f:
        if "trajectories" not in f:
            raise ValueError(f"{path} has no per-trajectory metadata (group `trajectories`, docs/dataset.md)")
        meta = {k: f["trajectories"][k][()] for k in f["trajectories"]}
        ids = [int(t) for t in meta["trajectory_id"]]
        if not ids:
            raise ValueError(f"{path} holds no trajectory")
        chosen = ids[:1] if not trajectory_ids else list(trajectory_ids)
        unknown = sorted(set(chosen) - set(ids))
        if unknown:
            raise ValueError(f"{path} has no trajectory {unknown} (it has {ids[0]}..{ids[-1]}, {len(ids)} in all)")
        names = json.loads(f.attrs.get("indenter_names", "[]")) or list(INDENTERS)
        mesh_max_edge = float(json.loads(f.attrs.get("provenance", "{}")).get("config", {}).get("mesh_max_edge", 2e-3))
        stored = "nodal_res" in f and "mesh" in f
        features = {name: f[f"{name}/data"] for name in ROW_FEATURES if name in f}
        scene: SkinScene | None = None
        row = 0
        for tid in chosen:
            i = ids.index(tid)
            first, n = int(meta["first_row"][i]), int(meta["n_rows"][i])
            rows = {name: data[first : first + n] for name, data in features.items()}
            indenter, rotation = names[int(meta["indenter_type"][i])], meta["rotation"][i]
            if stored:
                reference, triangles = f["mesh/vertices"][()], f["mesh/triangles"][()]
            else:
                tips = meta["touch_point"][i] + np.outer(rows["depth"], meta["direction"][i])
                rows["nodal_res"], reference, triangles = _replayed_displacement(
                    mesh_max_edge, indenter, rotation, tips
                )
            if scene is None:
                scene = SkinScene(recording, reference, triangles, electrode_table().positions, root)
            row = log_rows(scene, rows, rotation, indenter, row)
    return chosen


def log_report(recording: rr.RecordingStream, report: Path) -> None:
    """Log a `twin compare` report folder: its residual field on the skin (`report/residual_field`, the
    RMS force residual per vertex, N) and its overall error table (`report/summary`, markdown)."""
    field_path = report / REPORT_FIELD if report.is_dir() else report
    if not field_path.exists():
        raise ValueError(f"{report} is not a `twin compare` report: no {REPORT_FIELD}")
    with np.load(field_path) as field:
        log_residual_field(recording, field["vertices"], field["triangles"], field["values"], "report/residual_field")
    summary_path = field_path.parent / "summary.json"
    if summary_path.exists():
        overall = json.loads(summary_path.read_text()).get("overall", {})
        lines = ["| channel | rms | mean | n |", "|---|---|---|---|"]
        lines += [f"| {c} | {s['rms']} | {s['mean']} | {s['n']} |" for c, s in overall.items()]
        recording.log(
            "report/summary", rr.TextDocument("\n".join(lines), media_type=rr.MediaType.MARKDOWN), static=True
        )


def log_path(recording: rr.RecordingStream, path: Path, trajectory_ids: list[int] | None = None) -> str:
    """Log a dataset file or a report (folder or its residual_field.npz); returns "dataset" or "report"."""
    path = Path(path)
    if path.is_dir() or path.name == REPORT_FIELD:
        log_report(recording, path)
        return "report"
    log_dataset(recording, path, trajectory_ids)
    return "dataset"


class CampaignViewer:
    """Live view of a running campaign: one skin scene per sensor (`biotac<id>`; the default layout is
    re-sent with a tab per sensor when a new one appears), each finished trajectory logged from its
    part-file arrays (`twin.campaign.trajectory_arrays` plus the FE rows and
    `mesh_reference`, as `twin.dataset.read_part` returns them).

    triangles: (T, 3) the campaign's skin mesh (`make_biotac(config.mesh_max_edge).skin.triangles`).
    """

    def __init__(self, recording: rr.RecordingStream, triangles: np.ndarray) -> None:
        self.recording = recording
        self.triangles = np.asarray(triangles)
        self._scenes: dict[int, SkinScene] = {}
        self._next_row: dict[int, int] = {}

    def close(self) -> None:
        """Finish the recording (a saved .rrd is complete after this)."""
        self.recording.flush()
        self.recording.disconnect()

    def log_trajectory(self, sensor_id: int, arrays: dict[str, np.ndarray]) -> None:
        """Log one finished trajectory of sensor `sensor_id` (its rows, on the `row` and `time` timelines)."""
        missing = [
            k for k in ("row_nodal_res", "meta_rotation", "meta_indenter_type", "mesh_reference") if k not in arrays
        ]
        if missing:
            raise ValueError(f"trajectory arrays lack {missing} (a simulated campaign's part file has them)")
        if sensor_id not in self._scenes:
            self._scenes[sensor_id] = SkinScene(
                self.recording,
                arrays["mesh_reference"],
                self.triangles,
                electrode_table().positions,
                f"biotac{sensor_id}",
            )
            self._next_row[sensor_id] = 0
            self.recording.send_blueprint(default_blueprint([f"biotac{s}" for s in sorted(self._scenes)]))
        rows = {k[4:]: v for k, v in arrays.items() if k.startswith("row_") and k[4:] in ROW_FEATURES}
        indenter = list(INDENTERS)[int(arrays["meta_indenter_type"])]
        self._next_row[sensor_id] = log_rows(
            self._scenes[sensor_id], rows, arrays["meta_rotation"], indenter, self._next_row[sensor_id]
        )
