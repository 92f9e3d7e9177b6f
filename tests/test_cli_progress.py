"""Progress on a non-terminal stderr (a log file, a batch job): plain lines, so long runs can be followed."""

import io

from rich.console import Console

from twin.cli.common import LoggedProgress


class Clock:
    """A hand-driven monotonic clock (s)."""

    def __init__(self) -> None:
        self.now = 0.0

    def __call__(self) -> float:
        return self.now


def test_plain_lines_after_the_interval_on_stage_changes_and_at_the_end(monkeypatch):
    clock = Clock()
    monkeypatch.setattr("twin.cli.common.time.monotonic", clock)
    log = io.StringIO()
    progress = LoggedProgress(console=Console(file=log), interval_s=10.0)
    task = progress.add_task("schedules", total=4)
    progress.update(task, completed=1)  # 0 s: a short run says nothing
    clock.now = 4.0
    progress.update(task, description="fe batch", completed=2)
    assert log.getvalue() == ""
    clock.now = 11.0
    progress.update(task, completed=3)  # past the interval: a line
    clock.now = 12.0
    progress.update(task, completed=3)  # nothing new within the interval: silent
    progress.update(task, description="synthesis", completed=0)  # a new stage: a line
    clock.now = 13.0
    progress.update(task, completed=4)  # finished: a line
    assert log.getvalue().splitlines() == ["fe batch 3/4 (11 s)", "synthesis 0/4 (12 s)", "synthesis 4/4 (13 s)"]


def test_a_terminal_gets_rich_bars_and_no_plain_lines(monkeypatch):
    clock = Clock()
    monkeypatch.setattr("twin.cli.common.time.monotonic", clock)
    log = io.StringIO()
    progress = LoggedProgress(console=Console(file=log, force_terminal=True), interval_s=1.0, auto_refresh=False)
    task = progress.add_task("fe batch", total=2)
    clock.now = 5.0
    progress.update(task, completed=2)
    assert "fe batch 2/2 (5 s)" not in log.getvalue()


def test_the_loops_progress_follows_the_predictors_replays(monkeypatch):
    from twin.analysis.predict import Predictor
    from twin.cli.common import replay_progress

    clock = Clock()
    monkeypatch.setattr("twin.cli.common.time.monotonic", clock)
    log = io.StringIO()
    monkeypatch.setattr(
        "twin.cli.common.progress_bar", lambda: LoggedProgress(console=Console(file=log), interval_s=10.0)
    )
    predictor = Predictor()
    with replay_progress(predictor):
        predictor.on_replays(1, 8)  # 0 s: silent
        clock.now = 11.0
        predictor.on_replays(3, 8)
        clock.now = 12.0
        predictor.on_replays(8, 8)
    assert predictor.on_replays is None  # unwired after the command
    assert log.getvalue().splitlines()[:2] == ["fe replays 3/8 (11 s)", "fe replays 8/8 (12 s)"]  # then rich's last bar
