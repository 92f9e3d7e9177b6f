"""Readers of the three layouts, clear errors for anything else, splits and metrics."""

from pathlib import Path

import h5py
import numpy as np
import pytest

from learn.data import (
    N_FIELD_NODES,
    UnknownLayoutError,
    concatenate,
    detect_layout,
    load,
    segment_trajectories,
    tare_per_trajectory,
)
from learn.metrics import ANGLE_MIN_FORCE, paper_metrics
from learn.splits import split
from learn.synthetic import SYNTHETIC_INDENTERS, write_synthetic_campaign


@pytest.fixture(scope="module")
def campaign(tmp_path_factory: pytest.TempPathFactory) -> Path:
    return write_synthetic_campaign(tmp_path_factory.mktemp("data") / "biotac1.hdf5", 12, sensor_id=1, seed=5)


def test_synthetic_campaign_follows_the_schema(campaign: Path) -> None:
    with h5py.File(campaign, "r") as f:
        assert int(f.attrs["schema_version"]) == 1 and int(f.attrs["sensor_id"]) == 1
        n = f["electrode_vals/data"].shape[0]
        for name in ("electrode_tare", "force", "contact_loc", "indenter_type", "trajectory_id", "nodal_res"):
            assert f[f"{name}/data"].shape[0] == n, name
            assert "units" in f[f"{name}/data"].attrs
        traj = f["trajectories"]
        assert traj["n_rows"][:].sum() == n
        first = traj["first_row"][:]
        np.testing.assert_array_equal(f["trajectory_id/data"][:][first], traj["trajectory_id"][:])
        np.testing.assert_allclose(f["electrode_vals/data"][:][first], 0.0)  # tared at each first sample
        raw = f["electrode_vals/data"][:] + f["electrode_tare/data"][:]
        assert raw.min() >= 0 and raw.max() <= 4095


def test_campaign_reader(campaign: Path) -> None:
    data = load(campaign)
    assert detect_layout(campaign) == "campaign" and data.layout == "campaign" and data.sensor == "biotac1"
    assert data.electrodes.shape == (len(data), 19) and data.force.shape == (len(data), 3)
    assert data.nodal.shape == (len(data), N_FIELD_NODES, 3)
    with h5py.File(campaign, "r") as f:
        ventral = f["mesh/ventral"][:]
        np.testing.assert_allclose(data.nodal[:, 5], f["nodal_res/data"][:, data.node_ids[5]])
    assert ventral[data.node_ids].all()
    assert set(data.indenter_names) <= set(SYNTHETIC_INDENTERS)
    same = load(campaign, node_ids=data.node_ids)
    assert same.content_hash() == data.content_hash()
    assert load(campaign, node_seed=1).content_hash() != data.content_hash()


def test_paper_layout_with_mm_locations_and_companion(tmp_path: Path) -> None:
    rng = np.random.default_rng(0)
    loc_mm = np.concatenate([np.full((5, 3), [1.0, 2.0, -8.0]), np.full((4, 3), [-6.0, 0.0, -9.0])])
    loc_mm += np.cumsum(rng.normal(0, 0.05, loc_mm.shape), axis=0)
    electrodes = 2500.0 + rng.normal(0, 50, (9, 19))
    path = tmp_path / "biotac2.hdf5"
    with h5py.File(path, "w") as f:
        f["electrode_vals/data"] = electrodes
        f["contact_loc/data"] = loc_mm
        f["indenter_type/data"] = np.zeros(9, dtype=int)
    with h5py.File(tmp_path / "biotac2_simulated.hdf5", "w") as f:
        f["nodal_res/data"] = rng.normal(size=(9, 200, 3))
        f["mesh_max_dist/data"] = np.ones(9)
    data = load(path)
    assert data.layout == "paper" and data.sensor == "biotac2"
    np.testing.assert_allclose(data.contact_loc, loc_mm * 1e-3)
    np.testing.assert_array_equal(data.trajectory, [0] * 5 + [1] * 4)
    np.testing.assert_allclose(data.electrodes[[0, 5]], 0.0)
    np.testing.assert_allclose(data.electrodes[6], electrodes[6] - electrodes[5])
    assert data.nodal.shape == (9, N_FIELD_NODES, 3)
    with pytest.raises(UnknownLayoutError, match="companion"):
        load(tmp_path / "biotac2_simulated.hdf5")


