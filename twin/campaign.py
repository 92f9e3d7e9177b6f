"""Campaigns: plan, register, execute on workers (local processes or Ray), process, write datasets; resumable.

Every trajectory draws its randomness from `SeedSequence([seed, sensor, trajectory_id])` and starts
from the same simulated state and clock time whatever the order or worker it runs in, so a killed
and resumed campaign writes exactly the file an uninterrupted one writes. Finished trajectories are
part files (written atomically); a resume skips them. The same holds for the executor
(`twin.executors`): a trajectory re-run after its worker died rewrites the same part file. A
`TrajectoryRunner` says how the trajectories' fe is solved: `one_at_a_time` (the default, each worker
stepping its trajectory's skin as the controller reaches each pose) or `twin.campaign_batched.BatchedRunner`
(all of a sensor's trajectories as one batch on a warp device, the same parts within the engine's tolerance).
"""

from __future__ import annotations

import hashlib
import json
import os
import shutil
import tempfile
import threading
from collections import Counter
from collections.abc import Callable, Iterator
from contextlib import contextmanager
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from assets.biotac import BioTacGeometry, SkinMesh, make_biotac
from assets.indenters import INDENTERS, indenter_name
from fe.electrodes import ElectrodeModel
from fe.params import SkinParameters
from fe.sensor import BioTacModel
from twin.backend import ARMS
from twin.controller import Recording, execute
from twin.dataset import assemble_sensor_file, part_path, read_part, remove_stale_temporaries, write_part
from twin.effects import apply_path, apply_skin
from twin.executors import Executor, LocalExecutor
from twin.fe_models import inflated_model
from twin.lanes import FirstFailure, Lane
from twin.planning import PlannedTrajectory, plan_statistics, plan_trajectory, scene_tool_tip
from twin.plant import Plant, make_plant, rigid_transform
from twin.processing import process
from twin.protocol import QUICK_SETTINGS, PathDraw, ProtocolSettings, TrajectorySpec, draw_paths, plan_spec
from twin.readout import electrode_model
from twin.registration import RegistrationResult, simulate_registration
from twin.scene import SceneParameters, TestbedScene
from twin.sim_backend import SimBackend, SkinSolver

SPHERES = ("sphere_small", "sphere_medium", "sphere_large")
INDENTER_ADAPTER_LENGTH = 0.10
"""Spacer (m) between flange and indenter shank, so the wrist clears the mount (a 3D-printed adapter)."""
TRAJECTORY_SLOT_S = 600.0
"""Clock time (s) reserved per trajectory: trajectory k of a sensor starts at k * TRAJECTORY_SLOT_S."""


@dataclass(frozen=True)
class CampaignConfig:
    """What to run. `spheres_only` lists sensors that only get the sphere indenters (the paper's BioTac 1)."""

    sensors: tuple[int, ...] = (1, 2, 3)
    indenters: tuple[str, ...] = tuple(INDENTERS)
    settings: ProtocolSettings = field(default_factory=ProtocolSettings)
    seed: int = 0
    mesh_max_edge: float = 0.5e-3
    spheres_only: tuple[int, ...] = (1,)
    nominal: SkinParameters = field(default_factory=SkinParameters)
    scene: SceneParameters = field(default_factory=lambda: SceneParameters(adapter_length=INDENTER_ADAPTER_LENGTH))

    def __post_init__(self) -> None:
        object.__setattr__(self, "indenters", tuple(indenter_name(n) for n in self.indenters))  # public names too
        if not self.sensors or min(self.sensors) < 1:
            raise ValueError(f"sensors must be positive ids, got {self.sensors!r}")

    def indenters_for(self, sensor_id: int) -> list[str]:
        """Indenters this sensor is indented with."""
        if sensor_id in self.spheres_only:
            return [n for n in self.indenters if n in SPHERES]
        return list(self.indenters)


QUICK_CONFIG = CampaignConfig(settings=QUICK_SETTINGS, mesh_max_edge=2e-3)
"""A quick campaign: one point per indenter, one normal and one angled path, coarse mesh, short pauses."""


