"""Campaign executors: a Ray run equals the local process pool, and a worker killed mid-trajectory loses
nothing (the trajectory re-runs, no part is duplicated)."""

import os
import sys
import time
from collections.abc import Callable, Iterator, Sequence
from dataclasses import replace
from pathlib import Path
from typing import Any

import h5py
import numpy as np
import pytest
from typer.testing import CliRunner

from twin.campaign import QUICK_CONFIG, run_campaign
from twin.cli import app
from twin.executors import Executor, ExecutorUnavailable, LocalExecutor, make_executor
from twin.protocol import QUICK_SETTINGS

CONFIG = replace(
    QUICK_CONFIG,
    sensors=(2,),
    indenters=("sphere_medium",),
    settings=replace(QUICK_SETTINGS, normal_depth=0.4e-3, angled_depth=0.2e-3, pause_s=0.1),
)
"""Two short trajectories (one normal, one angled) on one sensor, 2 mm mesh: the tests' tiny campaign."""
KILLED = 0
"""Trajectory whose first attempt dies; the other one runs undisturbed on the second worker."""
KILL_AFTER_SOLVES = 3
"""The killed attempt's worker exits after this many fe solves of the trajectory (indenter in contact)."""


def _die_mid_trajectory(attempts_dir: str, task: Callable[..., Any], job: tuple) -> Any:
    """Run the task, logging each attempt of a trajectory (planning tasks run as they are); the first attempt
    of trajectory KILLED ends its worker process (`os._exit`) right after its KILL_AFTER_SOLVES-th fe solve,
    before any part file is written."""
    if not hasattr(job[0], "spec"):  # a planning task
        return task(*job)
    name = f"{job[0].sensor_id}-{job[0].spec.trajectory_id}"
    attempt = sum(not p.name.endswith(".done") for p in Path(attempts_dir).glob(f"{name}.*")) + 1
    (Path(attempts_dir) / f"{name}.{attempt}").touch()
    if job[0].spec.trajectory_id == KILLED and attempt == 1:
        from twin.sim_backend import SimBackend

        advance = SimBackend.advance

        def advance_then_die(self: SimBackend, dt: float) -> None:
            advance(self, dt)
            if len(self.solve_log) >= KILL_AFTER_SOLVES:
                os._exit(1)

        SimBackend.advance = advance_then_die  # this process dies with the patch in place
    result = task(*job)
    (Path(attempts_dir) / f"{name}.{attempt}.done").touch()
    return result


class _KillingExecutor(Executor):
    """Wraps an executor so that trajectory KILLED's first attempt dies part-way through."""

    def __init__(self, inner: Executor, attempts_dir: Path) -> None:
        self.inner, self.attempts_dir = inner, attempts_dir

    def map_unordered(
        self, task: Callable[..., Any], jobs: Sequence[tuple], setup: Callable[..., None], setup_args: tuple
    ) -> Iterator[Any]:
        wrapped = [(str(self.attempts_dir), task, job) for job in jobs]
        return self.inner.map_unordered(_die_mid_trajectory, wrapped, setup, setup_args)


def _read_all(path: Path) -> dict[str, np.ndarray]:
    arrays: dict[str, np.ndarray] = {}
    with h5py.File(path, "r") as f:
        f.visititems(lambda name, item: arrays.__setitem__(name, item[()]) if isinstance(item, h5py.Dataset) else None)
    return arrays


