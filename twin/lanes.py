"""Background lanes: daemon threads that run jobs one after another while the calling thread does other work.

A campaign overlaps its host stages with the fe (`twin.campaign_batched.BatchedRunner`, `twin.campaign.run_campaign`):
executor maps are consumed on a lane while the driver solves, and the sensor files are assembled on another.
Every lane of a campaign shares one `FirstFailure`: the first exception raised on any of them (or recorded by the
driver) is the one the campaign ends with; later ones (often its consequences, such as a pool broken by it) are
dropped, and a lane runs no further job once a failure is recorded.

`thread_map` is the other way round: the calling thread waits while a pool of threads maps a function (the
diagnosis's per-candidate stages, numpy over large arrays).
"""

from __future__ import annotations

import os
import queue
import threading
from collections.abc import Callable, Sequence
from concurrent.futures import ThreadPoolExecutor
from typing import Any

WAIT_POLL_S = 0.2
"""How often (s) a thread waiting on a lane's results checks for a failure."""


class FirstFailure:
    """The first exception raised by any of several threads."""

    def __init__(self) -> None:
        self._lock = threading.Lock()
        self.error: BaseException | None = None

    def record(self, error: BaseException) -> None:
        """Keep `error` unless an earlier one is kept."""
        with self._lock:
            if self.error is None:
                self.error = error

    def raise_if_any(self) -> None:
        """Raise the kept exception, if any."""
        if self.error is not None:
            raise self.error


class Lane:
    """One daemon thread running the submitted jobs (callables without arguments) in submission order; a job that
    raises records its exception in `failure`, and no job runs after a recorded failure."""

    def __init__(self, name: str, failure: FirstFailure) -> None:
        self.failure = failure
        self._jobs: queue.Queue[Callable[[], None] | None] = queue.Queue()
        self._thread = threading.Thread(target=self._run, name=name, daemon=True)
        self._thread.start()

    def submit(self, job: Callable[[], None]) -> None:
        """Run `job` after the jobs submitted before it."""
        self._jobs.put(job)

    def take(self, results: queue.Queue[Any]) -> Any:
        """The next item a job puts in `results`; raises the campaign's failure instead once there is one."""
        while True:
            self.failure.raise_if_any()
            try:
                return results.get(timeout=WAIT_POLL_S)
            except queue.Empty:
                continue

    def join(self) -> None:
        """Wait for every submitted job, then raise the first failure, if any."""
        self._jobs.put(None)
        self._thread.join()
        self.failure.raise_if_any()

    def release(self) -> None:
        """Let the thread end after the jobs submitted so far, without waiting (e.g. when the caller failed)."""
        self._jobs.put(None)

    def _run(self) -> None:
        while (job := self._jobs.get()) is not None:
            if self.failure.error is not None:
                continue
            try:
                job()
            except BaseException as error:  # noqa: BLE001 (handed to the waiting thread, which raises it)
                self.failure.record(error)


def usable_cpus() -> int:
    """How many CPUs this process may run on (its affinity where the OS tells it, else the machine's count)."""
    return len(os.sched_getaffinity(0)) if hasattr(os, "sched_getaffinity") else os.cpu_count() or 1


def thread_map(function: Callable[[Any], Any], items: Sequence[Any], workers: int | None = None) -> list[Any]:
    """[function(item) for item in items], on up to `workers` threads (default: the usable CPUs), results in order; the
    first exception raised is raised here. For work whose heavy parts release Python's lock: numpy on large arrays,
    such as a diagnosis's per-candidate linearisations and held-out fits over a residual of millions of samples (the
    paper diagnose's CPU stages ran on one of an H200 host's 16 cores, docs/scale.md, session 26)."""
    workers = min(len(items), workers or usable_cpus())
    if workers <= 1:
        return [function(item) for item in items]
    with ThreadPoolExecutor(workers) as pool:
        return list(pool.map(function, items))