@dataclass(frozen=True)
class CampaignPlan:
    """Specs (biotac frame), their per-sensor robot plans and each sensor's estimated registration."""

    config: CampaignConfig
    specs: list[TrajectorySpec]
    planned: list[PlannedTrajectory]
    registration: dict[tuple[int, str], np.ndarray]  # (sensor, arm) -> 4x4 estimated robot<-biotac transform
    registration_error: dict[tuple[int, str], float]  # (sensor, arm) -> RMS error at the BioTac (m)

    def statistics(self) -> dict:
        """Planned/kept/dropped per indenter and totals (the `twin campaign plan --json` shape)."""
        stats = plan_statistics(self.planned)
        stats["registration_error_mm"] = {f"{s}/{a}": v * 1e3 for (s, a), v in self.registration_error.items()}
        return stats


def true_mount_pose(plant: Plant, sensor_id: int, scene: TestbedScene) -> np.ndarray:
    """Robot<-biotac transform of the mount CAD where the plant really placed this sensor's mount (nominal
    plus its placement error): where the registration holes are, and what registration estimates."""
    error = plant.sensor(sensor_id).mount_error
    return rigid_transform(error[:3], error[3:]) @ scene.biotac_pose


def true_biotac_pose(plant: Plant, sensor_id: int, scene: TestbedScene) -> np.ndarray:
    """Robot<-biotac transform of the BioTac itself: the true mount, and, with a hidden path effect
    (`registration_offset` d), the BioTac seated -d off its CAD place in the mount, so a tip sent to p
    by the registered transform reaches p + d in the BioTac's frame (what `apply_path` models), while
    registration, which only sees the mount's holes, cannot tell."""
    seat = np.eye(4)
    seat[:3, 3] = -apply_path(np.zeros((1, 3)), plant.effects)[0]
    return true_mount_pose(plant, sensor_id, scene) @ seat


def campaign_registration(plant: Plant, sensor_id: int, arm: str, scene: TestbedScene, seed: int) -> RegistrationResult:
    """The registration a campaign of `seed` simulates for sensor `sensor_id` with `arm`: the plant's clearance,
    encoder noise and joint offsets against the sensor's true mount, from the campaign's own random stream."""
    rng = np.random.default_rng(np.random.SeedSequence([seed, sensor_id, ARMS.index(arm), 0x9E6]))
    return simulate_registration(
        scene,
        rng,
        arm=arm,
        clearance=plant.registration_clearance,
        encoder_noise_rad=plant.registration_encoder_noise,
        joint_offset_rad=plant.joint_offset(arm),
        true_biotac_pose=true_mount_pose(plant, sensor_id, scene),
    )


def plan_campaign(
    config: CampaignConfig,
    plant: Plant | None = None,
    executor: Executor | None = None,
    on_stage: Callable[[str, int, int], None] | None = None,
) -> CampaignPlan:
    """Sample the trajectories, register each sensor, and plan each trajectory's first touch on the nominal skin
    and its joint paths (dropping what cannot run): here, or on the workers of `executor` (each set up by
    `init_worker(config, plant)`), the same plan. `on_stage(stage, done, total)` is told how far each stage
    ("first touches", "joint paths") has come, in trajectories."""
    plant = plant if plant is not None else make_plant(list(config.sensors), config.seed)
    planner = _Planner(config, plant, executor, on_stage)
    geometry = make_biotac(config.mesh_max_edge)
    draws = draw_paths(geometry, list(config.indenters), config.settings, config.seed)
    specs = planner.run("first touches", _plan_spec, list(enumerate(draws)))
    scene = TestbedScene(config.scene)
    jobs, registration, errors = [], {}, {}
    for sid in config.sensors:
        for arm in ARMS:
            result = campaign_registration(plant, sid, arm, scene, config.seed)
            registration[(sid, arm)] = result.transform  # the estimate, never the plant's truth
            errors[(sid, arm)] = result.error_rms
        wanted = set(config.indenters_for(sid))
        per_arm = {arm: registration[(sid, arm)] for arm in ARMS}
        jobs += [(spec, sid, per_arm) for spec in specs if spec.indenter in wanted]
    planned = planner.run("joint paths", _plan_joints, jobs)
    for round_ in range(1, config.settings.replacement_rounds + 1):
        uncovered = _uncovered(config, planned)
        if not uncovered:
            break
        draws = draw_paths(geometry, sorted({name for _, name in uncovered}), config.settings, config.seed + round_)
        extra = planner.run("first touches", _plan_spec, list(enumerate(draws, start=len(specs))))
        specs += extra
        jobs = []
        for sid in sorted({s for s, _ in uncovered}):
            names = {name for s, name in uncovered if s == sid}
            per_arm = {arm: registration[(sid, arm)] for arm in ARMS}
            jobs += [(spec, sid, per_arm) for spec in extra if spec.indenter in names]
        planned += planner.run("joint paths", _plan_joints, jobs)
    return CampaignPlan(config, specs, planned, registration, errors)


