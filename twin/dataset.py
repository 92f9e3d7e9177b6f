"""Campaign datasets: per-trajectory part files while running, one HDF5 per sensor at the end.

Layout and meaning of every feature: docs/dataset.md (schema version 1). Parts are `.npz` files
written to a temporary name and renamed, so a killed campaign leaves only whole parts behind; the
HDF5 file is assembled from the parts in trajectory order (also through a temporary name), so a
resumed campaign produces the same file as an uninterrupted one.
"""

from __future__ import annotations

import json
import os
from dataclasses import dataclass
from datetime import UTC, datetime
from pathlib import Path

import h5py
import numpy as np

SCHEMA_VERSION = 1

FEATURE_UNITS: dict[str, tuple[str, str | None]] = {
    "electrode_vals": ("counts", None),
    "electrode_tare": ("counts", None),
    "pdc": ("counts", None),
    "force": ("N", "biotac"),
    "contact_loc": ("m", "biotac"),
    "tip_pos": ("m", "robot"),
    "depth": ("m", None),
    "phase": ("1", None),
    "indenter_type": ("1", None),
    "trajectory_id": ("1", None),
    "joint_angles": ("rad", None),
    "time": ("s", None),
    "fe_force": ("N", "biotac"),
    "fe_pressure": ("Pa", None),
    "fe_converged": ("1", None),
    "nodal_res": ("m", "biotac"),
}
"""Every subsampled feature with its units and frame (None where it has none)."""

TRAJECTORY_FIELDS = (
    "trajectory_id",
    "indenter_type",
    "arm",
    "angle",
    "azimuth",
    "point",
    "direction",
    "rotation",
    "touch_point",
    "complete",
    "tool_tip",
    "registration",
    "sensor_in_biotac",
    "first_row",
    "n_rows",
)
RAW_FIELDS = ("time", "joints", "wrench", "electrodes", "pdc", "depth_command", "increment")


def part_path(parts_dir: Path, sensor_id: int, trajectory_id: int) -> Path:
    """Where one trajectory's part file lives."""
    return parts_dir / f"biotac{sensor_id}" / f"trajectory_{trajectory_id:06d}.npz"


def write_part(path: Path, arrays: dict[str, np.ndarray]) -> None:
    """Write a part atomically: a temporary file in the same folder, then a rename."""
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = path.with_name(path.name + ".tmp")
    with open(tmp, "wb") as handle:
        np.savez(handle, **arrays)
        handle.flush()
        os.fsync(handle.fileno())
    os.replace(tmp, path)


def read_part(path: Path) -> dict[str, np.ndarray]:
    """Load a part written by `write_part`."""
    with np.load(path, allow_pickle=False) as data:
        return {k: data[k] for k in data.files}


@dataclass(frozen=True)
class SensorFileInfo:
    """What a finished sensor file contains."""

    path: Path
    n_rows: int
    n_trajectories: int


