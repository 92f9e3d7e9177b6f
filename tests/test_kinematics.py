"""YuMi kinematics against an independent hand-built chain of the facts table, and IK behaviour."""

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from assets.tools import tool_tip_transform
from twin.kinematics import (
    IKSettings,
    forward,
    inverse,
    inverse_axis,
    jacobian,
    joint_limits,
    rotation_angle,
    velocity_limits,
)

# The facts table (facts/testbed.md), typed again here: xyz (m), rpy (rad), limits (rad), max speed (rad/s).
JOINT_1 = {
    "right": ((0.05355, -0.0725, 0.41492), (-0.9795, -0.5682, -2.3155)),
    "left": ((0.05355, 0.07250, 0.41492), (0.9781, -0.5716, 2.3180)),
}
LATER_JOINTS = [  # joint_2, joint_7, joint_3, joint_4, joint_5, joint_6
    ((0.03, 0, 0.1), (1.5708, 0, 0)),
    ((-0.03, 0.17283, 0), (-1.5708, 0, 0)),
    ((-0.04188, 0, 0.07873), (1.5708, -1.5708, 0)),
    ((0.0405, 0.16461, 0), (-1.5708, 0, 0)),
    ((-0.027, 0, 0.10039), (1.5708, 0, 0)),
    ((0.027, 0.029, 0), (-1.5708, 0, 0)),
]
LIMITS = [(-2.94088, 2.94088), (-2.50455, 0.75922), (-2.94088, 2.94088), (-2.15548, 1.39626)]
LIMITS += [(-5.06145, 5.06145), (-1.53589, 2.40855), (-3.99680, 3.99680)]
SPEEDS = [3.1416] * 4 + [6.9813] * 3
FLANGE = ((0, 0, 0.007), (0, 0, np.pi))


def _homogeneous(xyz, rotation: Rotation) -> np.ndarray:
    t = np.eye(4)
    t[:3, :3] = rotation.as_matrix()
    t[:3, 3] = xyz
    return t


def reference_forward(arm: str, q: np.ndarray) -> np.ndarray:
    """Flange pose by scipy rotations (extrinsic x-y-z = URDF rpy) and plain 4x4 products."""
    chain = [JOINT_1[arm], *LATER_JOINTS]
    pose = np.eye(4)
    for (xyz, rpy), angle in zip(chain, q, strict=True):
        pose = pose @ _homogeneous(xyz, Rotation.from_euler("xyz", rpy))
        pose = pose @ _homogeneous((0, 0, 0), Rotation.from_rotvec([0.0, 0.0, angle]))
    return pose @ _homogeneous(FLANGE[0], Rotation.from_euler("xyz", FLANGE[1]))


def random_q(arm: str, rng: np.random.Generator, margin: float = 0.0) -> np.ndarray:
    lim = joint_limits(arm)
    return rng.uniform(lim[:, 0] + margin, lim[:, 1] - margin)


@pytest.mark.parametrize("arm", ["left", "right"])
def test_limits_match_facts(arm):
    assert np.allclose(joint_limits(arm), LIMITS)
    assert np.allclose(velocity_limits(arm), SPEEDS)


@pytest.mark.parametrize("arm", ["left", "right"])
def test_forward_matches_independent_chain(arm):
    rng = np.random.default_rng(1)
    for _ in range(50):
        q = random_q(arm, rng)
        assert np.allclose(forward(arm, q), reference_forward(arm, q), atol=1e-12)
    tool = tool_tip_transform("sphere_medium")
    q = random_q(arm, rng)
    assert np.allclose(forward(arm, q, tool), reference_forward(arm, q) @ tool, atol=1e-12)


def test_arms_mirror_each_other():
    """The URDF arms are near mirror images in y (their joint_1 rpy differ by ~3 mrad)."""
    q_right = np.array([0.3, -1.0, -0.5, 0.4, 0.2, 0.6, 0.1])
    q_left = q_right * np.array([-1, 1, -1, 1, -1, 1, -1])
    p_right, p_left = forward("right", q_right)[:3, 3], forward("left", q_left)[:3, 3]
    assert np.allclose(p_right * [1, -1, 1], p_left, atol=3e-3)


