"""The campaign on the batched fe engine (`twin.campaign_batched`, warp's CPU device) against the one-at-a-time
campaign, whose fe is stepped increment by increment as the controller reaches each pose: the same file within
the engine's tolerance, also after an interrupted batched run is resumed.

The tiny campaign presses hard enough to exercise every path of the batched runner: a viscoelastic plant
skin (relaxation re-solves at held poses, each system on its own clock), a controller force-limit stop (the
retreat after it leaves the recorded schedule) and an F/T gain of 0.5 that hides half the force, so the
controller needs solves past the batch's fe force limit and the trajectory is solved again without one.
Also: the backend's held electrode impedance (computed once per skin state) changes no count.

Each campaign runs on the plant as well with `robot_compliance` (0.08 mm/N): the batch then solves every pose
where the load of the last solve puts the tip and settles it by more solves at the same time, as the one-at-a-time
backend does, and writes the solves it made, which the synthesis replays.
"""

from collections.abc import Callable, Iterator, Sequence
from dataclasses import replace
from pathlib import Path
from types import SimpleNamespace
from typing import Any

import h5py
import numpy as np
import pytest

import twin.campaign_batched as campaign_batched
from twin.campaign import QUICK_CONFIG, run_campaign
from twin.campaign_batched import (
    FE_FORCE_LIMIT_FACTOR,
    SOLVES_DIR,
    BatchedRunner,
    SolveSchedule,
    _kept,
    read_solves,
    solves_path,
    write_solves,
)
from twin.effects import COMPLIANCE
from twin.executors import Executor
from twin.plant import Plant, make_plant
from twin.protocol import QUICK_SETTINGS
from twin.sim_backend import SimSettings

CONFIG = replace(
    QUICK_CONFIG,
    sensors=(2,),
    indenters=("sphere_medium",),
    settings=replace(QUICK_SETTINGS, normal_depth=0.8e-3, angled_depth=0.4e-3, pause_s=0.2, force_limit=0.25),
)
"""A normal 0.8 mm and an angled 0.4 mm press of sphere_medium on sensor 2 (2 mm mesh, 0.2 s pauses), stopped
above 0.25 N measured (the normal press reaches about 0.32 N of fe force by 0.5 mm and 0.54 N by 0.8 mm with the
layer contact law, in steps of ~0.075 N: the batch ends it at 0.39 N, where half of it measured plus the noise
stays below the limit)."""
PLANT = make_plant(
    [2],
    0,
    mount_rotation_error=0.0,
    mount_translation_error=0.0,
    exact_registration=True,
    effects={"skin_relaxation": {"fraction": 0.3, "time_s": 0.2}, "ft_gain": {"scale": 0.5}},
)
"""Exact registration (the tip reaches the skin where planned), a relaxing skin, an F/T reading of half the force."""
COMPLIANCE_M_PER_N = 8e-5
"""The compliant plant's robot compliance (0.08 mm/N, as tests/test_robot_compliance.py)."""
COMPLIANT_PLANT = replace(PLANT, effects=PLANT.effects | {COMPLIANCE: {"compliance": COMPLIANCE_M_PER_N}})
"""`PLANT` on an arm and tool that give way under the load."""
FORCE_TOLERANCE = 1e-3
"""Forces agree within this share of the largest force (docs/scale.md: with friction, the batched and the
one-system engine agree within 1e-3 of |F|); on warp's CPU device they are in fact the same bits."""


class InProcess(Executor):
    """Runs every task here, one after the other (no worker start-up in a test); sets up again only for other
    setup arguments."""

    def __init__(self) -> None:
        self.set_up: tuple = ()

    def map_unordered(
        self, task: Callable[..., Any], jobs: Sequence[tuple], setup: Callable[..., None], setup_args: tuple
    ) -> Iterator[Any]:
        if self.set_up != (setup, *map(id, setup_args)):
            setup(*setup_args)
            self.set_up = (setup, *map(id, setup_args))
        for job in jobs:
            yield task(*job)


def _read_all(path: Path) -> dict[str, np.ndarray]:
    arrays: dict[str, np.ndarray] = {}
    with h5py.File(path, "r") as f:
        f.visititems(lambda name, item: arrays.__setitem__(name, item[()]) if isinstance(item, h5py.Dataset) else None)
    return arrays


