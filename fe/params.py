"""Parameters of the skin model and of its numerics (contact, Newton), with physical-bounds checks.

Defaults are the paper's calibrated optimum (Narang et al., Table I): t_s = 1.57e-3 m,
mu_NH = 2.80e5 Pa, mu_fr = 0.186, T_fl = 29.19 C with beta_T = 0.01 /C.
"""

from dataclasses import dataclass, field, fields
from typing import Any

_SKIN_CHANNELS = ("force", "pdc", "electrodes")


@dataclass(frozen=True)
class Knob:
    """How a candidate effect (twin.effects) moves one skin field: the effect's parameter and its search range.

    `acts="set"`: the effect's value is the field (off value: the field's default, units: the field's);
    `acts="scale"`: a factor on the nominal field (off value 1, units "1"). An effect over several fields names
    the same effect, description and channels on each; its parameters follow field order.
    """

    effect: str
    parameter: str
    acts: str
    search: tuple[float, float]
    """Bounds (of the value or of the factor) that diagnosis and the nuisance fit search within."""
    scale: float
    """Typical magnitude: finite-difference step and optimiser scaling."""
    description: str
    hidden: tuple[float, float]
    """Range of a hidden size (twin.hidden): drawn U(low, high), or off +- U(low, high) with `hidden_both_ways`."""
    channels: tuple[str, ...] = _SKIN_CHANNELS
    """Readings the effect shows in: all of the skin's unless it reaches fewer."""
    hidden_both_ways: bool = False
    probe: float | None = None
    """Value to linearise at while the effect is off, for a parameter that does nothing at its off value."""

    def __post_init__(self) -> None:
        if self.acts not in ("set", "scale"):
            raise ValueError(f"{self.effect}.{self.parameter}: acts={self.acts!r} is neither 'set' nor 'scale'")


@dataclass(frozen=True)
class Parameter:
    """What is declared of one skin parameter besides its nominal value (the `SkinParameters` field's default,
    which is also its off value for a physics term that is off by default)."""

    units: str
    physical: tuple[float, float] | None
    """The range `SkinParameters` accepts (None: any value of the field's type)."""
    paper: tuple[float, float] | None = None
    """The paper's SLSQP calibration bounds, for the parameters its calibration fits (twin.analysis.calibrate)."""
    effect: Knob | None = None
    """The candidate effect that moves this field, if any."""


def _parameter(
    default: Any,
    units: str,
    physical: tuple[float, float] | None,
    paper: tuple[float, float] | None = None,
    effect: Knob | None = None,
) -> Any:
    """A `SkinParameters` field with its `Parameter` declared beside it (in the field's metadata)."""
    return field(default=default, metadata={"parameter": Parameter(units, physical, paper, effect)})


_RELAXATION = "The skin is viscoelastic: one Prony branch relaxes a fraction of its moduli with a time constant."


