"""YuMi (IRB 14000) arm kinematics: forward kinematics, Jacobian and joint-limited inverse kinematics.

Frames and units (SI): the ``robot`` frame is the YuMi body frame of the public URDF (origin at the
base of the torso, x forward toward the workspace, y to the robot's left, z up). Joint vectors are (7,)
in radians in chain order 1-2-7-3-4-5-6 (``twin.backend``). ``forward`` returns the pose of the flange,
or of a tool tip when given the 4x4 flange->tip transform (``assets.tools.tool_tip_transform``), as a
4x4 homogeneous matrix mapping tip coordinates into robot coordinates.

Tool tips follow the indenter frame of ``assets.indenters``: the tool presses along the tip frame's -z.

``inverse`` solves the full 6-D pose; ``inverse_axis`` solves position plus pressing direction and leaves
the roll about the tool axis free. Both are damped least squares with the joint limits enforced by
clamping, a null-space pull toward the seed (so successive solutions along a path stay close), and
seeded random restarts; both report failure instead of returning an inaccurate pose.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from assets.yumi import (
    ARM_CHAINS,
    ArmChain,
    JointSpec,
    joint_limits,
    origin_transform,
    rpy_matrix,
    velocity_limits,
)
from twin.backend import N_JOINTS, check_arm

__all__ = [
    "ARM_CHAINS",
    "ArmChain",
    "IKResult",
    "IKSettings",
    "JointSpec",
    "forward",
    "inverse",
    "inverse_axis",
    "jacobian",
    "joint_frames",
    "joint_limits",
    "origin_transform",
    "rpy_matrix",
    "velocity_limits",
    "within_limits",
]

POSITION_TOLERANCE = 1e-5
"""Default IK acceptance on the tip position: 0.01 mm (m), the paper's reachability criterion."""
ROTATION_TOLERANCE = 1e-4
"""Default IK acceptance on the tip orientation (rad, geodesic angle)."""
_EYE6 = np.eye(6)


def _origins(arm: str) -> tuple[np.ndarray, np.ndarray]:
    """(7, 4, 4) fixed joint origins and (4, 4) link_7 -> flange transform of `arm`."""
    chain = ARM_CHAINS[check_arm(arm)]
    return (
        np.array([origin_transform(j.xyz, j.rpy) for j in chain.joints]),
        origin_transform(chain.flange_xyz, chain.flange_rpy),
    )


_ORIGINS = {arm: _origins(arm) for arm in ARM_CHAINS}


def within_limits(arm: str, q: np.ndarray, tol: float = 0.0) -> bool:
    """Whether joint vector q (7,) rad lies inside `arm`'s limits widened by tol (rad)."""
    lim = joint_limits(arm)
    q = np.asarray(q, dtype=float)
    return bool(np.all(q >= lim[:, 0] - tol) and np.all(q <= lim[:, 1] + tol))


def _check_q(q: np.ndarray) -> np.ndarray:
    q = np.asarray(q, dtype=float)
    if q.shape != (N_JOINTS,):
        raise ValueError(f"joint vector must have shape ({N_JOINTS},), got {q.shape}")
    return q


def joint_frames(arm: str, q: np.ndarray) -> np.ndarray:
    """(8, 4, 4) robot-frame poses of the 7 joint frames (after each joint's rotation) and the flange."""
    q = _check_q(q)
    origins, flange = _ORIGINS[check_arm(arm)]
    frames = np.empty((N_JOINTS + 1, 4, 4))
    t = np.eye(4)
    rot = np.eye(4)
    for i in range(N_JOINTS):
        c, s = np.cos(q[i]), np.sin(q[i])
        rot[0, 0], rot[0, 1], rot[1, 0], rot[1, 1] = c, -s, s, c
        t = t @ origins[i] @ rot
        frames[i] = t
    frames[N_JOINTS] = t @ flange
    return frames


def forward(arm: str, q: np.ndarray, tool_tip: np.ndarray | None = None) -> np.ndarray:
    """(4, 4) pose of the flange, or of the tool tip when `tool_tip` (flange->tip, 4x4) is given, robot frame."""
    flange = joint_frames(arm, q)[N_JOINTS]
    return flange if tool_tip is None else flange @ tool_tip


def jacobian(arm: str, q: np.ndarray, tool_tip: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray]:
    """Pose (4, 4) of the tip (or flange) and its geometric Jacobian (6, 7), robot frame.

    Rows 0-2: tip linear velocity (m/s per rad/s); rows 3-5: angular velocity (rad/s per rad/s).
    """
    frames = joint_frames(arm, q)
    tip = frames[N_JOINTS] if tool_tip is None else frames[N_JOINTS] @ tool_tip
    axes = frames[:N_JOINTS, :3, 2]
    jac = np.empty((6, N_JOINTS))
    arm_vec = tip[:3, 3] - frames[:N_JOINTS, :3, 3]
    jac[0] = axes[:, 1] * arm_vec[:, 2] - axes[:, 2] * arm_vec[:, 1]
    jac[1] = axes[:, 2] * arm_vec[:, 0] - axes[:, 0] * arm_vec[:, 2]
    jac[2] = axes[:, 0] * arm_vec[:, 1] - axes[:, 1] * arm_vec[:, 0]
    jac[3:] = axes.T
    return tip, jac


