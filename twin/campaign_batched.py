"""The campaign with the fe of all its trajectories solved on the batched engine (`twin campaign run --device`).

The protocol is open loop but for the controller's force-limit stop, so what the fe has to solve is known
before anything is solved. `BatchedRunner` works in three passes:

1. schedules (on the executor's workers): each trajectory's protocol runs on the simulated testbed with a
   `ScheduleRecorder` as its skin, which notes the pose (indenter body -> biotac frame, m) and the time (s)
   of every solve the backend asks for (each increment's pose once the arm rests; with a viscoelastic skin
   the held pose every `twin.sim_backend.RELAXATION_SOLVE_INTERVAL_S` as well) and answers with the rest
   state; electrode and PDC counts are not computed (their noise is drawn: the stream stays the same);
2. fe (in this process, on the warp device): every schedule of every sensor is a timed `PoseTrajectory` of one
   batched run, with its sensor's skin (`fe.batched_runner.run_trajectories`: a slot takes the next trajectory
   whatever its sensor, each system on its own clock, failed steps cut back as
   the one-at-a-time stepper does), which ends a trajectory at its first increment that fails or whose
   indenter force exceeds `FE_FORCE_LIMIT_FACTOR` times the protocol's force limit; each trajectory's
   schedule and results are written to `parts/fe_solves` as it ends (so a resume skips its fe);
3. synthesis (on the executor's workers): the protocol runs again on a fresh testbed with the same noise
   stream and clock, a `ScheduleReplay` answering each solve with its batched result, so the controller (its
   force-limit stop included), noise, measurement effects, processing and part file are those of the
   one-at-a-time campaign (`twin.campaign.one_at_a_time`); they agree within the engine's tolerance (bit for
   bit on warp's CPU device, tests/test_campaign_batched.py). The solves are dropped once the part is written.

The passes overlap by sensor (`fe_order`: most trajectories first): every schedule is submitted to the workers at
once, the fe batch starts as soon as it has a schedule for every slot (`_Arriving`: the others are read as the
batch reaches them), each trajectory's synthesis runs on the workers soon after it is solved (`_Solved`)
while the batch goes on with the others, and `twin.campaign.run_campaign` writes a sensor's file as soon as
its last part is written. One batch for all sensors pays the nearly empty rounds at its end once, not once per sensor.

With `robot_compliance` in the plant, where the tip stands depends on the forces, which a schedule is recorded
without: the recorder's rest state deflects nothing, so a schedule holds the commanded tips. The fe pass solves
each pose where the one-at-a-time backend does (`SettledTips`, a `PoseTrajectory.settle`: the commanded tip
deflected by the force of the trajectory's last solve, then settled by solves at the same time, the same
`twin.sim_backend.ComplianceSettle` as `SimBackend`'s), and writes the solves it made, every tip with its time
repeated for the settle solves, along with the recorded schedule (which a resume compares); the synthesis replays
those. A settle that spends its `COMPLIANCE_SOLVES` unsettled goes on at the backend's next sample, which no
schedule holds: its synthesis leaves the schedule and the campaign stops with that error.

A trajectory whose controller goes on past where the batch stopped it (a measurement effect that hides more
than a third of the force) is solved again, without a force limit, in a second batch.
"""

from __future__ import annotations

import itertools
import queue
import threading
from collections import Counter
from collections.abc import Callable, Iterator, Sequence
from dataclasses import dataclass, fields
from pathlib import Path

import numpy as np

from fe.batched_runner import PoseTrajectory, run_trajectories
from fe.results import IncrementResult
from fe.sensor import BioTacModel
from twin.campaign import (
    CampaignConfig,
    CampaignWorker,
    Finished,
    TrajectoryTask,
    init_worker,
    naming_trajectory,
    process_worker,
    simulate_trajectory,
    write_trajectory_part,
)
from twin.dataset import read_part, write_part
from twin.effects import COMPLIANCE
from twin.executors import Executor
from twin.lanes import FirstFailure, Lane
from twin.planning import PlannedTrajectory
from twin.plant import Plant
from twin.sim_backend import ComplianceSettle, SimSettings