@dataclass
class _Planner:
    """Runs planning tasks (`task(worker, *job)`, a module-level function) in the jobs' order: on a
    `CampaignWorker` of this process, or on the executor's workers; tells `on_stage(stage, done, total)`."""

    config: CampaignConfig
    plant: Plant
    executor: Executor | None
    on_stage: Callable[[str, int, int], None] | None = None
    _here: CampaignWorker | None = field(default=None, init=False, repr=False)

    def run(self, stage: str, task: Callable[..., Any], jobs: list[tuple]) -> list:
        if self.executor is None:
            if self._here is None:
                self._here = CampaignWorker(self.config, self.plant)
            done = ((k, task(self._here, *job)) for k, job in enumerate(jobs))
        else:
            indexed = [(task, k, job) for k, job in enumerate(jobs)]
            done = self.executor.map_unordered(_indexed_task, indexed, init_worker, (self.config, self.plant))
        found = {}
        for k, result in done:
            found[k] = result
            if self.on_stage:
                self.on_stage(stage, len(found), len(jobs))
        if len(found) != len(jobs):
            raise RuntimeError(f"the executor ran {len(found)} of {len(jobs)} planning tasks")
        return [found[k] for k in range(len(jobs))]


def _indexed_task(task: Callable[..., Any], index: int, job: tuple) -> tuple[int, Any]:
    """Executor task (after `init_worker`): the job's index and `task(this process's worker, *job)`."""
    return index, task(process_worker(), *job)


def _plan_spec(worker: CampaignWorker, trajectory_id: int, draw: PathDraw) -> TrajectorySpec:
    """The draw's trajectory (its first touch) on the campaign's nominal inflated skin."""
    return plan_spec(worker.nominal(), draw, worker.config.settings, trajectory_id)


def _plan_joints(
    worker: CampaignWorker, spec: TrajectorySpec, sensor_id: int, registration: dict[str, np.ndarray]
) -> PlannedTrajectory:
    """The trajectory's joint paths on the worker's reset testbed; `registration`: the sensor's estimated
    robot<-biotac 4x4 per arm."""
    return plan_trajectory(worker.scene(), spec, sensor_id, registration)


def _uncovered(config: CampaignConfig, planned: list[PlannedTrajectory]) -> set[tuple[int, str]]:
    """(sensor, indenter) pairs of the campaign without any kept trajectory."""
    kept = {(p.sensor_id, p.spec.indenter) for p in planned if p.kept}
    return {(sid, name) for sid in config.sensors for name in config.indenters_for(sid) if (sid, name) not in kept}