def rotation_exp(v: np.ndarray) -> np.ndarray:
    """Rotation matrix (3, 3) of a rotation vector v (3,) rad (axis times angle; Rodrigues' formula)."""
    theta = float(np.linalg.norm(v))
    if theta == 0.0:
        return np.eye(3)
    k = np.asarray(v, dtype=float) / theta
    kx = np.array([[0.0, -k[2], k[1]], [k[2], 0.0, -k[0]], [-k[1], k[0], 0.0]])
    return np.eye(3) + np.sin(theta) * kx + (1.0 - np.cos(theta)) * kx @ kx


def rotation_log(r: np.ndarray) -> np.ndarray:
    """Rotation vector (3,) rad of a rotation matrix (3, 3); robust near 0 and pi."""
    cos = np.clip(0.5 * (np.trace(r) - 1.0), -1.0, 1.0)
    angle = float(np.arccos(cos))
    w = np.array([r[2, 1] - r[1, 2], r[0, 2] - r[2, 0], r[1, 0] - r[0, 1]])
    if angle < 1e-6:
        return 0.5 * w
    if angle > np.pi - 1e-4:  # axis from the symmetric part: R + I = 2 a a^T (1 - cos) + ...
        b = 0.5 * (r + np.eye(3))
        axis = b[np.argmax(np.diag(b))]
        axis = axis / np.linalg.norm(axis)
        if w @ axis < 0.0:
            axis = -axis
        return angle * axis
    return angle / (2.0 * np.sin(angle)) * w


def rotation_angle(a: np.ndarray, b: np.ndarray) -> float:
    """Geodesic angle (rad) between rotations a and b (3, 3)."""
    return float(np.arccos(np.clip(0.5 * (np.trace(a.T @ b) - 1.0), -1.0, 1.0)))


@dataclass(frozen=True)
class IKResult:
    """Outcome of an IK solve. q: (7,) rad within limits (the best found, also on failure).

    position_error: |tip - target| (m); rotation_error: geodesic angle (rad) for `inverse`, angle
    between the achieved and the requested pressing direction for `inverse_axis`.
    """

    q: np.ndarray
    success: bool
    position_error: float
    rotation_error: float
    message: str
    iterations: int


@dataclass(frozen=True)
class IKSettings:
    """Damped-least-squares settings. Tolerances in m and rad; `seed` drives the restarts (reproducible).

    damping: Levenberg-Marquardt damping (m, rad scale) at the start of each attempt; it shrinks on
    progress and grows on a rejected step. null_gain: pull of the null-space term toward the seed,
    applied while the position error exceeds null_until (m); closer in, the iterations converge on the
    task alone (short moves from the seed are minimal-norm steps already).
    length_scale: m per rad used to weigh position against orientation errors.
    """

    position_tolerance: float = POSITION_TOLERANCE
    rotation_tolerance: float = ROTATION_TOLERANCE
    max_iterations: int = 200
    restarts: int = 30
    damping: float = 1e-2
    null_gain: float = 0.05
    length_scale: float = 0.1
    null_until: float = 1e-3
    seed: int = 0


def _task_error(tip: np.ndarray, position: np.ndarray, target_rot: np.ndarray | None, axis: np.ndarray | None):
    """Weighted-task error pieces: position error (3,), rotation error vector (3,) rad, scalar angle."""
    e_pos = position - tip[:3, 3]
    if target_rot is not None:
        e_rot = rotation_log(target_rot @ tip[:3, :3].T)
        return e_pos, e_rot, float(np.linalg.norm(e_rot))
    z = tip[:3, 2]
    cross = np.cross(z, axis)
    sin, cos = float(np.linalg.norm(cross)), float(z @ axis)
    angle = float(np.arctan2(sin, cos))
    if sin < 1e-12:
        e_rot = np.zeros(3) if cos > 0 else angle * np.cross(z, np.eye(3)[np.argmin(np.abs(z))])
        return e_pos, e_rot, angle
    return e_pos, angle * cross / sin, angle


