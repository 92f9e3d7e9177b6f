"""BioTacPress-v0: press at a target location to a target force, sensing only what a BioTac gives.

Episode: a target skin point is drawn among the ventral pad vertices of the FE mesh and a target force
magnitude from `target_force_n`. The target frame has its origin at the tip position where the indenter
(pressing along the inward skin normal at the point) first touches the inflated skin; its axes are t1
(the distal tangent), t2 = n x t1 and the press axis along the inward normal. The tip starts off the
skin: `standoff_mm` back along the normal, up to `start_offset_mm` off the target sideways.

Action (3,) in [-1, 1]: tip increment (t1, t2, press) in the target frame, times `max_step_mm`;
commands are clipped to +-`lateral_range_mm` sideways and [-`standoff_range_mm`, `max_depth_mm`] in press.

Observation: electrodes (19,) and pdc (1,) tared counts; force (3,) N biotac frame with `ft=True`;
tip (3,) mm: the commanded tip in the target frame (press > 0 is past the touch point); target_force
(1,) N.

Reward per step: -| |F| - F_target | (N) - `lateral_weight` * (sideways distance of the tip from the
target, mm), F the true FE force; minus `limit_penalty` when |F| > `force_limit_n` (terminates).
"""

from __future__ import annotations

from typing import Any

import numpy as np
from gymnasium import spaces

from assets.biotac import vertex_normals
from assets.indenters import get_indenter
from twin.envs.base import Pose, TactileEnv

PAD_NORMAL_Z = -0.3
"""Target points are ventral vertices whose outward skin normal has z below this (they face the pad side)."""


class PressEnv(TactileEnv):
    """Press at a target point to a target force (see the module docstring); kwargs as `TactileEnv`."""

    default_indenter = "sphere_medium"

    def __init__(
        self,
        indenter: str = default_indenter,
        *,
        target_force_n: tuple[float, float] = (0.5, 2.0),
        start_offset_mm: float = 1.0,
        standoff_mm: tuple[float, float] = (0.3, 0.8),
        lateral_range_mm: float = 3.0,
        standoff_range_mm: float = 3.0,
        max_depth_mm: float = 4.0,
        lateral_weight: float = 0.5,
        max_steps: int = 16,
        **kwargs: Any,
    ) -> None:
        low, high = target_force_n
        if not 0.0 < low <= high:
            raise ValueError(f"target_force_n must be 0 < low <= high (N), got {target_force_n!r}")
        if not 0.0 <= standoff_mm[0] <= standoff_mm[1] <= standoff_range_mm:
            raise ValueError(f"standoff_mm must be 0 <= low <= high <= standoff_range_mm, got {standoff_mm!r}")
        if not 0.0 <= start_offset_mm <= lateral_range_mm:
            raise ValueError("start_offset_mm must be in [0, lateral_range_mm]")
        self.target_force_range = (float(low), float(high))
        self.start_offset_mm, self.standoff_mm = float(start_offset_mm), tuple(map(float, standoff_mm))
        self.lateral_weight = float(lateral_weight)
        self._bounds = (
            np.array([-lateral_range_mm, -lateral_range_mm, -standoff_range_mm]),
            np.array([lateral_range_mm, lateral_range_mm, max_depth_mm]),
        )
        super().__init__(indenter, max_steps=max_steps, **kwargs)
        model = self.fe.model
        skin = model.geometry.skin
        normals = vertex_normals(model.reference, skin.triangles)
        self.candidates = np.flatnonzero(skin.ventral & (normals[:, 2] < PAD_NORMAL_Z))
        """Skin vertex ids a target point is drawn from."""
        self.target_point = np.zeros(3)
        self.target_force = float(low)
        self._frame_origin = np.zeros(3)
        self._rotation = np.eye(3)

    def _task_spaces(self) -> dict[str, spaces.Box]:
        return {"target_force": spaces.Box(0.0, 10.0, (1,), np.float32)}

    def _sample_episode(self, options: dict[str, Any] | None) -> None:
        rng = self.np_random
        model = self.fe.model
        self.target_point = model.reference[rng.choice(self.candidates)]
        trajectory = model.plan_trajectory(get_indenter(self.indenter), self.target_point, 0.0, 0.0, 0.0, 1.0)
        self._frame_origin, self._rotation = trajectory.touch_point, trajectory.rotation
        self.target_force = float(rng.uniform(*self.target_force_range))
        angle, radius = rng.uniform(0.0, 2 * np.pi), self.start_offset_mm * np.sqrt(rng.uniform())
        standoff = rng.uniform(*self.standoff_mm)
        self.tip_mm = np.array([radius * np.cos(angle), radius * np.sin(angle), -standoff])

    def _workspace_mm(self) -> tuple[np.ndarray, np.ndarray]:
        return self._bounds

    def _pose(self) -> Pose:
        t1, t2, axis = self._rotation.T  # the indenter presses along -axis
        a, b, press = self.tip_mm * 1e-3
        return self._rotation, self._frame_origin + a * t1 + b * t2 - press * axis

    def _task_observation(self) -> dict[str, np.ndarray]:
        return {"target_force": np.array([self.target_force])}

    def _task_reward(self, force: np.ndarray, previous_tip_mm: np.ndarray) -> tuple[float, dict[str, Any]]:
        error = abs(float(np.linalg.norm(force)) - self.target_force)
        lateral = float(np.hypot(*self.tip_mm[:2]))
        return -error - self.lateral_weight * lateral, {"force_error_n": error, "lateral_mm": lateral}