def test_jacobian_matches_finite_differences():
    rng = np.random.default_rng(2)
    tool = tool_tip_transform("cube")
    q = random_q("right", rng)
    pose, jac = jacobian("right", q, tool)
    h = 1e-7
    for i in range(7):
        dq = np.zeros(7)
        dq[i] = h
        plus = forward("right", q + dq, tool)
        assert np.allclose((plus[:3, 3] - pose[:3, 3]) / h, jac[:3, i], atol=1e-5)
        w = Rotation.from_matrix(plus[:3, :3] @ pose[:3, :3].T).as_rotvec() / h
        assert np.allclose(w, jac[3:, i], atol=1e-5)


@pytest.mark.parametrize("arm", ["left", "right"])
def test_inverse_reaches_random_reachable_poses(arm):
    rng = np.random.default_rng(3)
    tool = tool_tip_transform("sphere_medium")
    lim = joint_limits(arm)
    n, reached = 30, 0
    for _ in range(n):
        target = forward(arm, random_q(arm, rng), tool)
        result = inverse(arm, target, random_q(arm, rng), tool)
        if not result.success:
            continue
        reached += 1
        pose = reference_forward(arm, result.q) @ tool  # checked by the independent chain
        assert np.linalg.norm(pose[:3, 3] - target[:3, 3]) <= 1e-5
        assert rotation_angle(pose[:3, :3], target[:3, :3]) <= 1e-4
        assert np.all(result.q >= lim[:, 0]) and np.all(result.q <= lim[:, 1])
    assert reached >= 0.95 * n


def test_inverse_fails_clearly_when_unreachable():
    target = np.eye(4)
    target[:3, 3] = [1.5, 0.0, 0.3]  # far beyond the ~0.6 m reach
    result = inverse("left", target, np.zeros(7), settings=IKSettings(restarts=3))
    assert not result.success
    assert result.position_error > 0.5
    assert "not reached" in result.message
    lim = joint_limits("left")
    assert np.all(result.q >= lim[:, 0]) and np.all(result.q <= lim[:, 1])


def test_inverse_respects_tighter_tolerances():
    rng = np.random.default_rng(4)
    target = forward("right", random_q("right", rng, 0.3))
    result = inverse("right", target, random_q("right", rng), settings=IKSettings(position_tolerance=1e-10))
    assert result.success and result.position_error <= 1e-10


@pytest.mark.parametrize("arm", ["left", "right"])
def test_inverse_axis_aligns_pressing_direction(arm):
    rng = np.random.default_rng(5)
    tool = tool_tip_transform("cylinder_long")
    for _ in range(10):
        goal = forward(arm, random_q(arm, rng, 0.2), tool)
        direction = -goal[:3, 2]  # tools press along their tip frame's -z
        result = inverse_axis(arm, goal[:3, 3], direction, random_q(arm, rng), tool)
        assert result.success, result.message
        pose = forward(arm, result.q, tool)
        assert np.linalg.norm(pose[:3, 3] - goal[:3, 3]) <= 1e-5
        assert np.arccos(np.clip(-pose[:3, 2] @ direction, -1, 1)) <= 1e-4


def test_inverse_axis_keeps_roll_near_seed():
    """Solved from a configuration already at the goal, the free roll stays where the seed has it."""
    tool = tool_tip_transform("cube")
    q0 = np.array([0.2, -1.2, -0.4, 0.3, 0.5, 0.8, 0.3])
    goal = forward("right", q0, tool)
    shifted = goal[:3, 3] + np.array([0.0, 0.0, -1e-3])
    result = inverse_axis("right", shifted, -goal[:3, 2], q0, tool)
    assert result.success
    assert rotation_angle(forward("right", result.q, tool)[:3, :3], goal[:3, :3]) < 0.02
