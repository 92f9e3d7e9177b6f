"""Files in the paper's public layout (issue 22): each row feature a group holding a ``data`` dataset, forces in
``force_vec/data`` (N, biotac frame), contact locations in metres, ``indenter_type/data`` (N, 1) indexing the
public meshes, and an FE companion ``<stem>_simulated.hdf5`` whose ``nodal_res``, ``force_res`` and
``mesh_max_dist`` are plain datasets. No attributes, no ``raw/`` streams, no ``trajectories/`` group."""

import json
from pathlib import Path

import h5py
import numpy as np

from assets.indenters import PUBLIC_NAMES

ROWS, NODES = 12, 40


def write_paper_files(folder: Path, rng: np.random.Generator) -> dict[str, np.ndarray]:
    """biotac1.hdf5 (groups with a ``data`` dataset) and biotac1_simulated.hdf5 (plain datasets); the arrays."""
    arrays = {
        "electrode_vals": rng.integers(1500, 3500, (ROWS, 19)).astype(np.int32),
        "contact_loc": np.repeat([[0.004, -0.002, -0.0085], [-0.009, 0.003, -0.0082]], ROWS // 2, axis=0),
        "indenter_type": np.repeat([0, 1], ROWS // 2)[:, None],
        "force_vec": np.column_stack([rng.normal(0, 0.2, ROWS), rng.normal(0, 0.2, ROWS), -np.linspace(0, 4, ROWS)]),
    }
    _write_groups(folder / "biotac1.hdf5", arrays)
    simulated = {
        "nodal_res": rng.normal(0, 1e-4, (ROWS, NODES, 3)),
        "force_res": arrays["force_vec"] + rng.normal(0, 0.05, (ROWS, 3)),
        "mesh_max_dist": np.abs(rng.normal(0, 1e-3, ROWS)),
    }
    with h5py.File(folder / "biotac1_simulated.hdf5", "w") as f:
        for name, value in simulated.items():
            f.create_dataset(name, data=value)
    return arrays | simulated


def _write_groups(path: Path, arrays: dict[str, np.ndarray], attrs: dict[str, str] | None = None) -> Path:
    with h5py.File(path, "w") as f:
        for name, value in arrays.items():
            f.create_group(name).create_dataset("data", data=value)
        f.attrs.update(attrs or {})
    return path


def rows_of_campaign(campaign: Path) -> tuple[dict[str, np.ndarray], list[str]]:
    """A campaign file's electrode values (raw counts: tared + tare), forces, contact locations and indenter
    names per row, in row order."""
    with h5py.File(campaign, "r") as f:
        rows = {
            "electrode_vals": f["electrode_vals/data"][()] + f["electrode_tare/data"][()],
            "force": f["force/data"][()],
            "contact_loc": f["contact_loc/data"][()],
        }
        names = json.loads(f.attrs["indenter_names"])
        indenters = [names[i] for i in f["indenter_type/data"][()]]
    return rows, indenters


def paper_copy(campaign: Path, out: Path) -> Path:
    """The rows of a campaign file in the paper's layout (indenter indices into the public mesh list)."""
    rows, indenters = rows_of_campaign(campaign)
    public = list(PUBLIC_NAMES.values())
    arrays = {
        "electrode_vals": rows["electrode_vals"],
        "force_vec": rows["force"],
        "contact_loc": rows["contact_loc"],
        "indenter_type": np.array([[public.index(name)] for name in indenters]),
    }
    return _write_groups(out, arrays)


def repo_rows_copy(campaign: Path, out: Path) -> Path:
    """The same rows in this repository's feature names (``force/data``, indenter names as an attribute), still
    without raw streams or trajectory metadata."""
    rows, indenters = rows_of_campaign(campaign)
    names = sorted(set(indenters))
    arrays = rows | {"indenter_type": np.array([names.index(name) for name in indenters])}
    return _write_groups(out, arrays, {"indenter_names": json.dumps(names)})
