"""What the campaign's protocol passes save changes nothing: a reset testbed scene is a new scene (model and
data, bit for bit); a trajectory simulated on a worker whose scene another trajectory used is recorded
exactly as on a worker of its own; a campaign planned on a pool's workers (the pool that runs it next) is the
plan made in one process; a schedule pass without electrode counts draws the same noise stream, so its
schedule and every other reading are those of a pass with them."""

from dataclasses import fields, replace

import numpy as np
import pytest

from twin.backend import ARMS
from twin.campaign import QUICK_CONFIG, CampaignPlan, CampaignWorker, plan_campaign, simulate_trajectory
from twin.campaign_batched import ScheduleRecorder
from twin.controller import Recording
from twin.executors import LocalExecutor
from twin.planning import PlannedTrajectory
from twin.plant import Plant, make_plant
from twin.protocol import QUICK_SETTINGS
from twin.scene import TestbedScene

CONFIG = replace(
    QUICK_CONFIG,
    sensors=(2,),
    indenters=("sphere_medium",),
    settings=replace(QUICK_SETTINGS, normal_depth=0.4e-3, angled_depth=0.2e-3, pause_s=0.1),
)
"""Two short trajectories (one normal, one angled) on one sensor, 2 mm mesh."""


def _state(scene: TestbedScene) -> dict[str, np.ndarray]:
    """Every model field a tool changes and every data field the kinematics fill, plus the tool poses."""
    model, data = scene.model, scene.data
    state = {
        name: np.array(getattr(model, name))
        for name in ("geom_contype", "geom_conaffinity", "geom_rgba", "site_pos", "site_quat")
    }
    state |= {name: np.array(getattr(data, name)) for name in ("qpos", "xpos", "xmat", "site_xpos", "site_xmat")}
    for arm in ARMS:
        state[f"{arm}_tool_pose"] = scene.tool_pose(arm)
        state[f"{arm}_tool"] = np.asarray(str(scene.tool(arm)))
    return state


def test_a_reset_scene_is_a_new_scene() -> None:
    used = TestbedScene(QUICK_CONFIG.scene)
    for arm, tool in zip(ARMS, ("sphere_medium", "pin"), strict=True):
        used.attach_tool(arm, tool)
        used.set_joints(arm, used.home_joints(arm) + 0.05)
    dirty = _state(used)
    used.reset()
    fresh = _state(TestbedScene(QUICK_CONFIG.scene))
    assert any(not np.array_equal(dirty[k], fresh[k]) for k in fresh)  # the use did change the scene
    for key, expected in fresh.items():
        np.testing.assert_array_equal(_state(used)[key], expected, err_msg=key)


@pytest.fixture(scope="module")
def plan() -> tuple[Plant, CampaignPlan]:
    plant = make_plant([2], 0)
    return plant, plan_campaign(CONFIG, plant)


@pytest.fixture(scope="module")
def planned(plan: tuple[Plant, CampaignPlan]) -> tuple[Plant, list[PlannedTrajectory]]:
    plant, made = plan
    jobs = [job for job in made.planned if job.kept]
    assert len(jobs) == 2
    return plant, jobs


def test_a_campaign_planned_on_workers_is_the_plan_made_here(plan: tuple[Plant, CampaignPlan]) -> None:
    plant, here = plan
    with LocalExecutor(2) as executor:
        there = plan_campaign(CONFIG, plant, executor)
    assert len(there.planned) == len(here.planned) >= 2
    for a, b in zip(here.planned, there.planned, strict=True):
        assert (a.sensor_id, a.arm, a.dropped) == (b.sensor_id, b.arm, b.dropped)
        np.testing.assert_array_equal(a.joint_path, b.joint_path)
        for field in fields(a.spec):
            np.testing.assert_array_equal(getattr(a.spec, field.name), getattr(b.spec, field.name), err_msg=field.name)
    assert here.registration.keys() == there.registration.keys()
    for key, transform in here.registration.items():
        np.testing.assert_array_equal(there.registration[key], transform)


def _record(
    worker: CampaignWorker, job: PlannedTrajectory, slot: int, electrode_counts: bool = True
) -> tuple[Recording, list, dict]:
    """The recording, the schedules and the final noise-stream state of a schedule pass over `job`."""
    recorders: list[ScheduleRecorder] = []

    def recorder(indenter: str) -> ScheduleRecorder:
        recorders.append(ScheduleRecorder(worker.sensor(job.sensor_id)[0], indenter))
        return recorders[-1]

    backend, recording = simulate_trajectory(worker, job, slot, recorder, electrode_counts)
    return recording, [r.schedule() for r in recorders], backend.rng.bit_generator.state


def test_a_trajectory_on_a_reused_testbed_is_recorded_as_on_a_new_one(
    planned: tuple[Plant, list[PlannedTrajectory]],
) -> None:
    plant, jobs = planned
    reused = CampaignWorker(CONFIG, plant)
    _record(reused, jobs[0], 0)  # the worker's scene now carries the first trajectory's tool and joints
    again, again_schedules, _ = _record(reused, jobs[1], 1)
    alone, alone_schedules, _ = _record(CampaignWorker(CONFIG, plant), jobs[1], 1)
    assert len(alone.time) > 100 and alone.complete
    for name in ("time", "joints", "wrench", "electrodes", "pdc", "depth_command", "increment"):
        np.testing.assert_array_equal(getattr(again, name), getattr(alone, name), err_msg=name)
    assert len(again_schedules) == len(alone_schedules) == 1
    assert again_schedules[0].same_as(alone_schedules[0]) and len(alone_schedules[0].times) > 3


def test_a_schedule_pass_without_electrode_counts_draws_the_same_noise(
    planned: tuple[Plant, list[PlannedTrajectory]],
) -> None:
    plant, jobs = planned
    worker = CampaignWorker(CONFIG, plant)
    full, full_schedules, full_stream = _record(worker, jobs[0], 0)
    bare, bare_schedules, bare_stream = _record(worker, jobs[0], 0, electrode_counts=False)
    assert bare_stream == full_stream  # as many draws, so the same stream after every reading
    for name in ("time", "joints", "wrench", "depth_command", "increment"):
        np.testing.assert_array_equal(getattr(bare, name), getattr(full, name), err_msg=name)
    assert np.isnan(bare.electrodes).all() and np.isnan(bare.pdc).all()
    assert np.isfinite(full.electrodes).all() and np.ptp(full.electrodes[:, 0]) > 0  # noisy counts
    assert bare_schedules[0].same_as(full_schedules[0])


def test_a_trajectory_error_names_its_trajectory() -> None:
    from types import SimpleNamespace

    from twin.campaign import naming_trajectory

    job = SimpleNamespace(sensor_id=2, spec=SimpleNamespace(trajectory_id=17))
    with pytest.raises(ValueError, match=r"^sensor 2 trajectory 17: the recording is empty$"):
        with naming_trajectory(job):
            raise ValueError("the recording is empty")
    with pytest.raises(RuntimeError, match=r"^a skin fault$"):  # only bad-input errors are renamed
        with naming_trajectory(job):
            raise RuntimeError("a skin fault")
