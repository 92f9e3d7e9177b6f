"""Trapped air in the fluid cavity: an isothermal ideal-gas bubble that makes the fluid compressible.

The bubble obeys Boyle's law at the fluid's absolute pressure, (p_atm + p) V_air = k, so the cavity
holds V(x) = V_liquid + V_air(p) with an incompressible liquid. Newton keeps its volume constraint
with the liquid volume as target and V(x) - V_air(p) as the constrained volume, whose pressure
derivative (the bubble's compliance k / (p_atm + p)^2, m^3/Pa) enters the Schur complement. The
energy reported to Newton carries the gas's Legendre term k ln(p_atm + p) - p V_air(p), so that the merit
E - p (V - V_air - V_liquid) is the Lagrangian E - p (V - V_liquid) + k ln(p_atm + p), stationary in p
exactly at Boyle's law. Pressures are gauge pressures in Pa, volumes m^3.
"""

from dataclasses import dataclass, replace

import numpy as np

from fe.linsolve import SymmetricSolver
from fe.newton import EquilibriumProblem, Linearization

ATMOSPHERIC_PRESSURE = 101325.0
"""Absolute ambient pressure p_atm (Pa) to which the fluid's gauge pressure is added."""


@dataclass(frozen=True)
class TrappedAir:
    """An isothermal gas bubble: Boyle constant k = (p_atm + p) V_air (J)."""

    boyle_constant: float
    atmospheric_pressure: float = ATMOSPHERIC_PRESSURE

    @classmethod
    def at_reference(cls, volume_fraction: float, fluid_volume: float, pressure: float) -> "TrappedAir":
        """The bubble that fills `volume_fraction` of `fluid_volume` (m^3) at gauge `pressure` (Pa)."""
        if not 0.0 < volume_fraction < 1.0 or fluid_volume <= 0.0:
            raise ValueError("trapped air needs a volume fraction in (0, 1) of a positive fluid volume")
        if pressure <= -ATMOSPHERIC_PRESSURE:
            raise ValueError(f"gauge pressure {pressure} Pa is below vacuum")
        return cls(volume_fraction * fluid_volume * (ATMOSPHERIC_PRESSURE + pressure))

    def volume(self, pressure: float) -> float:
        """Bubble volume (m^3) at gauge `pressure` (Pa)."""
        return self.boyle_constant / self._absolute(pressure)

    def compliance(self, pressure: float) -> float:
        """-dV_air/dp (m^3/Pa) at gauge `pressure` (Pa)."""
        return self.boyle_constant / self._absolute(pressure) ** 2

    def pressure(self, volume: float) -> float:
        """Gauge pressure (Pa) at bubble `volume` (m^3)."""
        return self.boyle_constant / volume - self.atmospheric_pressure

    def legendre_energy(self, pressure: float) -> float:
        """k ln(p_atm + p) - p V_air(p) (J): the gas's part of Newton's merit, see the module docstring."""
        return self.boyle_constant * np.log(self._absolute(pressure)) - pressure * self.volume(pressure)

    def _absolute(self, pressure: float) -> float:
        absolute = self.atmospheric_pressure + pressure
        # Below vacuum the gas law has no solution; inf keeps Newton's line search away from it.
        return absolute if absolute > 0.0 else np.inf


class TrappedAirProblem:
    """Newton's view (`fe.newton.EquilibriumProblem`) of a model whose cavity also holds `air`: solve it with
    the liquid volume (m^3) as the target volume."""

    def __init__(self, problem: EquilibriumProblem, air: TrappedAir) -> None:
        self.problem, self.air = problem, air

    @property
    def linear_solver(self) -> SymmetricSolver:
        return self.problem.linear_solver

    def linearize(self, q: np.ndarray, pressure: float, want_matrix: bool, projected: bool = False) -> Linearization:
        """The wrapped linearisation with the bubble's volume taken off the enclosed volume."""
        lin = self.problem.linearize(q, pressure, want_matrix, projected)
        return replace(
            lin,
            energy=lin.energy + self.air.legendre_energy(pressure),
            volume=lin.volume - self.air.volume(pressure),
            volume_compliance=self.air.compliance(pressure),
        )
