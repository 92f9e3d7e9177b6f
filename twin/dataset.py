"""Campaign datasets: per-trajectory part files while running, one HDF5 per sensor at the end.

Layout and meaning of every feature: docs/dataset.md (schema version 1). Parts are `.npz` files
written to a temporary name of their writer's own and renamed, so a killed campaign leaves only whole
parts behind and two writers never share a temporary file; the HDF5 file is assembled from the parts
in trajectory order (also through a temporary name, after a check of the free disk space), so a
resumed campaign produces the same file as an uninterrupted one. Files are checked against the schema
when opened (`open_dataset`, `check_campaign`).
"""

from __future__ import annotations

import json
import os
import re
import secrets
import shutil
import zlib
from collections import deque
from collections.abc import Iterator
from concurrent.futures import Future, ThreadPoolExecutor
from contextlib import contextmanager
from dataclasses import dataclass
from datetime import UTC, datetime
from pathlib import Path

import h5py
import numpy as np

from assets.indenters import INDENTERS
from twin.lanes import usable_cpus

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
SIMULATION_ONLY = ("fe_force", "fe_pressure", "fe_converged", "nodal_res", "mesh")
"""What only a simulated campaign has: the plant's own fe view (its forces, pressure, convergence, nodal
displacements and inflated mesh). Marked `simulation_only` in the file; the analysis never reads them,
because a measurement has no such truth."""

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
    """Write a part atomically: a temporary file of its own in the same folder, then a rename."""
    path.parent.mkdir(parents=True, exist_ok=True)
    with _temporary_beside(path) as tmp:
        with open(tmp, "xb") as handle:
            np.savez(handle, **arrays)
            handle.flush()
            os.fsync(handle.fileno())
        os.replace(tmp, path)


_TEMPORARY = re.compile(r"\.(\d+)-[0-9a-f]{8}\.tmp$")
"""How `_temporary_beside` ends a temporary file's name: the writer's process id and its random tag."""


def remove_stale_temporaries(folder: Path) -> list[Path]:
    """Remove the temporary files under `folder` (`_temporary_beside`'s) whose writer is no longer running, e.g.
    a sensor file half-written when a campaign was killed; returns them."""
    stale = []
    for path in folder.rglob("*.tmp"):
        match = _TEMPORARY.search(path.name)
        if match and not _running(int(match.group(1))):
            path.unlink(missing_ok=True)
            stale.append(path)
    return stale


def _running(pid: int) -> bool:
    """Whether a process with this id exists (one we may not signal counts as running)."""
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    except PermissionError:
        return True
    return True


@contextmanager
def _temporary_beside(path: Path) -> Iterator[Path]:
    """A temporary file name next to `path` of this writer alone (process id and random tag: no two writers
    share one); the file is removed on any failure (if still there: a successful writer renames it)."""
    tmp = path.with_name(f"{path.name}.{os.getpid()}-{secrets.token_hex(4)}.tmp")
    try:
        yield tmp
    finally:
        tmp.unlink(missing_ok=True)


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

    Checks the free disk space first; a ValueError says when it is short or the writing fails, and no
    temporary file is left behind.

    triangles: (T, 3) skin mesh of `nodal_res`; its inflated reference vertices come from the parts.
    ventral: (V,) bool, the skin vertices of the ventral region (where indentation points are sampled).
    """
    check_free_space(out_path.parent, sum(p.stat().st_size for p in parts))
    loaded = sorted((read_part(p) for p in parts), key=lambda d: int(d["meta_trajectory_id"]))
    with _temporary_beside(out_path) as tmp:
        try:
            rows = _write_sensor_file(tmp, loaded, sensor_id, indenter_names, provenance, triangles, ventral)
        except OSError as exc:
            raise ValueError(f"writing {out_path} failed ({exc}); the parts are kept: rerun to assemble it") from exc
        os.replace(tmp, out_path)
    return SensorFileInfo(out_path, rows, len(loaded))


FREE_SPACE_MARGIN = 1.1
"""Free space `check_free_space` wants beyond the estimate (a fraction of it; uncompressed parts overestimate)."""


def check_free_space(folder: Path, estimate_bytes: int) -> None:
    """ValueError (one line) unless `folder`'s file system has room for `estimate_bytes` (times the margin)."""
    free = shutil.disk_usage(folder).free
    needed = int(estimate_bytes * FREE_SPACE_MARGIN)
    if free < needed:
        raise ValueError(
            f"not enough free disk space in {folder}: the sensor file needs about {needed / 1e6:.1f} MB, "
            f"{free / 1e6:.1f} MB are free; free some and rerun (the parts are kept)"
        )


