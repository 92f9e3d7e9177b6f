"""The campaign controller on a backend that faults before the tare: a press without rows, not a lost campaign."""

import numpy as np
import pytest

from twin.backend import BackendError, Sample
from twin.controller import execute
from twin.processing import process
from twin.protocol import ProtocolSettings, TrajectorySpec


class RefusingBackend:
    """Faults on its first `advance` (the simulated skin refusing the standoff pose); `readable` False: every read
    faults as well."""

    def __init__(self, readable: bool) -> None:
        self.readable, self.time_s, self.joints = readable, 0.0, np.zeros(7)

    def attach_tool(self, arm: str, tool: str | None) -> None:
        pass

    def command_joints(self, arm: str, joints: np.ndarray) -> None:
        self.joints = np.asarray(joints, dtype=float)

    def advance(self, dt: float) -> None:
        raise BackendError("the skin refused the pose")

    def read(self) -> Sample:
        if not self.readable:
            raise BackendError("no reading")
        return Sample(self.time_s, {"left": self.joints}, np.arange(6.0), np.full(19, 3000.0), 2000.0)

    def close(self) -> None:
        pass


def _spec() -> TrajectorySpec:
    depths = np.array([-1e-3, 0.0, 1e-4])
    return TrajectorySpec(
        0,
        "sphere_small",
        np.zeros(3),
        0.0,
        0.0,
        np.zeros(3),
        np.array([0.0, 0.0, 1.0]),
        np.eye(3),
        depths,
        np.array([-1, 0, 1]),
    )


def test_a_fault_before_the_tare_keeps_one_sample_and_gives_no_rows() -> None:
    recording = execute(RefusingBackend(readable=True), _spec(), "left", np.zeros((3, 7)), ProtocolSettings())
    assert not recording.complete and "the skin refused the pose" in recording.message
    assert len(recording.time) == 1 and recording.increment.tolist() == [-1]
    assert recording.wrench.shape == (1, 6) and recording.electrodes.shape == (1, 19)
    rows = process(recording, "left", np.eye(4), np.eye(4), np.eye(4), 100.0)
    assert len(rows.depth) == 0 and rows.electrode_vals.shape == (0, 19) and rows.contact_loc.shape == (0, 3)


def test_an_unreadable_backend_leaves_the_recording_empty() -> None:
    recording = execute(RefusingBackend(readable=False), _spec(), "left", np.zeros((3, 7)), ProtocolSettings())
    assert not recording.complete and len(recording.time) == 0
    with pytest.raises(ValueError, match="empty recording"):
        process(recording, "left", np.eye(4), np.eye(4), np.eye(4), 100.0)
