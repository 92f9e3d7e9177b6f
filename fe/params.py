"""Parameters of the skin model and of its numerics, with physical-bounds checks.

Defaults are the paper's calibrated optimum (Narang et al., Table I): t_s = 1.57e-3 m,
mu_NH = 2.80e5 Pa, mu_fr = 0.186, T_fl = 29.19 C with beta_T = 0.01 /C.
"""

from dataclasses import dataclass, fields

PAPER_CALIBRATION_BOUNDS: dict[str, tuple[float, float]] = {
    "thickness": (1e-3, 2e-3),
    "mu_nh": (1e5, 1e6),
    "friction": (0.1, 1.0),
    "fluid_temperature": (25.0, 35.0),
}
"""The paper's SLSQP bounds (m, Pa, -, C)."""

_PHYSICAL_BOUNDS: dict[str, tuple[float, float]] = {
    "thickness": (1e-5, 1e-2),
    "mu_nh": (1e2, 1e9),
    "friction": (0.0, 5.0),
    "fluid_temperature": (-20.0, 150.0),
    "thermal_expansion": (0.0, 1.0),
    "reference_temperature": (-20.0, 150.0),
}


@dataclass(frozen=True)
class SkinParameters:
    """Material and loading parameters of the BioTac skin model (SI units, temperatures in C)."""

    thickness: float = 1.57e-3
    """Skin shell thickness t_s (m)."""
    mu_nh: float = 2.80e5
    """Neo-Hookean shear modulus mu_NH (Pa)."""
    friction: float = 0.186
    """Coulomb friction coefficient mu_fr between indenter and skin."""
    fluid_temperature: float = 29.19
    """Fluid temperature T_fl (C) of the thermal inflation parametrisation."""
    thermal_expansion: float = 0.01
    """Volumetric thermal expansion coefficient beta_T of the fluid (1/C)."""
    reference_temperature: float = 20.0
    """Temperature (C) at which the fluid fills the unpressurised cavity."""
    bending: bool = True
    """Include discrete-shell bending (plate stiffness mu t^3 / 3)."""

    def __post_init__(self) -> None:
        for f in fields(self):
            if f.name not in _PHYSICAL_BOUNDS:
                continue
            low, high = _PHYSICAL_BOUNDS[f.name]
            value = getattr(self, f.name)
            if not (low <= value <= high):
                raise ValueError(f"{f.name}={value!r} is outside its physical range [{low:g}, {high:g}]")

    @property
    def membrane_modulus(self) -> float:
        """mu t (N/m): the membrane stiffness coefficient."""
        return self.mu_nh * self.thickness

    @property
    def bending_stiffness(self) -> float:
        """Plate bending stiffness D = E t^3 / (12 (1 - nu^2)) = mu t^3 / 3 for nu = 1/2 (J)."""
        return self.mu_nh * self.thickness**3 / 3.0 if self.bending else 0.0


@dataclass(frozen=True)
class ContactSettings:
    """Numerics of contact: penalty stiffness (Pa/m), friction slip smoothing length (m), lagging passes."""

    penalty_stiffness: float = 1e11
    slip_length: float = 1e-6
    friction_passes: int = 4
    friction_tolerance: float = 1e-3

    def __post_init__(self) -> None:
        if self.penalty_stiffness <= 0 or self.slip_length <= 0 or self.friction_passes < 1:
            raise ValueError("contact settings must be positive (penalty, slip length, passes >= 1)")