# -- execution ---------------------------------------------------------------------------------------
@dataclass
class CampaignWorker:
    """Per-process state: the geometry, the plant's inflated fe models and the testbed scene, built on first
    use."""

    config: CampaignConfig
    plant: Plant
    geometry: BioTacGeometry = field(init=False)
    models: dict = field(default_factory=dict)
    _scene: TestbedScene | None = field(default=None, init=False, repr=False)
    _nominal: BioTacModel | None = field(default=None, init=False, repr=False)

    def __post_init__(self) -> None:
        self.geometry = make_biotac(self.config.mesh_max_edge)

    def scene(self) -> TestbedScene:
        """The testbed scene in its starting state (`TestbedScene.reset`): built once per process, reset for
        each trajectory, so every trajectory starts from the same state as on a scene built for it alone."""
        if self._scene is None:
            self._scene = TestbedScene(self.config.scene)
        else:
            self._scene.reset()
        return self._scene

    def nominal(self) -> BioTacModel:
        """The campaign's nominal skin (`CampaignConfig.nominal`) inflated on the campaign's mesh, built once per
        process: the skin the protocol's first touches are planned on."""
        if self._nominal is None:
            self._nominal = inflated_model(self.geometry, self.config.nominal)
        return self._nominal

    def sensor(self, sid: int) -> tuple[BioTacModel, ElectrodeModel]:
        """Plant sensor `sid`'s fe model and electrodes (`plant_sensor_models`), built once per process."""
        if sid not in self.models:
            self.models[sid] = plant_sensor_models(self.plant, sid, self.geometry)
        return self.models[sid]


def plant_sensor_models(plant: Plant, sid: int, geometry: BioTacGeometry) -> tuple[BioTacModel, ElectrodeModel]:
    """The truth of plant sensor `sid` as the simulated testbed needs it: its skin (with the plant's physics
    effects) inflated on `geometry`, and its electrodes (its read-out parameters, seeing the skin through the
    sensor's own thickness) on that skin."""
    truth = plant.sensor(sid)
    model = inflated_model(geometry, apply_skin(truth.skin, plant.effects))
    return model, electrode_model(model, truth.electrodes, truth.skin.thickness)


_WORKER: CampaignWorker | None = None


def init_worker(config: CampaignConfig, plant: Plant) -> None:
    """Executor setup: this process's `CampaignWorker` (models built on first use)."""
    global _WORKER
    _WORKER = CampaignWorker(config, plant)


def process_worker() -> CampaignWorker:
    """This executor process's `CampaignWorker` (after `init_worker`)."""
    if _WORKER is None:
        raise RuntimeError("init_worker() has not run in this process")
    return _WORKER


def trajectory_arrays(
    job: PlannedTrajectory, recording: Recording, registration: np.ndarray, scene: TestbedScene, rate_hz: float
) -> dict[str, np.ndarray]:
    """A trajectory's part-file arrays (any backend): processed rows, raw recording, metadata.

    registration: the estimated robot<-biotac 4x4 used for this trajectory's arm.
    """
    spec = job.spec
    tool_tip = scene_tool_tip(scene, spec.indenter)
    sensor_in_biotac = np.linalg.inv(scene.biotac_pose) @ scene.ft_sensor_pose
    rows = process(recording, job.arm, tool_tip, np.linalg.inv(registration), sensor_in_biotac, rate_hz)
    arrays = {f"row_{k}": v for k, v in asdict(rows).items() if k != "sample_index"}
    n = len(rows.depth)
    arrays["row_trajectory_id"] = np.full(n, spec.trajectory_id, dtype=np.int64)
    arrays["row_indenter_type"] = np.full(n, list(INDENTERS).index(spec.indenter), dtype=np.int64)
    arrays.update({f"raw_{k}": v for k, v in asdict(recording).items() if k not in ("complete", "message")})
    meta = {
        "trajectory_id": spec.trajectory_id,
        "indenter_type": list(INDENTERS).index(spec.indenter),
        "arm": 0 if job.arm == "left" else 1,
        "angle": spec.angle,
        "azimuth": spec.azimuth,
        "point": spec.point,
        "direction": spec.direction,
        "rotation": spec.rotation,
        "touch_point": spec.touch_point,
        "complete": recording.complete,
        "message": recording.message,
        "tool_tip": tool_tip,
        "registration": registration,
        "sensor_in_biotac": sensor_in_biotac,
    }
    arrays.update({f"meta_{k}": np.asarray(v) for k, v in meta.items()})
    return arrays


