"""Model predictions of measured trajectories: replay each path through fe and the measurement chain.

A `TwinModel` is the nominal skin parameters plus effect values (twin.effects) and a mesh size. The
prediction of a trajectory re-solves the skin along the trajectory's recorded path (standoff,
loading, unloading: the same pose sequence the testbed ran; with a compliant arm, `robot_compliance`, each pose
deflected by the force measured at the end of its hold), turns each increment's force into the
F/T load the mount sees, runs it through the model's measurement effects at the recorded sample
times (the F/T signal chain; its electronics, which see the bias, taken from the measured first sample; the
PDC read-out), and then through the very processing the measurements went through (tare, 5 Hz zero-phase
low-pass, increment-end subsampling), so predicted and measured rows are directly comparable.
"""

from __future__ import annotations

import hashlib
import json
import multiprocessing
import queue
import sys
import threading
from collections.abc import Callable, Iterable, Iterator, Sequence
from concurrent.futures import ProcessPoolExecutor
from concurrent.futures.process import BrokenProcessPool
from contextlib import AbstractContextManager, contextmanager, nullcontext
from dataclasses import asdict, dataclass, field, replace
from functools import cache
from types import ModuleType
from typing import Any

import numpy as np
import warp as wp

from fe.batched_runner import PoseTrajectory, can_share_batch, run_trajectories
from fe.indentation import step_through
from fe.params import SkinParameters
from fe.results import IncrementResult
from fe.sensor import BioTacModel
from twin.analysis.data import TrajectoryRecord
from twin.controller import Recording
from twin.effects import (
    EffectValues,
    apply_path,
    apply_skin,
    check_values,
    has_reading_effects,
    measure_wrench,
    read_out,
    read_pdc,
)
from twin.fe_models import INFLATION_RULES, ModelCache
from twin.kinematics import rotation_exp
from twin.lanes import usable_cpus
from twin.processing import ProcessedRows, lowpass, process
from twin.readout import SensorReadout, ft_load
from twin.sim_backend import RELAXATION_SOLVE_INTERVAL_S

GPU_WORKERS = 2
"""Replay worker processes a GPU Predictor starts unless told (`_device_shares`): the paper diagnose (33 trajectories,
0.5 mm, ranked on 1 mm) took 296.2 s with two against 323.7 s in one process on one H200 (2026-11-28, 98c19f4): its
first wave (the 0.5 mm base beside the 1 mm columns) 62.9 against 78.0 s, its largest 1 mm wave (660 replays, halved)
43.8 against 59.7 s, its 1 mm waves of 198-359 replays and its last mixed wave (99) no faster; three took 318.2 s
(the GPU runs one context at a time, so the last wave's chain-bound 0.5 mm share waited behind two; docs/scale.md)."""
MODEL_CACHE_SIZE = 24
"""Inflated fe models a Predictor keeps (first built dropped first); replays, small arrays, are all kept."""
DEFAULT_WORKERS_MAX = 8
"""Replay worker processes a CPU Predictor starts at most unless told (`Predictor(workers=...)`): each holds its own
inflated models (up to `MODEL_CACHE_SIZE`) and inflates the skins of its shares, so more workers than a batch has
skins or a machine has memory for cost more than they give."""
PREFETCH_NODES = 256 * 3675
"""Skin nodes of the systems of one batched prefetch run at most: 256 systems of the paper's 0.5 mm mesh (3675
nodes), 945 of a 1 mm mesh (995), so a coarser mesh's wave is not queued through the slots a fine one needs (more
replays queue for the slots that free up)."""