def test_ruppel_csv(tmp_path: Path) -> None:
    header = ["%time", "position.x", "position.y", "position.z", "force.x", "force.y", "force.z", "pac0", "pac1"]
    header += ["pdc", "tac", "tdc"] + [f"electrodes{i}" for i in range(19)]
    rows = np.zeros((6, len(header)))
    rows[:, 0] = np.arange(6) * 0.01
    rows[:, 1:4] = [0.001, 0.0, -0.009]
    rows[3:, 1] = 0.008  # a second contact 7 mm away
    rows[:, 6] = np.arange(6)
    rows[:, 12:] = 3000.0 + np.arange(6)[:, None]
    path = tmp_path / "ruppel.csv"
    np.savetxt(path, rows, delimiter=",", header=",".join(header), comments="")
    data = load(path)
    assert data.layout == "ruppel" and len(data) == 6
    np.testing.assert_array_equal(data.trajectory, [0, 0, 0, 1, 1, 1])
    np.testing.assert_allclose(data.force[:, 2], np.arange(6))
    np.testing.assert_allclose(data.electrodes[:, 0], [0, 1, 2, 0, 1, 2])


@pytest.mark.parametrize("kind", ["text", "empty_hdf5", "csv_other", "schema_2"])
def test_unknown_files_get_a_clear_error(tmp_path: Path, kind: str) -> None:
    path = tmp_path / f"{kind}.dat"
    if kind == "text":
        path.write_text("hello\n")
    elif kind == "csv_other":
        path.write_text("a,b,c\n1,2,3\n")
    else:
        with h5py.File(path, "w") as f:
            f["something/data"] = np.zeros(3)
            if kind == "schema_2":
                f.attrs["schema_version"] = 2
    with pytest.raises(UnknownLayoutError, match="schema_version|campaign|Ruppel"):
        load(path)
    with pytest.raises(FileNotFoundError):
        load(tmp_path / "missing.h5")


def test_segmentation_and_tare() -> None:
    loc = np.array([[0, 0, 0], [1e-4, 0, 0], [5e-3, 0, 0], [5.1e-3, 0, 0]])
    np.testing.assert_array_equal(segment_trajectories(loc), [0, 0, 1, 1])
    np.testing.assert_array_equal(segment_trajectories(loc, np.array([0, 1, 1, 1])), [0, 1, 2, 2])
    values = np.array([[1.0], [3.0], [10.0], [7.0]])
    np.testing.assert_allclose(tare_per_trajectory(values, np.array([0, 0, 1, 1])), [[0], [2], [0], [-3]])


def test_splits(campaign: Path) -> None:
    data = load(campaign)
    train, test = split(data, "contiguous", 0.25, seed=0)
    assert not set(data.trajectory[train]) & set(data.trajectory[test])
    assert len(train) + len(test) == len(data) and 0.1 < len(test) / len(data) < 0.45
    train, test = split(data, "noncontiguous", 0.25, seed=0)
    assert set(data.trajectory[train]) & set(data.trajectory[test]), "random samples share trajectories"
    held = data.indenter_names[data.indenter[0]]
    train, test = split(data, f"indenter:{held}")
    assert (data.indenter[test] == data.indenter[0]).all() and (data.indenter[train] != data.indenter[0]).all()
    with pytest.raises(ValueError, match="unknown split"):
        split(data, "random")
    with pytest.raises(ValueError, match="unknown indenter"):
        split(data, "indenter:spoon")


def test_concatenate_keeps_trajectories_apart(campaign: Path) -> None:
    a = load(campaign)
    both = concatenate([a, a])
    assert len(both) == 2 * len(a)
    assert len(np.unique(both.trajectory)) == 2 * len(np.unique(a.trajectory))


def test_paper_metrics_on_known_errors() -> None:
    true = {"contact_loc": np.zeros((4, 3)), "force": np.tile([0.0, 0.0, 2.0], (4, 1)), "nodal": np.zeros((4, 2, 3))}
    pred = {
        "contact_loc": np.array([[1e-3, 0, 0], [0, 2e-3, 0], [0, 0, 3e-3], [0, 0, 10e-3]]),
        "force": np.array([[0.0, 0.0, 3.0], [2.0, 0.0, 0.0], [0.0, 0.0, 2.0], [0.0, 0.0, 1.0]]),
        "nodal": np.full((4, 2, 3), 1e-3 / np.sqrt(3.0)),
    }
    m = paper_metrics(pred, true)
    assert m["contact_loc_mean_mm"] == pytest.approx(4.0) and m["contact_loc_median_mm"] == pytest.approx(2.5)
    assert m["force_magnitude_median_N"] == pytest.approx(0.5)
    assert m["force_angle_mean_rad"] == pytest.approx(np.pi / 8) and m["force_angle_median_rad"] == pytest.approx(0.0)
    assert m["nodal_mean_mm"] == pytest.approx(1.0)
    small = paper_metrics({"force": np.ones((1, 3))}, {"force": np.full((1, 3), 0.1 * ANGLE_MIN_FORCE)})
    assert np.isnan(small["force_angle_mean_rad"]), "angles of near-zero forces are not scored"
