"""Campaigns on one robot: the simulated campaign's plan, controller and dataset, run on any `Backend`.

`run_hardware_campaign` executes a `CampaignPlan` (from `twin.campaign.plan_campaign`) trajectory by
trajectory with `twin.controller.execute`, on an open backend (any `twin.backend.Backend`; the CLI
layer opens `hardware.backend.HardwareBackend` for the real testbed or its simulated devices).
Before each trajectory both arms go to the scene's home pose, the state every simulated trajectory
starts from and the one the planner checked collisions against. Rows, raw recordings and metadata
are written as the same part files and HDF5 sensor file (`docs/dataset.md`) as a simulated
campaign, without the fe features (there is no fe model to read on a robot). Time is the backend's
clock: wall time on hardware.

One sensor is mounted at a time, so a plan must hold exactly one. Indenters are mounted by a person:
`on_tool_change(arm, indenter)` is called before the first trajectory that needs a different one on
that arm (trajectories run grouped by indenter, then arm). The campaign stops at the first
trajectory that does not complete (fault, force limit): its part is written and marked incomplete,
the sensor file is assembled from what exists, and a person looks before resuming. A resumed run
skips trajectories whose part exists; delete a part to run that trajectory again.

The registration used is the plan's: `plan_campaign` simulates it in the plant. On the real bench a
measured one must take its place before planning (not done yet: docs/hardware.md).
"""

from __future__ import annotations

import json
from collections.abc import Callable
from dataclasses import asdict, dataclass
from pathlib import Path

from assets.indenters import INDENTERS
from twin.backend import ARMS, Backend, BackendError
from twin.campaign import (
    CampaignConfig,
    CampaignPlan,
    CampaignResult,
    code_version,
    trajectory_arrays,
)
from twin.controller import Recording, execute, move_to
from twin.dataset import assemble_sensor_file, part_path, write_part
from twin.planning import PlannedTrajectory
from twin.scene import TestbedScene


@dataclass(frozen=True)
class HardwareCampaignResult(CampaignResult):
    """`CampaignResult` plus why the campaign stopped early (None when every trajectory ran)."""

    stopped: str | None = None


def mounted_sensor(config: CampaignConfig) -> int:
    """The one sensor a hardware campaign of `config` runs on; ValueError if it names several."""
    if len(config.sensors) != 1:
        raise ValueError(
            f"a hardware campaign runs on the one mounted sensor; got sensors {config.sensors} "
            "(run once per sensor, e.g. --sensors 2)"
        )
    return config.sensors[0]


def campaign_jobs(plan: CampaignPlan) -> list[PlannedTrajectory]:
    """The plan's kept trajectories in running order: by indenter (as configured), then arm, then id."""
    mounted_sensor(plan.config)
    order = {name: k for k, name in enumerate(plan.config.indenters)}
    jobs = [job for job in plan.planned if job.kept]
    return sorted(jobs, key=lambda j: (order[j.spec.indenter], ARMS.index(j.arm), j.spec.trajectory_id))


def run_hardware_campaign(
    plan: CampaignPlan,
    out_dir: Path,
    backend: Backend,
    provenance: dict | None = None,
    on_tool_change: Callable[[str, str], None] | None = None,
    on_progress: Callable[[int, int], None] | None = None,
) -> HardwareCampaignResult:
    """Run `plan` on `backend` (left open) into `out_dir`, resuming from existing parts.

    provenance: extra entries for the file's provenance (e.g. the hardware config). on_progress(done,
    total) is called after each trajectory. Parts live in `out_dir/parts`, as in `run_campaign`.
    """
    jobs = campaign_jobs(plan)
    sid = mounted_sensor(plan.config)
    out_dir = Path(out_dir)
    out_dir.mkdir(parents=True, exist_ok=True)
    parts_dir = out_dir / "parts"
    scene = TestbedScene(plan.config.scene)
    tick = 1.0 / plan.config.settings.sample_rate_hz
    todo = [j for j in jobs if not part_path(parts_dir, sid, j.spec.trajectory_id).exists()]
    ran, incomplete, stopped = 0, 0, None
    mounted: dict[str, str | None] = dict.fromkeys(ARMS)
    if on_progress:
        on_progress(len(jobs) - len(todo), len(jobs))
    for job in todo:
        tid = job.spec.trajectory_id
        if mounted[job.arm] != job.spec.indenter:
            if on_tool_change:
                on_tool_change(job.arm, job.spec.indenter)
            mounted[job.arm] = job.spec.indenter
        try:
            _park(backend, scene, tick)
        except BackendError as exc:
            stopped = f"could not park the arms before trajectory {tid}: {exc}"
            break
        recording = _execute(backend, plan, job, scene, parts_dir)
        ran += 1
        if on_progress:
            on_progress(len(jobs) - len(todo) + ran, len(jobs))
        if not recording.complete:
            incomplete += 1
            kept = "kept as incomplete" if len(recording.time) else "no sample recorded, nothing written"
            stopped = f"trajectory {tid} did not complete ({recording.message}); {kept}"
            break
    else:
        try:
            _park(backend, scene, tick)
        except BackendError as exc:
            stopped = f"could not park the arms after the last trajectory: {exc}"
    parts = sorted((parts_dir / f"biotac{sid}").glob("trajectory_*.npz"))
    info = assemble_sensor_file(
        parts, out_dir / f"biotac{sid}.hdf5", sid, list(INDENTERS), _provenance(plan, backend, provenance)
    )
    return HardwareCampaignResult({sid: info.path}, plan.statistics(), ran, len(jobs) - len(todo), incomplete, stopped)


def _execute(
    backend: Backend, plan: CampaignPlan, job: PlannedTrajectory, scene: TestbedScene, parts_dir: Path
) -> Recording:
    """Run `job` with the controller and write its part (unless not one sample was recorded)."""
    settings = plan.config.settings
    recording = execute(backend, job.spec, job.arm, job.joint_path, settings)
    if len(recording.time):
        registration = plan.registration[(job.sensor_id, job.arm)]
        arrays = trajectory_arrays(job, recording, registration, scene, settings.sample_rate_hz)
        write_part(part_path(parts_dir, job.sensor_id, job.spec.trajectory_id), arrays)
    return recording


def _park(backend: Backend, scene: TestbedScene, tick: float) -> None:
    """Both arms to the scene's home pose (rad), one after the other; BackendError if one cannot."""
    for arm in ARMS:
        move_to(backend, arm, scene.home_joints(arm), tick)


def _provenance(plan: CampaignPlan, backend: Backend, extra: dict | None) -> dict:
    """The sensor file's provenance: code, backend, campaign config, registration used, and `extra`.

    The plan's registration error is the simulated plant's truth, not the testbed's: never recorded."""
    sid = mounted_sensor(plan.config)
    return {
        "code_version": code_version(),
        "backend": type(backend).__name__,
        "config": json.loads(json.dumps(asdict(plan.config), default=str)),
        "registration": {a: plan.registration[(sid, a)].tolist() for a in ARMS},
        **(extra or {}),
    }
