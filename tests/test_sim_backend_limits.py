"""The simulated arm at its joint stops (session 31): a joint whose zero offset carries it past its range stops at
its hard stop, and its encoder with it, so the readings say where the arm really is (reading + offset = the true
joint) and a target past the stop is never reached. Before, the true joint was clipped while the reading ran on: data
whose kinematics no analysis could follow (a realistic plant's press, 4 mrad past a limit, left 3.9x the noise at the
plant's own values)."""

import numpy as np
import pytest

from assets.biotac import make_biotac
from twin.backend import BackendError
from twin.campaign import CampaignConfig, plant_sensor_models, true_biotac_pose
from twin.controller import move_to
from twin.kinematics import joint_limits
from twin.plant import make_plant
from twin.scene import TestbedScene
from twin.sim_backend import SimBackend

OFFSET = -5e-3
"""rad: the left arm's second joint's zero offset (the true joint is the reading plus it)."""
PAST = 1e-3
"""rad: how far inside its range (in readings) the joint is commanded: past the true stop by |OFFSET| - PAST."""
ENCODER_SIGMAS = 6.0


def test_a_joint_past_its_stop_stops_there_and_its_reading_with_it() -> None:
    plant = make_plant([2], 0)
    scene = TestbedScene(CampaignConfig().scene)
    model, electrodes = plant_sensor_models(plant, 2, make_biotac(2e-3))
    offsets = {"left": np.array([0.0, OFFSET, 0.0, 0.0, 0.0, 0.0, 0.0]), "right": np.zeros(7)}
    rng = np.random.default_rng(0)
    noise = plant.noise
    backend = SimBackend(
        scene, true_biotac_pose(plant, 2, scene), plant.sensor(2), model, electrodes, noise, rng, joint_offsets=offsets
    )
    lower = joint_limits("left")[1, 0]
    target = backend.read().joints["left"].copy()
    target[1] = lower + PAST  # inside the range the controller accepts, past where the true joint stops
    with pytest.raises(BackendError, match="did not reach"):
        move_to(backend, "left", target, 1e-3, timeout=5.0)
    assert scene.joints("left")[1] == pytest.approx(lower, abs=1e-9)  # the true joint at its stop
    reading = backend.read().joints["left"][1]
    assert reading == pytest.approx(lower - OFFSET, abs=ENCODER_SIGMAS * noise.encoder + 1e-9)  # and its encoder
    assert reading - target[1] > abs(OFFSET) - PAST - ENCODER_SIGMAS * noise.encoder  # short of the target
