"""The paper's public files as they are: forces in ``force_vec/data``, contact locations in metres, and an FE
companion ``<stem>_simulated.hdf5`` whose ``nodal_res``, ``force_res`` and ``mesh_max_dist`` are plain datasets
(issue 22; docs/dataset.md). ``write_paper_files`` writes a small pair in exactly that layout."""

from pathlib import Path

import h5py
import numpy as np

from learn.data import load

ROWS, NODES = 12, 40


def write_paper_files(folder: Path, rng: np.random.Generator) -> dict[str, np.ndarray]:
    """biotac1.hdf5 (groups with a ``data`` dataset) and biotac1_simulated.hdf5 (plain datasets); the arrays."""
    arrays = {
        "electrode_vals": rng.integers(1500, 3500, (ROWS, 19)).astype(np.int32),
        "contact_loc": np.repeat([[0.004, -0.002, -0.0085], [-0.009, 0.003, -0.0082]], ROWS // 2, axis=0),
        "indenter_type": np.repeat([0, 1], ROWS // 2)[:, None],
        "force_vec": np.column_stack([rng.normal(0, 0.2, ROWS), rng.normal(0, 0.2, ROWS), -np.linspace(0, 4, ROWS)]),
    }
    with h5py.File(folder / "biotac1.hdf5", "w") as f:
        for name, value in arrays.items():
            f.create_group(name).create_dataset("data", data=value)
    simulated = {
        "nodal_res": rng.normal(0, 1e-4, (ROWS, NODES, 3)),
        "force_res": arrays["force_vec"] + rng.normal(0, 0.05, (ROWS, 3)),
        "mesh_max_dist": np.abs(rng.normal(0, 1e-3, ROWS)),
    }
    with h5py.File(folder / "biotac1_simulated.hdf5", "w") as f:
        for name, value in simulated.items():
            f.create_dataset(name, data=value)
    return arrays | simulated


def test_paper_files_load_with_forces_in_newtons_and_locations_in_metres(tmp_path: Path) -> None:
    arrays = write_paper_files(tmp_path, np.random.default_rng(3))
    data = load(tmp_path / "biotac1.hdf5", node_ids=np.arange(0, NODES, 4))
    assert data.layout == "paper" and len(data) == ROWS
    assert data.force is not None
    np.testing.assert_allclose(data.force, arrays["force_vec"])
    np.testing.assert_allclose(data.contact_loc, arrays["contact_loc"])  # metres stay metres
    np.testing.assert_array_equal(data.trajectory, np.repeat([0, 1], ROWS // 2))
    np.testing.assert_allclose(data.nodal, arrays["nodal_res"][:, ::4])