def test_ray_with_a_killed_worker_writes_the_local_pool_dataset(tmp_path: Path) -> None:
    ray = pytest.importorskip("ray")
    from ray import cloudpickle

    from twin.executors import RayExecutor

    cloudpickle.register_pickle_by_value(sys.modules[__name__])  # Ray workers cannot import this test module
    attempts = tmp_path / "attempts"
    attempts.mkdir()
    executor = RayExecutor(num_cpus=2, object_store_memory=80 * 2**20)  # two workers, 3 retries
    try:
        # The reference (while Ray's workers start): the default local pool, one process running both
        # trajectories one after the other.
        local = run_campaign(CONFIG, tmp_path / "local", executor=LocalExecutor(1))
        result = run_campaign(CONFIG, tmp_path / "ray", executor=_KillingExecutor(executor, attempts))
    finally:
        ray.shutdown()
    assert local.ran == result.ran == 2 and result.incomplete == 0
    other = 1 - KILLED
    # The killed attempt never finished, its re-run did; the other trajectory ran once.
    assert sorted(p.name for p in attempts.iterdir()) == [
        f"2-{KILLED}.1",
        f"2-{KILLED}.2",
        f"2-{KILLED}.2.done",
        f"2-{other}.1",
        f"2-{other}.1.done",
    ]
    # Nothing lost or duplicated: the same part files (no leftovers of the killed attempt), the same arrays.
    parts = sorted(str(p.relative_to(tmp_path / "ray")) for p in (tmp_path / "ray" / "parts").rglob("*"))
    assert parts == sorted(str(p.relative_to(tmp_path / "local")) for p in (tmp_path / "local" / "parts").rglob("*"))
    a, b = _read_all(local.files[2]), _read_all(result.files[2])
    assert a.keys() == b.keys()
    for key in a:
        np.testing.assert_array_equal(a[key], b[key], err_msg=key)
    assert sorted(a["trajectories/trajectory_id"].tolist()) == [0, 1]


def test_a_local_pool_serves_every_map_with_the_same_setup_until_closed() -> None:
    """One start-up for both maps of a batched campaign; another setup gets new workers; close ends them."""
    executor, setup_args, other_args = LocalExecutor(1), (float(0),), (float(0),)  # two equal objects
    first = list(executor.map_unordered(os.getpid, [()], time.sleep, setup_args))
    again = list(executor.map_unordered(os.getpid, [()], time.sleep, setup_args))
    assert first == again and first[0] != os.getpid()
    other = list(executor.map_unordered(os.getpid, [()], time.sleep, other_args))  # equal, but not the same object
    assert other != first
    executor.close()
    assert executor._pool is None
    with pytest.raises(ProcessLookupError):  # the replaced and the closed workers are gone (and reaped)
        os.kill(first[0], 0)
    with pytest.raises(ProcessLookupError):
        os.kill(other[0], 0)


def _count_setup(tag: float) -> None:
    """A worker setup that counts its runs in this process (in the environment: Ray pickles this function)."""
    os.environ["TWIN_TEST_SETUPS"] = str(int(os.environ.get("TWIN_TEST_SETUPS", "0")) + 1)


def _setups_here() -> tuple[int, int]:
    return os.getpid(), int(os.environ["TWIN_TEST_SETUPS"])


def test_ray_runs_a_setup_once_per_worker_however_many_maps_use_it() -> None:
    """The batched campaign synthesises in many small maps with one setup: a Ray worker must not set up again
    for each (that would rebuild the sensor models every map); another setup object is run anew."""
    ray = pytest.importorskip("ray")
    from ray import cloudpickle

    from twin.executors import RayExecutor

    cloudpickle.register_pickle_by_value(sys.modules[__name__])
    executor = RayExecutor(num_cpus=1, object_store_memory=80 * 2**20)
    setup_args, other_args = (float(0),), (float(0),)  # two equal objects
    try:
        maps = [list(executor.map_unordered(_setups_here, [()] * 3, _count_setup, setup_args)) for _ in range(4)]
        other = list(executor.map_unordered(_setups_here, [()], _count_setup, other_args))
    finally:
        ray.shutdown()
    runs = {pid: count for results in maps for pid, count in results}
    assert set(runs.values()) == {1}, f"setups per worker over four maps: {runs}"
    assert other[0][1] == runs.get(other[0][0], 0) + 1


def test_executor_choice_is_checked() -> None:
    with pytest.raises(ValueError, match="unknown executor"):
        make_executor("dask")
    with pytest.raises(ValueError, match="needs --executor ray"):
        make_executor("local", address="10.0.0.1:6379")
    with pytest.raises(ValueError, match="workers"):
        LocalExecutor(0)


def test_cli_explains_a_missing_ray(monkeypatch: pytest.MonkeyPatch, tmp_path: Path) -> None:
    monkeypatch.setitem(sys.modules, "ray", None)  # import ray raises ImportError
    with pytest.raises(ExecutorUnavailable, match="pip install"):
        make_executor("ray")
    result = CliRunner().invoke(app, ["campaign", "run", "--quick", "--executor", "ray", "--out", str(tmp_path)])
    assert result.exit_code == 2
    assert "needs Ray" in result.output
