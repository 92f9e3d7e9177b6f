"""Campaign executors: a Ray run equals the local process pool, and a worker killed mid-trajectory loses
nothing (the trajectory re-runs, no part is duplicated)."""

import os
import sys
import threading
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

CONFIG = replace(QUICK_CONFIG, sensors=(2,), indenters=("sphere_medium",))
"""Two trajectories (one normal, one angled) on one sensor, 2 mm mesh."""


def _die_mid_task(marker_dir: str, delay_s: float, task: Callable[..., Any], job: tuple) -> Any:
    """Run the task; on its first attempt (no marker yet) the worker process dies `delay_s` into it."""
    marker = Path(marker_dir) / f"{job[0].sensor_id}-{job[0].spec.trajectory_id}"
    if not marker.exists():
        marker.touch()
        threading.Timer(delay_s, os._exit, (1,)).start()
    return task(*job)


class _KillingExecutor(Executor):
    """Wraps an executor so that every task's first attempt dies part-way through."""

    def __init__(self, inner: Executor, marker_dir: Path, delay_s: float) -> None:
        self.inner, self.marker_dir, self.delay_s = inner, marker_dir, delay_s

    def map_unordered(
        self, task: Callable[..., Any], jobs: Sequence[tuple], setup: Callable[..., None], setup_args: tuple
    ) -> Iterator[Any]:
        wrapped = [(str(self.marker_dir), self.delay_s, task, job) for job in jobs]
        return self.inner.map_unordered(_die_mid_task, wrapped, setup, setup_args)


def _read_all(path: Path) -> dict[str, np.ndarray]:
    arrays: dict[str, np.ndarray] = {}
    with h5py.File(path, "r") as f:
        f.visititems(lambda name, item: arrays.__setitem__(name, item[()]) if isinstance(item, h5py.Dataset) else None)
    return arrays


def test_ray_with_killed_workers_writes_the_local_pool_dataset(tmp_path: Path) -> None:
    ray = pytest.importorskip("ray")
    from ray import cloudpickle

    from twin.executors import RayExecutor

    cloudpickle.register_pickle_by_value(sys.modules[__name__])  # Ray workers cannot import this test module
    local = run_campaign(CONFIG, tmp_path / "local", executor=LocalExecutor(2))
    markers = tmp_path / "markers"
    markers.mkdir()
    try:
        killing = _KillingExecutor(RayExecutor(num_cpus=2, max_retries=2), markers, delay_s=1.0)
        result = run_campaign(CONFIG, tmp_path / "ray", executor=killing)
    finally:
        ray.shutdown()
    assert local.ran == result.ran == 2 and result.incomplete == 0
    assert len(list(markers.iterdir())) == 2, "every trajectory's first attempt was killed"
    parts = sorted(p.name for p in (tmp_path / "ray" / "parts").rglob("*"))
    assert parts == sorted(p.name for p in (tmp_path / "local" / "parts").rglob("*"))
    a, b = _read_all(local.files[2]), _read_all(result.files[2])
    assert a.keys() == b.keys()
    for key in a:
        np.testing.assert_array_equal(a[key], b[key], err_msg=key)
    assert sorted(a["trajectories/trajectory_id"].tolist()) == [0, 1]


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
