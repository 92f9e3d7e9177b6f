"""The batched campaign's pipeline by sensor (`twin.campaign_batched.BatchedRunner`, `twin.lanes`), with its three
stages replaced by recorders (no simulation, no fe): the fe of every sensor runs as one batch, the largest sensor
first, each trajectory with its sensor's skin; it starts while the other sensors' schedules are still being
recorded; every part is reported once; a worker's exception ends the campaign with its own message and stops the
workers. (That the pipelined campaign writes the same files is tests/test_campaign_batched.py's.)"""

import threading
from collections.abc import Callable, Iterator, Sequence
from pathlib import Path
from types import SimpleNamespace
from typing import Any

import numpy as np
import pytest

import twin.campaign_batched as campaign_batched
from twin.campaign_batched import BatchedRunner, SolveSchedule, fe_order
from twin.executors import Executor
from twin.lanes import FirstFailure, Lane

SENSOR_SIZES = {1: 1, 2: 3, 3: 2}
"""Trajectories per sensor of the fake campaign."""
WAIT_S = 10.0
"""Longest a fake stage waits for another (s): a pipeline that does not overlap them fails instead of hanging."""


class InThisProcess(Executor):
    """Runs each task here when its result is asked for; remembers being cancelled."""

    def __init__(self) -> None:
        self.cancelled = False

    def map_unordered(
        self, task: Callable[..., Any], jobs: Sequence[tuple], setup: Callable[..., None], setup_args: tuple
    ) -> Iterator[Any]:
        for job in jobs:
            yield task(*job)

    def cancel(self) -> None:
        self.cancelled = True


class FakeStages:
    """Records what each stage was asked to do, in order; the schedules of the last sensor in fe order wait for
    the first fe batch to start, and the batch's second trajectory waits for the first one's part to be synthesised."""

    def __init__(self, failing: tuple[int, int] | None = None) -> None:
        self.events: list[tuple] = []
        self.first_batch, self.first_part = threading.Event(), threading.Event()
        self.overlapped: list[bool] = []
        self.synthesis_overlapped: list[bool] = []
        self.failing = failing
        self.last_sensor = fe_order(_tasks(Path(".")))[-1]

    def plan_schedule(self, job: Any, slot: int, registration: np.ndarray, parts_dir: str) -> tuple:
        if job.sensor_id == self.last_sensor:
            self.overlapped.append(self.first_batch.wait(WAIT_S))
        self.events.append(("schedule", job.sensor_id))
        one_solve = SolveSchedule("sphere_medium", np.array([slot + 0.5]), np.eye(3)[None], np.zeros((1, 3)))
        return (job.sensor_id, job.spec.trajectory_id), one_solve

    def run_trajectories(self, skins: list, poses: Any, device: str, slots: int, limit: float, on_trajectory) -> None:
        self.events.append(("fe batch", list(skins)))
        self.first_batch.set()
        for index in range(len(poses)):
            assert len(poses[index].rotations) == 1  # read as the runner reads it: waits for its schedule
            if index == 1:  # the first sensor's second trajectory: the first one is solved, not its sensor
                self.synthesis_overlapped.append(self.first_part.wait(WAIT_S))
            job = poses.task(index)[0]
            self.events.append(("fe", (job.sensor_id, job.spec.trajectory_id)))
            on_trajectory(index, [])

    def synthesise_part(self, job: Any, slot: int, registration: np.ndarray, parts_dir: str) -> tuple:
        key = (job.sensor_id, job.spec.trajectory_id)
        if key == self.failing:
            raise ValueError(f"sensor {key[0]} trajectory {key[1]}: the worker's own message")
        self.events.append(("synthesis", key))
        self.first_part.set()
        return key, True


def _tasks(parts_dir: Path) -> list[tuple]:
    """The fake campaign's trajectory tasks, sensor by sensor in id order."""
    tasks = []
    for sid, count in SENSOR_SIZES.items():
        for tid in range(count):
            job = SimpleNamespace(sensor_id=sid, spec=SimpleNamespace(trajectory_id=10 * sid + tid))
            tasks.append((job, tid, np.eye(4), str(parts_dir)))
    return tasks


