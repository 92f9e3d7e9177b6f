"""The true indenter tip of simulated campaign rows (twin.label_truth; issue 19)."""

from __future__ import annotations

import h5py
import numpy as np
import pytest

from twin.label_truth import true_tip_locations
from twin.plant import make_plant


@pytest.fixture(scope="module")
def campaigns(tmp_path_factory, make_tiny_campaign) -> dict:
    """The tiny campaign made by the default plant and by one with an exact registration."""
    exact = make_plant([2], 0, exact_registration=True)
    return {
        "default": make_tiny_campaign(tmp_path_factory.mktemp("default")),
        "exact": (make_tiny_campaign(tmp_path_factory.mktemp("exact"), plant=exact), exact),
    }


def test_with_an_exact_registration_the_true_tip_is_the_label(campaigns) -> None:
    path, plant = campaigns["exact"]
    with h5py.File(path, "r") as f:
        label = f["contact_loc/data"][:]
    assert np.abs(true_tip_locations(path, plant=plant) - label).max() < 1e-6


def test_a_file_of_another_plant_is_refused(campaigns) -> None:
    path, _ = campaigns["exact"]
    with pytest.raises(ValueError, match="does not reproduce"):
        true_tip_locations(path)


def test_the_default_plant_labels_are_off_by_the_registration_error(campaigns) -> None:
    """The plant's joint offsets (sized to the paper's 0.5-1.5 mm band) move the real tip away from the label:
    the offset is of that size and the same within a trajectory (a rigid-motion error changes slowly)."""
    path = campaigns["default"]
    with h5py.File(path, "r") as f:
        label, trajectory = f["contact_loc/data"][:], f["trajectory_id/data"][:]
    offset = true_tip_locations(path) - label
    size = np.linalg.norm(offset, axis=1)
    assert 0.2e-3 < size.mean() < 3e-3
    for t in np.unique(trajectory):
        rows = offset[trajectory == t]
        assert np.linalg.norm(rows - rows.mean(axis=0), axis=1).max() < 0.1e-3
