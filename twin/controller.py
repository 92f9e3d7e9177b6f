"""The campaign controller: executes one planned trajectory on any `Backend` and records it.

The controller moves the tool along the planned joint path, one increment at a time: a move at the
protocol speed, then a settle pause, sampling every channel at the protocol rate throughout. It
stops and retracts when the tared force exceeds the protocol's limit, and marks a trajectory cut by
a backend fault as incomplete instead of losing it.
"""

from __future__ import annotations

from contextlib import suppress
from dataclasses import dataclass

import numpy as np

from twin.backend import Backend, BackendError, Sample
from twin.protocol import ProtocolSettings, TrajectorySpec


@dataclass(frozen=True)
class Recording:
    """Full-rate recording of one trajectory (T samples; SI units; joints of the active arm only)."""

    time: np.ndarray  # (T,) s
    joints: np.ndarray  # (T, 7) rad, chain order
    wrench: np.ndarray  # (T, 6) N, N·m, sensor frame, untared
    electrodes: np.ndarray  # (T, 19) counts
    pdc: np.ndarray  # (T,) counts
    depth_command: np.ndarray  # (T,) m, commanded depth past first contact
    increment: np.ndarray  # (T,) int, path index - 1 (-1 at the standoff)
    complete: bool
    message: str


class _Recorder:
    def __init__(self, arm: str) -> None:
        self.arm = arm
        self.rows: list[tuple[Sample, float, int]] = []

    def add(self, sample: Sample, depth: float, increment: int) -> None:
        self.rows.append((sample, depth, increment))

    def finish(self, complete: bool, message: str) -> Recording:
        samples = [r[0] for r in self.rows]
        return Recording(
            time=np.array([s.time_s for s in samples]),
            joints=np.array([s.joints[self.arm] for s in samples]).reshape(-1, 7),
            wrench=np.array([s.wrench for s in samples]).reshape(-1, 6),
            electrodes=np.array([s.electrodes for s in samples]).reshape(-1, 19),
            pdc=np.array([s.pdc for s in samples]),
            depth_command=np.array([r[1] for r in self.rows]),
            increment=np.array([r[2] for r in self.rows], dtype=np.int64),
            complete=complete,
            message=message,
        )


def move_to(backend: Backend, arm: str, joints: np.ndarray, tick: float, timeout: float = 60.0) -> None:
    """Command `joints` and let time pass until the arm's measured joints settle there (unrecorded)."""
    backend.command_joints(arm, joints)
    elapsed = 0.0
    while elapsed < timeout:
        backend.advance(tick)
        elapsed += tick
        if np.max(np.abs(backend.read().joints[arm] - joints)) < 1e-3:
            backend.advance(tick)
            return
    raise BackendError(f"{arm} arm did not reach its target within {timeout:.0f} s")


def execute(
    backend: Backend, spec: TrajectorySpec, arm: str, joint_path: np.ndarray, settings: ProtocolSettings
) -> Recording:
    """Run `spec` on `backend` with `arm` following `joint_path` (K, 7); never raises on a backend fault. A fault
    before the tare (e.g. the simulated skin refusing the standoff pose, when the plant's registration and skin
    put it in contact already) still records one sample, read where the fault left the testbed, as the tare of
    a press without rows; only a backend that cannot even be read then leaves the recording empty."""
    if joint_path.shape != (len(spec.depths), 7):
        raise ValueError(f"joint path must be ({len(spec.depths)}, 7), got {joint_path.shape}")
    tick = 1.0 / settings.sample_rate_hz
    recorder = _Recorder(arm)
    try:
        backend.attach_tool(arm, spec.indenter)
        move_to(backend, arm, joint_path[0], tick)
        tare = backend.read()
        recorder.add(tare, float(spec.depths[0]), -1)
        for k in range(1, len(spec.depths)):
            depth, increment = float(spec.depths[k]), int(spec.increment[k])
            backend.command_joints(arm, joint_path[k])
            n_move = max(1, int(np.ceil(abs(depth - spec.depths[k - 1]) / settings.speed / tick)))
            n_pause = int(round(settings.pause_s / tick))
            for _ in range(n_move + n_pause):
                backend.advance(tick)
                sample = backend.read()
                recorder.add(sample, depth, increment)
                force = np.linalg.norm(sample.wrench[:3] - tare.wrench[:3])
                if force > settings.force_limit:
                    _retract(backend, arm, joint_path[0], tick)
                    return recorder.finish(False, f"force limit {settings.force_limit:g} N exceeded ({force:.2f} N)")
    except BackendError as exc:
        if not recorder.rows:  # a fault before the tare: keep the one sample where it stopped (a press without rows)
            with suppress(BackendError):
                recorder.add(backend.read(), float(spec.depths[0]), -1)
        _retract(backend, arm, joint_path[0], tick)
        return recorder.finish(False, f"backend fault: {exc}")
    return recorder.finish(True, "ok")


def _retract(backend: Backend, arm: str, standoff: np.ndarray, tick: float) -> None:
    """Best-effort retreat to the standoff pose after a stop; a second fault is swallowed and reported."""
    try:
        move_to(backend, arm, standoff, tick)
    except BackendError:
        return
