"""Campaign files as analysis inputs: per-trajectory full-rate recordings, their paths and rows.

Reads the schema-v1 HDF5 files that `twin campaign run` writes (docs/dataset.md); a file without
the full-rate `raw/` group or the per-trajectory path metadata cannot be replayed and says so.
"""

from __future__ import annotations

import hashlib
import json
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from twin.controller import Recording
from twin.dataset import RAW_FIELDS, TRAJECTORY_FIELDS, open_dataset

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

    @property
    def rate_hz(self) -> float:
        """Sampling rate of the full-rate recording (Hz)."""
        return float(1.0 / np.median(np.diff(self.raw.time)))

    @property
    def normal(self) -> bool:
        """True for a trajectory along the surface normal (angle below 1 degree)."""
        return self.angle < np.radians(1.0)


@dataclass(frozen=True)
class CampaignData:
    """Every trajectory of one sensor file, plus what identifies the file."""

    path: Path
    sensor_id: int
    indenter_names: list[str]
    trajectories: list[TrajectoryRecord]
    mesh_max_edge: float
    digest: str  # sha256 of the file's bytes (first 16 hex digits)

    def subset(self, keep: set[int]) -> CampaignData:
        """The same campaign restricted to the trajectory ids in `keep`."""
        chosen = [t for t in self.trajectories if t.trajectory_id in keep]
        return CampaignData(self.path, self.sensor_id, self.indenter_names, chosen, self.mesh_max_edge, self.digest)


def _digest(path: Path) -> str:
    h = hashlib.sha256()
    with open(path, "rb") as handle:
        for block in iter(lambda: handle.read(1 << 20), b""):
            h.update(block)
    return h.hexdigest()[:16]


def load_campaign(path: Path | str) -> CampaignData:
    """Load a campaign file for replay; ValueError when it lacks what replay needs."""
    path = Path(path)
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
    return CampaignData(path, int(records[0].sensor_id) if records else 0, names, records, mesh, _digest(path))
