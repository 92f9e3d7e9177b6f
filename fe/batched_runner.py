"""Many indentation trajectories through a fixed number of batched FE slots, continuously batched.

`run_trajectories(skin, trajectories, device, slots)` keeps `slots` systems of one `BatchedStepper` busy:
each slot holds one trajectory at a time, a system that finishes an increment starts its next pose at
once (`BatchedStepper.admit`) while the others go on iterating (`BatchedStepper.advance`), and a slot
whose trajectory ends takes the next queued trajectory, whatever its indenter (the contact kernels read
each system's own) and whatever its skin, where trajectories carry skins of one mesh (several sensors, or
several models' parameters: `BatchedStepper.set_skin`). So no system waits for the slowest one of the
batch, as a lock-step `BatchedStepper.step` per pose would make it, and no slot idles while trajectories
are queued.

A trajectory ends after its last pose, at its first increment that does not converge even in smaller
steps (cut-backs through midpoints of the failed step, whose results are not reported), or at its first
increment whose indenter force exceeds `force_limit` (N), as the campaign controller stops a press.
A trajectory may solve a pose at other tips than its own, and more than once at its time (`PoseTrajectory.settle`:
a compliant robot's tip, where the loads put it; its force limit is judged once the pose is done).
Poses: rotation (3,3) indenter body -> sensor frame, tip position (3,) m; results are
`fe.indentation.IncrementResult`s (forces in N, sensor frame; `wall_s` from a pose's admission to its result).
"""

from __future__ import annotations

import time
from collections import deque
from collections.abc import Callable, Sequence
from dataclasses import dataclass, replace

import numpy as np

from fe.batched import InflatedSkin, per_system
from fe.batched_stepper import MAX_CUTS, BatchedStepper, CutBack, Pose
from fe.indentation import IncrementResult


@dataclass(frozen=True)
class PoseTrajectory:
    """One indenter's poses: rotations (K,3,3) body -> sensor frame, tip positions (K,3) m, and the time of
    each pose (K,) s (None: untimed, only for a skin without viscoelastic relaxation); K = 0: nothing to
    solve (the runner ends it at once, with no increments)."""

    indenter: str
    rotations: np.ndarray
    translations: np.ndarray
    times: np.ndarray | None = None
    settle: Callable[[int, IncrementResult | None], np.ndarray | None] | None = None
    """Where the tip (3,) m of pose k is solved, when not at `translations[k]` (e.g. a compliant robot,
    `twin.campaign_batched`): `settle(k, None)` gives its first tip; `settle(k, result)`, after each converged
    solve of pose k, the next tip to solve at its time and rotation, or None when pose k is done. Every solve
    is reported, in order."""

    def __post_init__(self) -> None:
        rotations, translations = np.asarray(self.rotations), np.asarray(self.translations)
        if rotations.ndim != 3 or rotations.shape[1:] != (3, 3) or translations.shape != (len(rotations), 3):
            raise ValueError(
                f"a trajectory's poses are rotations (K,3,3) and translations (K,3), got "
                f"{rotations.shape} and {translations.shape}"
            )
        if self.times is not None:
            times = np.asarray(self.times, dtype=np.float64)
            if times.shape != (len(rotations),) or not np.all(np.isfinite(times)) or np.any(np.diff(times) < 0):
                raise ValueError("a trajectory's times are one finite, non-decreasing time (s) per pose")

    def at_speed(self, speed: float) -> PoseTrajectory:
        """The same poses timed by a tip moving at `speed` (m/s) along them: t = cumulative tip travel / speed."""
        if not speed > 0.0:
            raise ValueError(f"speed={speed} m/s must be positive")
        travel = np.linalg.norm(np.diff(np.asarray(self.translations), axis=0), axis=1)
        return replace(self, times=np.concatenate([[0.0], np.cumsum(travel)]) / speed)


@dataclass
class BatchedRun:
    """Outcome of `run_trajectories`: per trajectory its increments (in pose order, every solve of a pose with a
    `PoseTrajectory.settle`, ending where the trajectory stopped), the number of rounds (one `advance` each),
    the wall time (s), the slots, the shell's work counters (`fe.batched.BatchedShell.counters`), whether every
    trajectory ended (False after a time limit), and per round the time it ended (s from the start) and the
    systems it iterated."""

    results: list[list[IncrementResult]]
    iterations: int
    wall_s: float
    slots: int
    counters: dict[str, float]
    complete: bool
    round_end_s: np.ndarray
    round_systems: np.ndarray