def _solve(
    arm: str,
    position: np.ndarray,
    target_rot: np.ndarray | None,
    axis: np.ndarray | None,
    q_seed: np.ndarray,
    tool_tip: np.ndarray | None,
    settings: IKSettings,
) -> IKResult:
    """Shared DLS core. target_rot (3, 3) for a full pose, or axis (3,) for the tip z axis only."""
    lim = joint_limits(arm)
    rng = np.random.default_rng(settings.seed)
    q_rest = np.clip(_check_q(q_seed), lim[:, 0], lim[:, 1])
    w = np.array([1.0 / settings.length_scale] * 3 + [1.0] * 3)
    best: tuple[float, np.ndarray, float, float] | None = None
    total = 0
    for attempt in range(settings.restarts + 1):
        q = q_rest.copy() if attempt == 0 else rng.uniform(lim[:, 0], lim[:, 1])
        damping = settings.damping
        tip, jac = jacobian(arm, q, tool_tip)
        e_pos, e_rot, angle = _task_error(tip, position, target_rot, axis)
        for _ in range(settings.max_iterations):
            total += 1
            pos_err = float(np.linalg.norm(e_pos))
            if pos_err <= 0.1 * settings.position_tolerance and angle <= 0.1 * settings.rotation_tolerance:
                break
            err = np.concatenate([e_pos, e_rot]) * w
            jw = jac * w[:, None]
            if axis is not None:  # free roll: drop the angular velocity about the tip z axis
                z = tip[:3, 2]
                jw[3:] -= np.outer(z, z @ jw[3:])
            jjt = jw @ jw.T
            step = jw.T @ np.linalg.solve(jjt + damping**2 * _EYE6, err)
            if pos_err > settings.null_until:  # shape the redundancy far out
                pinv_j = jw.T @ np.linalg.solve(jjt + 1e-8 * _EYE6, jw)
                step += settings.null_gain * (q_rest - q - pinv_j @ (q_rest - q))
            q_new = np.clip(q + step, lim[:, 0], lim[:, 1])
            tip_new, jac_new = jacobian(arm, q_new, tool_tip)
            new = _task_error(tip_new, position, target_rot, axis)
            cost_old = float(np.sum(err**2))
            cost_new = float(np.sum((np.concatenate(new[:2]) * w) ** 2))
            if cost_new < cost_old or cost_new < 1e-20:
                q, tip, jac, (e_pos, e_rot, angle) = q_new, tip_new, jac_new, new
                damping = max(0.5 * damping, 1e-6)
            else:
                damping *= 4.0
                if damping > 10.0:
                    break
        pos_err = float(np.linalg.norm(e_pos))
        score = pos_err / settings.length_scale + angle
        if best is None or score < best[0]:
            best = (score, q.copy(), pos_err, angle)
        if pos_err <= settings.position_tolerance and angle <= settings.rotation_tolerance:
            return IKResult(q, True, pos_err, angle, f"reached after {attempt} restart(s)", total)
    assert best is not None
    _, q, pos_err, angle = best
    return IKResult(
        q,
        False,
        pos_err,
        angle,
        f"not reached within tolerance after {settings.restarts} restarts: best position error "
        f"{pos_err * 1e3:.4g} mm, rotation error {angle:.3g} rad",
        total,
    )


def inverse(
    arm: str,
    target: np.ndarray,
    q_seed: np.ndarray,
    tool_tip: np.ndarray | None = None,
    settings: IKSettings = IKSettings(),  # noqa: B008 - frozen dataclass
) -> IKResult:
    """Joint angles (7,) rad within limits putting the tip (or flange) at `target` (4, 4), robot frame.

    Starts at `q_seed` (clipped into the limits), then random restarts; the 7th degree of freedom is
    resolved by a null-space pull toward `q_seed`. Succeeds when the tip is within
    settings.position_tolerance (m) and settings.rotation_tolerance (rad); otherwise `success` is False,
    `message` says why and `q` is the best configuration found.
    """
    target = np.asarray(target, dtype=float)
    if target.shape != (4, 4):
        raise ValueError(f"target must be a 4x4 pose, got shape {target.shape}")
    return _solve(arm, target[:3, 3], target[:3, :3], None, q_seed, tool_tip, settings)


def inverse_axis(
    arm: str,
    position: np.ndarray,
    approach_direction: np.ndarray,
    q_seed: np.ndarray,
    tool_tip: np.ndarray | None = None,
    settings: IKSettings = IKSettings(),  # noqa: B008 - frozen dataclass
) -> IKResult:
    """Joint angles (7,) rad putting the tip at `position` (3,) m, pressing along `approach_direction` (3,).

    Robot frame. The tip frame's -z is aligned with the unit approach direction; the roll about it is
    left free and settles where the null-space pull toward `q_seed` puts it (the least joint motion
    from the seed, so a path solved point after point keeps one roll). To then hold that roll along a
    path, take `forward(arm, result.q, tool_tip)` and solve the remaining poses with `inverse`.
    """
    direction = np.asarray(approach_direction, dtype=float)
    norm = float(np.linalg.norm(direction))
    if direction.shape != (3,) or not norm > 0.0:
        raise ValueError(f"approach_direction must be a non-zero (3,) vector, got {approach_direction!r}")
    return _solve(arm, np.asarray(position, dtype=float), None, -direction / norm, q_seed, tool_tip, settings)
