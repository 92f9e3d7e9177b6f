"""Where campaign trajectories run: local worker processes (the default) or a Ray cluster.

An executor maps a task function over argument tuples and yields the results as they finish, in any
order. Each worker process first runs `setup(*setup_args)` once (e.g. building the inflated FE models),
then any number of tasks; its workers may be kept for the next map with the same setup (the batched
campaign maps twice over the same trajectories), until `close()`. Tasks must be idempotent: a campaign
task writes its part file atomically, so a task that re-runs after its worker died writes exactly what the
first attempt would have written. Maps may be consumed on another thread than the one that made the executor
(one map at a time); `cancel()` then stops the workers when that thread's consumer is gone.

- `LocalExecutor`: a `ProcessPoolExecutor` over spawned processes that die with their parent; needs
  nothing extra. Its pool serves every map with the same setup (the same function and argument objects)
  and is replaced for another setup.
- `RayExecutor`: Ray tasks on a local or existing cluster (`pip install "biotac-twin[ray]"`); a task
  whose worker dies is re-run by Ray (up to `max_retries` times), so a killed worker loses nothing.
"""

from __future__ import annotations

import ctypes
import ctypes.util
import os
import signal
import sys
import threading
import time
from abc import ABC, abstractmethod
from collections.abc import Callable, Iterator, Sequence
from concurrent.futures import ProcessPoolExecutor, as_completed
from multiprocessing import get_context
from typing import Any

EXECUTORS = ("local", "ray")
"""Names accepted by `make_executor` (and `twin campaign run --executor`)."""


class ExecutorUnavailable(RuntimeError):
    """The chosen executor cannot run here (e.g. Ray is not installed or its cluster is unreachable)."""


class Executor(ABC):
    """Runs task functions on workers; see the module docstring for the contract."""

    @abstractmethod
    def map_unordered(
        self,
        task: Callable[..., Any],
        jobs: Sequence[tuple],
        setup: Callable[..., None],
        setup_args: tuple,
    ) -> Iterator[Any]:
        """Yield `task(*job)` for every job, in completion order, each worker having run `setup(*setup_args)`.

        A task that raises ends the iteration with that exception.
        """

    def close(self) -> None:  # noqa: B027 (an optional hook: most executors keep nothing)
        """Release the workers kept between maps (none by default)."""

    def cancel(self) -> None:  # noqa: B027 (an optional hook: most executors have nothing to stop)
        """Stop the workers' running tasks now, for a map consumed in another thread whose consumer is gone (an
        interrupt or a failure in the thread that started it); that map then ends with an error. Nothing by
        default (e.g. Ray's tasks finish on their own and write only what a re-run would write)."""

    def __enter__(self) -> Executor:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()


class LocalExecutor(Executor):
    """`workers` spawned local processes (spawn, so warp and MuJoCo start clean in each).

    The workers die with this process, however it ends (`_die_with_parent`), and leave Ctrl-C to it; when
    the iteration ends early (an exception, KeyboardInterrupt, the consumer stopping) they are terminated
    at once rather than left to finish their trajectories. A map that ends normally leaves them running for
    the next map with the same setup (no new start-up: imports, PARDISO, the models inflated again), until
    `close()` or a map with another setup.
    """

    def __init__(self, workers: int = 2) -> None:
        if workers < 1:
            raise ValueError(f"workers must be >= 1, got {workers}")
        self.workers = workers
        self._pool: ProcessPoolExecutor | None = None
        self._setup: tuple = ()
        """The kept pool's setup function and argument objects (held, so that their ids stay theirs)."""

    def map_unordered(
        self, task: Callable[..., Any], jobs: Sequence[tuple], setup: Callable[..., None], setup_args: tuple
    ) -> Iterator[Any]:
        if not jobs:
            return
        pool = self._pool_for(setup, setup_args)
        try:
            futures = [pool.submit(task, *job) for job in jobs]
            for future in as_completed(futures):
                yield future.result()
        except BaseException:
            _terminate(pool)
            self.close()
            raise

    def close(self) -> None:
        """Shut the kept pool down (its workers end after their current task; none is pending)."""
        pool, self._pool, self._setup = self._pool, None, ()
        if pool is not None:
            pool.shutdown(wait=True, cancel_futures=True)

    def cancel(self) -> None:
        """Terminate the kept pool's workers at once and drop the pool (a running map ends with BrokenProcessPool)."""
        if self._pool is not None:
            _terminate(self._pool)
        self.close()

    def _pool_for(self, setup: Callable[..., None], setup_args: tuple) -> ProcessPoolExecutor:
        """The kept pool when it was set up by `setup` with these very argument objects, else a new one."""
        if self._pool is None or not _same_setup(self._setup, setup, setup_args):
            self.close()
            initargs = (os.getpid(), setup, setup_args)
            self._pool = ProcessPoolExecutor(self.workers, get_context("spawn"), _local_setup, initargs)
            self._setup = (setup, *setup_args)
        return self._pool


def _same_setup(kept: tuple, setup: Callable[..., None], setup_args: tuple) -> bool:
    """Whether `kept` (a setup function and its argument objects) is `setup` with these very argument objects."""
    key = (setup, *setup_args)
    return len(key) == len(kept) and all(a is b for a, b in zip(key, kept, strict=True))