FE_FORCE_LIMIT_FACTOR = 1.5
"""The batch ends a trajectory once its fe force exceeds this many times the protocol's force limit (the
controller stops on the measured, noisy force; the margin keeps the solves it may still need)."""
OFF_SCHEDULE = "asked for a solve off the planned schedule"
"""What a `ScheduleReplay` says when the replayed protocol leaves the recorded one."""


@dataclass(frozen=True)
class SolveSchedule:
    """The fe solves one trajectory's protocol asks for, in order: indenter, times (S,) s on the trajectory's
    clock, rotations (S,3,3) indenter body -> biotac frame, tip positions (S,3) m (biotac frame)."""

    indenter: str
    times: np.ndarray
    rotations: np.ndarray
    translations: np.ndarray

    def poses(self, compliance: float | None = None) -> PoseTrajectory:
        """The schedule as a timed trajectory of the batched runner; on a robot of `compliance` (m/N), its tips
        settle where the loads put them (`SettledTips`)."""
        settle = None if compliance is None else SettledTips(self, compliance)
        return PoseTrajectory(self.indenter, self.rotations, self.translations, self.times, settle)

    def at(self, poses: np.ndarray, translations: np.ndarray) -> SolveSchedule:
        """Solves at the times and rotations of the schedule's poses `poses` (S,) (indices), with the tips at
        `translations` (S,3) m (biotac frame)."""
        return SolveSchedule(self.indenter, self.times[poses], self.rotations[poses], translations)

    def same_as(self, other: SolveSchedule) -> bool:
        """Whether `other` asks for exactly these solves (indenter, times, poses, bit for bit)."""
        return self.indenter == other.indenter and all(
            np.array_equal(getattr(self, name), getattr(other, name)) for name in ("times", "rotations", "translations")
        )


def _relaxes(model: BioTacModel) -> bool:
    """Whether the model's skin is viscoelastic (as `fe.indentation.IndentationStepper.relaxes`)."""
    return model.params.relaxation_fraction > 0.0


class ScheduleRecorder:
    """A `twin.sim_backend.SkinSolver` that solves nothing: it records each pose and time it is asked to solve
    and answers with the model's rest state (converged, no force), which the schedule does not depend on."""

    def __init__(self, model: BioTacModel, indenter: str) -> None:
        self.indenter = indenter
        self.relaxes = _relaxes(model)
        self._rest = IncrementResult(
            0.0, np.zeros(3), model.pressure, 0.0, 0.0, 0.0, np.zeros_like(model.reference), 0, 0.0, 0.0, True, "", 0.0
        )
        self._poses: list[tuple[float, np.ndarray, np.ndarray]] = []

    def step(self, rotation: np.ndarray, translation: np.ndarray, time_s: float | None = None) -> IncrementResult:
        """Record the pose (rotation (3,3), tip (3,) m) and time (s); return the rest state."""
        if time_s is None:
            raise ValueError("a campaign's solves are timed")
        self._poses.append((float(time_s), np.array(rotation, dtype=float), np.array(translation, dtype=float)))
        return self._rest

    def schedule(self) -> SolveSchedule:
        """The recorded solves."""
        times = np.array([p[0] for p in self._poses], dtype=float)
        rotations = np.array([p[1] for p in self._poses], dtype=float).reshape(-1, 3, 3)
        translations = np.array([p[2] for p in self._poses], dtype=float).reshape(-1, 3)
        return SolveSchedule(self.indenter, times, rotations, translations)