def _write_sensor_file(
    tmp: Path,
    loaded: list[dict[str, np.ndarray]],
    sensor_id: int,
    indenter_names: list[str],
    provenance: dict,
    triangles: np.ndarray | None,
    ventral: np.ndarray | None,
) -> int:
    """Write the loaded parts (trajectory order) as a schema-v1 file at `tmp`; returns the number of rows."""
    first_row = 0
    meta: dict[str, list] = {name: [] for name in TRAJECTORY_FIELDS}
    features: dict[str, list[np.ndarray]] = {}
    with h5py.File(tmp, "w") as f, _GzipChunks() as chunks:
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
                chunks.create(raw, name, part[f"raw_{name}"])
            raw.attrs["message"] = str(part["meta_message"])
            first_row += n
        for name, parts in features.items():
            units, frame = FEATURE_UNITS[name]
            dataset = chunks.create(f, f"{name}/data", np.concatenate(parts))
            dataset.attrs["units"] = units
            if frame is not None:
                dataset.attrs["frame"] = frame
            if name in SIMULATION_ONLY:
                dataset.attrs["simulation_only"] = True
        group = f.create_group("trajectories")
        for name, values in meta.items():
            group.create_dataset(name, data=np.array(values))
        if triangles is not None and loaded:
            f.create_dataset("mesh/vertices", data=loaded[0]["mesh_reference"]).attrs["units"] = "m"
            f.create_dataset("mesh/triangles", data=triangles)
            f["mesh"].attrs["simulation_only"] = True
            if ventral is not None:
                f.create_dataset("mesh/ventral", data=np.asarray(ventral, dtype=bool))
        f.flush()
    return first_row


CHUNK_BYTES = 1 << 20
"""Uncompressed size (bytes, about) of a chunk of a dataset written by `_GzipChunks`: whole rows."""