# -- what made the parts (resume safety) ------------------------------------------------------------
MANIFEST = "campaign.json"
"""File in `out/parts` recording the options its parts were made with (`campaign_options`)."""
OPTION_NAMES = {
    "seed": "--seed",
    "mesh_max_edge": "--mesh-mm",
    "sensors": "--sensors",
    "indenters": "--indenters",
    "settings": "--quick/--paper (protocol)",
    "plant": "the plant (hidden effects)",
}
"""The command-line name of each option a resume must repeat (other config fields go by their own name)."""


_START_OVER = "`twin campaign run ... --restart` discards the parts (or delete {parts})"


def campaign_options(config: CampaignConfig, plant: Plant) -> dict:
    """Everything a trajectory's part depends on: the config (as JSON values) and the plant's fingerprint."""
    return {**json.loads(json.dumps(asdict(config), default=str)), "plant": plant.fingerprint()}


def options_digest(options: dict) -> str:
    """A short hash of `campaign_options` (each part carries it as `meta_options_digest`)."""
    return hashlib.sha256(json.dumps(options, sort_keys=True).encode()).hexdigest()[:16]


def prepare_out_dir(out_dir: Path) -> None:
    """Create the output folder; ValueError (one line) when it is a file, under a file, or not writable."""
    if out_dir.exists() and not out_dir.is_dir():
        raise ValueError(f"--out {out_dir} is a file, not a folder")
    try:
        out_dir.mkdir(parents=True, exist_ok=True)
        with tempfile.TemporaryFile(dir=out_dir):
            pass
    except OSError as exc:
        raise ValueError(f"--out {out_dir} is not a writable folder: {exc.strerror or exc}") from exc


def claim_parts(parts_dir: Path, options: dict, restart: bool = False) -> None:
    """Make `parts_dir` hold parts of the campaign `options` describe: discard its parts when `restart`,
    start it (writing MANIFEST) when new, and refuse with a ValueError naming the differing options when its
    parts were made with other options or carry no record of them (a resume would mix two campaigns)."""
    manifest = parts_dir / MANIFEST
    if restart and parts_dir.exists():
        shutil.rmtree(parts_dir)
    if manifest.exists():
        stored = json.loads(manifest.read_text())
        differing = _differences(stored, options)
        if differing:
            detail = "; ".join(differing)
            raise ValueError(
                f"{parts_dir.parent} holds parts of a campaign made with other options ({detail}); "
                f"repeat its options to resume it, or start over: {_START_OVER.format(parts=parts_dir)}"
            )
        return
    if any(parts_dir.rglob("*.npz")):
        raise ValueError(
            f"{parts_dir.parent} holds parts without a record of their options ({MANIFEST}); "
            f"start over: {_START_OVER.format(parts=parts_dir)}"
        )
    parts_dir.mkdir(parents=True, exist_ok=True)
    tmp = manifest.with_name(f"{MANIFEST}.{os.getpid()}.tmp")
    tmp.write_text(json.dumps(options, sort_keys=True, indent=1))
    os.replace(tmp, manifest)


def _differences(stored: dict, options: dict) -> list[str]:
    """ "NAME: A there, B here" for each option that differs (a group such as the protocol settings by its
    differing fields), NAME as the command line spells it (`OPTION_NAMES`)."""
    out = []
    for key in sorted(stored.keys() | options.keys()):
        old, new = stored.get(key), options.get(key)
        if old == new:
            continue
        if isinstance(old, dict) and isinstance(new, dict):
            fields = [k for k in sorted(old.keys() | new.keys()) if old.get(k) != new.get(k)]
            shown = ", ".join(f"{k} {old.get(k)} there, {new.get(k)} here" for k in fields)
            out.append(f"{OPTION_NAMES.get(key, key)}: {shown}")
        else:
            out.append(f"{OPTION_NAMES.get(key, key)}: {_shown(key, old)} there, {_shown(key, new)} here")
    return out


