"""The paper's indentation protocol: which points, which trajectories, which depths, and the settings.

Everything geometric here is in the `biotac` frame (m): x distal, -z ventral pad. A trajectory is a
straight path of the indenter tip: it starts `standoff` before the first contact with the nominal
inflated skin, reaches first contact (depth 0), then goes `depth` past it in `step` increments, each
followed by a settle pause. Robot-side feasibility (IK, collisions) is checked in `twin.planning`.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from assets.biotac import BioTacGeometry, sample_ventral_points
from assets.indenters import INDENTERS, get_indenter
from fe.sensor import BioTacModel


@dataclass(frozen=True)
class ProtocolSettings:
    """Campaign protocol (SI units). Defaults are the paper's (Methods B)."""

    points_per_indenter: int = 10
    angled_per_point: int = 4
    angle_deg: float = 30.0
    normal_depth: float = 3e-3
    angled_depth: float = 1.5e-3
    step: float = 1e-4
    pause_s: float = 5.0
    standoff: float = 1e-3
    """Distance (m) before first contact where each trajectory starts (and is tared)."""
    speed: float = 1e-3
    """Tip speed (m/s) during each increment's move."""
    sample_rate_hz: float = 100.0
    unload: bool = True
    """Retract through the same increments after the deepest one (an unloading phase)."""
    force_limit: float = 25.0
    """The controller stops and retracts above this force magnitude (N)."""
    replacement_rounds: int = 0
    """Draw new points for an indenter whose trajectories were all dropped on a sensor, up to this many
    times (0: the paper's protocol, drop and move on)."""

    def __post_init__(self) -> None:
        positive = {
            "step": self.step,
            "speed": self.speed,
            "sample_rate_hz": self.sample_rate_hz,
            "standoff": self.standoff,
            "force_limit": self.force_limit,
        }
        for name, value in positive.items():
            if not value > 0:
                raise ValueError(f"{name} must be > 0, got {value!r}")
        if self.points_per_indenter < 1 or self.angled_per_point < 0:
            raise ValueError("points_per_indenter must be >= 1 and angled_per_point >= 0")
        if self.normal_depth < 0 or self.angled_depth < 0 or self.pause_s < 0:
            raise ValueError("depths and pause must be >= 0")
        if not 0.0 <= self.angle_deg < 90.0:
            raise ValueError(f"angle_deg must be in [0, 90), got {self.angle_deg!r}")


QUICK_SETTINGS = ProtocolSettings(
    points_per_indenter=1,
    angled_per_point=1,
    normal_depth=1.0e-3,
    angled_depth=0.6e-3,
    pause_s=0.5,
    unload=True,
    replacement_rounds=4,
)
"""A small campaign for tests and demos: one point per indenter, one normal and one angled path; a
point whose paths the robot cannot run is replaced, so every indenter is covered."""


@dataclass(frozen=True)
class TrajectorySpec:
    """One planned indentation in the biotac frame (m, rad), before any robot is involved.

    rotation: (3, 3) orientation of the indenter frame (tip at origin, presses along its -z) in the
    biotac frame; its z column is -direction. depths: (K,) tip distances past first contact, starting
    at -standoff, then 0, step, ..., the deepest, then (when unloading) back to -standoff.
    """

    trajectory_id: int
    indenter: str
    point: np.ndarray
    angle: float
    azimuth: float
    touch_point: np.ndarray
    direction: np.ndarray
    rotation: np.ndarray
    depths: np.ndarray
    increment: np.ndarray = field(repr=False)
    """(K,) increment index of each depth: -1 at the standoff, 0.. for the loading/unloading steps."""

    def tip_pose(self, k: int) -> np.ndarray:
        """4x4 pose of the indenter frame in the biotac frame at path index k."""
        pose = np.eye(4)
        pose[:3, :3] = self.rotation
        pose[:3, 3] = self.touch_point + self.depths[k] * self.direction
        return pose


def depth_schedule(depth: float, settings: ProtocolSettings) -> tuple[np.ndarray, np.ndarray]:
    """Depths (m) and increment indices of one trajectory: standoff, loading, optional unloading."""
    n = int(round(depth / settings.step))
    loading = np.arange(n + 1) * settings.step
    depths = [np.array([-settings.standoff]), loading]
    if settings.unload and n > 0:
        depths += [loading[-2::-1], np.array([-settings.standoff])]
    values = np.concatenate(depths)
    increments = np.arange(len(values)) - 1
    return values, increments


@dataclass(frozen=True)
class PathDraw:
    """One drawn trajectory before its first touch is found: the indenter, the ventral point (m, biotac frame),
    the tilt from the inward normal and its azimuth (rad), and the depth past first contact (m)."""

    indenter: str
    point: np.ndarray
    angle: float
    azimuth: float
    depth: float


def draw_paths(
    geometry: BioTacGeometry,
    indenters: list[str] | None = None,
    settings: ProtocolSettings = ProtocolSettings(),
    seed: int = 0,
) -> list[PathDraw]:
    """Seeded random ventral points per indenter; one normal and `angled_per_point` angled paths each, in a
    fixed order (indenter, point, path), so the same seed gives the same draws.

    Azimuths of the angled paths are spread evenly around the normal with a random phase per point.
    """
    names = list(INDENTERS) if indenters is None else list(indenters)
    rng = np.random.default_rng(seed)
    draws: list[PathDraw] = []
    for name in names:
        points, _ = sample_ventral_points(geometry, settings.points_per_indenter, rng)
        phases = rng.uniform(0.0, 2.0 * np.pi, size=len(points))
        for point, phase in zip(points, phases, strict=True):
            draws.append(PathDraw(name, point, 0.0, 0.0, settings.normal_depth))
            for j in range(settings.angled_per_point):
                azimuth = phase + 2.0 * np.pi * j / settings.angled_per_point
                draws.append(
                    PathDraw(name, point, float(np.radians(settings.angle_deg)), azimuth, settings.angled_depth)
                )
    return draws


def plan_spec(model: BioTacModel, draw: PathDraw, settings: ProtocolSettings, trajectory_id: int) -> TrajectorySpec:
    """The trajectory of `draw` on `model`, which must be inflated (its outer surface defines first contact)."""
    planned = model.plan_trajectory(
        get_indenter(draw.indenter),
        draw.point,
        np.degrees(draw.angle),
        np.degrees(draw.azimuth),
        draw.depth,
        settings.step,
    )
    depths, increments = depth_schedule(draw.depth, settings)
    return TrajectorySpec(
        trajectory_id=trajectory_id,
        indenter=draw.indenter,
        point=draw.point,
        angle=float(draw.angle),
        azimuth=float(draw.azimuth % (2.0 * np.pi)),
        touch_point=planned.touch_point,
        direction=planned.direction,
        rotation=planned.rotation,
        depths=depths,
        increment=increments,
    )
