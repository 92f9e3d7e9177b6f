"""Quick simulated campaigns: the CLI contracts, the HDF5 layout, and kill-and-resume equality."""

import json
import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import h5py
import numpy as np
import pytest
from typer.testing import CliRunner

from assets.indenters import INDENTERS
from twin.cli import app

runner = CliRunner()
SUBSAMPLED = (
    "electrode_vals",
    "pdc",
    "force",
    "contact_loc",
    "indenter_type",
    "trajectory_id",
    "depth",
    "joint_angles",
)


@pytest.fixture(scope="module")
def quick_campaign(tmp_path_factory: pytest.TempPathFactory) -> Path:
    out = tmp_path_factory.mktemp("quick")
    result = runner.invoke(app, ["campaign", "run", "--quick", "--out", str(out), "--workers", "2"])
    assert result.exit_code == 0, result.output
    return out


def test_quick_three_sensor_campaign_writes_the_documented_features(quick_campaign: Path) -> None:
    files = sorted(quick_campaign.glob("biotac*.hdf5"))
    assert [f.name for f in files] == ["biotac1.hdf5", "biotac2.hdf5", "biotac3.hdf5"]
    for path in files:
        with h5py.File(path, "r") as f:
            n = f["force/data"].shape[0]
            assert n > 0
            for name in SUBSAMPLED:
                assert f[f"{name}/data"].shape[0] == n, name
            assert f["electrode_vals/data"].shape == (n, 19)
            assert f["joint_angles/data"].shape == (n, 7)
            assert f["force/data"].attrs["units"] == "N" and f["force/data"].attrs["frame"] == "biotac"
            names = json.loads(f.attrs["indenter_names"])
            used = {names[k] for k in np.unique(f["indenter_type/data"][:])}
            expected = (
                {"sphere_small", "sphere_medium", "sphere_large"} if path.name == "biotac1.hdf5" else set(INDENTERS)
            )
            assert used <= expected
            # every trajectory's rows are where its metadata says, and its raw recording is kept
            traj = f["trajectories"]
            ids = f["trajectory_id/data"][:]
            for tid, first, count in zip(
                traj["trajectory_id"][:], traj["first_row"][:], traj["n_rows"][:], strict=True
            ):
                assert np.all(ids[first : first + count] == tid)
                assert f[f"raw/{tid}/time"].shape[0] >= count
            # physics sanity: deeper loading rows push harder into the pad (+z force on the skin side)
            force = f["force/data"][:]
            assert np.isfinite(force).all()
            assert np.abs(force).max() > 0.1


def test_quick_campaign_covers_all_nine_indenters(quick_campaign: Path) -> None:
    used = set()
    for path in quick_campaign.glob("biotac*.hdf5"):
        with h5py.File(path, "r") as f:
            names = json.loads(f.attrs["indenter_names"])
            used |= {names[k] for k in np.unique(f["indenter_type/data"][:])}
    assert used == set(INDENTERS)


def test_dataset_info_json(quick_campaign: Path) -> None:
    result = runner.invoke(app, ["dataset", "info", str(quick_campaign / "biotac2.hdf5"), "--json"])
    assert result.exit_code == 0, result.output
    info = json.loads(result.stdout.strip().splitlines()[-1])
    assert info["features"]["electrode_vals"]["shape"][1] == 19
    assert info["features"]["force"]["units"] == "N"
    assert info["trajectories"]["total"] >= 1
    assert info["attributes"]["schema_version"] == 1


def test_dataset_info_rejects_a_non_hdf5_file(tmp_path: Path) -> None:
    bogus = tmp_path / "x.hdf5"
    bogus.write_text("not hdf5")
    result = runner.invoke(app, ["dataset", "info", str(bogus)])
    assert result.exit_code == 2
    assert "not an HDF5 file" in result.output


def _read_all(path: Path) -> dict[str, np.ndarray]:
    arrays: dict[str, np.ndarray] = {}
    with h5py.File(path, "r") as f:
        f.visititems(lambda name, item: arrays.__setitem__(name, item[()]) if isinstance(item, h5py.Dataset) else None)
    return arrays


def test_killed_and_resumed_campaign_equals_an_uninterrupted_one(tmp_path: Path) -> None:
    args = ["campaign", "run", "--quick", "--sensors", "2", "--indenters", "sphere_medium,cylinder_short_small"]
    whole = tmp_path / "whole"
    assert runner.invoke(app, [*args, "--out", str(whole), "--workers", "1"]).exit_code == 0
    cut = tmp_path / "cut"
    command = [sys.executable, "-m", "twin", *args, "--out", str(cut), "--workers", "1"]
    process = subprocess.Popen(command, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL, start_new_session=True)
    deadline = time.time() + 300
    while time.time() < deadline and not list((cut / "parts").rglob("*.npz")):
        time.sleep(0.2)
    os.killpg(process.pid, signal.SIGKILL)
    process.wait()
    parts = list((cut / "parts").rglob("*.npz"))
    assert 1 <= len(parts) < 4, "the kill should land mid-campaign"
    assert not (cut / "biotac2.hdf5").exists()
    resumed = runner.invoke(app, [*args, "--out", str(cut), "--workers", "1"])
    assert resumed.exit_code == 0, resumed.output
    a, b = _read_all(whole / "biotac2.hdf5"), _read_all(cut / "biotac2.hdf5")
    assert a.keys() == b.keys()
    for key in a:
        np.testing.assert_array_equal(a[key], b[key], err_msg=key)