class SettledTips:
    """The `PoseTrajectory.settle` of a schedule on a plant of `compliance` (m/N): pose k is first solved at its
    recorded (commanded) tip deflected by the force of the trajectory's last solve, then again at the same time
    where `ComplianceSettle` moves the tip (as `twin.sim_backend.SimBackend` solves it, with its default
    `SimSettings`). Notes every tip it gives (m, biotac frame), in the order they are solved."""

    def __init__(self, schedule: SolveSchedule, compliance: float) -> None:
        self.schedule, self.compliance = schedule, compliance
        self._load = np.zeros(3)
        """The indenter's force (N) on the skin of the last solve (zero on the rest skin)."""
        self._settle: ComplianceSettle | None = None
        self._poses: list[int] = []
        self._tips: list[np.ndarray] = []

    def __call__(self, pose: int, result: IncrementResult | None) -> np.ndarray | None:
        """Pose `pose`'s first tip (`result` None), or its next tip after the converged `result` (None: settled)."""
        if result is None:
            self._settle = self._first(pose)
            tip = self._settle.tip
        else:
            self._load = np.array(result.force, dtype=float)
            tip = self._settle.next_tip(result.force)
        if tip is not None:
            self._poses.append(pose)
            self._tips.append(tip)
        return tip

    def solved(self) -> SolveSchedule:
        """The solves made (times repeated for the settle solves) and, where the run ended the trajectory before
        its last pose (its force limit), the first tip of the next pose, which a replay past the batch's end then
        asks for (`ScheduleExhausted`)."""
        poses, tips = list(self._poses), list(self._tips)
        if poses and poses[-1] + 1 < len(self.schedule.times):
            poses.append(poses[-1] + 1)
            tips.append(self._first(poses[-1]).tip)
        return self.schedule.at(np.array(poses, dtype=int), np.array(tips, dtype=float).reshape(-1, 3))

    def _first(self, pose: int) -> ComplianceSettle:
        """The settle of pose `pose` from its commanded tip, under the last solve's force."""
        commanded = self.schedule.translations[pose]
        return ComplianceSettle(commanded, self._load, self.compliance, SimSettings().pose_tolerance)


class ScheduleExhausted(Exception):
    """The replayed protocol asked for a solve past the one at which the batch stopped the trajectory at its
    fe force limit (not a RuntimeError: it must not pass for a skin fault)."""


class ScheduleReplay:
    """A `twin.sim_backend.SkinSolver` answering the k-th solve of a `SolveSchedule` with the k-th batched
    result. A solve off the schedule (a pose or time that differs) is refused with a RuntimeError saying
    `OFF_SCHEDULE` (the backend then reports a skin fault, which ends a retreat after a stop quietly and
    marks a bug otherwise); past the batch's end: after a failed increment the refusal of a stopped stepper,
    after a force-limit stop `ScheduleExhausted`."""

    def __init__(self, schedule: SolveSchedule, increments: list[IncrementResult], relaxes: bool) -> None:
        self.schedule, self.increments, self.relaxes = schedule, increments, relaxes
        self.solved = 0

    def step(self, rotation: np.ndarray, translation: np.ndarray, time_s: float | None = None) -> IncrementResult:
        """The batched result of the next scheduled solve, which must be at this pose and time."""
        k, schedule = self.solved, self.schedule
        if not (
            k < len(schedule.times)
            and time_s == schedule.times[k]
            and np.array_equal(rotation, schedule.rotations[k])
            and np.array_equal(translation, schedule.translations[k])
        ):
            raise RuntimeError(f"{OFF_SCHEDULE} (solve {k} at t = {time_s} s)")
        if k >= len(self.increments):
            if self.increments and not self.increments[-1].converged:
                raise RuntimeError(f"the last step did not converge ({self.increments[-1].message})")
            raise ScheduleExhausted(f"solve {k} of {len(schedule.times)} is past the batch's force-limit stop")
        self.solved += 1
        return self.increments[k]


def plan_schedule(
    job: PlannedTrajectory, slot: int, registration: np.ndarray, parts_dir: str
) -> tuple[tuple[int, int], SolveSchedule]:
    """Executor task (after `twin.campaign.init_worker`): the trajectory's (sensor id, trajectory id) and the
    fe solves its protocol asks for."""
    worker = process_worker()
    model = worker.sensor(job.sensor_id)[0]
    recorders: list[ScheduleRecorder] = []

    def recorder(indenter: str) -> ScheduleRecorder:
        recorders.append(ScheduleRecorder(model, indenter))
        return recorders[-1]

    with naming_trajectory(job):
        simulate_trajectory(worker, job, slot, recorder, electrode_counts=False)  # its recording is not kept
    if len(recorders) > 1:
        raise RuntimeError(f"trajectory {job.spec.trajectory_id} attached {len(recorders)} indenters, not one")
    schedule = recorders[0].schedule() if recorders else ScheduleRecorder(model, job.spec.indenter).schedule()
    return (job.sensor_id, job.spec.trajectory_id), schedule


