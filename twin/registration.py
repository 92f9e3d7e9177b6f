"""Mechanical robot-BioTac registration (paper, Methods B): a pin in the mount's hole liners.

The pin is seated in a liner (shoulder on the rim) and its shoulder point is recorded twice: in the
robot frame R by forward kinematics of the measured joints, and in the biotac frame B from the mount
CAD. Three non-collinear points define an intermediate frame I (origin at the first point, x toward
the second, z normal to the plane of the three), known in both frames as H_RI and H_BI. The paper
writes the result as H_BR = H_BI (H_RI)^-1 (maps robot points into the biotac frame); this module
returns its inverse H_RB = H_RI (H_BI)^-1 (p_robot = H_RB @ p_biotac), the convention of
``TestbedScene.biotac_pose``. All four 3-hole combinations are averaged: rotations by the chordal L2
mean (the element-wise mean projected onto SO(3) by SVD), translations arithmetically.

``simulate_registration`` simulates the procedure on one arm of a scene: each seated pin lands
anywhere in its liner's clearance (the pin axis uniform in a disc of radius clearance / 2, the
diametral clearance), joint encoders read with Gaussian noise, and the real arm may differ from the
nominal kinematic model by joint zero offsets. ``registration_error`` then measures the error where it
matters, at the BioTac: the sphere-medium indenter is sent (nominal IK, estimated transform) to ventral
skin points, and the real tip is compared with the intended point in the true biotac frame.
"""

from __future__ import annotations

from dataclasses import dataclass
from itertools import combinations

import numpy as np

from assets.biotac import make_biotac, sample_ventral_points
from assets.tools import PIN, tool_tip_transform
from twin.kinematics import IKSettings, forward, inverse_axis, joint_limits
from twin.scene import TestbedScene

EXACT_IK = IKSettings(position_tolerance=1e-10, rotation_tolerance=1e-9)
"""IK settings used to place the pin and the indenter in simulation (round-off, not 0.01 mm)."""
ENCODER_NOISE_RAD = 2e-5
"""Default joint-encoder noise (rad, 1 sigma): about the YuMi's 0.02 mm repeatability at a 0.5 m reach
spread over the joints."""
SEAT_ATTEMPTS = 20
"""IK seeds tried per hole to find an arm configuration that reaches it without touching anything."""
PAPER_JOINT_OFFSET_STD = 2e-3
"""RMS over the joints (rad) of the real arm's joint zero offsets against the nominal URDF that reproduces the
paper's observed 0.5-1.5 mm error (`twin.plant.make_plant` draws offsets of this RMS in a random direction).
Not a YuMi specification: clearance and encoder noise alone give under 0.15 mm here, so the paper's band
must come from unmodelled kinematic error of about this size (docs/testbed.md)."""


def frame_from_points(points: np.ndarray) -> np.ndarray:
    """(4, 4) pose of frame I built on three points (3, 3) m: origin p0, x toward p1, z = (p1-p0) x (p2-p0)."""
    p = np.asarray(points, dtype=float)
    x, y = p[1] - p[0], p[2] - p[0]
    z = np.cross(x, y)
    nz = np.linalg.norm(z)
    if nz <= 1e-9 * np.linalg.norm(x) * np.linalg.norm(y):
        raise ValueError("frame_from_points: the three points are collinear")
    x, z = x / np.linalg.norm(x), z / nz
    frame = np.eye(4)
    frame[:3, :3] = np.column_stack([x, np.cross(z, x), z])
    frame[:3, 3] = p[0]
    return frame


def project_to_rotation(m: np.ndarray) -> np.ndarray:
    """The rotation (3, 3) closest to `m` (3, 3) in the Frobenius norm (SVD projection onto SO(3))."""
    u, _, vt = np.linalg.svd(m)
    d = np.sign(np.linalg.det(u @ vt))
    return u @ np.diag([1.0, 1.0, d]) @ vt


def average_transforms(transforms: np.ndarray) -> np.ndarray:
    """(4, 4) average of rigid transforms (N, 4, 4): chordal L2 mean rotation, mean translation."""
    t = np.asarray(transforms, dtype=float)
    out = np.eye(4)
    out[:3, :3] = project_to_rotation(t[:, :3, :3].mean(axis=0))
    out[:3, 3] = t[:, :3, 3].mean(axis=0)
    return out