@pytest.fixture
def stages(monkeypatch: pytest.MonkeyPatch) -> Callable[..., FakeStages]:
    def install(failing: tuple[int, int] | None = None) -> FakeStages:
        fake = FakeStages(failing)
        monkeypatch.setattr(campaign_batched, "plan_schedule", fake.plan_schedule)
        monkeypatch.setattr(campaign_batched, "run_trajectories", fake.run_trajectories)
        monkeypatch.setattr(campaign_batched, "synthesise_part", fake.synthesise_part)
        sensors = {sid: (SimpleNamespace(inflated_skin=lambda sid=sid: sid), None) for sid in SENSOR_SIZES}
        worker = SimpleNamespace(sensor=sensors.__getitem__)
        monkeypatch.setattr(campaign_batched, "CampaignWorker", lambda config, plant: worker)
        return fake

    return install


CONFIG = SimpleNamespace(settings=SimpleNamespace(force_limit=1.0))


def test_the_sensors_are_solved_largest_first_while_the_others_are_still_planned(
    stages: Callable[..., FakeStages], tmp_path: Path
) -> None:
    fake = stages()
    finished: list[tuple[int, int, bool]] = []
    lock = threading.Lock()

    def record(sid: int, tid: int, complete: bool) -> None:
        with lock:
            finished.append((sid, tid, complete))

    BatchedRunner("cpu")(_tasks(tmp_path), CONFIG, None, InThisProcess(), record)
    assert fe_order(_tasks(tmp_path)) == [2, 3, 1]
    batches = [e[1] for e in fake.events if e[0] == "fe batch"]
    assert batches == [[2, 2, 2, 3, 3, 1]]  # one batch of every trajectory (its skin is its sensor's), largest first
    assert fake.overlapped == [True]  # sensor 1's schedule was recorded after the fe had started
    started = next(k for k, e in enumerate(fake.events) if e[0] == "fe batch")
    assert ("schedule", 1) in fake.events[started:]
    assert fake.synthesis_overlapped == [True]  # a trajectory's part is synthesised while its sensor's fe still runs
    solved = [e[1] for e in fake.events if e[0] == "fe"]
    assert [key[0] for key in solved] == [2, 2, 2, 3, 3, 1]
    for key in solved:  # each trajectory is synthesised once, after its fe
        assert [e for e in fake.events if e[0] == "synthesis"].count(("synthesis", key)) == 1
        assert fake.events.index(("synthesis", key)) > fake.events.index(("fe", key))
    expected = sorted((t[0].sensor_id, t[0].spec.trajectory_id, True) for t in _tasks(tmp_path))
    assert sorted(finished) == expected


def test_a_worker_failure_ends_the_campaign_with_its_message_and_stops_the_workers(
    stages: Callable[..., FakeStages], tmp_path: Path
) -> None:
    stages(failing=(2, 21))
    executor = InThisProcess()
    with pytest.raises(ValueError, match=r"^sensor 2 trajectory 21: the worker's own message$"):
        BatchedRunner("cpu")(_tasks(tmp_path), CONFIG, None, executor, lambda *done: None)
    assert executor.cancelled


def test_a_lane_keeps_the_first_failure_and_runs_nothing_after_it() -> None:
    failure, ran = FirstFailure(), []

    def fail(message: str) -> None:
        raise RuntimeError(message)

    lane = Lane("test", failure)
    lane.submit(lambda: ran.append(1))
    lane.submit(lambda: fail("first"))
    lane.submit(lambda: ran.append(2))
    with pytest.raises(RuntimeError, match="^first$"):
        lane.join()
    other = Lane("other", failure)  # a lane of the same campaign, after the failure
    other.submit(lambda: ran.append(3))
    other.submit(lambda: fail("second"))
    with pytest.raises(RuntimeError, match="^first$"):
        other.join()
    assert ran == [1]