def synthesise(
    worker: CampaignWorker, task: TrajectoryTask, schedule: SolveSchedule, increments: list[IncrementResult]
) -> tuple[int, int, bool]:
    """Run the task's protocol with its solves answered from `increments` (the batched results of `schedule`)
    and write its part file; returns (sensor id, trajectory id, complete). ScheduleExhausted when the
    protocol needs solves the batch did not make; RuntimeError when it leaves the schedule while recording."""
    job, slot = task[0], task[1]
    replay = ScheduleReplay(schedule, increments, _relaxes(worker.sensor(job.sensor_id)[0]))

    def solver(indenter: str) -> ScheduleReplay:
        if indenter != schedule.indenter:
            raise RuntimeError(f"the schedule is for {schedule.indenter}, the protocol attached {indenter}")
        return replay

    backend, recording = simulate_trajectory(worker, job, slot, solver)
    if OFF_SCHEDULE in recording.message:
        raise RuntimeError(
            f"sensor {job.sensor_id} trajectory {job.spec.trajectory_id}: the replayed protocol left its recorded "
            f"schedule ({recording.message})"
        )
    return write_trajectory_part(worker, task, backend, recording)


# -- solved schedules on disk, between the fe batch and the synthesis workers -------------------------------
SOLVES_DIR = "fe_solves"
"""Folder in the parts folder holding each solved schedule until its part is written."""
_RESULT_FIELDS = tuple(f.name for f in fields(IncrementResult))


def solves_path(task: TrajectoryTask) -> Path:
    """Where the task's solved schedule waits for its synthesis."""
    job, parts_dir = task[0], Path(task[3])
    return parts_dir / SOLVES_DIR / f"biotac{job.sensor_id}" / f"solves_{job.spec.trajectory_id:06d}.npz"


_POSE_FIELDS = ("times", "rotations", "translations")
SOLVED_PREFIX = "solved_"
"""Prefix of the arrays of the solves made, where they are not the schedule's (a compliant plant's, `SettledTips`)."""


def write_solves(
    path: Path, schedule: SolveSchedule, increments: list[IncrementResult], solved: SolveSchedule | None = None
) -> None:
    """Write a schedule, the solves made for it (`solved`, where they are not the schedule's poses) and their
    batched results (every `IncrementResult` field, stacked) atomically."""
    arrays = {"indenter": np.asarray(schedule.indenter), "solved": np.asarray(len(increments))}
    for prefix, poses in (("", schedule), (SOLVED_PREFIX, solved)):
        if poses is not None:
            arrays |= {prefix + name: getattr(poses, name) for name in _POSE_FIELDS}
    for name in _RESULT_FIELDS:
        arrays[f"result_{name}"] = np.asarray([getattr(r, name) for r in increments])
    write_part(path, arrays)


def read_solves(path: Path) -> tuple[SolveSchedule, SolveSchedule, list[IncrementResult]]:
    """The schedule, the solves made for it (the schedule itself unless others were written) and their results,
    as `write_solves` wrote them (the same values)."""
    arrays = read_part(path)
    prefixes = ("", SOLVED_PREFIX if SOLVED_PREFIX + "times" in arrays else "")
    schedule, solved = (
        SolveSchedule(str(arrays["indenter"]), *(arrays[prefix + name] for name in _POSE_FIELDS)) for prefix in prefixes
    )
    columns = [arrays[f"result_{name}"] for name in _RESULT_FIELDS]
    increments = [
        IncrementResult(*(c[k] if c.ndim > 1 else c[k].item() for c in columns)) for k in range(int(arrays["solved"]))
    ]
    return schedule, solved, increments


