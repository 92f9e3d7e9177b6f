"""The ABB YuMi (IRB 14000) as data: joint chains of both arms and collision volumes of every link.

Robot frame (the YuMi body frame of the public URDF, metres): origin at the base of the torso on the
bench, x forward toward the workspace, y to the robot's left, z up. Chains follow ABB axes in the
order 1-2-7-3-4-5-6. Joint origins, limits and speeds are the facts table (facts/testbed.md).

Collision volumes are simple primitives that envelope each link, not the vendor meshes (which are not
redistributable): every arm link is a capsule from its joint origin to the next joint origin, the
flange link a short cylinder; the torso is three boxes. Radii and torso boxes are estimates from the
YuMi's published outline (about 0.57 m tall, shoulders 0.145 m apart), chosen slightly generous so a
collision-free plan keeps a few millimetres of margin; see docs/testbed.md.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np


@dataclass(frozen=True)
class JointSpec:
    """One revolute joint about its own z axis, placed by a fixed URDF origin in its parent link.

    xyz: origin translation (m) in the parent frame; rpy: URDF roll-pitch-yaw (rad), R = Rz(y) Ry(p) Rx(r).
    lower, upper: position limits (rad). max_velocity: speed limit (rad/s).
    """

    name: str
    xyz: tuple[float, float, float]
    rpy: tuple[float, float, float]
    lower: float
    upper: float
    max_velocity: float


@dataclass(frozen=True)
class ArmChain:
    """A 7-joint arm: joints in chain order 1-2-7-3-4-5-6, then the fixed link_7 -> flange origin."""

    joints: tuple[JointSpec, ...]
    flange_xyz: tuple[float, float, float]
    flange_rpy: tuple[float, float, float]


_PI = float(np.pi)
_HALF_PI = 1.5708  # the URDF's rounded pi/2, kept as published


def _shared_joints(suffix: str) -> tuple[JointSpec, ...]:
    """Joints 2, 7, 3, 4, 5, 6 (identical for both arms), from the facts table."""
    return (
        JointSpec(f"joint_2_{suffix}", (0.03, 0.0, 0.1), (_HALF_PI, 0.0, 0.0), -2.50455, 0.75922, 3.1416),
        JointSpec(f"joint_7_{suffix}", (-0.03, 0.17283, 0.0), (-_HALF_PI, 0.0, 0.0), -2.94088, 2.94088, 3.1416),
        JointSpec(f"joint_3_{suffix}", (-0.04188, 0.0, 0.07873), (_HALF_PI, -_HALF_PI, 0.0), -2.15548, 1.39626, 3.1416),
        JointSpec(f"joint_4_{suffix}", (0.0405, 0.16461, 0.0), (-_HALF_PI, 0.0, 0.0), -5.06145, 5.06145, 6.9813),
        JointSpec(f"joint_5_{suffix}", (-0.027, 0.0, 0.10039), (_HALF_PI, 0.0, 0.0), -1.53589, 2.40855, 6.9813),
        JointSpec(f"joint_6_{suffix}", (0.027, 0.029, 0.0), (-_HALF_PI, 0.0, 0.0), -3.99680, 3.99680, 6.9813),
    )


ARM_CHAINS: dict[str, ArmChain] = {
    "right": ArmChain(
        (
            JointSpec("joint_1_r", (0.05355, -0.0725, 0.41492), (-0.9795, -0.5682, -2.3155), -2.94088, 2.94088, 3.1416),
            *_shared_joints("r"),
        ),
        flange_xyz=(0.0, 0.0, 0.007),
        flange_rpy=(0.0, 0.0, _PI),
    ),
    "left": ArmChain(
        (
            JointSpec("joint_1_l", (0.05355, 0.0725, 0.41492), (0.9781, -0.5716, 2.3180), -2.94088, 2.94088, 3.1416),
            *_shared_joints("l"),
        ),
        flange_xyz=(0.0, 0.0, 0.007),
        flange_rpy=(0.0, 0.0, _PI),
    ),
}
"""Both YuMi arms from the public URDF (facts/testbed.md), robot frame, m and rad."""


def arm_chain(arm: str) -> ArmChain:
    """The chain of `arm` ("left" or "right"); ValueError for any other name."""
    if arm not in ARM_CHAINS:
        raise ValueError(f"unknown arm {arm!r}; expected one of ('left', 'right')")
    return ARM_CHAINS[arm]


def joint_limits(arm: str) -> np.ndarray:
    """(7, 2) lower and upper joint position limits of `arm` (rad, chain order 1-2-7-3-4-5-6)."""
    return np.array([(j.lower, j.upper) for j in arm_chain(arm).joints])


def velocity_limits(arm: str) -> np.ndarray:
    """(7,) joint speed limits of `arm` (rad/s, chain order 1-2-7-3-4-5-6)."""
    return np.array([j.max_velocity for j in arm_chain(arm).joints])


def rpy_matrix(rpy: tuple[float, float, float] | np.ndarray) -> np.ndarray:
    """(3, 3) rotation of URDF roll-pitch-yaw (rad): Rz(yaw) @ Ry(pitch) @ Rx(roll)."""
    r, p, y = rpy
    cr, sr, cp, sp, cy, sy = np.cos(r), np.sin(r), np.cos(p), np.sin(p), np.cos(y), np.sin(y)
    return np.array(
        [
            [cy * cp, cy * sp * sr - sy * cr, cy * sp * cr + sy * sr],
            [sy * cp, sy * sp * sr + cy * cr, sy * sp * cr - cy * sr],
            [-sp, cp * sr, cp * cr],
        ]
    )


def origin_transform(xyz: tuple[float, float, float], rpy: tuple[float, float, float]) -> np.ndarray:
    """(4, 4) homogeneous transform of a URDF origin (xyz in m, rpy in rad)."""
    t = np.eye(4)
    t[:3, :3] = rpy_matrix(rpy)
    t[:3, 3] = xyz
    return t


@dataclass(frozen=True)
class Shape:
    """A collision primitive in a body frame (m). kind: "capsule" | "cylinder" | "box".

    capsule / cylinder: radius and segment end points `a`, `b` (3,); box: half sizes (3,) and centre
    `a`, axis-aligned in the body frame (`b` unused). `collide=False` makes it visual only.
    """

    name: str
    kind: str
    size: tuple[float, ...]
    a: tuple[float, float, float]
    b: tuple[float, float, float] = (0.0, 0.0, 0.0)
    collide: bool = True


LINK_RADII = (0.050, 0.045, 0.040, 0.040, 0.035, 0.025, 0.021)
"""Collision radius (m) of link_1 .. link_7 (link_7 carries the flange)."""
FLANGE_LINK_BACK = 0.015
"""How far (m) the flange link's cylinder extends behind the joint-6 frame origin."""
WRIST_SETBACK = 0.003
"""The wrist capsule (link_6) ends this far (m) plus its radius behind joint 6 along the tool axis, so
it never reaches past the flange face: the flange link's cylinder covers the space in between."""
NEIGHBOUR_EXCLUDE = 2
"""Links this many or fewer apart in one chain never collide (the real joints keep them apart)."""

