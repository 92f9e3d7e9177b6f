"""Trapped air in the fluid cavity: an isothermal ideal-gas bubble that makes the fluid compressible.

The bubble obeys Boyle's law at the fluid's absolute pressure, (p_atm + p) V_air = k, so the cavity
holds V(x) = V_liquid + V_air(p) with an incompressible liquid. Newton keeps its volume constraint
with the liquid volume as target and V(x) - V_air(p) as the constrained volume, whose pressure
derivative (the bubble's compliance k / (p_atm + p)^2, m^3/Pa) enters the Schur complement. The
energy reported to Newton carries the gas's Legendre term k ln(p_atm + p) - p V_air(p), so that the merit
E - p (V - V_air - V_liquid) is the Lagrangian E - p (V - V_liquid) + k ln(p_atm + p), stationary in p
exactly at Boyle's law. Pressures are gauge pressures in Pa, volumes m^3. `TrappedAir` holds one bubble per
system of a batch (Boyle constant 0: no air) and answers with (B,) arrays.
"""

from dataclasses import dataclass

import numpy as np

ATMOSPHERIC_PRESSURE = 101325.0
"""Absolute ambient pressure p_atm (Pa) to which the fluid's gauge pressure is added."""


@dataclass(frozen=True)
class TrappedAir:
    """Isothermal gas bubbles, one per system: Boyle constants k = (p_atm + p) V_air (J), shape (B,); a
    system with k = 0 holds no air (all its answers are 0)."""

    boyle_constant: np.ndarray
    atmospheric_pressure: float = ATMOSPHERIC_PRESSURE

    @staticmethod
    def boyle(volume_fraction: float, fluid_volume: float, pressure: float) -> float:
        """Boyle constant (J) of the bubble filling `volume_fraction` of `fluid_volume` (m^3) at gauge
        `pressure` (Pa); 0 for a fraction of 0 (no air)."""
        if volume_fraction == 0.0:
            return 0.0
        if not 0.0 < volume_fraction < 1.0 or fluid_volume <= 0.0:
            raise ValueError("trapped air needs a volume fraction in (0, 1) of a positive fluid volume")
        if pressure <= -ATMOSPHERIC_PRESSURE:
            raise ValueError(f"gauge pressure {pressure} Pa is below vacuum")
        return volume_fraction * fluid_volume * (ATMOSPHERIC_PRESSURE + pressure)

    def volume(self, pressure: np.ndarray) -> np.ndarray:
        """Bubble volumes (m^3) at gauge pressures (Pa)."""
        return self.boyle_constant / self._absolute(pressure)

    def compliance(self, pressure: np.ndarray) -> np.ndarray:
        """-dV_air/dp (m^3/Pa) at gauge pressures (Pa)."""
        return self.boyle_constant / self._absolute(pressure) ** 2

    def legendre_energy(self, pressure: np.ndarray) -> np.ndarray:
        """k ln(p_atm + p) - p V_air(p) (J): the gas's part of Newton's merit, see the module docstring."""
        absolute = self._absolute(pressure)
        with np.errstate(divide="ignore", invalid="ignore"):
            log = np.where(self.boyle_constant > 0.0, self.boyle_constant * np.log(absolute), 0.0)
        return log - np.asarray(pressure) * self.volume(pressure)

    def _absolute(self, pressure: np.ndarray) -> np.ndarray:
        absolute = self.atmospheric_pressure + np.asarray(pressure, dtype=np.float64)
        # Below vacuum the gas law has no solution; inf keeps Newton's line search away from it.
        return np.where(absolute > 0.0, absolute, np.inf)