def _shown(key: str, value: object) -> str:
    """An option value as the command line writes it (mesh sizes in mm, lists comma-separated)."""
    if key == "mesh_max_edge" and isinstance(value, int | float):
        return f"{value * 1e3:g}"
    if isinstance(value, list):
        return ",".join(map(str, value))
    return str(value)


TrajectoryTask = tuple[PlannedTrajectory, int, np.ndarray, str]
"""A trajectory to run: its plan, its slot (its clock starts at slot * TRAJECTORY_SLOT_S), the estimated
robot<-biotac 4x4 of its arm, and the parts folder."""


def simulate_trajectory(
    worker: CampaignWorker,
    job: PlannedTrajectory,
    slot: int,
    solver: Callable[[str], SkinSolver] | None = None,
    electrode_counts: bool = True,
) -> tuple[SimBackend, Recording]:
    """Run one trajectory's protocol on the worker's testbed, reset (its own noise stream and clock); the skin
    solved by `solver` (default: the sensor's fe stepper, one solve at a time); electrode and PDC readings
    left out (NaN) unless `electrode_counts` (`SimBackend`). Returns the backend (its `solve_log`) and the
    recording."""
    config, sid, spec = worker.config, job.sensor_id, job.spec
    model, electrodes = worker.sensor(sid)
    scene = worker.scene()
    rng = np.random.default_rng(np.random.SeedSequence([config.seed, sid, spec.trajectory_id]))
    backend = SimBackend(
        scene,
        true_biotac_pose(worker.plant, sid, scene),
        worker.plant.sensor(sid),
        model,
        electrodes,
        worker.plant.noise,
        rng,
        slot * TRAJECTORY_SLOT_S,
        effects=worker.plant.effects,
        joint_offsets={arm: worker.plant.joint_offset(arm) for arm in ARMS},
        solver=solver,
        electrode_counts=electrode_counts,
    )
    return backend, execute(backend, spec, job.arm, job.joint_path, config.settings)


def write_trajectory_part(
    worker: CampaignWorker, task: TrajectoryTask, backend: SimBackend, recording: Recording
) -> tuple[int, int, bool]:
    """Write a simulated trajectory's part file (atomically); returns (sensor id, trajectory id, complete)."""
    job, _, registration, parts_dir = task
    config, sid = worker.config, job.sensor_id
    model = worker.sensor(sid)[0]
    arrays = trajectory_arrays(job, recording, registration, backend.scene, config.settings.sample_rate_hz)
    arrays.update(_fe_rows(backend, arrays["row_time"], model))
    arrays["mesh_reference"] = model.reference
    arrays["meta_options_digest"] = np.asarray(options_digest(campaign_options(config, worker.plant)))
    write_part(part_path(Path(parts_dir), sid, job.spec.trajectory_id), arrays)
    return sid, job.spec.trajectory_id, recording.complete


def _run_one(job: PlannedTrajectory, slot: int, registration: np.ndarray, parts_dir: str) -> tuple[int, int, bool]:
    """Executor task: one trajectory, its fe solved one increment at a time, to its part file."""
    worker = process_worker()
    with naming_trajectory(job):
        backend, recording = simulate_trajectory(worker, job, slot)
        return write_trajectory_part(worker, (job, slot, registration, parts_dir), backend, recording)


@contextmanager
def naming_trajectory(job: PlannedTrajectory) -> Iterator[None]:
    """Re-raise a ValueError from inside with the trajectory it came from ("sensor S trajectory T: ..."), so
    that the one-line error a campaign ends with says which of its hundreds of trajectories to look at."""
    try:
        yield
    except ValueError as exc:
        raise ValueError(f"sensor {job.sensor_id} trajectory {job.spec.trajectory_id}: {exc}") from exc


Finished = Callable[[int, int, bool], None]
"""Called with (sensor id, trajectory id, complete) as each trajectory's part file is written."""
TrajectoryRunner = Callable[[list[TrajectoryTask], CampaignConfig, Plant, Executor, Finished], None]
"""Runs a campaign's trajectory tasks to their part files, calling `Finished` after each (in any order)."""


