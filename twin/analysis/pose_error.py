"""How an arm's registration rotation and joint zero offsets move a trajectory's indenter (the nuisance fit's pose).

A campaign knows where the indenter was only through the arm's joint readings, its kinematic model and the
estimated registration (the `contact_loc` labels are that forward kinematics). The real arm's joints are off their
zeros by a few milliradians and the registration is off by a rigid motion, so the real indenter is elsewhere, by an
amount that depends on the pose: its tip where the commanded depth is zero moves (`offset`), the press turns and
stretches (`slope`: the tip's extra displacement per metre of commanded depth) and the indenter tilts (`tilt`). On a
realistic plant's campaign all three matter at the F/T noise (docs/analysis.md: a 10 mrad tilt or a 10 um offset
moves a cylinder's force by several times 0.01 N).

`pose_error` works them out by exact forward kinematics at each path index's joint reading, so the cross terms of a
large registration rotation and the joint offsets' displacement (11 mrad of a millimetre: 11 um) are kept; its
sensitivities (`pose_jacobian`) are central differences of it (no replay). The registration's translation is the
`registration_offset` effect's and adds to `offset`.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from twin.analysis.data import TrajectoryRecord
from twin.kinematics import forward, rotation_exp, rotation_log

POSE_ERROR_SIZE = 9
"""offset (3), slope (3), tilt (3): the pose error as one vector (`PoseError.vector`)."""
DIFFERENCE_STEP = 1e-6
"""rad: the central-difference step of `pose_jacobian` (the map is smooth; its error is ~step^2)."""


@dataclass(frozen=True)
class ArmPath:
    """What the pose error of one trajectory needs: the joint reading (rad) and commanded depth (m) of each path
    index's first sample, the arm, tool tip (4x4, flange -> tip), the estimated robot -> biotac transform (4x4) and
    the tool's poses there as the campaign knows them (`nominal`: tips (n, 3) m, rotations (n, 3, 3))."""

    arm: str
    joints: np.ndarray  # (n, 7) rad
    depths: np.ndarray  # (n,) m
    tool_tip: np.ndarray  # (4, 4)
    to_biotac: np.ndarray  # (4, 4) robot -> biotac, estimated
    nominal: tuple[np.ndarray, np.ndarray]

    def tips(self, offsets: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """(tips (n, 3) m, rotations (n, 3, 3)) of the tool in the estimated biotac frame at the readings plus joint
        zero offsets `offsets` (7,) rad."""
        return _tool_poses(self.arm, self.joints + offsets, self.tool_tip, self.to_biotac)


@dataclass(frozen=True)
class PoseError:
    """A trajectory's indenter pose error (biotac frame): the tip where the commanded depth is zero moved by
    `offset` (m), displaced by `slope` per metre of commanded depth, the indenter turned by `tilt` (rotation vector,
    rad) about its tip."""

    offset: np.ndarray
    slope: np.ndarray
    tilt: np.ndarray

    @property
    def vector(self) -> np.ndarray:
        """(9,): offset, slope, tilt."""
        return np.concatenate([self.offset, self.slope, self.tilt])


def _tool_poses(
    arm: str, joints: np.ndarray, tool_tip: np.ndarray, to_biotac: np.ndarray
) -> tuple[np.ndarray, np.ndarray]:
    """(tips (n, 3) m, rotations (n, 3, 3)) of the tool at joints (n, 7) rad, in the frame `to_biotac` maps to."""
    poses = np.array([to_biotac @ forward(arm, q, tool_tip) for q in joints])
    return poses[:, :3, 3], poses[:, :3, :3]


def arm_path(trajectory: TrajectoryRecord) -> ArmPath:
    """The `ArmPath` of a trajectory with joint readings."""
    raw = trajectory.raw
    first = np.unique(raw.increment, return_index=True)[1]
    joints, to_biotac = raw.joints[first], np.linalg.inv(trajectory.registration)
    nominal = _tool_poses(trajectory.arm, joints, trajectory.tool_tip, to_biotac)
    return ArmPath(trajectory.arm, joints, raw.depth_command[first], trajectory.tool_tip, to_biotac, nominal)


def pose_error(path: ArmPath, rotation: np.ndarray, joints: np.ndarray) -> PoseError:
    """The pose error of a registration rotation (rotation vector (3,) rad, biotac frame, about its origin) and the
    arm's joint zero offsets (7,) rad: the tips at every path index moved to where they really are, their change
    regressed on the commanded depth (offset where the depth is zero, slope), the tilt averaged over the path."""
    turn = rotation_exp(rotation)
    nominal, nominal_rotations = path.nominal
    real, real_rotations = path.tips(np.asarray(joints, dtype=float))
    moved = real @ turn.T - nominal
    if np.ptp(path.depths) > 1e-6:
        design = np.column_stack([np.ones_like(path.depths), path.depths])
        offset, slope = np.linalg.lstsq(design, moved, rcond=None)[0]
    else:  # one depth: no slope to tell
        offset, slope = moved.mean(axis=0), np.zeros(3)
    tilts = [rotation_log(turn @ r @ n.T) for r, n in zip(real_rotations, nominal_rotations, strict=True)]
    return PoseError(offset, slope, np.mean(tilts, axis=0))


def pose_jacobian(path: ArmPath, rotation: np.ndarray, joints: np.ndarray) -> np.ndarray:
    """(9, 10): d `PoseError.vector` / d (rotation (3), joints (7)) at those values (central differences)."""
    point = np.concatenate([rotation, joints]).astype(float)
    columns = []
    for i in range(len(point)):
        step = np.zeros_like(point)
        step[i] = DIFFERENCE_STEP
        plus, minus = point + step, point - step
        difference = pose_error(path, plus[:3], plus[3:]).vector - pose_error(path, minus[:3], minus[3:]).vector
        columns.append(difference / (2.0 * DIFFERENCE_STEP))
    return np.column_stack(columns)
