"""What a simulated campaign file gives away (issue 24): it records what the registration procedure
estimated, never the plant's truth, and marks the plant's own fe view as simulation-only, which the
analysis never reads."""

import json
from dataclasses import replace
from pathlib import Path

import h5py
import numpy as np
from fake_campaign import write_fake_campaign
from measurement import strip_plant_view
from typer.testing import CliRunner

from twin.analysis.data import load_campaign
from twin.campaign import QUICK_CONFIG, plan_campaign, true_biotac_pose
from twin.cli import app
from twin.dataset import SIMULATION_ONLY
from twin.plant import make_plant
from twin.scene import TestbedScene

runner = CliRunner()
PLANT_VIEW = ("fe_force", "fe_pressure", "fe_converged", "nodal_res")


def test_a_hidden_registration_offset_is_not_in_the_recorded_registration_but_moves_the_tip() -> None:
    offset = np.array([0.4e-3, -0.2e-3, 0.3e-3])
    plant = make_plant(
        [2],
        0,
        variability=0.0,
        mount_rotation_error=0.0,
        mount_translation_error=0.0,
        effects={"registration_offset": dict(zip(("dx", "dy", "dz"), offset, strict=True))},
        exact_registration=True,
    )
    config = replace(QUICK_CONFIG, sensors=(2,), indenters=("sphere_small",))
    plan = plan_campaign(config, plant)
    scene = TestbedScene(config.scene)
    point = np.array([-5e-3, 2e-3, -8e-3, 1.0])
    for arm in ("left", "right"):
        recorded = plan.registration[(2, arm)]
        # exact registration of a mount where it should be: the estimate is the nominal pose, whatever is hidden
        np.testing.assert_allclose(recorded, scene.biotac_pose, atol=1e-9)
        # yet the tip sent to a point by the recorded registration reaches it shifted by the hidden offset
        reached = np.linalg.inv(true_biotac_pose(plant, 2, scene)) @ recorded @ point
        np.testing.assert_allclose(reached[:3], point[:3] + offset, atol=1e-9)


def test_the_plants_fe_view_is_marked_simulation_only_and_dataset_info_says_so(tmp_path: Path) -> None:
    path = write_fake_campaign(tmp_path)
    assert set(PLANT_VIEW) | {"mesh"} == set(SIMULATION_ONLY)
    with h5py.File(path, "r") as f:
        for name in PLANT_VIEW:
            assert f[f"{name}/data"].attrs["simulation_only"], name
        assert f["mesh"].attrs["simulation_only"]
        assert "simulation_only" not in f["force/data"].attrs
    info = runner.invoke(app, ["dataset", "info", str(path), "--json"])
    assert info.exit_code == 0, info.output
    parsed = json.loads(info.stdout)
    assert {n for n, v in parsed["features"].items() if v["simulation_only"]} == set(PLANT_VIEW)
    assert set(parsed["simulation_only"]) == set(PLANT_VIEW) | {"mesh"}
    text = runner.invoke(app, ["dataset", "info", str(path)], env={"COLUMNS": "300"})
    assert text.exit_code == 0 and "simulation only" in text.output and "nodal_res" in text.output


def test_the_analysis_reads_the_same_data_without_the_plants_fe_view(tmp_path: Path) -> None:
    path = write_fake_campaign(tmp_path)
    stripped = strip_plant_view(path, tmp_path / "stripped.hdf5")
    with h5py.File(stripped, "r") as f:
        assert not set(SIMULATION_ONLY) & set(f)
    full, bare = load_campaign(path), load_campaign(stripped)
    assert len(full.trajectories) == len(bare.trajectories) > 0
    for a, b in zip(full.trajectories, bare.trajectories, strict=True):
        assert a.rows.keys() == b.rows.keys()
        for key in a.rows:
            np.testing.assert_array_equal(a.rows[key], b.rows[key], err_msg=key)
        np.testing.assert_array_equal(a.raw.wrench, b.raw.wrench)
        np.testing.assert_array_equal(a.registration, b.registration)
