"""The BioTac mount (paper, Methods A-B) as parametric geometry: base plate, KMS40, circular plate, fixture.

Mount frame (metres): origin at the centre of the base plate's underside (on the bench), z up along the
F/T sensor axis, x away from the robot when the mount is placed with zero yaw. Stacked bottom to top:

- base plate (couples the sensor to the bench), a square slab;
- Weiss KMS40 F/T sensor, a cylinder; its measurement frame is the centre of its top face, axes parallel
  to the mount frame (dimensions are *unverified* defaults: 54 mm across, 32.5 mm tall);
- circular plate with four metal hole liners on a circle near its rim, flush with its top face;
- fixture: a block rising from the plate that grips the BioTac's rigid base (the BioTac is an
  interference fit in it), holding the finger horizontally, pad up, tip pointing toward the robot.

BioTac pose in the mount: biotac x = -mount x (tip toward the robot), y = mount y, z = -mount z (the
ventral pad, biotac -z, faces up); the BioTac origin lies on the sensor axis ``biotac_height`` above
the plate's top face. The fixture starts ``fixture_gap_x`` proximal of the BioTac origin (biotac x), past
the skin, so it never touches free skin. Everything here is a design choice documented in
docs/testbed.md, not a measured CAD model.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from assets.yumi import Shape


@dataclass(frozen=True)
class MountGeometry:
    """Mount dimensions (m). Holes: `n` liners on a circle of radius `hole_circle_radius` at `hole_azimuths`
    (rad, from mount +x toward +y); liner bore radius `liner_bore_radius`, outer radius `liner_outer_radius`.
    """

    base_half_size: tuple[float, float] = (0.075, 0.075)
    base_thickness: float = 0.012
    sensor_radius: float = 0.027
    sensor_height: float = 0.0325
    plate_radius: float = 0.065
    plate_thickness: float = 0.008
    hole_circle_radius: float = 0.055
    hole_azimuths: tuple[float, ...] = tuple(np.deg2rad([45.0, 135.0, 225.0, 315.0]))
    liner_bore_radius: float = 3.15e-3
    liner_outer_radius: float = 5.0e-3
    biotac_height: float = 0.040
    fixture_gap_x: float = 0.016
    fixture_length: float = 0.036
    fixture_half_width: float = 0.015
    biotac_base_radius: float = 0.007

    def __post_init__(self) -> None:
        if len(self.hole_azimuths) != 4:
            raise ValueError(f"MountGeometry: the registration needs 4 holes, got {len(self.hole_azimuths)}")
        if self.hole_circle_radius + self.liner_outer_radius > self.plate_radius:
            raise ValueError("MountGeometry: hole liners must lie on the plate")
        if self.biotac_height <= self.biotac_base_radius:
            raise ValueError("MountGeometry: the BioTac must clear the plate (biotac_height > biotac_base_radius)")

    @property
    def sensor_top_z(self) -> float:
        """Height (m) of the F/T sensor's top face (its measurement frame) above the bench."""
        return self.base_thickness + self.sensor_height

    @property
    def plate_top_z(self) -> float:
        """Height (m) of the circular plate's top face (the liner rims) above the bench."""
        return self.sensor_top_z + self.plate_thickness

    def biotac_in_mount(self) -> np.ndarray:
        """(4, 4) mount <- biotac transform (p_mount = T @ p_biotac)."""
        t = np.eye(4)
        t[:3, :3] = np.diag([-1.0, 1.0, -1.0])
        t[2, 3] = self.plate_top_z + self.biotac_height
        return t

    def ft_sensor_in_mount(self) -> np.ndarray:
        """(4, 4) mount <- F/T sensor frame transform: top face centre, axes parallel to the mount's."""
        t = np.eye(4)
        t[2, 3] = self.sensor_top_z
        return t

    def holes_in_mount(self) -> np.ndarray:
        """(4, 3) centres of the liner rims (where a seated pin's shoulder sits), mount frame, m."""
        az = np.asarray(self.hole_azimuths)
        r = self.hole_circle_radius
        return np.column_stack([r * np.cos(az), r * np.sin(az), np.full(len(az), self.plate_top_z)])

    def shapes(self) -> tuple[Shape, ...]:
        """Collision and visual primitives of the mount in the mount frame (the BioTac excluded)."""
        z_sensor, z_plate = self.sensor_top_z, self.plate_top_z
        z_axis = z_plate + self.biotac_height
        x0 = self.fixture_gap_x  # biotac x = -fixture_gap_x lies at mount x = +fixture_gap_x
        x1 = x0 + self.fixture_length
        fixture_top = z_axis + self.biotac_base_radius + 0.005
        liners = tuple(
            Shape(f"liner_{k}", "cylinder", (self.liner_outer_radius,), (x, y, z - 0.0015), (x, y, z + 1e-4), False)
            for k, (x, y, z) in enumerate(self.holes_in_mount())
        )
        return (
            Shape(
                "base_plate",
                "box",
                (*self.base_half_size, 0.5 * self.base_thickness),
                (0, 0, 0.5 * self.base_thickness),
            ),
            Shape("ft_sensor", "cylinder", (self.sensor_radius,), (0, 0, self.base_thickness), (0, 0, z_sensor)),
            Shape("circular_plate", "cylinder", (self.plate_radius,), (0, 0, z_sensor), (0, 0, z_plate)),
            Shape(
                "fixture",
                "box",
                (0.5 * (x1 - x0), self.fixture_half_width, 0.5 * (fixture_top - z_plate)),
                (0.5 * (x0 + x1), 0.0, 0.5 * (fixture_top + z_plate)),
            ),
            *liners,
        )

    def biotac_base_shape(self) -> Shape:
        """The BioTac's rigid base, a cylinder from just proximal of the skin into the fixture, biotac frame."""
        x_start = -(self.fixture_gap_x + self.fixture_length)
        return Shape(
            "biotac_base", "cylinder", (self.biotac_base_radius,), (-self.fixture_gap_x, 0, 0), (x_start, 0, 0)
        )
