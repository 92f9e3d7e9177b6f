"""Robot-side planning: turn biotac-frame trajectories into joint paths, or drop them with a reason.

A trajectory is kept when inverse kinematics reaches every path pose to 0.01 mm and 1e-4 rad within
the joint limits (checked again by forward kinematics) and no pose collides (indenter-skin contact
is the point of the exercise and is allowed). The indenter may be rolled about its own axis (in
quarter turns) to find a reachable pose; the roll chosen is part of the plan.
"""

from __future__ import annotations

from collections import Counter
from dataclasses import dataclass, replace

import numpy as np

from assets.tools import tool_tip_transform
from twin.kinematics import forward, inverse
from twin.protocol import TrajectorySpec
from twin.scene import TestbedScene

POSITION_TOLERANCE = 1e-5
"""The paper's reachability tolerance: 0.01 mm (m)."""
ROTATION_TOLERANCE = 1e-4
"""Orientation tolerance (rad)."""
ROLLS = (0.0, np.pi / 2, -np.pi / 2, np.pi)


@dataclass(frozen=True)
class PlannedTrajectory:
    """A trajectory for one sensor: its spec (possibly rolled), arm, joint path or the reason it was dropped."""

    sensor_id: int
    spec: TrajectorySpec
    arm: str
    joint_path: np.ndarray | None  # (K, 7) rad when kept
    dropped: str | None  # reason when not kept: "unreachable", "collision"

    @property
    def kept(self) -> bool:
        return self.dropped is None


def _rolled(spec: TrajectorySpec, roll: float) -> TrajectorySpec:
    c, s = np.cos(roll), np.sin(roll)
    about_z = np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])
    return replace(spec, rotation=spec.rotation @ about_z)


def scene_tool_tip(scene: TestbedScene, tool: str) -> np.ndarray:
    """Flange->tip 4x4 of `tool` as mounted in `scene` (its adapter and pin geometry)."""
    return tool_tip_transform(tool, scene.params.adapter_length, scene.params.pin)


def _joint_path(
    spec: TrajectorySpec, arm: str, biotac_to_robot: np.ndarray, seed: np.ndarray, tool: np.ndarray
) -> np.ndarray | None:
    path, q = [], seed
    for k in range(len(spec.depths)):
        target = biotac_to_robot @ spec.tip_pose(k)
        result = inverse(arm, target, q, tool)
        if not result.success:
            return None
        reached = forward(arm, result.q, tool)
        position_error = np.linalg.norm(reached[:3, 3] - target[:3, 3])
        rotation_error = np.linalg.norm(reached[:3, :3] - target[:3, :3]) / np.sqrt(2.0)
        if position_error > POSITION_TOLERANCE or rotation_error > ROTATION_TOLERANCE:
            return None
        q = result.q
        path.append(q)
    return np.array(path)


def _collides(scene: TestbedScene, spec: TrajectorySpec, arm: str, path: np.ndarray) -> bool:
    scene.attach_tool(arm, spec.indenter)
    try:
        for q in path:
            scene.set_joints(arm, q)
            if scene.collisions(allow_tool_biotac=True):
                return True
        return False
    finally:
        scene.set_joints(arm, scene.home_joints(arm))
        scene.attach_tool(arm, None)


def plan_trajectory(
    scene: TestbedScene, spec: TrajectorySpec, sensor_id: int, registration: dict[str, np.ndarray]
) -> PlannedTrajectory:
    """The joint path of one spec on one sensor, or why it was dropped; `registration` maps arm -> estimated
    robot<-biotac 4x4. `scene` must hold both arms at home without tools (it is left so)."""
    arm = scene.arm_for_point(spec.point)
    biotac_to_robot = registration[arm]
    outcome = PlannedTrajectory(sensor_id, spec, arm, None, "unreachable")
    for roll in ROLLS:
        candidate = _rolled(spec, roll)
        path = _joint_path(
            candidate, arm, biotac_to_robot, scene.home_joints(arm), scene_tool_tip(scene, spec.indenter)
        )
        if path is None:
            continue
        if _collides(scene, candidate, arm, path):
            outcome = PlannedTrajectory(sensor_id, candidate, arm, None, "collision")
            continue
        return PlannedTrajectory(sensor_id, candidate, arm, path, None)
    return outcome


def plan_statistics(planned: list[PlannedTrajectory]) -> dict:
    """The `twin campaign plan --json` shape: per indenter planned/kept/dropped-by-reason, and totals."""
    stats: dict[str, dict] = {}
    for p in planned:
        entry = stats.setdefault(p.spec.indenter, {"planned": 0, "kept": 0, "dropped": Counter()})
        entry["planned"] += 1
        if p.kept:
            entry["kept"] += 1
        else:
            entry["dropped"][p.dropped] += 1
    per_sensor = Counter(p.sensor_id for p in planned if p.kept)
    unique = {p.spec.trajectory_id for p in planned if p.kept}
    return {
        "indenters": {name: {**e, "dropped": dict(e["dropped"])} for name, e in stats.items()},
        "kept_total": sum(1 for p in planned if p.kept),
        "kept_unique": len(unique),
        "planned_total": len(planned),
        "kept_per_sensor": {str(k): v for k, v in sorted(per_sensor.items())},
    }