def assemble_sensor_file(
    parts: list[Path],
    out_path: Path,
    sensor_id: int,
    indenter_names: list[str],
    provenance: dict,
    triangles: np.ndarray | None = None,
    ventral: np.ndarray | None = None,
) -> SensorFileInfo:
    """Concatenate part files (sorted by trajectory id) into one schema-v1 HDF5 file, atomically.

    triangles: (T, 3) skin mesh of `nodal_res`; its inflated reference vertices come from the parts.
    ventral: (V,) bool, the skin vertices of the ventral region (where indentation points are sampled).
    """
    loaded = sorted((read_part(p) for p in parts), key=lambda d: int(d["meta_trajectory_id"]))
    tmp = out_path.with_name(out_path.name + ".tmp")
    first_row = 0
    meta: dict[str, list] = {name: [] for name in TRAJECTORY_FIELDS}
    features: dict[str, list[np.ndarray]] = {}
    with h5py.File(tmp, "w") as f:
        f.attrs["schema_version"] = SCHEMA_VERSION
        f.attrs["sensor_id"] = sensor_id
        f.attrs["producer"] = f"biotac-twin {_version()}"
        f.attrs["provenance"] = json.dumps(provenance, sort_keys=True)
        f.attrs["created_utc"] = datetime.now(UTC).isoformat(timespec="seconds")
        f.attrs["indenter_names"] = json.dumps(indenter_names)
        for part in loaded:
            n = len(part["row_depth"])
            for key, value in part.items():
                if key.startswith("row_"):
                    features.setdefault(key[4:], []).append(value)
            for name in TRAJECTORY_FIELDS:
                if name == "first_row":
                    meta[name].append(first_row)
                elif name == "n_rows":
                    meta[name].append(n)
                else:
                    meta[name].append(part[f"meta_{name}"])
            raw = f.create_group(f"raw/{int(part['meta_trajectory_id'])}")
            for name in RAW_FIELDS:
                raw.create_dataset(name, data=part[f"raw_{name}"], compression="gzip", compression_opts=1)
            raw.attrs["message"] = str(part["meta_message"])
            first_row += n
        for name, chunks in features.items():
            units, frame = FEATURE_UNITS[name]
            dataset = f.create_dataset(
                f"{name}/data", data=np.concatenate(chunks), compression="gzip", compression_opts=1
            )
            dataset.attrs["units"] = units
            if frame is not None:
                dataset.attrs["frame"] = frame
        group = f.create_group("trajectories")
        for name, values in meta.items():
            group.create_dataset(name, data=np.array(values))
        if triangles is not None and loaded:
            f.create_dataset("mesh/vertices", data=loaded[0]["mesh_reference"]).attrs["units"] = "m"
            f.create_dataset("mesh/triangles", data=triangles)
            if ventral is not None:
                f.create_dataset("mesh/ventral", data=np.asarray(ventral, dtype=bool))
        f.flush()
    os.replace(tmp, out_path)
    return SensorFileInfo(out_path, first_row, len(loaded))


def _version() -> str:
    from twin import __version__

    return __version__


def open_dataset(path: Path | str) -> h5py.File:
    """Open an HDF5 file for reading, with a clear ValueError when it is missing or not HDF5."""
    path = Path(path)
    if not path.exists():
        raise ValueError(f"no such dataset file: {path}")
    try:
        return h5py.File(path, "r")
    except OSError as exc:
        raise ValueError(f"{path} is not an HDF5 file ({exc})") from exc


def dataset_info(path: Path) -> dict:
    """Features (shape, dtype, units, frame), trajectory counts and attributes of a campaign file."""
    path = Path(path)
    with open_dataset(path) as f:
        features = {}
        for name, item in f.items():
            if isinstance(item, h5py.Group) and "data" in item:
                data = item["data"]
                features[name] = {
                    "shape": list(data.shape),
                    "dtype": str(data.dtype),
                    "units": str(data.attrs.get("units", "")),
                    "frame": str(data.attrs.get("frame", "")) or None,
                }
        info: dict = {"path": str(path), "features": features}
        if "trajectories" in f:
            traj = f["trajectories"]
            complete = traj["complete"][:]
            names = json.loads(f.attrs.get("indenter_names", "[]"))
            kinds = traj["indenter_type"][:]
            info["trajectories"] = {
                "total": int(len(complete)),
                "complete": int(complete.sum()),
                "per_indenter": {
                    names[k] if k < len(names) else str(k): int((kinds == k).sum()) for k in np.unique(kinds)
                },
            }
        info["rows"] = next((v["shape"][0] for v in features.values()), 0)
        info["attributes"] = {k: _plain(v) for k, v in f.attrs.items()}
    return info


def _plain(value: object) -> object:
    if isinstance(value, np.generic):
        return value.item()
    if isinstance(value, bytes):
        return value.decode()
    return value
