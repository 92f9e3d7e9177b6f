"""Tactile data in memory and the readers that fill it (numpy + h5py; no torch).

Three layouts are read, chosen by content, never by file name:
- ``campaign``: this project's campaign HDF5 (docs/dataset.md; file attribute ``schema_version`` = 1).
- ``paper``: the paper's public HDF5 (``electrode_vals/data``, ``contact_loc/data``, ``indenter_type/data``,
  forces in ``force_vec/data`` (or ``force/data``); nodal fields from the FE companion
  ``<stem>_simulated.hdf5`` next to it when present).
- ``ruppel``: the Ruppel et al. single-contact CSV (``%time``, ``position.x/y/z`` m, ``force.x/y/z`` N,
  ``electrodes0..18``).
Anything else raises `UnknownLayoutError` naming the three.

Everything is SI in the ``biotac`` frame: electrode values are counts *tared* at each trajectory's
first sample, contact locations metres, forces newtons, nodal displacements metres.
"""

from __future__ import annotations

import csv
import hashlib
import json
from dataclasses import dataclass, replace
from pathlib import Path

import h5py
import numpy as np

from assets.biotac import electrode_table

N_ELECTRODES = 19
N_FIELD_NODES = 128
"""Nodes sampled on the ventral skin for field targets (the paper's 128)."""
LOCATION_JUMP = 2e-3
"""Files without trajectory ids: a new trajectory starts where the contact location jumps by more (m)."""
CHUNK_ROWS = 1024
"""Rows read at once from a nodal field dataset."""
PAPER_FORCE_GROUPS = ("force_vec", "force")
"""Where a paper-layout file keeps the force (N): the public files' group first, then this project's."""


class UnknownLayoutError(ValueError):
    """A file that is none of the layouts `load` reads."""


@dataclass(frozen=True)
class TactileData:
    """Samples of one sensor; row i of every array is the same sample.

    sensor: a name (e.g. "biotac1"). electrodes: (N, 19) counts, tared per trajectory.
    contact_loc: (N, 3) m or None. force: (N, 3) N (applied to the BioTac) or None.
    nodal: (N, K, 3) m displacements of K skin nodes, or None. nodes: (K, 3) m reference positions of those
    nodes (None if unknown). node_ids: (K,) their ids in the file's mesh, or None.
    trajectory: (N,) int. indenter: (N,) int index into indenter_names.
    source: file path; layout: "campaign" | "paper" | "ruppel" | "memory".
    """

    sensor: str
    electrodes: np.ndarray
    trajectory: np.ndarray
    indenter: np.ndarray
    indenter_names: tuple[str, ...]
    contact_loc: np.ndarray | None = None
    force: np.ndarray | None = None
    nodal: np.ndarray | None = None
    nodes: np.ndarray | None = None
    node_ids: np.ndarray | None = None
    source: str = ""
    layout: str = "memory"

    def __post_init__(self) -> None:
        n = len(self.electrodes)
        if self.electrodes.shape != (n, N_ELECTRODES):
            raise ValueError(f"electrodes must be (N, 19), got {self.electrodes.shape}")
        for name in ("trajectory", "indenter", "contact_loc", "force", "nodal"):
            value = getattr(self, name)
            if value is not None and len(value) != n:
                raise ValueError(f"{name} has {len(value)} rows, electrodes {n}")

    def __len__(self) -> int:
        return len(self.electrodes)

    @property
    def electrode_positions(self) -> np.ndarray:
        """(19, 3) m, the product manual's electrode table (the same for every BioTac)."""
        return electrode_table().positions

    @property
    def electrode_normals(self) -> np.ndarray:
        """(19, 3) unit outward normals of the electrodes."""
        return electrode_table().normals

    def targets(self) -> dict[str, np.ndarray]:
        """The available targets: "contact_loc" (N, 3), "force" (N, 3), "nodal" (N, K, 3)."""
        names = ("contact_loc", "force", "nodal")
        return {k: getattr(self, k) for k in names if getattr(self, k) is not None}

    def subset(self, rows: np.ndarray) -> TactileData:
        """The samples at ``rows`` (indices or boolean mask)."""
        pick = {
            k: getattr(self, k)[rows] if getattr(self, k) is not None else None
            for k in ("electrodes", "trajectory", "indenter", "contact_loc", "force", "nodal")
        }
        return replace(self, **pick)

    def content_hash(self) -> str:
        """sha256 (hex) of the arrays: which data a model saw, independent of file names."""
        h = hashlib.sha256()
        for k in ("electrodes", "trajectory", "indenter", "contact_loc", "force", "nodal", "node_ids"):
            value = getattr(self, k)
            if value is not None:
                h.update(k.encode())
                h.update(np.ascontiguousarray(value).tobytes())
        return h.hexdigest()