def prefetch_slots(nodes: int) -> int:
    """Systems of a batched prefetch run of skins of `nodes` nodes (`PREFETCH_NODES`)."""
    return max(1, PREFETCH_NODES // nodes)


HELD_SOLVES_FIRST = 1
"""Events a replay solves at the start of every held pose besides its last (`held_solves`): 2 of a 5 s pause's 50."""


NO_POSE_ERROR = (0.0, 0.0, 0.0)
POSE_ERRORS = ("indenter_tilt", "path_slope")
"""The `TwinModel` fields of an indenter pose error (each a 3-vector, biotac frame)."""


@dataclass(frozen=True)
class TwinModel:
    """What predicts: nominal skin parameters, effect values, fe mesh size (m) and how the skin is
    inflated: "thickness" (fill until the sensor is 15.1 mm thick, the twin's default) or "thermal" (the
    paper's rule: the fluid expands from the reference to `skin.fluid_temperature`)."""

    skin: SkinParameters = field(default_factory=SkinParameters)
    effects: EffectValues = field(default_factory=dict)
    mesh_max_edge: float = 2e-3
    inflation: str = "thickness"
    indenter_tilt: tuple[float, float, float] = NO_POSE_ERROR
    """Rotation vector (rad, biotac frame) of the indenter about its tip against each trajectory's recorded
    orientation: the orientation error an arm's joint offsets and a registration's rotation leave (the nuisance
    fit's, per trajectory; zero for a nominal model)."""
    path_slope: tuple[float, float, float] = NO_POSE_ERROR
    """The tip's displacement (biotac frame) per metre of commanded depth besides the commanded direction: how
    those errors turn and stretch the press (zero for a nominal model)."""

    def __post_init__(self) -> None:
        check_values(self.effects)
        if self.inflation not in INFLATION_RULES:
            raise ValueError(f"inflation must be one of {INFLATION_RULES}, got {self.inflation!r}")
        for name in POSE_ERRORS:
            value = getattr(self, name)
            if len(value) != 3 or not np.isfinite(value).all():
                raise ValueError(f"{name} must be three finite numbers, got {value!r}")

    def with_effects(self, effects: EffectValues) -> TwinModel:
        """The same model with `effects` merged over its own (per effect, per parameter)."""
        merged = {k: dict(v) for k, v in self.effects.items()}
        for name, values in effects.items():
            merged.setdefault(name, {}).update(values)
        return replace(self, effects=merged)

    def to_dict(self) -> dict:
        """JSON-ready description (a pose error only where it is not zero)."""
        pose = {name: list(getattr(self, name)) for name in POSE_ERRORS if any(getattr(self, name))}
        return {
            "skin": asdict(self.skin),
            "effects": self.effects,
            "mesh_max_edge": self.mesh_max_edge,
            "inflation": self.inflation,
            **pose,
        }

    @classmethod
    def from_dict(cls, data: dict) -> TwinModel:
        """Inverse of `to_dict`."""
        return cls(
            SkinParameters(**data["skin"]),
            data.get("effects", {}),
            float(data["mesh_max_edge"]),
            data.get("inflation", "thickness"),
            **{name: tuple(float(v) for v in data[name]) for name in POSE_ERRORS if name in data},
        )

    def key(self) -> str:
        """Stable hash of the model."""
        return hashlib.sha256(json.dumps(self.to_dict(), sort_keys=True).encode()).hexdigest()[:16]


@dataclass(frozen=True)
class Prediction:
    """A model's view of one trajectory: per-increment fe results, full-rate signals and rows."""

    increment_force: np.ndarray  # (K, 3) N, biotac frame, fe force of each path index
    increment_pressure: np.ndarray  # (K,) Pa
    converged: np.ndarray  # (K,) bool; later indices after a failure are NaN-filled
    force_fullrate: np.ndarray  # (T, 3) N, biotac frame, tared, unfiltered (model + measurement effects)
    pdc_fullrate: np.ndarray  # (T,) counts, tared: the PDC read-out (the model's PDC effects) of the pressure change
    rows: ProcessedRows | None  # None when predicted with rows=False


@dataclass(frozen=True)
class _ReplayPlan:
    """What a trajectory's replay under a model needs: its cache key, indenter tip of each path index (m,
    biotac frame) and orientation, events (see `solve_events`), whether the skin relaxes (timed solves), which
    events are solved (`held_solves`; the others are filled, `fill_holds`) and the skin's relaxation time (s)."""

    key: tuple
    tips: np.ndarray
    rotation: np.ndarray  # (3, 3) indenter body -> biotac frame
    events: tuple[np.ndarray, np.ndarray]
    timed: bool
    solved: np.ndarray
    relaxation_time_s: float

    @property
    def solves(self) -> tuple[np.ndarray, np.ndarray]:
        """(times s, path indices) of the events the fe solves."""
        return self.events[0][self.solved], self.events[1][self.solved]


@dataclass(frozen=True)
class _ReplayJob:
    """A replay to solve, small enough to send to a worker process: the skin of its model (effects applied),
    mesh (m) and inflation rule, the indenter, its rotation (3, 3) body -> sensor frame, the plan and whether its
    replay reads the electrodes (`Predictor.electrodes`)."""

    skin: SkinParameters
    mesh_max_edge: float
    inflation: str
    indenter: str
    rotation: np.ndarray
    plan: _ReplayPlan
    electrodes: bool = True

    @property
    def model_key(self) -> tuple:
        """What its inflated fe model depends on (jobs of one key share a model)."""
        return self.plan.key[0]

    @property
    def events(self) -> int:
        """The fe solves it takes."""
        return int(self.plan.solved.sum())


class _ReplaySolver:
    """Inflated fe models (cached, with their read-outs) and batched runs of replay jobs on one warp device: a
    Predictor's own, and each replay worker process's (`_solve_share`)."""

    def __init__(self, device: str) -> None:
        self.device = device
        self.exclusive: AbstractContextManager = nullcontext() if device == "cpu" else threading.RLock()
        """Held while a thread drives a GPU (inflation, a batched run, a single replay): warp keeps one current stream
        a device, not a thread, so two threads' solves would share it (a graph captured on it by one while the other
        launches: "unknown stream"); the analyses' threaded stages read cached replays, and one that is not is then
        solved in turn. Threads on warp's CPU device solve at once."""
        self._readouts: dict[int, SensorReadout] = {}
        self._models = ModelCache(MODEL_CACHE_SIZE, on_drop=lambda model: self._readouts.pop(id(model), None))

    def inflated(self, skin: SkinParameters, mesh_max_edge: float, inflation: str) -> tuple:
        """(fe model, its InflationResult) for these parameters (built once); raises if it did not inflate."""
        with self.exclusive:
            model, result = self._models.get(skin, mesh_max_edge, inflation)
        if not result.converged:
            raise RuntimeError(f"the model did not inflate for {skin}: {result.message}")
        return model, result

    def readout(self, fe: BioTacModel) -> SensorReadout:
        """The nominal sensor read-out of this fe model's inflated skin (built once)."""
        key = id(fe)
        if key not in self._readouts:
            self._readouts[key] = SensorReadout.of_model(fe)
        return self._readouts[key]

    def solve(self, jobs: Sequence[_ReplayJob], done: Callable[[tuple, Replay], None]) -> None:
        """Solve the jobs, done(key, replay) after each: one batched run per set of skins that can share a batch,
        relaxing (timed) and elastic replays together, the longest first. When any skin of a run relaxes the run
        is timed, and each elastic replay is given its events' times, which a skin that does not relax ignores
        (its solves are those of an untimed run, tests/test_batched_replay.py): on a GPU the elastic replays then
        share the run's slots with the relaxing ones instead of waiting for them."""
        with self.exclusive:
            fes = {job.model_key: self.inflated(job.skin, job.mesh_max_edge, job.inflation)[0] for job in jobs}
            groups: list[list[_ReplayJob]] = []
            for job in sorted(jobs, key=lambda job: -job.events):
                fe = fes[job.model_key]
                for group in groups:
                    first = fes[group[0].model_key]
                    if first is fe or can_share_batch(first.inflated_skin(), fe.inflated_skin()):
                        group.append(job)
                        break
                else:
                    groups.append([job])
            for group in groups:
                self._run(group, [fes[job.model_key] for job in group], done)

    def _run(self, jobs: list[_ReplayJob], fes: list[BioTacModel], done: Callable[[tuple, Replay], None]) -> None:
        """One batched run of `jobs` (their fe models `fes`)."""
        skins = [fe.inflated_skin() for fe in fes]
        one_skin = all(fe is fes[0] for fe in fes)
        timed = any(job.plan.timed for job in jobs)

        def finished(index: int, increments: list[IncrementResult]) -> None:
            job = jobs[index]
            replay = _replay_of(self.readout(fes[index]), job.plan, increments, job.electrodes)
            increments.clear()  # the displacement fields are read: free them as the run goes on
            done(job.plan.key, replay)

        run_trajectories(
            skins[0] if one_skin else skins,
            [_pose_trajectory(job, timed) for job in jobs],
            self.device,
            slots=min(len(jobs), prefetch_slots(len(fes[0].reference))),
            on_trajectory=finished,
        )


def _solves(jobs: list[_ReplayJob]) -> int:
    """The fe solves (events) of these jobs together."""
    return sum(job.events for job in jobs)


def _shares(jobs: list[_ReplayJob], parts: int) -> list[list[_ReplayJob]]:
    """The jobs split into at most `parts` non-empty shares of about equal solves (events): units, the longest
    first, each go to the share with the fewest events so far. A unit is all the jobs of one skin when there are
    at least two skins a share (each worker then inflates fewer models), else one job."""
    by_model: dict[tuple, list[_ReplayJob]] = {}
    for job in jobs:
        by_model.setdefault(job.model_key, []).append(job)
    units = list(by_model.values()) if len(by_model) >= 2 * parts else [[job] for job in jobs]
    shares: list[list[_ReplayJob]] = [[] for _ in range(min(parts, len(units)))]
    events = [0] * len(shares)
    for unit in sorted(units, key=lambda unit: -_solves(unit)):
        least = events.index(min(events))
        shares[least].extend(unit)
        events[least] += _solves(unit)
    return shares


def _device_shares(jobs: list[_ReplayJob], parts: int) -> list[list[_ReplayJob]]:
    """The jobs of a GPU batch split into at most `parts` non-empty shares: each fe mesh's jobs apart (a batched run
    on a GPU costs about its longest chain of solves on its mesh, so a wave's 0.5 mm and 1 mm replays run side by
    side rather than one run after the other), then the share of most jobs halved (`_shares`) while parts are left
    and it has two jobs or more. Meshes beyond `parts` join the share of fewest solves (events)."""
    by_mesh: dict[float, list[_ReplayJob]] = {}
    for job in jobs:
        by_mesh.setdefault(job.mesh_max_edge, []).append(job)
    meshes = sorted(by_mesh.values(), key=lambda share: -_solves(share))
    shares = meshes[:parts]
    for rest in meshes[parts:]:
        min(shares, key=_solves).extend(rest)
    while len(shares) < parts and max(len(share) for share in shares) > 1:
        largest = max(shares, key=len)
        shares.remove(largest)
        shares += _shares(largest, 2)
    return shares


_WORKER: tuple[_ReplaySolver, Any] | None = None
"""In a replay worker process: its solver (models cached across the shares it solves) and the queue on which it
tells each replay solved (`_start_worker`); None elsewhere."""


def _start_worker(progress: Any, device: str) -> None:
    """A replay worker process's initializer: its own solver on warp `device` and the progress queue; the fe kernels
    loaded."""
    global _WORKER
    _WORKER = (_ReplaySolver(device), progress)
    wp.force_load(device=device)


def _started() -> None:
    """A task that only makes the pool start a worker."""


@contextmanager
def _main_hidden() -> Iterator[None]:
    """While it lasts, this process's __main__ is an empty module: a worker spawned then re-imports nothing of the
    caller's script (an unguarded script would otherwise run again in each worker); workers run this module's
    functions only."""
    main = sys.modules["__main__"]
    sys.modules["__main__"] = ModuleType("__main__")
    try:
        yield
    finally:
        sys.modules["__main__"] = main


def _solve_share(batch: int, jobs: list[_ReplayJob]) -> list[tuple[tuple, Replay]]:
    """(In a replay worker) solve a share of batch `batch`; (key, replay) of each job, each told on the progress
    queue as (batch, key) when solved."""
    solver, progress = _WORKER
    out: list[tuple[tuple, Replay]] = []

    def done(key: tuple, replay: Replay) -> None:
        out.append((key, replay))
        progress.put((batch, key))

    solver.solve(jobs, done)
    return out


class ReplayWorkers:
    """Worker processes that solve shares of a batch of replays on a warp device, each share one batched run of its
    own. On the CPU (shares of about equal solves, `_shares`) the fe kernels, the sparse factorisations and the Python
    between them all run at once (threads shared Python's lock: the demo diagnosis kept 1.6 of 2 cores busy in
    threads, 1.75 here, 0.92x the wall time; docs/scale.md, session 21). On a GPU (each mesh's jobs apart,
    `_device_shares`) each worker is a CUDA context of its own: the GPU interleaves their kernels while each waits on
    its host. Each worker keeps its own cache of inflated models. Every system iterates on its own, so however a batch
    is split the replays are the same, bit for bit on the CPU (on a GPU to its run-to-run round-off: CUDA's sums have
    no fixed order). Started once per process, count and device (`replay_workers`), shut down at exit."""

    def __init__(self, count: int, device: str = "cpu") -> None:
        context = multiprocessing.get_context("spawn")  # never fork a process that holds warp's state
        self._progress = context.Queue()
        initargs = (self._progress, device)
        self._pool = ProcessPoolExecutor(count, context, initializer=_start_worker, initargs=initargs)
        with _main_hidden():
            for _ in range(count):  # each submit to a pool with no idle worker starts one
                self._pool.submit(_started)
        self._batches = 0
        self.count, self.device = count, device

    def solve(self, jobs: list[_ReplayJob], done: Callable[[tuple, Replay], None], told: Callable[[], None]) -> None:
        """Solve the jobs in up to `count` shares (`_shares`), done(key, replay) for each as its share returns and
        told() as each is solved in a worker (progress). A worker that dies loses the batch: RuntimeError, and the
        next batch starts new workers."""
        self._batches += 1
        batch = self._batches
        try:
            split = _shares if self.device == "cpu" else _device_shares
            futures = [self._pool.submit(_solve_share, batch, share) for share in split(jobs, self.count)]
            heard = 0
            while not all(future.done() for future in futures) or heard < len(jobs):
                try:
                    if self._progress.get(timeout=0.05)[0] == batch:
                        heard += 1
                        told()
                except queue.Empty:
                    if all(future.done() for future in futures):
                        break
            shares = [future.result() for future in futures]
        except BrokenProcessPool as error:
            self._pool.shutdown(wait=False, cancel_futures=True)
            replay_workers.cache_clear()  # the next batch starts new workers
            raise RuntimeError(f"a replay worker process died (killed, or out of memory?): {error}") from error
        for share in shares:
            for key, replay in share:
                done(key, replay)
        for _ in range(len(jobs) - heard):
            told()


@cache
def replay_workers(count: int, device: str = "cpu") -> ReplayWorkers:
    """This process's `count` replay worker processes on warp `device` (started at the first call)."""
    return ReplayWorkers(count, device)


class Predictor:
    """Replays trajectories on a warp `device` ("cpu", "cuda", ...); inflated fe models and fe replays are
    cached.

    A replay depends only on the skin parameters, the mesh and the indenter path, so predictions that
    differ only in measurement effects reuse it. `predict` replays one trajectory at a time when its replay
    is not cached; `prefetch` solves the missing replays of many trajectories of one model, and
    `prefetch_many` those of many models, as the systems of one batched run (`fe.batched_runner`), which is
    how a GPU is kept busy and the per-round overhead of a run is paid once for them all.

    With `workers` > 1 a batch is split into that many shares, each share's batched runs in a worker process of its
    own (`ReplayWorkers`): on warp's CPU device shares of about equal work (default: one worker per usable CPU, at
    most `DEFAULT_WORKERS_MAX`), on a GPU each fe mesh's replays apart, then halved (default: `GPU_WORKERS`). Every
    system iterates on its own, so on warp's CPU device the replays are the same (bit for bit) whatever the split (on a
    GPU, to the engine's run-to-run round-off).

    With `electrodes=False` replays read no electrodes (NaN counts) and predictions have no processed rows: for
    the residual's analyses (diagnose, improve), which compare force and PDC only; reading the 19 electrodes at
    every solve is ~8 % of a paper-mesh diagnosis on a GPU (docs/scale.md, session 22).

    `solve_ahead` (default: on any device but warp's CPU) asks the analyses to solve, with each replay set whose
    result may call for a linearisation at its point, that linearisation's replays too (`sensitivity.point_models`):
    on a GPU a batch costs about its longest replay's chain of solves, not its size, so a set solved ahead is a
    wave saved; on the CPU a batch costs its solves, so the replays a fit does not use are time lost.
    """

    def __init__(
        self,
        device: str = "cpu",
        on_replays: Callable[[int, int], None] | None = None,
        workers: int | None = None,
        held_first: int = HELD_SOLVES_FIRST,
        electrodes: bool = True,
        solve_ahead: bool | None = None,
    ) -> None:
        self.device = device
        self.solve_ahead = device != "cpu" if solve_ahead is None else solve_ahead
        """Whether the analyses solve linearisations' replays ahead, with their point's (see the class docstring)."""
        self.electrodes = electrodes
        """Whether replays read the electrodes (False: NaN counts, and `predict` gives no rows)."""
        self.held_first = held_first
        """Events solved at the start of each held pose besides its last (`held_solves`; more than a hold has:
        every event, as the plant solves them)."""
        self.on_replays = on_replays
        """Told (done, total) as each replay of a `prefetch_many` without its own `progress` is solved."""
        default = min(usable_cpus(), DEFAULT_WORKERS_MAX) if device == "cpu" else GPU_WORKERS
        self.workers = max(1, workers if workers is not None else default)
        """Worker processes a batch is split over (see the class docstring); 1: solved in this process."""
        self._solver = _ReplaySolver(device)
        self._replays: dict[tuple, Replay] = {}
        self._paths: dict[tuple[int, bool], tuple] = {}  # (id, timed) -> (trajectory, `_trajectory_path` of it)

    def inflated(self, skin: SkinParameters, mesh_max_edge: float, inflation: str = "thickness") -> tuple:
        """(fe model, its InflationResult) for these parameters, inflated by `inflation` (built once)."""
        return self._solver.inflated(skin, mesh_max_edge, inflation)

    def fe_model(self, skin: SkinParameters, mesh_max_edge: float, inflation: str = "thickness") -> BioTacModel:
        """An inflated fe model for these parameters (built once)."""
        return self.inflated(skin, mesh_max_edge, inflation)[0]

    def readout(self, fe: BioTacModel) -> SensorReadout:
        """The nominal sensor read-out of this fe model's inflated skin (read-out gains unknown: nominal)."""
        return self._solver.readout(fe)

    def _plan(self, model: TwinModel, trajectory: TrajectoryRecord) -> _ReplayPlan:
        """The replay `model` needs for `trajectory` (its key says which cached replay serves it)."""
        skin = apply_skin(model.skin, model.effects)
        timed = skin.relaxation_fraction > 0.0
        commanded, loads, events, solved = self._trajectory_path(trajectory, timed)
        if any(model.path_slope):
            commanded = commanded + np.outer(_path_depths(trajectory.raw), model.path_slope)
        tips = apply_path(commanded, model.effects, loads)
        rotation = np.asarray(trajectory.rotation, dtype=np.float64)
        if any(model.indenter_tilt):
            rotation = rotation_exp(np.array(model.indenter_tilt)) @ rotation
        model_key = (tuple(sorted(asdict(skin).items())), model.mesh_max_edge, model.inflation)
        pose = (tips.round(12).tobytes(), rotation.round(12).tobytes())  # the replay's indenter poses
        key = (model_key, trajectory.sensor_id, trajectory.trajectory_id, *pose)
        return _ReplayPlan(key, tips, rotation, events, timed, solved, skin.relaxation_time_s)

    def _trajectory_path(
        self, trajectory: TrajectoryRecord, timed: bool
    ) -> tuple[np.ndarray, np.ndarray, tuple[np.ndarray, np.ndarray], np.ndarray]:
        """What every model's replay plan of `trajectory` shares, worked out once per trajectory object: the commanded
        tip of each path index (m, biotac frame), the measured loads (`measured_loads`), the events (`solve_events`;
        timed: at the relaxation's interval) and which are solved (`held_solves`)."""
        cached = self._paths.get((id(trajectory), timed))
        if cached is None or cached[0] is not trajectory:
            raw = trajectory.raw
            events = solve_events(raw, RELAXATION_SOLVE_INTERVAL_S if timed else None)
            commanded = trajectory.touch_point + np.outer(_path_depths(raw), trajectory.direction)
            cached = (
                trajectory,
                (commanded, measured_loads(trajectory), events, held_solves(events[1], self.held_first)),
            )
            self._paths[(id(trajectory), timed)] = cached
        return cached[1]

    def _model_fe(self, model: TwinModel) -> BioTacModel:
        """The inflated fe model of `model`'s skin with its effects applied."""
        return self.fe_model(apply_skin(model.skin, model.effects), model.mesh_max_edge, model.inflation)

    def prefetch(
        self,
        model: TwinModel,
        trajectories: Sequence[TrajectoryRecord],
        progress: Callable[[int, int], None] | None = None,
    ) -> int:
        """Solve the replays `model` needs for `trajectories` and does not have cached yet, all in one batched
        run on the predictor's device (`prefetch_many` with one model). progress(done, total) after each
        replay solved; returns how many were solved."""
        return self.prefetch_many([(model, trajectories)], progress)

    def prefetch_many(
        self,
        requests: Sequence[tuple[TwinModel, Sequence[TrajectoryRecord]]],
        progress: Callable[[int, int], None] | None = None,
    ) -> int:
        """Solve the replays that the (model, trajectories) `requests` need and are not cached yet as the
        systems of as few batched runs on the predictor's device as the skins allow, so that `predict` then
        finds them cached. Each system carries its own model's inflated skin; replays that models share (same
        skin, same path: models that differ only in measurement effects) are solved once. Systems are
        grouped into one run when their skins share a mesh (`fe.batched_runner.can_share_batch`), queued
        through at most `prefetch_slots` systems (a system takes the next replay whatever its skin), the
        longest first; on the CPU with several `workers`, a run per share and worker. Each replay is what
        `predict` would solve one at a time: the same events, stopped at the first increment that does not
        converge. progress(done, total) (default: the predictor's `on_replays`) after each replay solved;
        returns how many were solved."""
        jobs: dict[tuple, _ReplayJob] = {}
        for model, trajectory, plan in self._missing(requests):
            skin = apply_skin(model.skin, model.effects)
            job = _ReplayJob(
                skin, model.mesh_max_edge, model.inflation, trajectory.indenter, plan.rotation, plan, self.electrodes
            )
            jobs.setdefault(plan.key, job)
        work = list(jobs.values())
        solved = 0
        progress = progress or self.on_replays

        def told() -> None:
            nonlocal solved
            solved += 1
            if progress is not None:
                progress(solved, len(work))

        def done(key: tuple, replay: Replay) -> None:
            self._replays[key] = replay

        if self.workers > 1 and len(work) > 1:
            replay_workers(self.workers, self.device).solve(work, done, told)
        elif work:
            self._solver.solve(work, lambda key, replay: (done(key, replay), told()))
        return len(work)

    def missing(self, requests: Sequence[tuple[TwinModel, Sequence[TrajectoryRecord]]]) -> int:
        """How many of the replays that the (model, trajectories) `requests` need are not cached (repeats counted)."""
        return sum(1 for _ in self._missing(requests))

    def _missing(
        self, requests: Sequence[tuple[TwinModel, Sequence[TrajectoryRecord]]]
    ) -> Iterator[tuple[TwinModel, TrajectoryRecord, _ReplayPlan]]:
        """(model, trajectory, replay plan) of each request whose replay is not cached."""
        for model, trajectories in requests:
            for trajectory in trajectories:
                plan = self._plan(model, trajectory)
                if plan.key not in self._replays:
                    yield model, trajectory, plan

    def standoff_force(self, model: TwinModel, trajectory: TrajectoryRecord) -> float:
        """|force| (N, the fe's, untared) of `model`'s replay of `trajectory` at its first event, the standoff pose
        where the recording is tared (path index 0); NaN when that replay failed there. Above the F/T noise the press
        starts in contact and is tared under that load. The replay solves that pose from the rest skin in one step,
        as the simulated plant does (it solves the skin at rest poses only); a real skin got there along the arm's
        move, which the data do not hold, so its friction state there may differ."""
        key = self._plan(model, trajectory).key
        if key not in self._replays:
            self.predict(model, trajectory, rows=False)
        replay = self._replays[key]
        return float(np.linalg.norm(replay.force[0])) if replay.path_index[0] == 0 else float("nan")

    def predict(self, model: TwinModel, trajectory: TrajectoryRecord, rows: bool = True) -> Prediction:
        """The model's prediction of `trajectory` (see the module docstring); `rows=False` leaves the processed
        rows out (None: the residual reads the full-rate signals only); a predictor without electrodes gives none.
        """
        if rows and not self.electrodes:
            raise ValueError("this predictor reads no electrodes (electrodes=False): ask for predictions without rows")
        plan = self._plan(model, trajectory)
        if plan.key not in self._replays:
            with self._solver.exclusive:
                fe = self._model_fe(model)
                stepper = fe.stepper(trajectory.indenter, self.device)
                times, indices = plan.solves
                tips, at = plan.tips[indices], times if plan.timed else None
                increments = step_through(stepper, plan.rotation, tips, at)
            self._replays[plan.key] = _replay_of(self.readout(fe), plan, increments, self.electrodes)
        replay = self._replays[plan.key]
        tips, raw = plan.tips, trajectory.raw
        times = raw.time
        sample_event = np.clip(np.searchsorted(replay.time, times, side="right") - 1, 0, None)
        loads = ft_load(replay.force, tips[replay.path_index], trajectory.sensor_in_biotac)

        def clean_at(t: np.ndarray) -> np.ndarray:
            return loads[np.clip(np.searchsorted(replay.time, t, side="right") - 1, 0, None)]

        wrench = measure_wrench(times, clean_at, model.effects)
        if has_reading_effects(model.effects):  # the F/T electronics see the bias: the measured first sample
            wrench = read_out(wrench + (raw.wrench[0] - wrench[0]), model.effects)  # less the load there
        read = read_pdc(times, replay.pdc_change[sample_event], model.effects)  # affine: taring drops the offset
        pdc_change = read - read[0]
        processed = None
        if rows:  # the recording the testbed would have made, processed as the measurements were
            predicted = Recording(
                time=times,
                joints=raw.joints,
                wrench=wrench,
                electrodes=raw.electrodes[0] + replay.electrodes[sample_event] - replay.electrodes[0],
                pdc=raw.pdc[0] + pdc_change,
                depth_command=raw.depth_command,
                increment=raw.increment,
                complete=bool(replay.converged.all()),
                message="",
            )
            registration = np.linalg.inv(trajectory.registration)
            processed = process(
                predicted,
                trajectory.arm,
                trajectory.tool_tip,
                registration,
                trajectory.sensor_in_biotac,
                trajectory.rate_hz,
            )
        tared = (wrench[:, :3] - wrench[0, :3]) @ trajectory.sensor_in_biotac[:3, :3].T
        last = np.r_[np.flatnonzero(np.diff(replay.path_index)), len(replay.path_index) - 1]  # per path index
        return Prediction(
            replay.force[last], replay.pressure[last], replay.converged[last], tared, pdc_change, processed
        )


def _path_depths(raw: Recording) -> np.ndarray:
    """Commanded depth of each path index (-1 standoff first), from the recording's labels."""
    n = int(raw.increment.max()) + 2
    depths = np.full(n, np.nan)
    depths[raw.increment + 1] = raw.depth_command
    return depths


@dataclass(frozen=True)
class Replay:
    """fe solves along a trajectory's path, one per event: the event's time (s, the recording's clock),
    path index, force (N, biotac frame), pressure (Pa), its read-out (electrode counts, the PDC change from
    the first event) and converged flag (NaN after a failure)."""

    time: np.ndarray  # (S,)
    path_index: np.ndarray  # (S,)
    force: np.ndarray  # (S, 3)
    pressure: np.ndarray  # (S,)
    electrodes: np.ndarray  # (S, 19) counts, expected (noise-free)
    pdc_change: np.ndarray  # (S,) counts, noise-free, from the first event's pressure
    converged: np.ndarray  # (S,) bool


def solve_events(raw: Recording, interval_s: float | None) -> tuple[np.ndarray, np.ndarray]:
    """(times s, path indices) at which the skin is solved: each path index when its increment starts,
    and, with `interval_s`, again every `interval_s` while the pose is held (relaxation); a pose reached at the
    recording's last sample (a trajectory stopped there, or of one sample) is solved once, when it is reached."""
    starts = np.r_[0, np.flatnonzero(np.diff(raw.increment)) + 1]
    ends = np.r_[raw.time[starts[1:]], raw.time[-1]]
    times, indices = [], []
    for start, end in zip(starts, ends, strict=True):
        held = [raw.time[start]]
        if interval_s is not None and end > raw.time[start]:
            held = np.arange(raw.time[start], end, interval_s)
        times.extend(held)
        indices.extend([raw.increment[start] + 1] * len(held))
    return np.asarray(times, dtype=float), np.asarray(indices, dtype=int)


def held_solves(indices: np.ndarray, first: int = HELD_SOLVES_FIRST) -> np.ndarray:
    """Which events (path indices (S,), `solve_events`) a replay solves ((S,) bool): of each run of events at
    one pose (a hold, re-solved every `RELAXATION_SOLVE_INTERVAL_S` by the plant while the skin relaxes) its
    first `first` and its last; `fill_holds` fills the others with the relaxation's exponential. Sound because
    a held pose's state depends on time only, not on how often it is solved (the friction keeps its stick
    anchors across solves, docs/fe.md), and one Prony branch relaxes along one exponential: measured against
    solving every event, 0.3 mN apart at most with the first alone (benchmarks/hold_solves.py,
    docs/scale.md)."""
    starts = np.r_[0, np.flatnonzero(np.diff(indices)) + 1]
    position = np.arange(len(indices)) - np.repeat(starts, np.diff(np.r_[starts, len(indices)]))
    last = np.r_[np.diff(indices) != 0, True]
    return (position < first) | last


def fill_holds(times: np.ndarray, solved: np.ndarray, values: np.ndarray, relaxation_time_s: float) -> np.ndarray:
    """`values` (S, ...) at the solved events completed at the others (times (S,) s): between the solved events
    a and b around each (the same hold: a hold's first and last are solved), the exponential of the skin's
    relaxation time through both, v_b + (v_a - v_b) (e^(-(t - t_a)/tau) - e^(-(t_b - t_a)/tau)) /
    (1 - e^(-(t_b - t_a)/tau)): exact for one Prony branch's decay; NaN where either is NaN; the solved events'
    values returned as they are."""
    index = np.arange(len(times))
    before = np.maximum.accumulate(np.where(solved, index, 0))
    after = np.minimum.accumulate(np.where(solved, index, len(times) - 1)[::-1])[::-1]
    span = np.where(solved, 1.0, times[after] - times[before]) / relaxation_time_s
    decay = np.exp(-span)
    weight = (np.exp(-(times - times[before]) / relaxation_time_s) - decay) / np.where(solved, 1.0, 1.0 - decay)
    weight = np.where(solved, 1.0, weight).reshape(-1, *([1] * (values.ndim - 1)))
    return values[after] + weight * (values[before] - values[after])


def _pose_trajectory(job: _ReplayJob, timed: bool) -> PoseTrajectory:
    """The indenter poses of a replay's solved events for the batched runner, with their times when `timed`."""
    times, indices = job.plan.solves
    rotations = np.repeat(job.rotation[None], len(times), axis=0)
    return PoseTrajectory(job.indenter, rotations, job.plan.tips[indices], times if timed else None)


def _replay_of(
    readout: SensorReadout, plan: _ReplayPlan, increments: Iterable[IncrementResult], electrodes: bool = True
) -> Replay:
    """The replay of the plan's events (see `solve_events`) from the increments of its solved ones in order
    (read one by one), which end at the first that did not converge: that event, the later ones and those
    filled from it are NaN and not converged; the unsolved events filled (`fill_holds`). The PDC, and with
    `electrodes` the electrodes (else NaN), read by `readout`."""
    n = int(plan.solved.sum())
    force, pressure, counts = np.full((n, 3), np.nan), np.full(n, np.nan), np.full((n, 19), np.nan)
    for s, result in enumerate(increments):
        if not result.converged:
            break
        force[s], pressure[s] = result.force, result.pressure
        if electrodes:
            counts[s] = readout.electrode_counts(result.displacement)
    times, indices = plan.events

    def every_event(values: np.ndarray) -> np.ndarray:
        full = np.full((len(times), *values.shape[1:]), np.nan)
        full[plan.solved] = values
        return fill_holds(times, plan.solved, full, plan.relaxation_time_s)

    force, pressure, counts = every_event(force), every_event(pressure), every_event(counts)
    pdc_change = readout.pdc_change(pressure - pressure[0])
    return Replay(times, indices, force, pressure, counts, pdc_change, np.isfinite(pressure))


def measured_force_fullrate(trajectory: TrajectoryRecord, samples: np.ndarray | None = None) -> np.ndarray:
    """(T, 3) measured force on the BioTac (N, biotac frame), tared, unfiltered; at `samples` (indices) only when
    given."""
    wrench = trajectory.raw.wrench
    picked = wrench if samples is None else wrench[samples]
    return (picked[:, :3] - wrench[0, :3]) @ trajectory.sensor_in_biotac[:3, :3].T


def measured_loads(trajectory: TrajectoryRecord) -> np.ndarray:
    """(K, 3) the measured force on the BioTac (N, biotac frame, tared, unfiltered: `measured_force_fullrate`) at
    the last sample of each path index's hold, standoff first (NaN at an index without samples): the loads that
    deflect a model's path (`twin.effects.apply_path`). One sample carries the F/T noise, 10 mN on the testbed,
    a micrometre of tip at 0.1 mm/N."""
    increment = trajectory.raw.increment
    ends = np.r_[np.flatnonzero(np.diff(increment)), len(increment) - 1]
    loads = np.full((int(increment.max()) + 2, 3), np.nan)
    loads[increment[ends] + 1] = measured_force_fullrate(trajectory, ends)  # those rows only: called per replay plan
    return loads


def measured_pdc_fullrate(trajectory: TrajectoryRecord) -> np.ndarray:
    """(T,) measured PDC counts, tared (first sample subtracted), unfiltered."""
    pdc = np.asarray(trajectory.raw.pdc, dtype=float)
    return pdc - pdc[0]


def filtered(force: np.ndarray, rate_hz: float) -> np.ndarray:
    """The paper's force filter applied to a full-rate series."""
    return lowpass(force, rate_hz)