def can_share_batch(first: InflatedSkin, other: InflatedSkin) -> bool:
    """Whether two skins can be systems of one batch (`fe.batched.per_system`: one mesh, core, contact and
    Newton settings; parameters and starting states may differ)."""
    try:
        per_system([first, other], 2)
    except ValueError:
        return False
    return True


def run_trajectories(
    skin: InflatedSkin | Sequence[InflatedSkin],
    trajectories: Sequence[PoseTrajectory],
    device: str = "cpu",
    slots: int = 256,
    force_limit: float = np.inf,
    on_trajectory: Callable[[int, list[IncrementResult]], None] | None = None,
    time_limit_s: float = np.inf,
    forcing: str = "adaptive",
    max_cuts: int = MAX_CUTS,
    linear: str = "auto",
) -> BatchedRun:
    """Solve every trajectory's poses in order on `slots` continuously batched systems on the warp `device`,
    the trajectories with the most poses first where they share one skin (so that few long ones do not start
    last and run on alone at the end); `on_trajectory(index, increments)` is called as each trajectory ends
    (for progress and streaming; `index` into `trajectories`, whatever the order they ran in). Where the
    trajectories carry skins of their own they run in the order given (e.g. by skin, for streaming). After
    `time_limit_s` the run stops where it is (`BatchedRun.complete` False; unfinished trajectories keep the
    increments they finished). `forcing`, `linear`: the CG tolerance rule and linear algebra of
    `fe.batched.BatchedShell`. A failed increment is cut back: retried from the last accepted pose through
    the midpoint (in pose and time), and so on up to `max_cuts` halvings of one step, before it ends the
    trajectory (`BatchedRun.counters["cut_backs"]`). Timed trajectories (all or none) are stepped at their
    times, each from its own clock. `skin`: the inflated skin of every trajectory, or one per trajectory
    (skins that can share a batch, `can_share_batch`); a slot takes any skin."""
    if not trajectories:
        raise ValueError("no trajectories to run")
    if slots < 1:
        raise ValueError(f"slots must be at least 1, got {slots}")
    if max_cuts < 0:
        raise ValueError(f"max_cuts must be at least 0, got {max_cuts}")
    slots = min(slots, len(trajectories))
    start = time.perf_counter()
    order = list(range(len(trajectories)))
    if isinstance(skin, InflatedSkin):  # one skin: the longest first
        order.sort(key=lambda k: -len(trajectories[k].rotations))
    skins = per_system(skin, len(trajectories))
    initial, indenters = [skins[k] for k in order[:slots]], [trajectories[k].indenter for k in order[:slots]]
    later = list({id(s): s for s in skins}.values())
    stepper = BatchedStepper(initial, indenters, device, forcing, linear, later)
    schedule = _Schedule(trajectories, skins, order, force_limit, on_trajectory, stepper, max_cuts)
    round_end_s: list[float] = []
    round_systems: list[int] = []
    while complete := time.perf_counter() - start <= time_limit_s:  # complete: not stopped by the time limit
        while schedule.waiting.any():
            rotation, translation, times = schedule.poses()
            admitted = schedule.waiting.copy()
            schedule.waiting[:] = False
            schedule.record(stepper.admit(admitted, rotation, translation, times))
        if not stepper.newton.running.any():
            break
        round_systems.append(int(stepper.newton.running.sum()))
        schedule.record(stepper.advance())
        round_end_s.append(time.perf_counter() - start)
    counters = dict(stepper.shell.counters) | {"cut_backs": sum(plan.total for plan in schedule.cut_back)}
    wall, rounds = time.perf_counter() - start, (np.array(round_end_s), np.array(round_systems, dtype=int))
    return BatchedRun(schedule.results, len(round_end_s), wall, slots, counters, complete, *rounds)


