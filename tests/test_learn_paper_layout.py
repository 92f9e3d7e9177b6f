"""The paper's public files as they are: forces in ``force_vec/data``, contact locations in metres, and an FE
companion ``<stem>_simulated.hdf5`` whose ``nodal_res``, ``force_res`` and ``mesh_max_dist`` are plain datasets
(issue 22; docs/dataset.md). ``paper_layout.write_paper_files`` writes a small pair in exactly that layout."""

from pathlib import Path

import numpy as np
from paper_layout import NODES, ROWS, write_paper_files

from learn.data import load


def test_paper_files_load_with_forces_in_newtons_and_locations_in_metres(tmp_path: Path) -> None:
    arrays = write_paper_files(tmp_path, np.random.default_rng(3))
    data = load(tmp_path / "biotac1.hdf5", node_ids=np.arange(0, NODES, 4))
    assert data.layout == "paper" and len(data) == ROWS
    assert data.force is not None
    np.testing.assert_allclose(data.force, arrays["force_vec"])
    np.testing.assert_allclose(data.contact_loc, arrays["contact_loc"])  # metres stay metres
    np.testing.assert_array_equal(data.trajectory, np.repeat([0, 1], ROWS // 2))
    np.testing.assert_allclose(data.nodal, arrays["nodal_res"][:, ::4])