@dataclass(frozen=True)
class SkinParameters:
    """Material and loading parameters of the BioTac skin model (SI units, temperatures in C); each field's
    units and ranges are declared with it (`SKIN_PARAMETERS`)."""

    thickness: float = _parameter(
        1.57e-3,
        "m",
        (1e-5, 1e-2),
        paper=(1e-3, 2e-3),
        effect=Knob(
            effect="skin_thickness",
            parameter="scale",
            acts="scale",
            search=(0.6, 1.5),
            scale=0.05,
            description="Skin shell thickness differs from the model's (scale factor on t_s).",
            hidden=(0.12, 0.25),
            hidden_both_ways=True,
        ),
    )
    """Skin shell thickness t_s (m)."""
    mu_nh: float = _parameter(
        2.80e5,
        "Pa",
        (1e2, 1e9),
        paper=(1e5, 1e6),
        effect=Knob(
            effect="skin_modulus",
            parameter="scale",
            acts="scale",
            search=(0.5, 2.0),
            scale=0.05,
            description="Skin shear modulus differs from the model's (scale factor on mu_NH).",
            hidden=(0.15, 0.3),
            hidden_both_ways=True,
        ),
    )
    """Neo-Hookean shear modulus mu_NH (Pa)."""
    friction: float = _parameter(
        0.186,
        "1",
        (0.0, 5.0),
        paper=(0.1, 1.0),
        effect=Knob(
            effect="indenter_friction",
            parameter="scale",
            acts="scale",
            search=(0.0, 5.0),
            scale=0.25,
            description="Coulomb friction between indenter and skin differs (scale factor on mu_fr).",
            channels=("force",),
            hidden=(2.5, 4.0),
        ),
    )
    """Coulomb friction coefficient mu_fr between indenter and skin."""
    fluid_temperature: float = _parameter(29.19, "C", (-20.0, 150.0), paper=(25.0, 35.0))
    """Fluid temperature T_fl (C) of the thermal inflation parametrisation."""
    thermal_expansion: float = _parameter(0.01, "1/C", (0.0, 1.0))
    """Volumetric thermal expansion coefficient beta_T of the fluid (1/C)."""
    reference_temperature: float = _parameter(20.0, "C", (-20.0, 150.0))
    """Temperature (C) at which the fluid fills the unpressurised cavity."""
    bending: bool = _parameter(True, "bool", None)
    """Include discrete-shell bending (plate stiffness mu t^3 / 3)."""
    inflation_volume_scale: float = _parameter(
        1.0,
        "1",
        (0.5, 2.0),
        effect=Knob(
            effect="fill_volume",
            parameter="scale",
            acts="scale",
            search=(0.7, 1.4),
            scale=0.03,
            description="The sensor holds more or less fluid than the model (skin pretension; scale on the inflation "
            "volume).",
            hidden=(0.08, 0.15),
            hidden_both_ways=True,
        ),
    )
    """Fill (pretension) knob: the inflated sensor holds this multiple of the fluid volume that inflation adds
    to the unpressurised cavity (to the 15.1 mm thickness, or by the thermal rule); 1 = off."""
    relaxation_fraction: float = _parameter(
        0.0,
        "1",
        (0.0, 0.95),
        effect=Knob(
            effect="skin_relaxation",
            parameter="fraction",
            acts="set",
            search=(0.0, 0.6),
            scale=0.05,
            description=_RELAXATION,
            hidden=(0.2, 0.4),
            probe=0.15,
        ),
    )
    """Prony fraction g of one quasi-linear-viscoelastic branch of the skin (membrane and bending): moduli
    relax from mu_nh (instantaneous) to (1 - g) mu_nh (long-term) as exp(-t / relaxation_time_s); 0 = off."""
    relaxation_time_s: float = _parameter(
        1.0,
        "s",
        (1e-3, 1e4),
        effect=Knob(
            effect="skin_relaxation",
            parameter="time_s",
            acts="set",
            search=(0.05, 10.0),
            scale=0.2,
            description=_RELAXATION,
            hidden=(0.3, 1.0),
        ),
    )
    """Relaxation time tau (s) of the Prony branch (used only when relaxation_fraction > 0)."""
    gent_inverse_jm: float = _parameter(
        0.0,
        "1",
        (0.0, 10.0),
        effect=Knob(
            effect="skin_stiffening",
            parameter="inverse_jm",
            acts="set",
            search=(0.0, 2.0),
            scale=0.1,
            description="The skin stiffens with strain beyond Neo-Hookean (Gent, parameter 1/J_m).",
            hidden=(0.3, 0.8),
        ),
    )
    """Gent strain stiffening 1/J_m (-): energy -(mu t / 2) J_m ln(1 - (I1 - 3) / J_m) per reference area,
    I1 = tr C + 1/det C; the membrane locks at I1 = 3 + J_m. 0 = off (Neo-Hookean)."""
    air_volume_fraction: float = _parameter(
        0.0,
        "1",
        (0.0, 0.5),
        effect=Knob(
            effect="trapped_air",
            parameter="fraction",
            acts="set",
            search=(0.0, 0.5),
            scale=0.02,
            description="A gas bubble in the fluid (volume fraction of the cavity) makes the fluid compressible "
            "(Boyle).",
            hidden=(0.2, 0.35),
        ),
    )
    """Trapped air: gas volume as a fraction of the fluid cavity volume at the inflated reference state (at the
    absolute pressure p_atm + p_ref), compressed isothermally (Boyle) during indentation; 0 = off."""

    def __post_init__(self) -> None:
        for name, parameter in SKIN_PARAMETERS.items():
            if parameter.physical is None:
                continue
            low, high = parameter.physical
            value = getattr(self, name)
            if not (low <= value <= high):
                raise ValueError(f"{name}={value!r} is outside its physical range [{low:g}, {high:g}]")

    @property
    def long_term_fraction(self) -> float:
        """(1 - g): the share of the instantaneous moduli left after full relaxation."""
        return 1.0 - self.relaxation_fraction

    @property
    def membrane_modulus(self) -> float:
        """mu t (N/m): the membrane stiffness coefficient."""
        return self.mu_nh * self.thickness

    @property
    def bending_stiffness(self) -> float:
        """Plate bending stiffness D = E t^3 / (12 (1 - nu^2)) = mu t^3 / 3 for nu = 1/2 (J)."""
        return self.mu_nh * self.thickness**3 / 3.0 if self.bending else 0.0