def concatenate(parts: list[TactileData], sensor: str = "combined") -> TactileData:
    """Samples of several sensors in one set (indenters mapped onto one shared name list)."""
    if not parts:
        raise ValueError("concatenate: nothing to concatenate")
    names = tuple(dict.fromkeys(n for p in parts for n in p.indenter_names))
    out: dict[str, np.ndarray | None] = {}
    for key in ("contact_loc", "force", "nodal"):
        values = [getattr(p, key) for p in parts]
        out[key] = np.concatenate(values) if all(v is not None for v in values) else None
    if out["nodal"] is not None and len({p.nodal.shape[1] for p in parts}) > 1:
        out["nodal"] = None
    offset = 0
    trajectories = []
    for p in parts:
        trajectories.append(p.trajectory - p.trajectory.min() + offset if len(p) else p.trajectory)
        offset = int(trajectories[-1].max()) + 1 if len(p) else offset
    return TactileData(
        sensor=sensor,
        electrodes=np.concatenate([p.electrodes for p in parts]),
        trajectory=np.concatenate(trajectories),
        indenter=np.concatenate(
            [np.asarray([names.index(p.indenter_names[i]) for i in p.indenter], int) for p in parts]
        ),
        indenter_names=names,
        nodes=parts[0].nodes if out["nodal"] is not None else None,
        node_ids=parts[0].node_ids if out["nodal"] is not None else None,
        source=";".join(p.source for p in parts),
        layout="memory",
        **out,
    )


def with_min_force(data: TactileData, min_force: float) -> TactileData:
    """The rows whose force magnitude is at least ``min_force`` (N): rows in contact. Below ~0.1 N the F/T
    reading is noise and the skin may not be touched at all, so the contact location is unobservable."""
    if data.force is None:
        raise ValueError("with_min_force needs force targets")
    return data.subset(np.linalg.norm(data.force, axis=1) >= min_force)


# ----------------------------------------------------------------------------------------------- layouts


def detect_layout(path: str | Path) -> str:
    """ "campaign", "paper" or "ruppel" from the file's content; UnknownLayoutError otherwise."""
    path = Path(path)
    if not path.is_file():
        raise FileNotFoundError(f"{path}: no such file")
    if h5py.is_hdf5(path):
        with h5py.File(path, "r") as f:
            if "schema_version" in f.attrs:
                version = int(f.attrs["schema_version"])
                if version != 1:
                    raise UnknownLayoutError(f"{path}: campaign schema_version {version}; this reader knows 1")
                return "campaign"
            if "electrode_vals" in f:
                return "paper"
            if "nodal_res" in f:
                raise UnknownLayoutError(
                    f"{path}: an FE companion file (nodal_res only); open the sensor file biotacN.hdf5 next to it"
                )
    else:
        header = _csv_header(path)
        if header is not None and {"force.x", "position.x", "electrodes0"} <= set(header):
            return "ruppel"
    raise UnknownLayoutError(
        f"{path}: not a file this reader knows. Expected a biotac-twin campaign HDF5 (attribute "
        "schema_version = 1), the paper's public HDF5 (group electrode_vals/data) or a Ruppel et al. CSV "
        "(columns %time, position.x/y/z, force.x/y/z, electrodes0..18)."
    )