def combination_transforms(points_robot: np.ndarray, points_biotac: np.ndarray) -> np.ndarray:
    """(C, 4, 4) H_RB = H_RI (H_BI)^-1 for every 3-point combination of the N >= 3 matched points (N, 3)."""
    pr, pb = np.asarray(points_robot, dtype=float), np.asarray(points_biotac, dtype=float)
    if pr.shape != pb.shape or pr.ndim != 2 or pr.shape[1] != 3 or len(pr) < 3:
        raise ValueError(f"need matched (N >= 3, 3) point sets, got {pr.shape} and {pb.shape}")
    out = []
    for combo in combinations(range(len(pr)), 3):
        idx = list(combo)
        out.append(frame_from_points(pr[idx]) @ np.linalg.inv(frame_from_points(pb[idx])))
    return np.array(out)


def estimate_transform(points_robot: np.ndarray, points_biotac: np.ndarray) -> np.ndarray:
    """(4, 4) H_RB (p_robot = H_RB @ p_biotac) from matched hole points (4, 3) m, averaged over 3-hole sets.

    The paper's H_BR (robot -> biotac) is ``np.linalg.inv`` of the result.
    """
    return average_transforms(combination_transforms(points_robot, points_biotac))


@dataclass(frozen=True)
class RegistrationResult:
    """One simulated registration of one arm.

    transform: (4, 4) estimated H_RB. per_combination: (4, 4, 4) H_RB of each 3-hole combination.
    points_robot: (4, 3) recorded shoulder points (robot frame, m); joints: (4, 7) measured joints (rad).
    point_errors: (n,) registration error at n ventral skin points (m), see ``registration_error``.
    collisions: geom pairs in contact while the pin was seated (should be empty).
    """

    arm: str
    transform: np.ndarray
    per_combination: np.ndarray
    points_robot: np.ndarray
    joints: np.ndarray
    point_errors: np.ndarray
    collisions: tuple[tuple[str, str], ...]

    @property
    def error_rms(self) -> float:
        """RMS registration error at the BioTac (m)."""
        return float(np.sqrt(np.mean(self.point_errors**2)))

    @property
    def error_max(self) -> float:
        """Largest registration error at the BioTac (m)."""
        return float(self.point_errors.max())


def _disc_offset(axis: np.ndarray, radius: float, rng: np.random.Generator) -> np.ndarray:
    """A point uniform in the disc of `radius` (m) perpendicular to the unit `axis`, as a (3,) offset."""
    helper = np.eye(3)[np.argmin(np.abs(axis))]
    e1 = np.cross(axis, helper)
    e1 /= np.linalg.norm(e1)
    e2 = np.cross(axis, e1)
    r, phi = radius * np.sqrt(rng.random()), 2.0 * np.pi * rng.random()
    return r * (np.cos(phi) * e1 + np.sin(phi) * e2)


def _place_tool(
    arm: str, point: np.ndarray, direction: np.ndarray, seed: np.ndarray, tool_tip: np.ndarray
) -> np.ndarray:
    """Nominal-model joints (7,) rad with the tip at `point` (m) pressing along `direction`; raises if unreachable."""
    result = inverse_axis(arm, point, direction, seed, tool_tip, EXACT_IK)
    if not result.success:
        raise RuntimeError(f"{arm} arm cannot reach {np.round(point * 1e3, 2)} mm: {result.message}")
    return result.q


def _seat_pin(
    scene: TestbedScene, arm: str, point: np.ndarray, direction: np.ndarray, tool_tip: np.ndarray, hole: int
) -> tuple[np.ndarray, list[tuple[str, str]]]:
    """A collision-free arm configuration seating the pin (the operator guides the arm around the mount).

    Tries the home pose as IK seed, then SEAT_ATTEMPTS seeded random seeds; returns joints (7,) rad and
    the collisions of the last attempt when none is free (empty list on success).
    """
    lim = joint_limits(arm)
    seeds = np.random.default_rng(hole)
    seed = scene.home_joints(arm)
    for _ in range(SEAT_ATTEMPTS):
        q = _place_tool(arm, point, direction, seed, tool_tip)
        scene.set_joints(arm, q)
        contacts = scene.collisions()
        if not contacts:
            break
        seed = seeds.uniform(lim[:, 0], lim[:, 1])
    return q, contacts