class _GzipChunks:
    """Writes gzip (level 1) datasets whose chunks are compressed on threads: zlib releases the GIL, where h5py's
    own deflate filter compresses one chunk at a time under its library lock. The chunks are written in order as
    they are ready (`finish`, or leaving the context); the file reads back as any gzip dataset does."""

    def __init__(self, workers: int | None = None) -> None:
        self._workers = workers or min(8, usable_cpus())
        self._pool = ThreadPoolExecutor(self._workers)
        self._pending: deque[tuple[h5py.Dataset, int, Future[bytes]]] = deque()

    def create(self, parent: h5py.Group, name: str, data: np.ndarray) -> h5py.Dataset:
        """Dataset `name` under `parent` holding `data`, compressed (scalars and empty arrays stored plainly)."""
        data = np.ascontiguousarray(data)
        if data.ndim == 0 or data.size == 0 or data.dtype.kind not in "biuf":
            return parent.create_dataset(name, data=data)
        rows = min(len(data), max(1, CHUNK_BYTES // data[0].nbytes))
        dataset = parent.create_dataset(
            name, data.shape, data.dtype, chunks=(rows, *data.shape[1:]), compression="gzip", compression_opts=1
        )
        for start in range(0, len(data), rows):
            self._pending.append((dataset, start, self._pool.submit(_deflate, data, start, rows)))
        while len(self._pending) > 4 * self._workers:  # bounded: the written chunks' memory is freed
            self._write_next()
        return dataset

    def finish(self) -> None:
        """Write every chunk still pending."""
        while self._pending:
            self._write_next()

    def _write_next(self) -> None:
        dataset, start, payload = self._pending.popleft()
        dataset.id.write_direct_chunk((start,) + (0,) * (dataset.ndim - 1), payload.result())

    def __enter__(self) -> _GzipChunks:
        return self

    def __exit__(self, *exc: object) -> None:
        try:
            if exc[0] is None:
                self.finish()
        finally:
            self._pool.shutdown(wait=True, cancel_futures=True)


def _deflate(data: np.ndarray, start: int, rows: int) -> bytes:
    """The chunk of `rows` rows of `data` from `start` (zero-padded past the end, as HDF5 stores edge chunks),
    deflated at level 1 in the zlib format HDF5's gzip filter reads."""
    block = data[start : start + rows]
    if len(block) < rows:
        block = np.concatenate([block, np.zeros((rows - len(block), *data.shape[1:]), data.dtype)])
    return zlib.compress(block.tobytes(), 1)


def _version() -> str:
    from twin import __version__

    return __version__


def open_dataset(path: Path | str) -> h5py.File:
    """Open an HDF5 file for reading, with a clear ValueError when it is missing or not HDF5, or when it is a
    campaign file (attribute `schema_version`) that breaks the schema (`check_campaign`)."""
    path = Path(path)
    if not path.is_file():
        what = "a folder, not a dataset file" if path.is_dir() else "no such dataset file"
        raise ValueError(f"{what}: {path}")
    try:
        f = h5py.File(path, "r")
    except OSError as exc:
        raise ValueError(f"{path} is not an HDF5 file ({exc})") from exc
    if "schema_version" in f.attrs:
        try:
            check_campaign(f)
        except BaseException:
            f.close()
            raise
    return f


def check_campaign_file(path: Path | str) -> None:
    """ValueError (one line) when `path` is missing, not HDF5, or a campaign file that breaks the schema."""
    open_dataset(path).close()


FEATURE_SHAPES: dict[str, tuple[int, ...]] = {
    "electrode_vals": (19,),
    "electrode_tare": (19,),
    "force": (3,),
    "contact_loc": (3,),
    "tip_pos": (3,),
    "joint_angles": (7,),
    "fe_force": (3,),
}
"""Row shape of the subsampled features that are not one number per row (`nodal_res` is (V, 3))."""
TRAJECTORY_SHAPES: dict[str, tuple[int, ...]] = {
    "point": (3,),
    "direction": (3,),
    "touch_point": (3,),
    "rotation": (3, 3),
    "tool_tip": (4, 4),
    "registration": (4, 4),
    "sensor_in_biotac": (4, 4),
}
"""Row shape of the per-trajectory metadata that is not one number per trajectory."""
RAW_SHAPES: dict[str, tuple[int, ...]] = {"joints": (7,), "wrench": (6,), "electrodes": (19,)}
"""Sample shape of the full-rate recordings that are not one number per sample."""


def check_campaign(f: h5py.File) -> None:
    """ValueError (one line, naming the file and the fault) unless an open campaign file is self-consistent:
    every subsampled feature has the same number of rows and its documented row shape (docs/dataset.md),
    the per-trajectory metadata has one finite row per trajectory and its rows lie inside the features,
    indenter indices name an entry of `indenter_names` (default: the nine indenters), every trajectory has
    its full-rate recording, the mesh's triangles index its vertices. Reads the small arrays only; NaN
    measurements are left to the commands (they report them)."""
    where = f.filename
    names = _json_attr(f, "indenter_names", list) if "indenter_names" in f.attrs else list(INDENTERS)
    config = _json_attr(f, "provenance", dict).get("config", {})
    mesh_max_edge = config.get("mesh_max_edge", 0.5e-3) if isinstance(config, dict) else None
    if not isinstance(mesh_max_edge, int | float) or not 0 < mesh_max_edge < 1:
        raise ValueError(f"{where}: provenance mesh_max_edge {mesh_max_edge!r} is not a length in m")
    sensor_id = f.attrs.get("sensor_id", 1)
    if not isinstance(sensor_id, int | np.integer) or sensor_id < 1:
        raise ValueError(f"{where}: attribute sensor_id {sensor_id!r} is not a positive integer")
    rows = _check_features(f, where)
    if "indenter_type" in f:
        _check_indices(f["indenter_type/data"][()], len(names), f"{where}: indenter_type/data")
    if "trajectories" in f:
        _check_trajectories(f, where, rows, len(names))
    if "mesh" in f:
        _check_mesh(f, where)


def _json_attr(f: h5py.File, name: str, kind: type) -> object:
    """A JSON file attribute of the given kind (list or dict); empty when absent."""
    text = f.attrs.get(name)
    if text is None:
        return kind()
    try:
        value = json.loads(text)
    except (TypeError, ValueError) as exc:
        raise ValueError(f"{f.filename}: attribute {name} is not JSON ({exc})") from exc
    if not isinstance(value, kind):
        raise ValueError(f"{f.filename}: attribute {name} is not a JSON {kind.__name__}")
    return value


def _dataset(f: h5py.File, key: str, where: str) -> h5py.Dataset:
    item = f.get(key)
    if not isinstance(item, h5py.Dataset):
        raise ValueError(f"{where}: {key} is missing or not a dataset (docs/dataset.md)")
    return item


def _check_shape(data: h5py.Dataset, row_shape: tuple[int | None, ...], label: str) -> None:
    """ValueError unless `data` is (n, *row_shape) (None: any size)."""
    shape = tuple(data.shape)
    if len(shape) != 1 + len(row_shape) or any(
        e is not None and e != s for e, s in zip(row_shape, shape[1:], strict=True)
    ):
        wanted = ", ".join("n" if e is None else str(e) for e in (None, *row_shape))
        raise ValueError(f"{label} has shape {shape}, expected ({wanted})")


def _check_features(f: h5py.File, where: str) -> int:
    """The number of subsampled rows, after checking each feature's row shape and that all have that many."""
    vertices = f["mesh/vertices"].shape[0] if isinstance(f.get("mesh/vertices"), h5py.Dataset) else None
    counts: dict[str, int] = {}
    for name in FEATURE_UNITS:
        if name in f:
            data = _dataset(f, f"{name}/data", where)
            row_shape = (vertices, 3) if name == "nodal_res" else FEATURE_SHAPES.get(name, ())
            _check_shape(data, row_shape, f"{where}: {name}/data")
            counts[name] = data.shape[0]
    if len(set(counts.values())) > 1:
        detail = ", ".join(f"{k} {v}" for k, v in counts.items())
        raise ValueError(f"{where}: the subsampled features disagree on their number of rows ({detail})")
    return next(iter(counts.values()), 0)


def _check_indices(values: np.ndarray, count: int, label: str) -> None:
    """ValueError unless every value is an integer index into `count` entries."""
    values = np.asarray(values)
    if values.size and (values.dtype.kind not in "iu" or values.min() < 0 or values.max() >= count):
        raise ValueError(f"{label} holds indices outside 0..{count - 1} (or not integers)")


def _check_trajectories(f: h5py.File, where: str, rows: int, n_names: int) -> None:
    """Per-trajectory metadata (the fields present): one finite row each of its documented shape, rows inside
    the features and of that trajectory, indenter indices in the names, full-rate recordings present."""
    group = f["trajectories"]
    if not isinstance(group, h5py.Group):
        raise ValueError(f"{where}: trajectories is not a group")
    meta = {}
    for name in (n for n in TRAJECTORY_FIELDS if n in group):
        data = _dataset(f, f"trajectories/{name}", where)
        _check_shape(data, TRAJECTORY_SHAPES.get(name, ()), f"{where}: trajectories/{name}")
        meta[name] = data[()]
        if meta[name].dtype.kind == "f" and not np.isfinite(meta[name]).all():
            raise ValueError(f"{where}: trajectories/{name} holds NaN or infinite values")
    if len({len(v) for v in meta.values()}) > 1:
        raise ValueError(f"{where}: the trajectories datasets disagree on the number of trajectories")
    for name in ("trajectory_id", "first_row", "n_rows", "arm", "indenter_type"):
        count = {"arm": 2, "indenter_type": n_names}.get(name, np.iinfo(np.int64).max)
        _check_indices(meta.get(name, np.zeros(0, dtype=np.int64)), count, f"{where}: trajectories/{name}")
    ids = meta.get("trajectory_id", np.zeros(0, dtype=np.int64))
    if len(np.unique(ids)) != len(ids):
        raise ValueError(f"{where}: trajectories/trajectory_id repeats an id")
    if "first_row" in meta and "n_rows" in meta:
        _check_row_ranges(f, where, rows, ids, meta["first_row"], meta["n_rows"])
    if "raw" in f:
        for tid in ids:
            _check_raw(f, where, int(tid))


def _check_row_ranges(
    f: h5py.File, where: str, rows: int, ids: np.ndarray, first: np.ndarray, count: np.ndarray
) -> None:
    """Each trajectory's rows first..first+count-1 lie inside the `rows` subsampled rows and are its own."""
    ends = first + count
    if ends.size and ends.max() > rows:
        raise ValueError(f"{where}: trajectories first_row + n_rows reach row {ends.max()}, beyond the {rows} rows")
    row_ids = f["trajectory_id/data"][()] if "trajectory_id" in f else None
    for tid, start, n in zip(ids, first, count, strict=True):
        if row_ids is not None and not np.all(row_ids[start : start + n] == tid):
            raise ValueError(f"{where}: rows {start}..{start + n - 1} are not all of trajectory {tid}")


def _check_raw(f: h5py.File, where: str, trajectory_id: int) -> None:
    """The full-rate recording of one trajectory: every field, one sample per time, finite times."""
    key = f"raw/{trajectory_id}"
    if not isinstance(f.get(key), h5py.Group):
        raise ValueError(f"{where}: trajectory {trajectory_id} has no full-rate recording {key}")
    samples = None
    for name in RAW_FIELDS:
        data = _dataset(f, f"{key}/{name}", where)
        _check_shape(data, RAW_SHAPES.get(name, ()), f"{where}: {key}/{name}")
        if samples is not None and data.shape[0] != samples:
            raise ValueError(f"{where}: {key}/{name} has {data.shape[0]} samples, time has {samples}")
        samples = data.shape[0]
    if not np.isfinite(f[f"{key}/time"][()]).all():
        raise ValueError(f"{where}: {key}/time holds NaN or infinite values")


def _check_mesh(f: h5py.File, where: str) -> None:
    """mesh/vertices (V, 3) finite, mesh/triangles (T, 3) indices into them, mesh/ventral (V,) if present."""
    vertices = _dataset(f, "mesh/vertices", where)
    _check_shape(vertices, (3,), f"{where}: mesh/vertices")
    if not np.isfinite(vertices[()]).all():
        raise ValueError(f"{where}: mesh/vertices holds NaN or infinite values")
    triangles = _dataset(f, "mesh/triangles", where)
    _check_shape(triangles, (3,), f"{where}: mesh/triangles")
    _check_indices(triangles[()], vertices.shape[0], f"{where}: mesh/triangles")
    if "mesh/ventral" in f and _dataset(f, "mesh/ventral", where).shape != (vertices.shape[0],):
        raise ValueError(f"{where}: mesh/ventral has shape {f['mesh/ventral'].shape}, expected ({vertices.shape[0]},)")


def nonfinite_rows(path: Path | str, feature: str = "force") -> tuple[int, int]:
    """(rows with a NaN or infinite value of `feature`, all rows) of an HDF5 file's `feature/data`; (0, 0)
    when the file lacks it."""
    with h5py.File(path, "r") as f:
        data = f.get(f"{feature}/data")
        if not isinstance(data, h5py.Dataset) or data.ndim == 0:
            return 0, 0
        values = data[()].reshape(data.shape[0], -1)
    return int((~np.isfinite(values).all(axis=1)).sum()), len(values)


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
                    "simulation_only": name in SIMULATION_ONLY or bool(data.attrs.get("simulation_only", False)),
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
        info["simulation_only"] = [name for name in SIMULATION_ONLY if name in f]
        info["attributes"] = {k: _plain(v) for k, v in f.attrs.items()}
    return info


def _plain(value: object) -> object:
    if isinstance(value, np.generic):
        return value.item()
    if isinstance(value, bytes):
        return value.decode()
    return value