def _csv_header(path: Path) -> list[str] | None:
    try:
        with open(path, newline="", encoding="utf-8") as f:
            return [c.strip() for c in next(csv.reader(f))]
    except (UnicodeDecodeError, StopIteration, csv.Error):
        return None


def load(path: str | Path, node_ids: np.ndarray | None = None, node_seed: int = 0) -> TactileData:
    """Read any supported file into `TactileData`.

    node_ids: skin nodes whose displacements become the field target (a trained model's); default
    `N_FIELD_NODES` sampled on the ventral skin with ``node_seed``.
    """
    layout = detect_layout(path)
    if layout == "campaign":
        return _load_campaign(Path(path), node_ids, node_seed)
    if layout == "paper":
        return _load_paper(Path(path), node_ids, node_seed)
    return _load_ruppel(Path(path))


def pick_field_nodes(candidates: np.ndarray, seed: int, count: int = N_FIELD_NODES) -> np.ndarray:
    """``count`` sorted node ids drawn without replacement from the candidate ids (all if fewer)."""
    rng = np.random.default_rng(seed)
    chosen = rng.choice(candidates, size=min(count, len(candidates)), replace=False)
    return np.sort(chosen)


def _read_nodal(dataset: h5py.Dataset, node_ids: np.ndarray) -> np.ndarray:
    """(N, K, 3) rows of a (N, V, 3) dataset at sorted node ids, read in row chunks."""
    ids = np.asarray(node_ids)
    if np.any(np.diff(ids) <= 0):
        raise ValueError("node_ids must be strictly increasing")
    out = np.empty((dataset.shape[0], len(ids), 3))
    for start in range(0, dataset.shape[0], CHUNK_ROWS):
        out[start : start + CHUNK_ROWS] = dataset[start : start + CHUNK_ROWS, ids, :]
    return out


def _names(attr: object, count: int) -> tuple[str, ...]:
    if attr is None:
        return tuple(f"indenter{i}" for i in range(count))
    return tuple(json.loads(attr) if isinstance(attr, str | bytes) else attr)


def _load_campaign(path: Path, node_ids: np.ndarray | None, node_seed: int) -> TactileData:
    with h5py.File(path, "r") as f:
        required = ("electrode_vals", "trajectory_id", "indenter_type")
        missing = [k for k in required if k not in f]
        if missing:
            raise UnknownLayoutError(f"{path}: campaign file lacks {', '.join(missing)}")
        indenter = f["indenter_type/data"][:].astype(np.int64)
        nodal = nodes = None
        if "nodal_res" in f and "mesh" in f:
            vertices = f["mesh/vertices"][:]
            if node_ids is None:
                ventral = f["mesh/ventral"][:] if "mesh/ventral" in f else vertices[:, 2] < 0.0
                node_ids = pick_field_nodes(np.flatnonzero(ventral), node_seed)
            nodal, nodes = _read_nodal(f["nodal_res/data"], node_ids), vertices[node_ids]
        return TactileData(
            sensor=f"biotac{int(f.attrs.get('sensor_id', 0))}",
            electrodes=f["electrode_vals/data"][:].astype(float),
            trajectory=f["trajectory_id/data"][:].astype(np.int64),
            indenter=indenter,
            indenter_names=_names(f.attrs.get("indenter_names"), int(indenter.max(initial=-1)) + 1),
            contact_loc=f["contact_loc/data"][:] if "contact_loc" in f else None,
            force=f["force/data"][:] if "force" in f else None,
            nodal=nodal,
            nodes=nodes,
            node_ids=None if nodal is None else np.asarray(node_ids),
            source=str(path),
            layout="campaign",
        )


def segment_trajectories(location: np.ndarray, indenter: np.ndarray | None = None) -> np.ndarray:
    """(N,) trajectory ids for files without them: a new one where the location (m) jumps by more than
    `LOCATION_JUMP` or the indenter changes."""
    jump = np.linalg.norm(np.diff(location, axis=0), axis=1) > LOCATION_JUMP
    if indenter is not None:
        jump |= np.diff(indenter) != 0
    return np.concatenate([[0], np.cumsum(jump)]).astype(np.int64)