def registration_error(
    scene: TestbedScene,
    arm: str,
    transform: np.ndarray,
    true_biotac_pose: np.ndarray | None = None,
    joint_offset_rad: np.ndarray | None = None,
    n_points: int = 24,
    seed: int = 0,
) -> np.ndarray:
    """Errors (n_points,) m at the BioTac of an estimated H_RB `transform` for `arm`.

    Seeded random ventral skin points of `arm`'s side; for each, the sphere-medium indenter is placed by
    nominal IK at ``transform @ p``, pressing along the inward skin normal; the real tip (nominal FK at
    the joints plus `joint_offset_rad`) is mapped into the true biotac frame and compared with p.
    """
    truth = scene.biotac_pose if true_biotac_pose is None else np.asarray(true_biotac_pose, dtype=float)
    offset = np.zeros(7) if joint_offset_rad is None else np.asarray(joint_offset_rad, dtype=float)
    geometry = make_biotac(scene.params.biotac_max_edge)
    points, normals = sample_ventral_points(geometry, 4 * n_points, np.random.default_rng(seed))
    mine = [i for i, p in enumerate(points) if scene.arm_for_point(p) == arm][:n_points]
    tip = tool_tip_transform("sphere_medium")
    to_biotac = np.linalg.inv(truth)
    errors = []
    q = scene.home_joints(arm)
    for p, n in zip(points[mine], normals[mine], strict=True):
        target = transform[:3, :3] @ p + transform[:3, 3]
        q = _place_tool(arm, target, -(transform[:3, :3] @ n), q, tip)
        real = forward(arm, q + offset, tip)[:3, 3]
        errors.append(np.linalg.norm(to_biotac[:3, :3] @ real + to_biotac[:3, 3] - p))
    return np.array(errors)


def simulate_registration(
    scene: TestbedScene,
    rng: np.random.Generator,
    arm: str = "right",
    clearance: float = 0.3e-3,
    encoder_noise_rad: float = ENCODER_NOISE_RAD,
    joint_offset_rad: np.ndarray | None = None,
    true_biotac_pose: np.ndarray | None = None,
    n_error_points: int = 24,
) -> RegistrationResult:
    """Simulate the pin-in-hole registration of `arm` and measure its error at the BioTac.

    The paper registers each arm on its own: call this once per arm and use each arm's transform for
    the trajectories of that arm.

    clearance: diametral pin-liner clearance (m); the pin axis lands uniformly within clearance / 2 of
    the liner axis. encoder_noise_rad: joint-reading noise (rad, 1 sigma, independent per joint and
    hole). joint_offset_rad: (7,) real-arm joint zero offsets w.r.t. the nominal model (rad; None: a
    perfect model). true_biotac_pose: the real H_RB (default: the scene's nominal mount).
    n_error_points: ventral points used by ``registration_error``. The pin is attached to `arm` in
    `scene` while seated; the arm is left at home without a tool afterwards.
    """
    truth = scene.biotac_pose if true_biotac_pose is None else np.asarray(true_biotac_pose, dtype=float)
    offset = np.zeros(7) if joint_offset_rad is None else np.asarray(joint_offset_rad, dtype=float)
    holes_b = scene.hole_positions_biotac
    axis_b = np.linalg.inv(scene.params.mount.biotac_in_mount())[:3, 2]  # liner axis (mount z), biotac frame
    axis = truth[:3, :3] @ axis_b
    pin_tip = tool_tip_transform(PIN, scene.params.adapter_length, scene.params.pin)
    scene.attach_tool(arm, PIN)
    joints, recorded, contacts = [], [], set()
    try:
        for hole_index, hole in enumerate(holes_b):
            seat = truth[:3, :3] @ hole + truth[:3, 3] + _disc_offset(axis, 0.5 * clearance, rng)
            # the real arm's shape is the nominal model at (reading + offset)
            q_geometric, collided = _seat_pin(scene, arm, seat, -axis, pin_tip, hole_index)
            contacts.update(collided)
            q_meas = q_geometric - offset + encoder_noise_rad * rng.standard_normal(7)
            joints.append(q_meas)
            recorded.append(forward(arm, q_meas, pin_tip)[:3, 3])
    finally:
        scene.set_joints(arm, scene.home_joints(arm))
        scene.attach_tool(arm, None)
    points = np.array(recorded)
    per_combination = combination_transforms(points, holes_b)
    estimate = average_transforms(per_combination)
    errors = registration_error(scene, arm, estimate, truth, offset, n_error_points)
    return RegistrationResult(arm, estimate, per_combination, points, np.array(joints), errors, tuple(sorted(contacts)))
