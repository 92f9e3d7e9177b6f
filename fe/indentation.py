"""Quasi-static, pose-driven indentation of the pressurised skin by a rigid indenter: one system.

`IndentationStepper` is the one-system view of the FE engine (`fe.batched_stepper.BatchedStepper` with
B = 1, on any warp device): it holds the skin state between prescribed indenter poses (as a robot arm would
move the indenter), each `step` re-solving equilibrium with the fluid volume held, warm-started, friction
lagged, with viscoelastic relaxation and trapped air as the skin's parameters say. `step_through` steps it
along a path of tips, `drive` along a straight `Trajectory`. Forces are in newtons in the sensor frame, the
force the indenter applies to the skin.
"""

from collections.abc import Iterator

import numpy as np

from assets.indenters import Indenter
from fe.batched import InflatedSkin
from fe.batched_stepper import MAX_CUTS, BatchedStepper, CutBack
from fe.results import IncrementResult, Trajectory

__all__ = ["IncrementResult", "IndentationStepper", "Trajectory", "drive", "step_through"]


class IndentationStepper:
    """Skin equilibrium under a sequence of prescribed rigid indenter poses, starting from the inflated state.

    Poses are in the sensor frame: `rotation` (3,3) maps the indenter body frame (tip at the origin, body
    along +z, pressing along -z) to the sensor frame and `translation` (3,) is the tip position (m). A pose
    with no skin vertex inside the contact band while the skin is free and relaxed costs no Newton work.
    A step that fails is cut back (`max_cuts` halvings); after one that still does not converge the stepper
    refuses further steps until `reset()`. A viscoelastic
    skin (relaxation_fraction > 0) needs the time of every step; trapped air makes the held volume the
    liquid's.
    """

    def __init__(
        self,
        skin: InflatedSkin,
        indenter: str | Indenter,
        origin: np.ndarray | None = None,
        device: str = "cpu",
        max_cuts: int = MAX_CUTS,
    ) -> None:
        """`skin`: the inflated model; `indenter`: one of `assets.indenters` or its name; `origin` (3,) m: tip position
        of zero depth (None: the first pose stepped after each reset); `device`: a warp device; `max_cuts`: how
        often a failed step is halved (`step`)."""
        if max_cuts < 0:
            raise ValueError(f"max_cuts must be at least 0, got {max_cuts}")
        self.engine = BatchedStepper(skin, [indenter], device)
        self.max_cuts = max_cuts
        self._fixed_origin = None if origin is None else np.array(origin, dtype=np.float64)
        self.reset()

    def reset(self) -> None:
        """Back to the inflated reference state, indenter released, relaxation history cleared."""
        self.engine.reset()
        if self._fixed_origin is not None:
            self.engine.origin[0], self.engine.has_origin[0] = self._fixed_origin, True

    @property
    def x(self) -> np.ndarray:
        """(V,3) skin mid-surface positions (m) of the last accepted state."""
        return self.engine.x[0]

    @property
    def pressure(self) -> float:
        """Fluid pressure (Pa) of the last accepted state."""
        return float(self.engine.pressure[0])

    @property
    def failure(self) -> str | None:
        """Why the last step did not converge (None: it did)."""
        return self.engine.failure[0]

    @property
    def relaxes(self) -> bool:
        """Whether the skin is viscoelastic (its steps need times)."""
        return self.engine.relaxation is not None

    def step(self, rotation: np.ndarray, translation: np.ndarray, time_s: float | None = None) -> IncrementResult:
        """Move the indenter to the pose (rotation (3,3) body->sensor, tip position (3,) m) at time `time_s`
        (s, any clock, non-decreasing between steps; None: no time passes) and re-solve. The engine's
        `fe.batched_stepper.BatchedStepper.admit` refuses a bad pose and a step after a failed one (`reset`)."""
        rotation, translation = np.asarray(rotation, dtype=np.float64), np.asarray(translation, dtype=np.float64)
        # A failed step (not converged, or inadmissible) is cut back as `fe.batched_runner.run_trajectories` does.
        target, plan = (rotation, translation, time_s), CutBack(self.max_cuts)
        while True:
            pose = plan.pose(target)
            times = None if pose[2] is None else np.array([float(pose[2])])
            result = self.engine.step(pose[0][None], pose[1][None], None, times)[0]
            if plan.settle(self.engine, 0, result.converged, target):
                return result


def step_through(
    stepper: IndentationStepper, rotation: np.ndarray, tips: np.ndarray, times: np.ndarray | None = None
) -> Iterator[IncrementResult]:
    """Step `stepper` through the indenter tips (K, 3) m (one rotation (3, 3) body->sensor) at `times` (K,) s
    (None: no time passes), yielding each increment; stop after the first one that does not converge."""
    for k, tip in enumerate(tips):
        result = stepper.step(rotation, tip, None if times is None else float(times[k]))
        yield result
        if not result.converged:
            return


def drive(stepper: IndentationStepper, trajectory: Trajectory) -> Iterator[IncrementResult]:
    """Step `stepper` through the poses (and times) of a straight trajectory (`step_through`)."""
    tips = trajectory.touch_point + np.outer(trajectory.depths, trajectory.direction)
    return step_through(stepper, trajectory.rotation, tips, trajectory.times)
