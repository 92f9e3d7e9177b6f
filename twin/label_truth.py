"""Where the indenter tip of a simulated campaign row really was (simulation only; issue 19).

A row's `contact_loc` is what the testbed can know, as in the paper: forward kinematics of the joint
readings through the *estimated* registration. The simulated plant moved the real arm (readings + its
joint zero offsets) against the *true* BioTac pose, so the true tip in the BioTac's own frame differs by
the registration error. `true_tip_locations` recomputes it from the plant the file was made with
(`make_plant(sensors, seed)` of the file's provenance); it first re-runs that plant's registration and
refuses a file whose stored registration it does not reproduce (another plant made it).
"""

from __future__ import annotations

import json
from pathlib import Path

import h5py
import numpy as np

from twin.backend import ARMS
from twin.campaign import CampaignConfig, campaign_registration, true_biotac_pose
from twin.kinematics import forward
from twin.plant import Plant, make_plant
from twin.scene import SceneParameters, TestbedScene

REPRODUCED = 1e-9
"""Largest difference between the stored and the re-run registration transform (m and rotation entries)."""


def file_plant(path: str | Path, scene: SceneParameters | None = None) -> tuple[Plant, int, TestbedScene]:
    """(plant, sensor id, scene) that made a one-sensor campaign file, checked by re-running its registration.

    scene: the campaign's scene parameters (default `CampaignConfig().scene`, the campaign default).
    """
    with h5py.File(path, "r") as f:
        provenance = json.loads(f.attrs["provenance"])
        sensor_id = int(f.attrs["sensor_id"])
    config = provenance["config"]
    plant = make_plant(list(config["sensors"]), int(config["seed"]))
    testbed = TestbedScene(scene if scene is not None else CampaignConfig().scene)
    for arm in ARMS:  # as twin.campaign.plan_campaign registered it
        result = campaign_registration(plant, sensor_id, arm, testbed, int(config["seed"]))
        stored = np.asarray(provenance["registration"][arm])
        if np.abs(result.transform - stored).max() > REPRODUCED:
            raise ValueError(f"{path}: the plant make_plant({config['sensors']}, {config['seed']}) does not "
                             f"reproduce the file's {arm} registration; another plant made this file")  # fmt: skip
    return plant, sensor_id, testbed


def true_tip_locations(
    path: str | Path, scene: SceneParameters | None = None, plant: Plant | None = None
) -> np.ndarray:
    """(N, 3) m: each row's true indenter tip in the true BioTac frame (the label `contact_loc` is the
    estimate through the registration). Rows in file order; uses `joint_angles` and the trajectories'
    arm and tool tip. plant: the plant that made the file when known (else `file_plant` rebuilds it)."""
    if plant is None:
        plant, sensor_id, testbed = file_plant(path, scene)
    else:
        with h5py.File(path, "r") as f:
            sensor_id = int(f.attrs["sensor_id"])
        testbed = TestbedScene(scene if scene is not None else CampaignConfig().scene)
    to_biotac = np.linalg.inv(true_biotac_pose(plant, sensor_id, testbed))
    with h5py.File(path, "r") as f:
        joints, row_trajectory = f["joint_angles/data"][:], f["trajectory_id/data"][:]
        ids, arms, tools = (f[f"trajectories/{k}"][:] for k in ("trajectory_id", "arm", "tool_tip"))
    index = {int(t): k for k, t in enumerate(ids)}
    tips = np.empty((len(joints), 3))
    for row, (q, t) in enumerate(zip(joints, row_trajectory, strict=True)):
        k = index[int(t)]
        arm = ARMS[int(arms[k])]
        tips[row] = forward(arm, q + plant.joint_offset(arm), tools[k])[:3, 3]
    return tips @ to_biotac[:3, :3].T + to_biotac[:3, 3]