def synthesise_part(
    job: PlannedTrajectory, slot: int, registration: np.ndarray, parts_dir: str
) -> tuple[tuple[int, int], bool | None]:
    """Executor task (after `twin.campaign.init_worker`): synthesise the trajectory from its solved schedule
    and write its part (then drop the solves); returns its (sensor id, trajectory id) and whether it is
    complete, None when the protocol needs solves past the batch's force-limit stop."""
    task = (job, slot, registration, parts_dir)
    path = solves_path(task)
    _, solved, increments = read_solves(path)
    try:
        with naming_trajectory(job):
            sid, tid, complete = synthesise(process_worker(), task, solved, increments)
    except ScheduleExhausted:
        return _key(task), None
    path.unlink()
    return (sid, tid), complete


@dataclass(frozen=True)
class BatchedRunner:
    """A `twin.campaign.TrajectoryRunner` that solves the fe of every trajectory of a sensor as the systems of
    one batched run on the warp `device` (`slots` systems at once); see the module docstring.
    `on_stage(stage, done, total)` is told how far each stage ("schedules", "fe", "synthesis") has come, in
    trajectories, e.g. for a progress bar."""

    device: str = "cpu"
    slots: int = 256
    on_stage: Callable[[str, int, int], None] | None = None

    def __call__(
        self,
        tasks: list[TrajectoryTask],
        config: CampaignConfig,
        plant: Plant,
        executor: Executor,
        finished: Finished,
    ) -> None:
        # Pipelined by sensor (`fe_order`): the workers record every schedule (all jobs submitted at once) while
        # this process solves the fe of all sensors as one batch, sensor after sensor, starting as soon as it has
        # a schedule for every slot (`_Arriving`), and the trajectories solved are synthesised on the workers
        # meanwhile, in maps of whatever was solved since the last one (`_Solved`). The executor's maps are
        # consumed on one lane (in order, so that an executor running tasks in this process never runs two at
        # once); `finished` is called from it.
        # Every task's schedule is recorded again, and a resume keeps a solved one only where the schedule is the
        # same: a plan re-derived in this run may differ by a hair (e.g. an inflation on CUDA, whose sums have no
        # fixed order, moving a touch point and with it the first solve by a controller tick).
        compliance = (
            plant.effects[COMPLIANCE]["compliance"] if plant is not None and COMPLIANCE in plant.effects else None
        )
        order = fe_order(tasks)
        tasks = sorted(tasks, key=lambda task: order.index(task[0].sensor_id))
        host = Lane("campaign host stages", FirstFailure())
        arrived: queue.Queue[tuple[tuple[int, int], SolveSchedule]] = queue.Queue()
        exhausted: list[TrajectoryTask] = []
        solved, synthesised, total = itertools.count(1), itertools.count(1), len(tasks)
        ready = _Solved()

        def record_schedules() -> None:
            jobs = executor.map_unordered(plan_schedule, tasks, init_worker, (config, plant))
            for done, result in enumerate(jobs, start=1):
                arrived.put(result)
                self._stage("schedules", done, len(tasks))

        def synthesise_solved() -> None:
            while solved_tasks := ready.take_all():
                exhausted.extend(self._synthesise(solved_tasks, config, plant, executor, finished, synthesised, total))

        def ended(task: TrajectoryTask) -> None:
            host.failure.raise_if_any()  # a worker's failure ends the campaign now, not after the batch
            self._stage("fe", next(solved), len(tasks))
            if ready.add(task):  # no synthesis is waiting on the lane: one takes this and all solved after it
                host.submit(synthesise_solved)

        try:
            host.submit(record_schedules)
            worker = CampaignWorker(config, plant)
            arriving = _Arriving(tasks, lambda: host.take(arrived), _kept, compliance)
            self._solve(worker, arriving, FE_FORCE_LIMIT_FACTOR * config.settings.force_limit, ended)
            host.join()
        except BaseException:
            host.release()
            executor.cancel()  # the workers stop now (a map consumed on the lane cannot end them itself)
            raise
        if exhausted:  # solve them again without a force limit, from their recorded schedules
            exhausted.sort(key=lambda task: order.index(task[0].sensor_id))
            recorded = {_key(task): read_solves(solves_path(task))[0] for task in exhausted}
            resolved = itertools.count(1)
            again = _Arriving(exhausted, iter(recorded.items()).__next__, lambda *_: False, compliance)
            self._solve(worker, again, np.inf, lambda _: self._stage("fe", next(resolved), len(exhausted)))
            done = itertools.count(1)
            if self._synthesise(exhausted, config, plant, executor, finished, done, len(exhausted)):
                raise RuntimeError("a trajectory solved without a force limit still ran out of solves")

    def _solve(
        self, worker: CampaignWorker, arriving: _Arriving, force_limit: float, ended: Callable[[TrajectoryTask], None]
    ) -> None:
        """Solve the arriving schedules (of any sensors) as one batch, ending trajectories above `force_limit` (N);
        write each trajectory's solves as it ends (but those kept from an earlier run) and tell `ended(task)`."""

        def written(index: int, increments: list[IncrementResult]) -> None:
            task = arriving.task(index)
            if _key(task) not in arriving.kept:
                settle = arriving[index].settle
                solved = settle.solved() if isinstance(settle, SettledTips) else None
                write_solves(solves_path(task), arriving.schedules[_key(task)], increments, solved)
            increments.clear()  # written: free the displacement fields as the run goes on
            ended(task)

        skins = {sid: worker.sensor(sid)[0].inflated_skin() for sid in arriving.sensors}
        per_task = [skins[sid] for sid in arriving.sensor_of]
        run_trajectories(per_task, arriving, self.device, self.slots, force_limit, on_trajectory=written)

    def _synthesise(
        self,
        tasks: list[TrajectoryTask],
        config: CampaignConfig,
        plant: Plant,
        executor: Executor,
        finished: Finished,
        counter: Iterator[int],
        total: int,
    ) -> list[TrajectoryTask]:
        """Synthesise the tasks' parts on the executor, telling the stage's progress (`next(counter)` of
        `total`); returns those that need more solves."""
        by_key = {_key(task): task for task in tasks}
        exhausted = []
        for key, complete in executor.map_unordered(synthesise_part, tasks, init_worker, (config, plant)):
            if complete is None:
                exhausted.append(by_key[key])
                continue
            finished(*key, complete)
            self._stage("synthesis", next(counter), total)
        return exhausted

    def _stage(self, name: str, done: int, total: int) -> None:
        if self.on_stage is not None:
            self.on_stage(name, done, total)


