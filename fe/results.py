"""What the FE engine reports: one increment's outputs, and the straight indentation paths it is driven along.

Forces are in newtons in the sensor frame and are the force the indenter applies to the skin; lengths m.
"""

from dataclasses import dataclass

import numpy as np


@dataclass(frozen=True)
class IncrementResult:
    """Outputs of one increment (SI units, sensor frame)."""

    depth: float
    """Signed tip travel (m) along the indenter's local -z axis (its pressing direction) from the stepper's
    origin: the first-touch point for `indent`, else the first pose stepped after a reset."""
    force: np.ndarray
    """(3,) force of the indenter on the skin (N)."""
    pressure: float
    """Fluid pressure (Pa)."""
    volume: float
    """Enclosed volume (m^3) as the skin triangles measure it."""
    contact_area: float
    """Deformed area of skin vertices in contact with the indenter (m^2)."""
    contact_radius: float
    """Largest distance of a contact vertex from the indenter's axis (its local z through the tip) (m); the dome
    (`fe.dome.run_dome`) reports that of its contact quadrature points instead."""
    displacement: np.ndarray
    """(V,3) nodal displacements from the reference (inflated) state (m)."""
    newton_iterations: int
    residual: float
    """Infinity norm of the free-DOF residual force (N)."""
    equilibrium_error: float
    """|indenter + core + anchor + pressure forces on the skin| / max(|indenter|, |pressure| force)."""
    converged: bool
    message: str
    wall_s: float


@dataclass(frozen=True)
class Trajectory:
    """A straight indentation: first-touch tip position (m), unit direction (the indenter's local -z, i.e.
    rotation[:, 2] = -direction), indenter rotation (3,3) body->sensor, depths past touch (m), and the time
    (s) of each depth (None: untimed, only for a skin without viscoelastic relaxation)."""

    touch_point: np.ndarray
    direction: np.ndarray
    rotation: np.ndarray
    depths: np.ndarray
    times: np.ndarray | None = None

    def __post_init__(self) -> None:
        if np.any(np.asarray(self.depths) < 0):
            raise ValueError("indentation depths must be non-negative")
        if self.times is not None and np.shape(self.times) != np.shape(self.depths):
            raise ValueError("a timed trajectory needs one time per depth")
        if not np.isclose(np.linalg.norm(self.direction), 1.0):
            raise ValueError("direction must be a unit vector")
        if not np.allclose(np.asarray(self.rotation)[:, 2], -np.asarray(self.direction), atol=1e-9):
            raise ValueError("the indenter presses along its local -z: rotation[:, 2] must equal -direction")