def one_at_a_time(
    tasks: list[TrajectoryTask], config: CampaignConfig, plant: Plant, executor: Executor, finished: Finished
) -> None:
    """The default `TrajectoryRunner`: each trajectory simulated on an executor worker, its fe solved one
    increment at a time as the controller reaches each pose."""
    for result in executor.map_unordered(_run_one, tasks, init_worker, (config, plant)):
        finished(*result)


def _fe_rows(backend: SimBackend, times: np.ndarray, model: BioTacModel) -> dict[str, np.ndarray]:
    """The plant's fe state at each row time (the last solve at or before it)."""
    log = backend.solve_log
    solve_times = np.array([t for t, _ in log])
    force, pressure, converged, nodal = [], [], [], []
    for t in times:
        k = int(np.searchsorted(solve_times, t, side="right")) - 1
        if k < 0:
            force.append(np.zeros(3))
            pressure.append(model.pressure)
            converged.append(True)
            nodal.append(np.zeros_like(model.reference))
            continue
        result = log[k][1]
        force.append(result.force)
        pressure.append(result.pressure)
        converged.append(result.converged)
        nodal.append(result.displacement)
    return {
        "row_fe_force": np.array(force).reshape(-1, 3),
        "row_fe_pressure": np.array(pressure),
        "row_fe_converged": np.array(converged, dtype=bool),
        "row_nodal_res": np.array(nodal, dtype=np.float32).reshape(len(times), len(model.reference), 3),
    }


@dataclass(frozen=True)
class CampaignResult:
    """Where the files went and what happened."""

    files: dict[int, Path]
    statistics: dict
    ran: int
    skipped: int
    incomplete: int


def run_campaign(
    config: CampaignConfig,
    out_dir: Path,
    workers: int = 1,
    plant: Plant | None = None,
    on_progress: Callable[[int, int], None] | None = None,
    executor: Executor | None = None,
    on_trajectory: Callable[[int, dict[str, np.ndarray]], None] | None = None,
    restart: bool = False,
    runner: TrajectoryRunner = one_at_a_time,
    on_plan: Callable[[str, int, int], None] | None = None,
) -> CampaignResult:
    """Plan and run the campaign into `out_dir` (one HDF5 per sensor); resumes from existing parts.

    Trajectories run on `executor` (default: `workers` local processes, closed at the end; one passed in is
    left to its owner to close) through `runner` (default
    `one_at_a_time`; `twin.campaign_batched.BatchedRunner` solves the fe of all of them as one batch); the
    files do not depend on the executor, and on the runner only within the fe engine's tolerance.
    on_plan(stage, done, total) is told how far planning has come (`plan_campaign`'s `on_stage`);
    on_progress(done, total) is called after each trajectory; on_trajectory(sensor id, part arrays as
    `twin.dataset.read_part` returns them) after each one that ran now (a live view). Parts live in
    `out_dir/parts` until the sensor files are assembled; they are kept so that a later run can resume
    or re-assemble. A resume must repeat the options the parts were made with (ValueError naming the
    difference, `claim_parts`) unless `restart` discards them.
    """
    out_dir = Path(out_dir)
    prepare_out_dir(out_dir)
    plant = plant if plant is not None else make_plant(list(config.sensors), config.seed)
    parts_dir = out_dir / "parts"
    options = campaign_options(config, plant)
    claim_parts(parts_dir, options, restart)
    remove_stale_temporaries(out_dir)  # files a killed run was writing (its workers' parts, its sensor files)
    _check_part_digests(parts_dir, options_digest(options))
    own_executor = executor is None
    executor = executor if executor is not None else LocalExecutor(max(1, workers))
    assembly = Lane("sensor files", FirstFailure())
    files: dict[int, Path] = {}
    try:  # one pool (one start-up a worker) plans and runs the trajectories
        plan = plan_campaign(config, plant, executor, on_plan)
        jobs = [job for job in plan.planned if job.kept]
        slots = {}
        for job in jobs:
            slots[(job.sensor_id, job.spec.trajectory_id)] = sum(1 for key in slots if key[0] == job.sensor_id)
        todo = [j for j in jobs if not part_path(parts_dir, j.sensor_id, j.spec.trajectory_id).exists()]
        done, incomplete = len(jobs) - len(todo), 0
        if on_progress:
            on_progress(done, len(jobs))
        tasks = [
            (j, slots[(j.sensor_id, j.spec.trajectory_id)], plan.registration[(j.sensor_id, j.arm)], str(parts_dir))
            for j in todo
        ]
        skin = make_biotac(config.mesh_max_edge).skin
        assemble = _SensorFiles(config, plant, plan, skin, parts_dir, out_dir)
        # each sensor's file is written on the lane as soon as its last part is (during the other sensors' work)
        missing = Counter(j.sensor_id for j in todo)
        for sid in config.sensors:
            if not missing[sid]:
                assembly.submit(lambda sid=sid: files.__setitem__(sid, assemble(sid)))
        lock = threading.Lock()  # `finished` may be called from a runner's background thread

        def finished(sensor_id: int, trajectory_id: int, complete: bool) -> None:
            nonlocal done, incomplete
            with lock:
                incomplete += not complete
                if on_trajectory:
                    on_trajectory(sensor_id, read_part(part_path(parts_dir, sensor_id, trajectory_id)))
                done += 1
                missing[sensor_id] -= 1
                if not missing[sensor_id]:
                    assembly.submit(lambda: files.__setitem__(sensor_id, assemble(sensor_id)))
                if on_progress:
                    on_progress(done, len(jobs))

        runner(tasks, config, plant, executor, finished)
        assembly.join()
    finally:
        assembly.release()
        if own_executor:
            executor.close()
    files = {sid: files[sid] for sid in config.sensors}
    return CampaignResult(files, plan.statistics(), len(todo), len(jobs) - len(todo), incomplete)


