"""Several fits that replay trajectories, run side by side so that their replays are solved together (issue 18).

A refit is a chain of replay sets (each damped Gauss-Newton step is predicted again, nonlinearly), and diagnosis
refits its top candidates: one after another, each set is one wave of the batched engine, as long as its longest
trajectory (on the paper campaign's 0.5 mm mesh ~33 s on an H100 however few trajectories share it), so the
chains add up. `run_in_lockstep` runs the fits in threads and gathers their replays: a fit that needs replays not
solved yet waits until every other running fit waits too (or has ended), and then all of them are solved as the
systems of one batched run (`Predictor.prefetch_many`). A fit whose replays are all cached (a measurement effect's)
never waits. Each fit gets exactly the replays it would have solved alone (a replay depends only on its model and
trajectory), so every result is the same as one fit after another.
"""

from __future__ import annotations

import threading
from collections.abc import Callable, Sequence
from typing import Any

from twin.analysis.data import TrajectoryRecord
from twin.analysis.predict import Predictor, TwinModel

Requests = Sequence[tuple[TwinModel, Sequence[TrajectoryRecord]]]


class _Gather:
    """The replay requests of `parties` threads, solved together once every thread still running waits."""

    def __init__(self, predictor: Predictor, parties: int) -> None:
        self.predictor = predictor
        self.running = parties
        self.waiting: list[Requests] = []
        self.generation = 0
        self.solved = 0  # replays the last batch solved
        self.condition = threading.Condition()

    def prefetch_many(self, requests: Requests) -> int:
        """Wait for the others, then solve every waiting thread's missing replays in one batch (`requests`' share is
        not told apart: returns how many the batch solved); at once 0 when all of `requests` are cached."""
        with self.condition:
            if not self.predictor.missing(requests):
                return 0
            self.waiting.append(requests)
            generation = self.generation
            if len(self.waiting) == self.running:
                return self._solve()
            self.condition.wait_for(lambda: self.generation != generation)
            return self.solved

    def leave(self) -> None:
        """A thread has ended: solve for the others if they all wait."""
        with self.condition:
            self.running -= 1
            if self.waiting and len(self.waiting) == self.running:
                self._solve()

    def _solve(self) -> int:
        """(Holding the lock) every waiting request as one `prefetch_many`; wakes the waiting threads."""
        requests = [request for waiting in self.waiting for request in waiting]
        self.waiting = []
        try:
            self.solved = self.predictor.prefetch_many(requests)
        finally:
            self.generation += 1
            self.condition.notify_all()
        return self.solved


class _GatheringPredictor:
    """A thread's view of the shared predictor: replays requested through `prefetch_many` / `prefetch` go through
    the gather; everything else is the predictor's."""

    def __init__(self, gather: _Gather) -> None:
        self._gather = gather

    prefetch = Predictor.prefetch  # one model's replays, through this view's `prefetch_many`

    def prefetch_many(self, requests: Requests, progress: Callable[[int, int], None] | None = None) -> int:
        return self._gather.prefetch_many(requests)

    def __getattr__(self, name: str) -> Any:
        return getattr(self._gather.predictor, name)


def run_in_lockstep(predictor: Predictor, fits: Sequence[Callable[[Predictor], None]]) -> None:
    """Run each fit(predictor view) in its own thread, their replays solved together (see the module docstring);
    returns when all have ended; the first exception a fit raised is raised here (the others still end)."""
    if len(fits) <= 1:
        for fit in fits:
            fit(predictor)
        return
    gather = _Gather(predictor, len(fits))
    errors: list[BaseException] = []

    def run(fit: Callable[[Predictor], None]) -> None:
        try:
            fit(_GatheringPredictor(gather))  # type: ignore[arg-type]  (the predictor's interface, by delegation)
        except BaseException as error:  # noqa: BLE001  (re-raised in the caller's thread)
            errors.append(error)
        finally:
            gather.leave()

    threads = [threading.Thread(target=run, args=(fit,), name=f"fit-{k}") for k, fit in enumerate(fits)]
    for thread in threads:
        thread.start()
    for thread in threads:
        thread.join()
    if errors:
        raise errors[0]