SKIN_PARAMETERS: dict[str, Parameter] = {f.name: f.metadata["parameter"] for f in fields(SkinParameters)}
"""The one table of skin parameters: field name -> units and ranges, in field order."""
PAPER_CALIBRATION_BOUNDS: dict[str, tuple[float, float]] = {
    name: p.paper for name, p in SKIN_PARAMETERS.items() if p.paper is not None
}
"""The paper's SLSQP bounds (m, Pa, -, C) of the parameters its calibration fits, in field order."""


@dataclass(frozen=True)
class ContactSettings:
    """Numerics of contact (`fe.contact`): the penalty stiffness (Pa/m) of a zero-thickness contact, friction
    slip smoothing length (m), lagging passes and tolerance, and the admissible closures
    (`fe.batched_stepper.BatchedStepper` refuses a converged increment beyond them)."""

    penalty_stiffness: float = 1e11
    """Penalty kappa (Pa/m) where the skin keeps no half-thickness from a body (offset 0: a membrane)."""
    slip_length: float = 1e-6
    friction_passes: int = 4
    friction_tolerance: float = 1e-3
    max_penetration: float = 0.1
    """Deepest penetration of a body into a zero-thickness (penalty) contact that a converged increment may
    show, as a fraction of the skin thickness: deeper, the forces are the penalty's, not the skin's."""
    min_stretch: float = 0.25
    """Smallest through-thickness stretch of a squeezed half-layer (`fe.contact.layer_response`) that a
    converged increment may show; below it the law is continued quadratically and the state refused: the
    Neo-Hookean layer then carries mu (lam^-2 - lam) = 15.75 mu (4.4 MPa at the paper's mu), far beyond
    rubber's working range, so the indenter has reached the core or the rigid base through the skin."""

    surface_rule: str = "split-4"
    """Quadrature rule of the indenter contact on each skin triangle (`fe.surface_quadrature.rule`)."""

    def __post_init__(self) -> None:
        if self.penalty_stiffness <= 0 or self.slip_length <= 0 or self.friction_passes < 1:
            raise ValueError("contact settings must be positive (penalty, slip length, passes >= 1)")
        if not self.max_penetration > 0.0:
            raise ValueError(f"max_penetration={self.max_penetration} must be positive")
        if not 0.0 < self.min_stretch < 1.0:
            raise ValueError(f"min_stretch={self.min_stretch} must be within (0, 1)")


@dataclass(frozen=True)
class NewtonSettings:
    """Newton's stopping rules and step controls (`fe.batched.BatchedShell`, which solves grad E(x) - p grad V(x)
    = 0 and V(x) = V_target for the free positions x (m) and the fluid pressure p (Pa), the Lagrange multiplier
    of the volume constraint, through the bordered KKT system's Schur complement, backtracking on an
    augmented-Lagrangian merit function): residual force (infinity norm), relative volume error, iteration cap.

    The residual must fall below max(force_tolerance (N), relative_force_tolerance x the largest nodal
    load |grad E| or |p grad V|), i.e. a part-per-million balance of every node's forces by default.
    """

    force_tolerance: float = 1e-10
    relative_force_tolerance: float = 1e-6
    volume_tolerance: float = 1e-10
    max_iterations: int = 60
    max_backtracks: int = 30
    refresh_factor: float = 1e5
    """Lagged quantities are refreshed, and chord steps tried, once the residual is below refresh_factor x
    its tolerance."""
    chord_contraction: float = 0.2
    """A chord step (last factorisation reused) is kept when it cuts the residual by at least this factor."""
    min_forcing: float = 0.03
    """The tightest relative CG tolerance the adaptive forcing asks of a Newton step (but never a linear residual
    below half the Newton tolerance): tighter, block-Jacobi CG pays far more iterations than the Newton rounds it
    saves (benchmarks/cg_work.py; 0 restores Eisenstat and Walker's choice alone)."""