def _assert_same_campaign(reference: dict[str, np.ndarray], other: dict[str, np.ndarray]) -> None:
    """Same layout, rows and completeness exactly; forces, pressures, displacements within the fe tolerance;
    electrode and PDC counts within one count (noise is added before rounding)."""
    assert reference.keys() == other.keys()
    scale = np.abs(reference["fe_force/data"]).max()
    for key, expected in reference.items():
        got = other[key]
        assert got.shape == expected.shape, key
        if key.endswith(("force/data", "/wrench")):
            np.testing.assert_allclose(got, expected, rtol=0, atol=FORCE_TOLERANCE * scale, err_msg=key)
        elif key.endswith("fe_pressure/data"):
            np.testing.assert_allclose(got, expected, rtol=1e-5, err_msg=key)
        elif key.endswith("nodal_res/data"):
            np.testing.assert_allclose(got, expected, rtol=0, atol=1e-6, err_msg=key)
        elif key.endswith(("electrode_vals/data", "pdc/data", "/electrodes", "/pdc")):
            np.testing.assert_allclose(got, expected, rtol=0, atol=1.0, err_msg=key)
        else:
            np.testing.assert_array_equal(got, expected, err_msg=key)


def _spy_on_batches(monkeypatch: pytest.MonkeyPatch) -> list[float]:
    """The force limit (N) of each batched fe run the campaign makes that solves something, in order."""
    limits: list[float] = []
    run_trajectories = campaign_batched.run_trajectories

    def spy(*args: Any, **kwargs: Any) -> Any:
        solved, told = [], kwargs["on_trajectory"]

        def on_trajectory(index: int, increments: list) -> None:
            solved.append(len(increments))  # before the campaign writes and drops them
            told(index, increments)

        run = run_trajectories(*args, **(kwargs | {"on_trajectory": on_trajectory}))
        if any(solved):
            limits.append(args[4])
        return run

    monkeypatch.setattr(campaign_batched, "run_trajectories", spy)
    return limits


@pytest.fixture(scope="module", params=[PLANT, COMPLIANT_PLANT], ids=["rigid", "compliant"])
def plant(request: pytest.FixtureRequest) -> Plant:
    return request.param


@pytest.fixture(scope="module")
def one_at_a_time(plant: Plant, tmp_path_factory: pytest.TempPathFactory) -> dict[str, np.ndarray]:
    out = tmp_path_factory.mktemp("one_at_a_time")
    run_campaign(CONFIG, out, plant=plant, executor=InProcess())
    return _read_all(out / "biotac2.hdf5")