TORSO_SHAPES: tuple[Shape, ...] = (
    Shape("torso_base", "box", (0.16, 0.19, 0.05), (-0.06, 0.0, 0.05)),
    Shape("torso_body", "box", (0.09, 0.11, 0.17), (-0.07, 0.0, 0.27)),
    Shape("torso_head", "box", (0.07, 0.06, 0.05), (-0.06, 0.0, 0.49)),
)
"""Torso volumes in the robot frame (box half sizes and centres, m)."""

HOME_JOINTS: dict[str, np.ndarray] = {
    "right": np.deg2rad([0.0, -130.0, -135.0, 30.0, 0.0, 40.0, 0.0]),
    "left": np.deg2rad([0.0, -130.0, 135.0, 30.0, 0.0, 40.0, 0.0]),
}
"""ABB's synchronisation pose of YuMi, chain order 1-2-7-3-4-5-6 (rad): arms folded, clear of the bench."""


def link_shapes(arm: str) -> tuple[tuple[Shape, ...], ...]:
    """Collision shapes of link_1 .. link_7 of `arm`, each in its own link frame (after its joint)."""
    joints = ARM_CHAINS[arm].joints
    links = []
    for i in range(len(joints)):
        name = f"{arm}_link_{i + 1}"
        if i + 1 < len(joints):
            end = np.asarray(joints[i + 1].xyz, dtype=float)
            if i + 2 == len(joints):  # the wrist: pull the end back along the tool axis (joint 6's z)
                end = end - (LINK_RADII[i] + WRIST_SETBACK) * rpy_matrix(joints[i + 1].rpy)[:, 2]
            links.append((Shape(name, "capsule", (LINK_RADII[i],), (0.0, 0.0, 0.0), tuple(end)),))
        else:
            flange = ARM_CHAINS[arm].flange_xyz
            links.append((Shape(name, "cylinder", (LINK_RADII[i],), (0.0, 0.0, -FLANGE_LINK_BACK), flange),))
    return tuple(links)
