"""CPU cost per trajectory of the batched campaign's protocol passes (issue 18), this code against another commit.

The campaign: sensor 2, sphere_medium, the paper's protocol (`ProtocolSettings()`: a normal 3 mm and four
angled 1.5 mm presses per point, 0.1 mm increments, 5 s pauses, unloading, 100 Hz), `--points` points, the
2 mm mesh by default (the fe is not what is measured). Two runs of `twin campaign run --device cpu`'s runner
(`BatchedRunner`) per code:

- in process: every executor task runs in this process, its worker set up (models inflated) before the
  clock starts, and `process_time` is read at every stage report: CPU seconds of the schedule pass, the fe
  (warp's CPU device) and the synthesis pass, per trajectory;
- pool: `run_campaign` on `LocalExecutor(--workers)`: wall and CPU seconds of the driver and its workers
  together (planning and fe included), where the pool's start-ups (imports, PARDISO, the models inflated
  again in each worker) show.

Each code runs in its own subprocess with its tree first on PYTHONPATH: this checkout, and `--compare-with`
(a commit, extracted with `git archive`, or a folder holding another tree); the HDF5 files of the two are
compared array by array.

    python benchmarks/campaign_cpu_bench.py [--points 1] [--mesh-mm 2] [--workers 1] [--compare-with REV]
        [--out runs/campaign_cpu_bench] [--json FILE]

One point (5 trajectories, ~90 thousand samples a pass) takes about 2 min per code and run on a quiet
2-core box with the base commit of this benchmark.
"""

from __future__ import annotations

import argparse
import json
import os
import resource
import subprocess
import sys
import tarfile
import tempfile
import time
from collections.abc import Callable, Iterator, Sequence
from pathlib import Path
from typing import Any

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
STAGES = ("schedules", "fe", "synthesis")


def _config(points: int, mesh_mm: float) -> Any:
    from twin.campaign import CampaignConfig
    from twin.protocol import ProtocolSettings

    settings = ProtocolSettings(points_per_indenter=points)
    return CampaignConfig(sensors=(2,), indenters=("sphere_medium",), settings=settings, mesh_max_edge=mesh_mm * 1e-3)


def _in_process_executor() -> Any:
    from twin.executors import Executor

    class InProcess(Executor):
        """Runs every task here, one after the other; sets up once per setup (`prepare` before the clock)."""

        def __init__(self) -> None:
            self.set_up: tuple = ()

        def prepare(self, setup: Callable[..., None], setup_args: tuple) -> None:
            setup(*setup_args)
            self.set_up = (setup, *map(id, setup_args))

        def map_unordered(
            self, task: Callable[..., Any], jobs: Sequence[tuple], setup: Callable[..., None], setup_args: tuple
        ) -> Iterator[Any]:
            if self.set_up != (setup, *map(id, setup_args)):
                self.prepare(setup, setup_args)
            for job in jobs:
                yield task(*job)

    return InProcess()


def _in_process(out: Path, points: int, mesh_mm: float) -> dict:
    """CPU seconds (process_time) of each stage of the batched runner, every task in this process."""
    from twin.campaign import init_worker, process_worker, run_campaign
    from twin.campaign_batched import BatchedRunner
    from twin.plant import make_plant

    config, plant = _config(points, mesh_mm), make_plant([2], 0)
    executor = _in_process_executor()
    executor.prepare(init_worker, (config, plant))
    process_worker().sensor(2)  # the worker's inflated model, as a pool worker has it after its first task
    seconds = dict.fromkeys(STAGES, 0.0)
    marks: list[float] = []

    def on_stage(stage: str, done: int, total: int) -> None:
        now = time.process_time()
        seconds[stage] += now - marks[-1]  # the time since the last report went to this stage
        marks.append(now)

    batched = BatchedRunner("cpu", on_stage=on_stage)

    def runner(*args: Any) -> None:
        marks.append(time.process_time())
        batched(*args)
        seconds["synthesis"] += time.process_time() - marks[-1]  # the last task's tail, if it reported nothing

    result = run_campaign(config, out, plant=plant, executor=executor, runner=runner, restart=True)
    return {"trajectories": result.ran, "incomplete": result.incomplete, "cpu_s": seconds}


def _pool(out: Path, points: int, mesh_mm: float, workers: int) -> dict:
    """Wall and CPU seconds (driver and workers) of the whole batched campaign on a local process pool."""
    from twin.campaign import run_campaign
    from twin.campaign_batched import BatchedRunner
    from twin.executors import LocalExecutor
    from twin.plant import make_plant

    config, plant = _config(points, mesh_mm), make_plant([2], 0)
    executor = LocalExecutor(workers)
    before = [resource.getrusage(who) for who in (resource.RUSAGE_SELF, resource.RUSAGE_CHILDREN)]
    start = time.perf_counter()
    result = run_campaign(config, out, plant=plant, executor=executor, runner=BatchedRunner("cpu"), restart=True)
    getattr(executor, "close", lambda: None)()  # a kept pool's workers are reaped (and counted) here
    wall = time.perf_counter() - start
    after = [resource.getrusage(who) for who in (resource.RUSAGE_SELF, resource.RUSAGE_CHILDREN)]
    cpu = [a.ru_utime + a.ru_stime - b.ru_utime - b.ru_stime for a, b in zip(after, before, strict=True)]
    return {"trajectories": result.ran, "wall_s": wall, "driver_cpu_s": cpu[0], "worker_cpu_s": cpu[1]}