def test_batched_campaign_equals_the_one_at_a_time_campaign(
    plant: Plant, one_at_a_time: dict[str, np.ndarray], tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    limits = _spy_on_batches(monkeypatch)
    result = run_campaign(CONFIG, tmp_path, plant=plant, executor=InProcess(), runner=BatchedRunner("cpu"))
    # the normal press ran past the batch's fe force limit (half the force measured) and was solved again
    assert limits == [FE_FORCE_LIMIT_FACTOR * CONFIG.settings.force_limit, np.inf]
    assert result.ran == 2 and result.incomplete == 1
    batched = _read_all(tmp_path / "biotac2.hdf5")
    _assert_same_campaign(one_at_a_time, batched)
    wrench = batched["raw/0/wrench"]  # the normal press: stopped once the tared reading passed the limit
    assert np.linalg.norm(wrench[-1, :3] - wrench[0, :3]) > CONFIG.settings.force_limit
    assert batched["fe_converged/data"].all()
    assert not list((tmp_path / "parts" / SOLVES_DIR).rglob("*.npz"))  # dropped once the parts are written


def test_an_interrupted_batched_campaign_resumes_to_the_same_file(
    plant: Plant, one_at_a_time: dict[str, np.ndarray], tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    def interrupt_after_the_first_part(done: int, total: int) -> None:
        if done == 1:
            raise KeyboardInterrupt

    with pytest.raises(KeyboardInterrupt):
        run_campaign(
            CONFIG,
            tmp_path,
            plant=plant,
            executor=InProcess(),
            runner=BatchedRunner("cpu"),
            on_progress=interrupt_after_the_first_part,
        )
    assert len(list((tmp_path / "parts").rglob("trajectory_*.npz"))) == 1
    assert len(list((tmp_path / "parts" / SOLVES_DIR).rglob("solves_*.npz"))) == 1  # solved, not yet synthesised
    assert not (tmp_path / "biotac2.hdf5").exists()
    limits = _spy_on_batches(monkeypatch)
    resumed = run_campaign(CONFIG, tmp_path, plant=plant, executor=InProcess(), runner=BatchedRunner("cpu"))
    assert (resumed.ran, resumed.skipped) == (1, 1)
    assert limits == [np.inf]  # its batched solves were kept: only the normal press's re-solve without a limit
    assert not list((tmp_path / "parts" / SOLVES_DIR).rglob("*.npz"))
    _assert_same_campaign(one_at_a_time, _read_all(tmp_path / "biotac2.hdf5"))


def test_a_resume_keeps_solves_only_for_the_schedule_they_were_solved_for(tmp_path: Path) -> None:
    """A plan re-derived in another run may ask for its first solve a controller tick later (on a GPU the
    inflation's sums have no fixed order): the kept solves are then solved again, not replayed off schedule."""
    job = SimpleNamespace(sensor_id=2, spec=SimpleNamespace(trajectory_id=7))
    task = (job, 0, np.eye(4), str(tmp_path))
    schedule = SolveSchedule("sphere_medium", np.array([0.5, 0.6]), np.tile(np.eye(3), (2, 1, 1)), np.zeros((2, 3)))
    assert not _kept(task, schedule)  # nothing solved yet
    solves_path(task).parent.mkdir(parents=True)
    write_solves(solves_path(task), schedule, [])
    assert _kept(task, schedule)
    assert not _kept(task, replace(schedule, times=schedule.times + 0.01))
    assert not _kept(task, replace(schedule, translations=schedule.translations + 1e-12))
    assert not _kept(task, replace(schedule, indenter="sphere_large"))
    settled = replace(schedule.at(np.array([0, 0, 1]), np.ones((3, 3))), times=np.array([0.5, 0.5, 0.6]))
    write_solves(solves_path(task), schedule, [], settled)  # a compliant plant's solves: kept for the schedule
    assert _kept(task, schedule) and not _kept(task, settled)
    written, solved, _ = read_solves(solves_path(task))
    assert written.same_as(schedule) and solved.same_as(settled)


def test_a_compliant_plants_batch_settles_each_tip_where_its_force_puts_it(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    """The solves the batch writes for a compliant plant: the poses' commanded tips deflected by the skin's force
    (tens of um on these presses), repeated at the same time until the tip stands within the backend's pose
    tolerance of where its force puts it."""
    written: list[tuple[SolveSchedule, SolveSchedule, np.ndarray]] = []

    def spy(path: Path, schedule: SolveSchedule, increments: list, solved: SolveSchedule | None = None) -> None:
        written.append((schedule, solved, np.array([r.force for r in increments])))
        write_solves(path, schedule, increments, solved)

    monkeypatch.setattr(campaign_batched, "write_solves", spy)
    run_campaign(CONFIG, tmp_path, plant=COMPLIANT_PLANT, executor=InProcess(), runner=BatchedRunner("cpu"))
    assert len(written) == 3  # both presses, then the normal one again without a force limit
    settles, deflection = 0, 0.0
    for schedule, solved, forces in written:
        assert len(np.unique(schedule.times)) == len(schedule.times)
        pose = np.searchsorted(schedule.times, solved.times[: len(forces)])
        np.testing.assert_array_equal(solved.rotations[: len(forces)], schedule.rotations[pose])
        commanded, tips = schedule.translations[pose], solved.translations[: len(forces)]
        last = np.append(solved.times[1 : len(forces)] != solved.times[: len(forces) - 1], True)  # a time's last
        settled = commanded - COMPLIANCE_M_PER_N * forces
        assert np.linalg.norm(settled - tips, axis=1)[last].max() <= SimSettings().pose_tolerance
        deflection = max(deflection, np.linalg.norm(commanded - tips, axis=1).max())
        settles += int((~last).sum())
    assert settles >= 10, settles  # measured: 108 (272 solves at 164 times)
    assert deflection > 2e-5, deflection  # measured: 37 um
