"""Fits side by side, their replays solved together (`twin.analysis.lockstep`, issue 18): each wave holds what every
running fit waits for, a fit whose replays are cached never waits, an ended or failed fit releases the others."""

import threading
import time

import pytest

from twin.analysis.lockstep import run_in_lockstep


class CountingPredictor:
    """Stands in for `Predictor`: a replay is a (model, trajectory) pair, cached once solved; every batch is noted."""

    def __init__(self, cached: set[tuple[str, str]] = frozenset()) -> None:
        self.cache = set(cached)
        self.batches: list[set[tuple[str, str]]] = []
        self.lock = threading.Lock()

    def _pairs(self, requests) -> set[tuple[str, str]]:
        return {(model, trajectory) for model, trajectories in requests for trajectory in trajectories}

    def missing(self, requests) -> int:
        return len(self._pairs(requests) - self.cache)

    def prefetch_many(self, requests, progress=None) -> int:
        with self.lock:  # would fail the test if two batches ran at once
            new = self._pairs(requests) - self.cache
            self.batches.append(new)
            time.sleep(0.01)
            self.cache |= new
            return len(new)

    def predict(self, model: str, trajectory: str) -> str:
        assert (model, trajectory) in self.cache, "predicted before its replay was solved"
        return f"{model}@{trajectory}"


def chain(models: list[str], log: list[str], pause_s: float = 0.0):
    """A fit that replays each model on trajectories a and b in turn (as a refit's steps do)."""

    def fit(predictor) -> None:
        for model in models:
            time.sleep(pause_s)
            predictor.prefetch(model, ["a", "b"])
            log.extend(predictor.predict(model, t) for t in ["a", "b"])

    return fit


def test_each_wave_holds_every_waiting_fits_replays_and_the_results_are_the_fits_alone() -> None:
    predictor = CountingPredictor(cached={("base", "a"), ("base", "b")})
    logs: list[list[str]] = [[], [], []]
    fits = [
        chain(["m1", "m2"], logs[0]),
        chain(["n1", "n2", "n3"], logs[1], pause_s=0.02),  # slower between its steps: the others wait for it
        chain(["base"] * 50, logs[2]),  # cached replays only (a measurement effect): never waits
    ]
    run_in_lockstep(predictor, fits)
    pairs = lambda *models: {(m, t) for m in models for t in "ab"}  # noqa: E731
    assert predictor.batches == [pairs("m1", "n1"), pairs("m2", "n2"), pairs("n3")]
    assert logs[0] == ["m1@a", "m1@b", "m2@a", "m2@b"]
    assert logs[1] == [f"n{k}@{t}" for k in (1, 2, 3) for t in "ab"]
    assert len(logs[2]) == 100


def test_a_failing_fit_releases_the_others_and_its_error_is_raised() -> None:
    predictor = CountingPredictor()
    log: list[str] = []

    def failing(view) -> None:
        view.prefetch("f1", ["a"])
        raise RuntimeError("this fit failed")

    with pytest.raises(RuntimeError, match="this fit failed"):
        run_in_lockstep(predictor, [chain(["m1", "m2", "m3"], log), failing])
    assert log == [f"m{k}@{t}" for k in (1, 2, 3) for t in "ab"]  # the other fit ran to its end
    assert predictor.batches[0] == {("m1", "a"), ("m1", "b"), ("f1", "a")}


def test_one_fit_runs_on_the_predictor_itself() -> None:
    predictor = CountingPredictor()
    seen = []
    run_in_lockstep(predictor, [seen.append])
    assert seen == [predictor]
