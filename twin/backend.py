"""The Backend contract: what the campaign controller talks to, in simulation or on the real testbed.

The controller never knows which backend it has. `twin.sim_backend.SimBackend` (MuJoCo + fe + electrode
model, measurements from a plant) and `hardware.backend.HardwareBackend` (YuMi EGM/RWS, KMS40, BioTac
over SPI) both implement `Backend`.

Conventions (all SI):
- Arms are named "left" and "right".
- Joint vectors are (7,) in radians in the kinematic chain order of the YuMi URDF, i.e. ABB axes
  1, 2, 7, 3, 4, 5, 6 (EGM carries axis 7 in `externalJoints[0]`; drivers convert).
- The wrench is (fx, fy, fz, mx, my, mz) in N and N·m in the F/T sensor's own frame, untared.
- Electrodes are (19,) raw 12-bit counts E1..E19; `pdc` is the raw 12-bit fluid-pressure count.
- Time is seconds on the backend's clock (simulated time for SimBackend, monotonic wall time on hardware).
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Protocol, runtime_checkable

import numpy as np

ARMS = ("left", "right")
N_JOINTS = 7
N_ELECTRODES = 19


@dataclass(frozen=True)
class Sample:
    """One reading of every channel, taken at `time_s` (s)."""

    time_s: float
    joints: dict[str, np.ndarray]  # arm -> (7,) measured joint angles (rad, chain order 1-2-7-3-4-5-6)
    wrench: np.ndarray  # (6,) F/T reading (N, N·m), sensor frame, untared
    electrodes: np.ndarray  # (19,) raw counts
    pdc: float  # raw fluid-pressure counts


class BackendError(RuntimeError):
    """A backend could not do what was asked (device fault, stale data, limit violated)."""


@runtime_checkable
class Backend(Protocol):
    """Move an arm, let time pass, read every channel. Implementations own their devices' lifetimes."""

    def attach_tool(self, arm: str, tool: str | None) -> None:
        """Declare what is mounted on `arm`'s flange: an indenter name, "pin", or None."""

    def command_joints(self, arm: str, joints: np.ndarray) -> None:
        """Set `arm`'s joint position target (rad, chain order); raises BackendError outside joint limits."""

    def advance(self, dt: float) -> None:
        """Let `dt` seconds pass (simulate them, or wait for them in real time while streaming)."""

    def read(self) -> Sample:
        """The most recent reading of every channel."""

    def close(self) -> None:
        """Stop streaming and release devices; safe to call twice."""


def check_arm(arm: str) -> str:
    """Return `arm` if it names one of ARMS, else raise ValueError."""
    if arm not in ARMS:
        raise ValueError(f"unknown arm {arm!r}; expected one of {ARMS}")
    return arm