def _terminate(pool: ProcessPoolExecutor) -> None:
    """Terminate a pool's worker processes (no public way before Python 3.14's terminate_workers)."""
    for process in list((pool._processes or {}).values()):
        process.terminate()


PR_SET_PDEATHSIG = 1
"""Linux prctl option: the signal this process gets when its parent dies."""
PARENT_POLL_S = 1.0
"""How often a worker without prctl checks that its parent is alive (s)."""


def _local_setup(parent_pid: int, setup: Callable[..., None], setup_args: tuple) -> None:
    """A local worker's start: tie its life to the parent's, leave Ctrl-C to the parent, run `setup`."""
    _die_with_parent(parent_pid)
    signal.signal(signal.SIGINT, signal.SIG_IGN)
    setup(*setup_args)


def _die_with_parent(parent_pid: int) -> None:
    """Make this process end when `parent_pid` (its parent) ends, even by SIGKILL: PR_SET_PDEATHSIG on Linux,
    else a daemon thread polling the parent pid every PARENT_POLL_S."""
    libc = ctypes.util.find_library("c") if sys.platform.startswith("linux") else None
    if libc is not None and ctypes.CDLL(libc, use_errno=True).prctl(PR_SET_PDEATHSIG, signal.SIGKILL) == 0:
        if os.getppid() != parent_pid:  # the parent died before prctl took effect
            os._exit(1)
        return

    def watch() -> None:
        while os.getppid() == parent_pid:
            time.sleep(PARENT_POLL_S)
        os._exit(1)

    threading.Thread(target=watch, name="parent-watchdog", daemon=True).start()


_RAY_SETUP_DONE: set[str] = set()
"""Setup keys already run in this (Ray worker) process."""


def _ray_task(setup_key: str, setup: Callable[..., None], setup_args: tuple, task: Callable[..., Any], job: tuple):
    """Body of every Ray task: run the worker's setup on first use in this process, then the task."""
    if setup_key not in _RAY_SETUP_DONE:
        setup(*setup_args)
        _RAY_SETUP_DONE.add(setup_key)
    return task(*job)


class RayExecutor(Executor):
    """Ray tasks, one CPU each, on the cluster at `address` (None: start or join a local Ray).

    `num_cpus` and `object_store_memory` (bytes; Ray's default is 30 % of the memory) size a locally
    started Ray (ignored when joining a cluster); tasks pass only small arguments and results, the part
    files go to disk. Tasks whose worker process dies are retried up to `max_retries` times; a task
    that raises is not retried.
    """

    def __init__(
        self,
        address: str | None = None,
        num_cpus: int | None = None,
        max_retries: int = 3,
        object_store_memory: int | None = None,
    ) -> None:
        try:
            import ray
        except ImportError as error:
            raise ExecutorUnavailable(
                'the ray executor needs Ray: pip install "biotac-twin[ray]" (or pip install ray)'
            ) from error
        self._ray = ray
        self.max_retries = max_retries
        self._setup_ref: Any = None
        self._setup: tuple = ()
        """The last map's setup function and argument objects (held, so that their ids stay theirs)."""
        if not ray.is_initialized():
            options: dict[str, Any] = {"address": address, "include_dashboard": False, "log_to_driver": False}
            if address is None and num_cpus is not None:
                options["num_cpus"] = num_cpus
            if address is None and object_store_memory is not None:
                options["object_store_memory"] = object_store_memory
            try:
                ray.init(**options)
            except (ConnectionError, RuntimeError, ValueError) as error:
                where = address or "a local cluster"
                raise ExecutorUnavailable(f"cannot start or reach Ray at {where}: {error}") from error

    def map_unordered(
        self, task: Callable[..., Any], jobs: Sequence[tuple], setup: Callable[..., None], setup_args: tuple
    ) -> Iterator[Any]:
        ray = self._ray
        if not jobs:
            return
        remote = ray.remote(num_cpus=1, max_retries=self.max_retries, retry_exceptions=False)(_ray_task)
        if self._setup_ref is None or not _same_setup(self._setup, setup, setup_args):
            # one object and key per setup: a worker runs it once, however many maps use it
            self._setup_ref, self._setup = ray.put(setup_args), (setup, *setup_args)
        # Ray resolves top-level ObjectRef arguments only; pass the setup arguments that way.
        key = f"{id(self)}-{self._setup_ref.hex()}"
        pending = [remote.remote(key, setup, self._setup_ref, task, job) for job in jobs]
        while pending:
            ready, pending = ray.wait(pending, num_returns=1)
            yield ray.get(ready[0])


def make_executor(name: str, workers: int = 2, address: str | None = None) -> Executor:
    """The executor called `name` ("local" or "ray"); `workers` sizes the local pool (and a locally started
    Ray); `address` is the Ray cluster to join (ray only)."""
    if name == "local":
        if address is not None:
            raise ValueError("--address is the Ray cluster address; it needs --executor ray")
        return LocalExecutor(workers)
    if name == "ray":
        return RayExecutor(address, num_cpus=workers if address is None else None)
    raise ValueError(f"unknown executor {name!r}; choose from {', '.join(EXECUTORS)}")