@dataclass(frozen=True)
class _SensorFiles:
    """Assembles a sensor's HDF5 file from its parts (`twin.dataset.assemble_sensor_file`) with the campaign's
    provenance; called with the sensor id, returns the file's path."""

    config: CampaignConfig
    plant: Plant
    plan: CampaignPlan
    skin: SkinMesh
    parts_dir: Path
    out_dir: Path

    def __call__(self, sid: int) -> Path:
        provenance = {
            "code_version": code_version(),
            "config": json.loads(json.dumps(asdict(self.config), default=str)),
            "plant_fingerprint": self.plant.fingerprint(),
            "registration": {a: self.plan.registration[(sid, a)].tolist() for a in ARMS},
        }  # the registration error is the plant's truth (nobody knows it on a real testbed): not in the file
        parts = sorted((self.parts_dir / f"biotac{sid}").glob("trajectory_*.npz"))
        out_path = self.out_dir / f"biotac{sid}.hdf5"
        triangles, ventral = self.skin.triangles, self.skin.ventral
        return assemble_sensor_file(parts, out_path, sid, list(INDENTERS), provenance, triangles, ventral).path


def _check_part_digests(parts_dir: Path, digest: str) -> None:
    """ValueError when a part in `parts_dir` was made with other options than those of `digest`."""
    for path in sorted(parts_dir.rglob("trajectory_*.npz")):
        with np.load(path, allow_pickle=False) as part:
            made_by = str(part["meta_options_digest"]) if "meta_options_digest" in part.files else "unknown"
        if made_by != digest:
            raise ValueError(
                f"{path} was made with other campaign options (digest {made_by}, this run {digest}); "
                f"start over: {_START_OVER.format(parts=parts_dir)}"
            )


def code_version() -> str:
    """The package version plus the commit from BIOTAC_TWIN_COMMIT when set."""
    from twin import __version__

    return f"{__version__}+{os.environ.get('BIOTAC_TWIN_COMMIT', 'unknown')}"
