"""Campaign files as analysis inputs: per-trajectory full-rate recordings, their paths and rows.

Reads the schema-v1 HDF5 files that `twin campaign run` writes (docs/dataset.md). A file with rows but
without the full-rate `raw/` group and the per-trajectory path metadata (the paper's public layout) is read
row-only (`twin.analysis.rows_only`); a file with neither cannot be replayed and says so.
"""

from __future__ import annotations

import hashlib
import json
from dataclasses import dataclass, replace
from pathlib import Path

import numpy as np

from twin.controller import Recording
from twin.dataset import RAW_FIELDS, TRAJECTORY_FIELDS, open_dataset

ROWS_ONLY_NORMAL_DEG = 15.0
"""A row-only press tilted less than this (degrees) from the nominal skin's normal counts as normal (halfway
between the paper's normal and 30-degree presses)."""
ROW_FEATURES = ("force", "pdc", "electrode_vals", "depth", "phase", "contact_loc", "time", "trajectory_id")


@dataclass(frozen=True)
class TrajectoryRecord:
    """One measured trajectory (SI units; biotac frame unless named)."""

    sensor_id: int
    trajectory_id: int
    indenter: str
    arm: str
    angle: float
    rotation: np.ndarray  # (3, 3) indenter frame in the biotac frame
    touch_point: np.ndarray  # (3,) m
    direction: np.ndarray  # (3,) unit
    tool_tip: np.ndarray  # (4, 4) flange -> tip
    registration: np.ndarray  # (4, 4) estimated robot <- biotac
    sensor_in_biotac: np.ndarray  # (4, 4)
    complete: bool
    raw: Recording
    rows: dict[str, np.ndarray]  # the file's subsampled rows of this trajectory (ROW_FEATURES)
    rows_only: bool = False  # raw is a stand-in made from the rows (twin.analysis.rows_only)

    @property
    def rate_hz(self) -> float:
        """Sampling rate of the full-rate recording (Hz); NaN for a recording of one sample."""
        return float(1.0 / np.median(np.diff(self.raw.time))) if len(self.raw.time) > 1 else float("nan")

    @property
    def normal(self) -> bool:
        """True for a trajectory along the surface normal: angle below 1 degree, or below
        `ROWS_ONLY_NORMAL_DEG` for a row-only press (its angle is measured from the nominal skin mesh)."""
        return self.angle < np.radians(ROWS_ONLY_NORMAL_DEG if self.rows_only else 1.0)


@dataclass(frozen=True)
class CampaignData:
    """Every trajectory of one sensor file, plus what identifies the file."""

    path: Path
    sensor_id: int
    indenter_names: list[str]
    trajectories: list[TrajectoryRecord]
    mesh_max_edge: float
    digest: str  # sha256 of the file's bytes (first 16 hex digits)
    rows_only: bool = False  # read from rows only (twin.analysis.rows_only)

    def subset(self, keep: set[int]) -> CampaignData:
        """The same campaign restricted to the trajectory ids in `keep`."""
        chosen = [t for t in self.trajectories if t.trajectory_id in keep]
        return replace(self, trajectories=chosen)


def file_digest(path: Path) -> str:
    """sha256 of a file's bytes (first 16 hex digits)."""
    h = hashlib.sha256()
    with open(path, "rb") as handle:
        for block in iter(lambda: handle.read(1 << 20), b""):
            h.update(block)
    return h.hexdigest()[:16]


def load_campaign(path: Path | str) -> CampaignData:
    """Load a campaign file for replay, or a row-only file (`rows_only.load_rows_only`); ValueError when it
    lacks what replay needs."""
    from twin.analysis.rows_only import is_rows_only, load_rows_only

    path = Path(path)
    with open_dataset(path) as f:
        rows_only = is_rows_only(f)
    if rows_only:
        return load_rows_only(path)
    with open_dataset(path) as f:
        missing = [g for g in ("trajectories", "raw", *ROW_FEATURES) if g not in f]
        missing += [
            f"trajectories/{k}" for k in TRAJECTORY_FIELDS if "trajectories" in f and k not in f["trajectories"]
        ]
        missing += [] if "indenter_names" in f.attrs else ["attribute indenter_names"]
        if missing:
            raise ValueError(f"{path} cannot be replayed: it has no {', '.join(missing)} (see docs/dataset.md)")
        names = json.loads(f.attrs.get("indenter_names", "[]"))
        provenance = json.loads(f.attrs.get("provenance", "{}"))
        mesh = float(provenance.get("config", {}).get("mesh_max_edge", 0.5e-3))
        meta = {k: f["trajectories"][k][()] for k in f["trajectories"]}
        row_data = {k: f[f"{k}/data"][()] for k in ROW_FEATURES}
        records = []
        for i, tid in enumerate(meta["trajectory_id"]):
            first, n = int(meta["first_row"][i]), int(meta["n_rows"][i])
            raw = f[f"raw/{int(tid)}"]
            recording = Recording(
                **{k: raw[k][()] for k in RAW_FIELDS},
                complete=bool(meta["complete"][i]),
                message=str(raw.attrs.get("message", "")),
            )
            records.append(
                TrajectoryRecord(
                    sensor_id=int(f.attrs["sensor_id"]),
                    trajectory_id=int(tid),
                    indenter=names[int(meta["indenter_type"][i])],
                    arm="left" if int(meta["arm"][i]) == 0 else "right",
                    angle=float(meta["angle"][i]),
                    rotation=meta["rotation"][i],
                    touch_point=meta["touch_point"][i],
                    direction=meta["direction"][i],
                    tool_tip=meta["tool_tip"][i],
                    registration=meta["registration"][i],
                    sensor_in_biotac=meta["sensor_in_biotac"][i],
                    complete=bool(meta["complete"][i]),
                    raw=recording,
                    rows={k: v[first : first + n] for k, v in row_data.items()},
                )
            )
    return CampaignData(path, int(records[0].sensor_id) if records else 0, names, records, mesh, file_digest(path))