class _Solved:
    """Trajectories whose fe is in and whose synthesis is not yet asked for, shared by the fe loop (`add`) and the
    host lane (`take_all`), so that the workers synthesise each trajectory soon after it is solved, in maps of
    whatever has been solved meanwhile."""

    def __init__(self) -> None:
        self._tasks: list[TrajectoryTask] = []
        self._lock = threading.Lock()
        self._taking = False

    def add(self, task: TrajectoryTask) -> bool:
        """Note a solved task; True when no taker is pending (the caller submits one)."""
        with self._lock:
            self._tasks.append(task)
            submit, self._taking = not self._taking, True
            return submit

    def take_all(self) -> list[TrajectoryTask]:
        """Every task noted and not yet taken; empty (and the taker ends) when there is none."""
        with self._lock:
            tasks, self._tasks = self._tasks, []
            self._taking = bool(tasks)
            return tasks


class _Arriving(Sequence[PoseTrajectory]):
    """Schedules as the trajectories of one batched run, read as the run asks for them (`take()`: the next (key,
    schedule) recorded, waiting for it): tasks (sorted sensor by sensor) keep their sensor's block of indices, and
    a block is filled as the run reaches it, with the sensor's schedules to solve in the order they arrive while
    some are still being recorded, then the rest the longest first, then those with nothing to solve (no solve
    asked for, or solves `kept(task, schedule)` from an earlier run) as trajectories without poses. So the fe
    starts once it has a schedule for every slot, while the workers record the others'. With a `compliance`
    (m/N), each trajectory's tips settle (`SettledTips`): a trajectory is made once and kept (its tips noted)."""

    def __init__(
        self,
        tasks: list[TrajectoryTask],
        take: Callable[[], tuple[tuple[int, int], SolveSchedule]],
        kept: Callable[[TrajectoryTask, SolveSchedule], bool],
        compliance: float | None = None,
    ) -> None:
        self._take, self._keep, self._count, self._compliance = take, kept, len(tasks), compliance
        self._trajectories: dict[tuple[int, int], PoseTrajectory] = {}
        self.sensor_of = [task[0].sensor_id for task in tasks]
        self.sensors = list(dict.fromkeys(self.sensor_of))
        self._tasks = {_key(task): task for task in tasks}
        self.schedules: dict[tuple[int, int], SolveSchedule] = {}
        self.kept: set[tuple[int, int]] = set()
        """Keys of the tasks whose solves an earlier run kept (not solved, not written again)."""
        self._order: dict[int, list[tuple[int, int]]] = {sid: [] for sid in self.sensors}
        self._start = {sid: self.sensor_of.index(sid) for sid in self.sensors}
        self._mine = {sid: [key for key in self._tasks if key[0] == sid] for sid in self.sensors}

    def __len__(self) -> int:
        return self._count

    def task(self, index: int) -> TrajectoryTask:
        """The task at `index` of the run (waiting for schedules until its sensor's block reaches it)."""
        sid = self.sensor_of[index]
        order, position, mine = self._order[sid], index - self._start[sid], self._mine[sid]
        while len(order) <= position:
            if all(key in self.schedules for key in mine):  # all in: the rest, the longest first
                rest = [key for key in mine if key not in order]
                solves = {key: 0 if self._kept(key) else len(self.schedules[key].times) for key in rest}
                order.extend(sorted(rest, key=lambda key: -solves[key]))
                break
            key, schedule = self._take()
            self.schedules[key] = schedule
            if key[0] == sid and len(schedule.times) and not self._kept(key):
                order.append(key)
        return self._tasks[order[position]]

    def _kept(self, key: tuple[int, int]) -> bool:
        """Whether the task's solves are kept from an earlier run (noted in `kept`)."""
        if self._keep(self._tasks[key], self.schedules[key]):
            self.kept.add(key)
        return key in self.kept

    def __getitem__(self, index: int) -> PoseTrajectory:
        task = self.task(index)
        key = _key(task)
        if key not in self._trajectories:
            self._trajectories[key] = self._trajectory(task)
        return self._trajectories[key]

    def _trajectory(self, task: TrajectoryTask) -> PoseTrajectory:
        """The task's schedule as a trajectory of the batched run (none for solves kept from an earlier run)."""
        schedule = self.schedules[_key(task)]
        if _key(task) in self.kept:
            return PoseTrajectory(schedule.indenter, np.zeros((0, 3, 3)), np.zeros((0, 3)), np.zeros(0))
        with naming_trajectory(task[0]):
            return schedule.poses(self._compliance)


def fe_order(tasks: list[TrajectoryTask]) -> list[int]:
    """The sensors of `tasks` in the order their fe is solved: most trajectories first (ties by id). What the
    GPU cannot hide is the head (the first sensor's schedules, before any fe) and the tail (the last sensor's
    synthesis and file, after the last fe); per trajectory the tail costs more (session 15 on an H200: 0.15 s
    against 0.10 s), so the smallest sensor goes last, and the largest batch first covers the most of the
    other sensors' schedules."""
    sizes = Counter(task[0].sensor_id for task in tasks)
    return sorted(sizes, key=lambda sid: (-sizes[sid], sid))


def _kept(task: TrajectoryTask, schedule: SolveSchedule) -> bool:
    """Whether the task's solves were kept by an earlier run for exactly this schedule."""
    path = solves_path(task)
    return path.exists() and read_solves(path)[0].same_as(schedule)


def _key(task: TrajectoryTask) -> tuple[int, int]:
    """(sensor id, trajectory id) of a task."""
    return task[0].sensor_id, task[0].spec.trajectory_id