class _Schedule:
    """Which trajectory and pose each slot is at; records results and refills slots, taking the trajectories in
    `order`."""

    def __init__(
        self,
        trajectories: Sequence[PoseTrajectory],
        skins: Sequence[InflatedSkin],
        order: Sequence[int],
        force_limit: float,
        on_trajectory: Callable[[int, list[IncrementResult]], None] | None,
        stepper: BatchedStepper,
        max_cuts: int,
    ) -> None:
        self.trajectories, self.skins, self.queue = trajectories, skins, deque(order)
        self.force_limit, self.on_trajectory, self.stepper = force_limit, on_trajectory, stepper
        n = stepper.batch
        self.results: list[list[IncrementResult]] = [[] for _ in range(len(trajectories))]
        self.current, self.pose = np.full(n, -1), np.zeros(n, dtype=int)
        self.waiting = np.zeros(n, dtype=bool)
        """Slots whose next pose is to be admitted."""
        self.tip = np.zeros((n, 3))
        """Per slot, the tip (m) its pose is solved at where its trajectory has a `settle`."""
        self.timed = trajectories[0].times is not None
        self.cut_back = [CutBack(max_cuts) for _ in range(n)]
        """Per slot, the way to its trajectory's next pose after failed steps."""
        for slot in range(n):
            self._take(slot)

    def _take(self, slot: int) -> None:
        """Give the slot the next queued trajectory with poses (or leave it empty); one without poses ends at
        once. A trajectory is first read here (a lazy sequence may wait for it)."""
        self.current[slot] = -1
        while self.queue and self.current[slot] < 0:
            index = self.queue.popleft()
            trajectory = self.trajectories[index]
            if (trajectory.times is not None) != self.timed:
                raise ValueError("either every trajectory is timed or none is")
            if len(trajectory.rotations):
                self.current[slot] = index
            elif self.on_trajectory is not None:
                self.on_trajectory(index, self.results[index])
        self.pose[slot] = 0
        self.cut_back[slot].restart()
        if self.current[slot] >= 0:
            name, skin = self.trajectories[self.current[slot]].indenter, self.skins[self.current[slot]]
            if self.stepper.indenters[slot] != name:
                self.stepper.set_indenter(slot, name)
            if self.stepper.skins[slot] is not skin:
                self.stepper.set_skin(slot, skin)
            self._next_pose(slot)

    def _next_pose(self, slot: int) -> None:
        """Queue the slot's pose `self.pose[slot]` (at the first tip of its trajectory's `settle`, if any)."""
        self.waiting[slot] = True
        settle = self.trajectories[self.current[slot]].settle
        if settle is not None:
            self.tip[slot] = settle(int(self.pose[slot]), None)

    def poses(self) -> tuple[np.ndarray, np.ndarray, np.ndarray | None]:
        """Rotations (S,3,3), tip positions (S,3) m and times (S,) s (None: untimed) of the waiting slots'
        next poses (identity, 0 elsewhere)."""
        n = self.stepper.batch
        rotation, translation, times = np.tile(np.eye(3), (n, 1, 1)), np.zeros((n, 3)), np.zeros(n)
        for slot in np.flatnonzero(self.waiting):
            rotation[slot], translation[slot], times[slot] = self.cut_back[slot].pose(self._target(slot))
        return rotation, translation, times if self.timed else None

    def _target(self, slot: int) -> Pose:
        """The slot's trajectory's next pose (at its `settle` tip, if any) and its time (0 when untimed)."""
        trajectory, k = self.trajectories[self.current[slot]], self.pose[slot]
        time_s = 0.0 if trajectory.times is None else float(trajectory.times[k])
        tip = trajectory.translations[k] if trajectory.settle is None else self.tip[slot]
        return trajectory.rotations[k], tip, time_s

    def record(self, finished: dict[int, IncrementResult]) -> None:
        """File the slots' finished increments; queue their next poses, cut failed steps back, or end their
        trajectories."""
        for slot, result in finished.items():
            if not self.cut_back[slot].settle(self.stepper, slot, result.converged, self._target(slot)):
                self.waiting[slot] = True  # an intermediate pose reached, or a failed step halved
                continue
            index = int(self.current[slot])
            self.results[index].append(result)
            settle = self.trajectories[index].settle
            if result.converged and settle is not None and (tip := settle(int(self.pose[slot]), result)) is not None:
                self.tip[slot], self.waiting[slot] = tip, True  # pose k again, at another tip
                continue
            self.pose[slot] += 1
            pressed = float(np.linalg.norm(result.force)) > self.force_limit
            if result.converged and not pressed and self.pose[slot] < len(self.trajectories[index].rotations):
                self._next_pose(slot)
                continue
            if self.on_trajectory is not None:
                self.on_trajectory(index, self.results[index])
            self.stepper.reset(np.arange(self.stepper.batch) == slot)
            self._take(slot)