def tare_per_trajectory(values: np.ndarray, trajectory: np.ndarray) -> np.ndarray:
    """Values minus each trajectory's first row."""
    first = np.concatenate([[True], trajectory[1:] != trajectory[:-1]])
    starts = np.flatnonzero(first)
    owner = np.cumsum(first) - 1
    return values - values[starts][owner]


def _load_paper(path: Path, node_ids: np.ndarray | None, node_seed: int) -> TactileData:
    """The paper's public layout. Contact locations given in mm (any |value| > 0.1) are converted to m;
    without ``trajectory_id`` trajectories are segmented by location jumps. Electrode values are tared
    per trajectory (a tare of already-tared values is a no-op)."""
    with h5py.File(path, "r") as f:
        electrodes = f["electrode_vals/data"][:].astype(float)
        loc = f["contact_loc/data"][:].astype(float) if "contact_loc" in f else None
        if loc is not None and np.abs(loc).max(initial=0.0) > 0.1:
            loc = loc * 1e-3
        indenter = f["indenter_type/data"][:].astype(np.int64).ravel() if "indenter_type" in f else None
        force = next((f[f"{k}/data"][:].astype(float) for k in PAPER_FORCE_GROUPS if k in f), None)
        if "trajectory_id" in f:
            trajectory = f["trajectory_id/data"][:].astype(np.int64)
        elif loc is not None:
            trajectory = segment_trajectories(loc, indenter)
        else:
            trajectory = np.zeros(len(electrodes), dtype=np.int64)
        indenter = np.zeros(len(electrodes), dtype=np.int64) if indenter is None else indenter
        names = _names(f.attrs.get("indenter_names"), int(indenter.max(initial=-1)) + 1)
    nodal = None
    companion = path.with_name(f"{path.stem}_simulated{path.suffix}")
    if companion.is_file():
        with h5py.File(companion, "r") as g:
            if "nodal_res" in g:
                ds = g["nodal_res/data"] if isinstance(g["nodal_res"], h5py.Group) else g["nodal_res"]
                if node_ids is None:  # no mesh in the companion: sample among all nodes
                    node_ids = pick_field_nodes(np.arange(ds.shape[1]), node_seed)
                nodal = _read_nodal(ds, node_ids)
    return TactileData(
        sensor=path.stem,
        electrodes=tare_per_trajectory(electrodes, trajectory),
        trajectory=trajectory,
        indenter=indenter,
        indenter_names=names,
        contact_loc=loc,
        force=force,
        nodal=nodal,
        node_ids=None if nodal is None else np.asarray(node_ids),
        source=str(path),
        layout="paper",
    )


def _load_ruppel(path: Path) -> TactileData:
    """Ruppel CSV: positions (m) and forces (N) as given; trajectories segmented by location jumps,
    electrodes tared per trajectory."""
    header = _csv_header(path)
    table = np.loadtxt(path, delimiter=",", skiprows=1, ndmin=2)
    column = {name: i for i, name in enumerate(header)}
    missing = [c for c in ["force.x", "position.x"] + [f"electrodes{i}" for i in range(19)] if c not in column]
    if missing:
        raise UnknownLayoutError(f"{path}: Ruppel CSV lacks columns {missing}")

    def cols(*names: str) -> np.ndarray:
        return table[:, [column[n] for n in names]]

    loc = cols("position.x", "position.y", "position.z")
    trajectory = segment_trajectories(loc)
    return TactileData(
        sensor=path.stem,
        electrodes=tare_per_trajectory(cols(*[f"electrodes{i}" for i in range(19)]), trajectory),
        trajectory=trajectory,
        indenter=np.zeros(len(table), dtype=np.int64),
        indenter_names=("unknown",),
        contact_loc=loc,
        force=cols("force.x", "force.y", "force.z"),
        source=str(path),
        layout="ruppel",
    )
