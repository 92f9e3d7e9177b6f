"""BioTacEdgeFollow-v0: slide along a straight edge whose direction is hidden, keeping a light contact.

The edge is the `cylinder_long` indenter (7 mm diameter, 28 mm long: "a table edge") lying under the
ventral pad, pressing up (+z, biotac frame) with its axis horizontal at a hidden yaw drawn from
+-`max_yaw_deg` about z (0: along x, distal). The policy moves the edge relative to the finger; its
axis a = (cos yaw, sin yaw, 0) points distally. Where the edge lies on the pad, and so which way to
slide, shows only in the contact's location and shape on the electrodes: the task needs contact
location.

Episode: the tip (the edge's lowest line, at its middle) starts `standoff_mm` below the pad's lowest
point, at x in `start_x_mm`, y in +-`start_y_mm`; the edge does not touch the skin.

Action (3,) in [-1, 1]: tip increment in the biotac frame, times `max_step_mm`; commands are clipped to
`workspace_mm` around the start. Observation: electrodes (19,) and pdc (1,) tared counts; force (3,) N
with `ft=True`; tip (3,) mm: the tip's displacement from its start (biotac frame).

Reward per step: the tip's progress along a (mm) when the true force magnitude ends in
[`force_window_n`], else -`miss_penalty`; minus `limit_penalty` when |F| > `force_limit_n` (terminates).
"""

from __future__ import annotations

from typing import Any

import numpy as np
from gymnasium import spaces

from twin.envs.base import Pose, TactileEnv


class EdgeFollowEnv(TactileEnv):
    """Follow a hidden straight edge (see the module docstring); kwargs as `TactileEnv`."""

    default_indenter = "cylinder_long"

    def __init__(
        self,
        indenter: str = default_indenter,
        *,
        max_yaw_deg: float = 45.0,
        start_x_mm: tuple[float, float] = (-8.0, -4.0),
        start_y_mm: float = 1.0,
        standoff_mm: tuple[float, float] = (0.2, 0.6),
        workspace_mm: tuple[float, float, float] = (12.0, 6.0, 4.0),
        force_window_n: tuple[float, float] = (0.2, 2.0),
        miss_penalty: float = 0.1,
        max_steps: int = 30,
        max_step_mm: float = 0.4,
        force_limit_n: float = 3.0,
        **kwargs: Any,
    ) -> None:
        if not 0.0 <= max_yaw_deg < 90.0:
            raise ValueError(f"max_yaw_deg must be in [0, 90), got {max_yaw_deg!r}")
        if not 0.0 <= force_window_n[0] < force_window_n[1]:
            raise ValueError(f"force_window_n must be 0 <= low < high (N), got {force_window_n!r}")
        self.max_yaw = np.radians(max_yaw_deg)
        self.start_x_mm, self.start_y_mm = tuple(map(float, start_x_mm)), float(start_y_mm)
        self.standoff_mm = tuple(map(float, standoff_mm))
        self.force_window_n = tuple(map(float, force_window_n))
        self.miss_penalty = float(miss_penalty)
        reach = np.asarray(workspace_mm, dtype=float)
        self._bounds = (np.array([-reach[0], -reach[1], -reach[2]]), reach)
        super().__init__(indenter, max_steps=max_steps, max_step_mm=max_step_mm, force_limit_n=force_limit_n, **kwargs)
        outer = self.fe.model.outer_surface().vertices
        self.pad_bottom_z = float(outer[:, 2].min())
        """z (m) of the lowest point of the inflated outer skin."""
        self.yaw = 0.0
        self.start = np.zeros(3)
        self._rotation = np.eye(3)

    def _task_spaces(self) -> dict[str, spaces.Box]:
        return {}

    def _sample_episode(self, options: dict[str, Any] | None) -> None:
        rng = self.np_random
        self.yaw = float(rng.uniform(-self.max_yaw, self.max_yaw))
        axis = np.array([np.cos(self.yaw), np.sin(self.yaw), 0.0])
        down = np.array([0.0, 0.0, -1.0])  # the indenter's body z: it presses up, along -body z
        self._rotation = np.column_stack([axis, np.cross(down, axis), down])
        x = rng.uniform(*self.start_x_mm) * 1e-3
        y = rng.uniform(-self.start_y_mm, self.start_y_mm) * 1e-3
        self.start = np.array([x, y, self.pad_bottom_z - rng.uniform(*self.standoff_mm) * 1e-3])
        self.tip_mm = np.zeros(3)

    def _workspace_mm(self) -> tuple[np.ndarray, np.ndarray]:
        return self._bounds

    def _pose(self) -> Pose:
        return self._rotation, self.start + self.tip_mm * 1e-3

    def _task_observation(self) -> dict[str, np.ndarray]:
        return {}

    def _task_reward(self, force: np.ndarray, previous_tip_mm: np.ndarray) -> tuple[float, dict[str, Any]]:
        progress = float((self.tip_mm - previous_tip_mm) @ self._rotation[:, 0])
        low, high = self.force_window_n
        in_window = low <= float(np.linalg.norm(force)) <= high
        return (progress if in_window else -self.miss_penalty), {"progress_mm": progress, "in_window": in_window}