def _measure(args: argparse.Namespace) -> None:
    """The subprocess's part: both runs with the package on sys.path, as JSON on stdout's last line."""
    out = Path(args.out)
    found = {
        "in_process": _in_process(out / "in_process", args.points, args.mesh_mm),
        "pool": _pool(out / "pool", args.points, args.mesh_mm, args.workers),
    }
    print(json.dumps(found))


def _tree(rev: str, where: Path) -> Path:
    """The files of commit `rev` of this repository, extracted under `where`."""
    archive = where / "tree.tar"
    subprocess.run(["git", "-C", str(ROOT), "archive", "-o", str(archive), rev], check=True)
    with tarfile.open(archive) as tar:
        tar.extractall(where / "tree", filter="data")
    return where / "tree"


def _run_code(tree: Path, out: Path, args: argparse.Namespace) -> dict:
    """Both runs in a subprocess importing the package from `tree`."""
    env = {**os.environ, "PYTHONPATH": os.pathsep.join([str(tree), os.environ.get("PYTHONPATH", "")])}
    command = [sys.executable, __file__, "--measure", "--out", str(out), "--points", str(args.points)]
    command += ["--mesh-mm", str(args.mesh_mm), "--workers", str(args.workers)]
    done = subprocess.run(command, env=env, cwd=tree, check=True, capture_output=True, text=True)
    return json.loads(done.stdout.strip().splitlines()[-1])


def _same_files(a: Path, b: Path) -> bool:
    """Whether two campaign folders hold the same HDF5 arrays, bit for bit."""
    import h5py

    def arrays(path: Path) -> dict[str, np.ndarray]:
        found: dict[str, np.ndarray] = {}
        with h5py.File(path, "r") as f:
            f.visititems(lambda name, item: found.__setitem__(name, item[()]) if isinstance(item, h5py.Dataset) else 0)
        return found

    names = sorted(p.name for p in a.glob("biotac*.hdf5"))
    if not names or names != sorted(p.name for p in b.glob("biotac*.hdf5")):
        return False
    for name in names:
        x, y = arrays(a / name), arrays(b / name)
        if x.keys() != y.keys() or any(not np.array_equal(x[k], y[k]) for k in x):
            return False
    return True


def _rows(label: str, found: dict) -> list[str]:
    n = found["in_process"]["trajectories"]
    cpu = found["in_process"]["cpu_s"]
    pool = found["pool"]
    per = {stage: cpu[stage] / n for stage in STAGES}
    return [
        f"| {label} | {n} | {per['schedules']:.2f} | {per['synthesis']:.2f} | "
        f"{per['schedules'] + per['synthesis']:.2f} | {per['fe']:.2f} | {pool['wall_s']:.1f} | "
        f"{pool['driver_cpu_s'] + pool['worker_cpu_s']:.1f} |"
    ]


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--points", type=int, default=1, help="points (5 paper trajectories each)")
    parser.add_argument("--mesh-mm", type=float, default=2.0)
    parser.add_argument("--workers", type=int, default=1, help="workers of the pool run")
    parser.add_argument("--compare-with", default=None, help="a commit (or a tree's folder) to measure beside this")
    parser.add_argument("--out", default="runs/campaign_cpu_bench")
    parser.add_argument("--json", default=None, help="also write the figures here")
    parser.add_argument("--measure", action="store_true", help=argparse.SUPPRESS)
    args = parser.parse_args()
    if args.points < 1 or args.workers < 1 or not args.mesh_mm > 0:
        parser.error("--points and --workers must be >= 1 and --mesh-mm > 0")
    if args.measure:
        _measure(args)
        return
    out = Path(args.out).resolve()
    found = {"this checkout": _run_code(ROOT, out / "this", args)}
    if args.compare_with:
        with tempfile.TemporaryDirectory() as where:
            other = Path(args.compare_with)
            tree = other.resolve() if other.is_dir() else _tree(args.compare_with, Path(where))
            found[args.compare_with] = _run_code(tree, out / "other", args)
    print(f"paper protocol, {args.points} point(s) of sphere_medium on sensor 2, {args.mesh_mm:g} mm mesh")
    print(
        "| code | trajectories | schedule CPU s/traj | synthesis CPU s/traj | passes CPU s/traj | fe CPU s/traj "
        f"| pool ({args.workers} workers) wall s | pool CPU s |"
    )
    print("| --- | --- | --- | --- | --- | --- | --- | --- |")
    for label, figures in found.items():
        print("\n".join(_rows(label, figures)))
    if args.compare_with:
        mine, other = (found[k]["in_process"] for k in ("this checkout", args.compare_with))
        passes = [sum(f["cpu_s"][s] for s in ("schedules", "synthesis")) / f["trajectories"] for f in (mine, other)]
        pools = [sum(found[k]["pool"][c] for c in ("driver_cpu_s", "worker_cpu_s")) for k in found]
        print(
            f"passes CPU ratio ({args.compare_with} / this): {passes[1] / passes[0]:.2f}; "
            f"pool CPU ratio: {pools[1] / pools[0]:.2f}"
        )
        for run in ("in_process", "pool"):
            print(f"{run} files identical: {_same_files(out / 'this' / run, out / 'other' / run)}")
    if args.json:
        Path(args.json).write_text(json.dumps(found, indent=1))


if __name__ == "__main__":
    main()
