"""TwinSources: the twin's readings follow the arms (contact loads the sensor, lifting off unloads it),
the streams never wait for a solve, and a failed solve is reported once and recovered from."""

import threading
import time
from dataclasses import replace

import numpy as np
import pytest

from hardware.testbed import driven_testbed
from twin.campaign import QUICK_CONFIG, plan_campaign
from twin.loopback_rig import TwinSources
from twin.planning import PlannedTrajectory
from twin.plant import make_plant

CONFIG = replace(QUICK_CONFIG, sensors=(1,), indenters=("sphere_medium",), mesh_max_edge=3e-3)
TRAVEL_S = 3.0  # s: long enough for an arm to go from home to the BioTac at its velocity limits


@pytest.fixture(scope="module")
def job() -> PlannedTrajectory:
    """The normal path of the quick plan: standoff, 0 .. 1 mm deep and back (registration without joint
    zero offsets, good to ~0.1 mm, so the path does press 1 mm into the twin below)."""
    plan = plan_campaign(CONFIG, make_plant([1], CONFIG.seed, joint_offset_std=0.0))
    return next(j for j in plan.planned if j.kept and j.spec.angle == 0)


@pytest.fixture(scope="module")
def template() -> TwinSources:
    return TwinSources.for_campaign(CONFIG, 1, "sphere_medium")


@pytest.fixture
def twin(template: TwinSources) -> TwinSources:
    """A fresh twin (new SimBackend and skin state, arms without zero offsets) around the module's models."""
    b = template.backend
    backend = type(b)(
        b.scene, b.true_biotac_pose, b.sensor, b.fe_model, b.electrodes, b.noise, b.rng, effects=b.effects
    )
    return TwinSources(backend, template.indenter)


def _joints(twin: TwinSources, job: PlannedTrajectory, k: int | None) -> dict[str, np.ndarray]:
    """Both arms at home, except `job.arm` at path index k (None: home too)."""
    joints = twin.home_joints()
    if k is not None:
        joints[job.arm] = job.joint_path[k]
    return joints


def test_pressing_loads_the_sensor_and_lifting_off_unloads_it(twin: TwinSources, job: PlannedTrajectory) -> None:
    rest_force = twin.wrench()[:3]
    rest_pdc = twin.electrodes()[1]
    twin.step(_joints(twin, job, 0), TRAVEL_S)  # the standoff: out of contact, nothing to solve
    assert twin.solves and not any(solve.contact for solve in twin.solves)
    deepest = int(np.argmax(job.spec.depths))
    for k in range(1, deepest + 1):  # touch, then 0.1 mm increments to 1 mm: a solve each
        twin.step(_joints(twin, job, k), 0.01)
    assert _contact_solves(twin) >= deepest - 1  # touching at depth 0 may not count as contact
    pressed_force, pressed = twin.wrench()[:3], twin.electrodes()
    assert np.linalg.norm(pressed_force - rest_force) > 0.5  # N, far above the 0.01 N noise
    assert pressed[1] > rest_pdc + 10  # the fluid pressure rises (counts, noise 1)
    twin.step(_joints(twin, job, 0), 0.01)  # back off: the skin is released
    assert np.linalg.norm(twin.wrench()[:3] - rest_force) < 0.1
    assert twin.failures == []


def test_the_twin_is_the_plant_sensor_of_the_campaign(template: TwinSources) -> None:
    plant = make_plant(list(CONFIG.sensors), CONFIG.seed)
    backend = template.backend
    truth = plant.sensor(1)
    assert backend.sensor.skin == truth.skin
    for name in ("mount_error", "ft_bias"):
        np.testing.assert_array_equal(getattr(backend.sensor, name), getattr(truth, name))
    np.testing.assert_array_equal(backend.electrodes.params.gain, truth.electrodes.gain)
    for arm in ("left", "right"):  # the true arm is at reading + offset, as in the simulated campaign
        assert np.any(plant.joint_offset(arm) != 0)
        np.testing.assert_array_equal(backend.joint_offsets[arm], plant.joint_offset(arm))
    assert backend.effects == plant.effects and backend.noise == plant.noise


def test_sources_return_copies_and_the_clock_follows_wall_time(twin: TwinSources) -> None:
    wrench = twin.wrench()
    wrench[:] = 1e9
    assert np.all(np.abs(twin.wrench()) < 100)
    with driven_testbed(twin, rws_port=0, kms40_port=0, egm_ports=(0, 0), biotac_port=0) as testbed:
        assert np.array_equal(testbed.arms["left"].joints, twin.home_joints()["left"])
        time.sleep(0.5)
        assert twin.stats["polls"] > 10
        assert abs(twin.backend.time_s - (time.monotonic() - twin.clock_origin)) < 0.1
    assert not any(t.name == "twin-sources" for t in threading.enumerate())  # closing the testbed stops it


def test_a_failed_solve_is_reported_once_and_the_skin_restarts_when_the_arm_moves_on(
    twin: TwinSources, job: PlannedTrajectory, monkeypatch: pytest.MonkeyPatch
) -> None:
    twin.step(_joints(twin, job, 0), TRAVEL_S)
    stuck = twin.backend._stepper  # the stepper of the indenting arm; refuses every step from now on

    def refuse(*args: object) -> None:
        raise RuntimeError("the last step did not converge (iteration limit)")

    monkeypatch.setattr(stuck, "step", refuse)
    held = twin.wrench()
    for _ in range(3):  # the arm stays at the pose where the solve failed
        twin.step(_joints(twin, job, 3), 0.01)
    assert len(twin.failures) == 1 and "iteration limit" in twin.failures[0]
    assert np.linalg.norm(twin.wrench()[:3] - held[:3]) < 0.1  # the last good state holds (plus noise)
    twin.step(_joints(twin, job, 4), 0.01)  # the arm moves on: a fresh skin, solved there
    assert twin.backend._stepper is not stuck
    assert _contact_solves(twin) == 1 and len(twin.failures) == 1
    assert np.linalg.norm(twin.wrench()[:3] - held[:3]) > 0.05


def _contact_solves(twin: TwinSources) -> int:
    return sum(solve.contact for solve in twin.solves)
