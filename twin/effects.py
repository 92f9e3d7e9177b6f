"""Candidate effects: physics or measurement mechanisms a model can lack, each with an "off" value.

An effect has named parameters (off value, bounds, typical scale, units), the channels it changes and
whether it acts on the physics (the fe model: skin parameters, the indenter path) or on the
measurement (the F/T signal chain). The base model has every effect off. The same code puts a hidden
effect into a plant and an added effect into a model, so what is fitted is what was simulated.
The effects on the skin are built from the parameter table (`fe.params`: each field's `Knob`); the path
and F/T effects are declared here.

Values are plain dicts: {effect name: {parameter name: value}}; missing effects or parameters are off.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass, field, replace
from functools import partial

import numpy as np

from fe.params import SKIN_PARAMETERS, Knob, SkinParameters

EffectValues = dict[str, dict[str, float]]
CleanWrench = Callable[[np.ndarray], np.ndarray]
"""Noise-free sensor-frame wrench (N, 6) at the given times (N,) s."""
Reading = Callable[[np.ndarray, dict[str, float]], np.ndarray]
"""What the F/T electronics put out (N, 6) of what the gauges carry (N, 6, sensor frame: the load through the
signal chain, the bias and the noise), given the effect's values."""
PdcReading = Callable[[np.ndarray, np.ndarray, dict[str, float]], np.ndarray]
"""The PDC counts read out (N,) at times (N,) s from the nominal read-out's counts (N,), given the values."""


@dataclass(frozen=True)
class EffectParameter:
    """One parameter of an effect (SI units)."""

    name: str
    off: float
    lower: float
    upper: float
    scale: float
    """Typical magnitude: finite-difference step and optimiser scaling."""
    units: str


@dataclass(frozen=True)
class Effect:
    """A candidate mechanism. Exactly one of `skin`, `path`, `deflection`, `wrench`, `reading`, `pdc` says how it
    acts: on the skin, the indenter path, the indenter path under the contact loads, the load the F/T gauges
    carry, the F/T electronics' output (bias and noise included: a range) or the PDC read-out."""

    name: str
    description: str
    kind: str  # "physics" or "measurement"
    parameters: tuple[EffectParameter, ...]
    channels: tuple[str, ...]
    skin: Callable[[SkinParameters, dict[str, float]], SkinParameters] | None = None
    path: Callable[[np.ndarray, dict[str, float]], np.ndarray] | None = None
    deflection: Callable[[np.ndarray, np.ndarray, dict[str, float]], np.ndarray] | None = None
    """The tips (K, 3) m under the contact loads (K, 3) N, both biotac frame (`apply_path`)."""
    wrench: Callable[[np.ndarray, CleanWrench, dict[str, float]], np.ndarray] | None = None
    reading: Reading | None = None
    pdc: PdcReading | None = None
    probe: dict[str, float] = field(default_factory=dict)
    """Values at which to linearise while the effect is off, for parameters that do nothing at the off
    point (a relaxation time while the relaxing fraction is zero); empty: linearise at the off point."""
    starts: tuple[dict[str, float], ...] = ()
    """Values across the range at which a search also tries the effect (each a prediction), for effects
    whose slope at the off value misjudges a large size (a registration offset of a millimetre); a start
    estimated from the data themselves is the analysis's (`twin.analysis.sensitivity.DATA_STARTS`)."""
    linear: bool = False
    """The measurement is linear in the parameters (an F/T calibration matrix, a drift rate): a linear
    least-squares fit is exact and needs no nonlinear polish."""

    def values(self, given: dict[str, float] | None = None) -> dict[str, float]:
        """Every parameter's value: `given` where present, the off value otherwise (bounds checked)."""
        given = given or {}
        unknown = set(given) - {p.name for p in self.parameters}
        if unknown:
            raise ValueError(f"effect {self.name!r} has no parameters {sorted(unknown)}")
        out = {}
        for p in self.parameters:
            value = float(given.get(p.name, p.off))
            if not p.lower <= value <= p.upper:
                raise ValueError(f"{self.name}.{p.name}={value:g} is outside [{p.lower:g}, {p.upper:g}] {p.units}")
            out[p.name] = value
        return out

    def is_off(self, given: dict[str, float] | None) -> bool:
        """True when every parameter sits at its off value."""
        values = self.values(given)
        return all(values[p.name] == p.off for p in self.parameters)


# -- the skin effects, built from the parameter table (fe.params: each field's Knob) ----------------------
def _knob_parameter(field_name: str, knob: Knob) -> EffectParameter:
    """The effect parameter of a knob: a factor on the nominal (off 1, units 1) or the field's value itself
    (off its default, units its own)."""
    if knob.acts == "scale":
        off, units = 1.0, "1"
    else:
        off, units = float(getattr(SkinParameters(), field_name)), SKIN_PARAMETERS[field_name].units
    return EffectParameter(knob.parameter, off, knob.search[0], knob.search[1], knob.scale, units)


def _apply_knobs(knobs: tuple[tuple[str, Knob], ...], skin: SkinParameters, v: dict[str, float]) -> SkinParameters:
    """`skin` with each knob's field set to its parameter's value or scaled by it."""
    return replace(
        skin,
        **{
            field_name: v[knob.parameter] if knob.acts == "set" else getattr(skin, field_name) * v[knob.parameter]
            for field_name, knob in knobs
        },
    )


def _skin_knobs() -> dict[str, tuple[tuple[str, Knob], ...]]:
    """Effect name -> its (field, knob) pairs in field order; an effect's knobs must agree on its texts."""
    grouped: dict[str, list[tuple[str, Knob]]] = {}
    for field_name, parameter in SKIN_PARAMETERS.items():
        if parameter.effect is not None:
            grouped.setdefault(parameter.effect.effect, []).append((field_name, parameter.effect))
    for name, knobs in grouped.items():
        if len({(knob.description, knob.channels) for _, knob in knobs}) != 1:
            raise RuntimeError(f"the knobs of effect {name!r} disagree on its description or channels")
    return {name: tuple(knobs) for name, knobs in grouped.items()}


SKIN_KNOBS = _skin_knobs()
"""The skin effects of the parameter table: effect name -> ((SkinParameters field, Knob), ...), field order."""


def _skin_effect(name: str, knobs: tuple[tuple[str, Knob], ...]) -> Effect:
    """The physics effect `name` that moves the knobs' fields."""
    first = knobs[0][1]
    return Effect(
        name,
        first.description,
        "physics",
        tuple(_knob_parameter(field_name, knob) for field_name, knob in knobs),
        first.channels,
        skin=partial(_apply_knobs, knobs),
        probe={knob.parameter: knob.probe for _, knob in knobs if knob.probe is not None},
    )


# -- the effects declared here: the indenter path and the F/T measurement ------------------------------------
REGISTRATION = "registration_offset"
"""The effect that offsets the indenter path (dx, dy, dz; m, biotac frame)."""
REGISTRATION_AXES = ("dx", "dy", "dz")
"""Its parameters, in the order of the offset's biotac-frame axes x, y, z."""


BACKLASH = "robot_backlash"
"""The effect by which the tip trails its commanded rest poses (`trail`); the plant applies it to each rest pose."""
COMPLIANCE = "robot_compliance"
"""The effect by which the tip gives way under the contact load (`deflect`); the plant settles each rest pose."""


def registration_vector(values: dict[str, float] | None) -> np.ndarray:
    """(3,) m, biotac frame: the offset of `registration_offset` values (missing parameters off)."""
    v = EFFECTS[REGISTRATION].values(values)
    return np.array([v[axis] for axis in REGISTRATION_AXES])


def registration_values(offset: np.ndarray) -> dict[str, float]:
    """The `registration_offset` values of an offset (3,) m, biotac frame, each axis clipped to its bounds."""
    bounds = {p.name: (p.lower, p.upper) for p in EFFECTS[REGISTRATION].parameters}
    return {axis: float(np.clip(o, *bounds[axis])) for axis, o in zip(REGISTRATION_AXES, offset, strict=True)}


def _registration(tips: np.ndarray, v: dict[str, float]) -> np.ndarray:
    return tips + registration_vector(v)


def trail(actual: np.ndarray, commanded: np.ndarray, lag: float) -> np.ndarray:
    """Where a tip with backlash stands once commanded to `commanded` (3,) m from where it stood, `actual` (3,) m:
    it trails its command by up to `lag` m along its last move (a play operator: a move shorter than the slack
    left after a reversal leaves it where it was)."""
    commanded = np.asarray(commanded, dtype=float)
    gap = commanded - actual
    distance = float(np.linalg.norm(gap))
    return commanded - lag * gap / distance if distance > lag else np.array(actual, dtype=float)


def _backlash(tips: np.ndarray, v: dict[str, float]) -> np.ndarray:
    out = np.array(tips, dtype=float)
    for k in range(1, len(out)):
        out[k] = trail(out[k - 1], tips[k], v["lag"])
    return out


def deflect(tips: np.ndarray, loads: np.ndarray, compliance: float) -> np.ndarray:
    """Where tips (..., 3) m stand under the loads (..., 3) N, the indenter's force on the skin (both biotac frame),
    on an arm and tool of `compliance` m/N: moved by -compliance * load, back along a press (the reaction on the
    tool pushes it away from the skin)."""
    return np.asarray(tips, dtype=float) - compliance * np.asarray(loads, dtype=float)


def _compliance(tips: np.ndarray, loads: np.ndarray, v: dict[str, float]) -> np.ndarray:
    return deflect(tips, loads, v["compliance"])


def _delay(times: np.ndarray, clean: CleanWrench, v: dict[str, float]) -> np.ndarray:
    return clean(times - v["seconds"])


def _drift(times: np.ndarray, clean: CleanWrench, v: dict[str, float]) -> np.ndarray:
    rate = np.array([v["fx_rate"], v["fy_rate"], v["fz_rate"], 0.0, 0.0, 0.0])
    return clean(times) + np.outer(times, rate)


_CROSSTALK_TERMS = ("xy", "xz", "yx", "yz", "zx", "zy")


def _crosstalk(times: np.ndarray, clean: CleanWrench, v: dict[str, float]) -> np.ndarray:
    mixing = np.eye(3)
    for term in _CROSSTALK_TERMS:
        mixing["xyz".index(term[0]), "xyz".index(term[1])] = v[term]
    wrench = np.array(clean(times), dtype=float)
    wrench[:, :3] = wrench[:, :3] @ mixing.T
    return wrench


_CALIBRATION_TERMS = tuple(row + column for row in "xyz" for column in "xyz")
"""Entries of the F/T force calibration map: "xy" is the reading on x per newton on y."""


def _calibration(times: np.ndarray, clean: CleanWrench, v: dict[str, float]) -> np.ndarray:
    mapping = np.array([[v[row + column] for column in "xyz"] for row in "xyz"])
    wrench = np.array(clean(times), dtype=float)
    wrench[:, :3] = wrench[:, :3] @ mapping.T
    return wrench


def _gain(times: np.ndarray, clean: CleanWrench, v: dict[str, float]) -> np.ndarray:
    wrench = np.array(clean(times), dtype=float)
    wrench[:, :3] *= v["scale"]
    return wrench


def _quadratic(times: np.ndarray, clean: CleanWrench, v: dict[str, float]) -> np.ndarray:
    wrench = np.array(clean(times), dtype=float)
    force = wrench[:, :3]
    wrench[:, :3] = force + v["coefficient"] * force * np.abs(force)
    return wrench


def _saturation(reading: np.ndarray, v: dict[str, float]) -> np.ndarray:
    limits = np.array([v["fx"], v["fy"], v["fz"]])
    out = np.array(reading, dtype=float)
    out[:, :3] = np.clip(out[:, :3], -limits, limits)
    return out


def _pdc_drift(times: np.ndarray, pdc: np.ndarray, v: dict[str, float]) -> np.ndarray:
    return pdc + v["rate"] * times


def _mm(name: str) -> EffectParameter:
    return EffectParameter(name, 0.0, -3e-3, 3e-3, 2e-4, "m")


def _calibration_parameter(term: str) -> EffectParameter:
    """A calibration-map entry: a gain (diagonal, 1 off) or a cross-axis term (0 off)."""
    if term[0] == term[1]:
        return EffectParameter(term, 1.0, 0.5, 1.5, 0.02, "1")
    return EffectParameter(term, 0.0, -0.2, 0.2, 0.01, "1")


FORCE_AXES = ("fx", "fy", "fz")
"""The F/T force axes (sensor frame): `ft_saturation`'s parameters, each axis's limit."""
SATURATION_OFF_N = 1000.0
"""`ft_saturation`'s off value (N): a range no press of the testbed reaches."""

_COMPLIANCE_UPPER = 2e-4
"""`robot_compliance`'s upper bound (m/N, 0.2 mm/N): twice the softest arm and tool at the tip that is plausible
here, a light industrial arm like ABB's YuMi with a tool giving roughly 0.01-0.1 mm/N at the tip (joint and gear
stiffness dominate). Its search step is 5e-6 m/N: 5 um of tip at the testbed's 1 N."""

_REGISTRATION_STARTS = tuple({axis: sign * 1e-3} for axis in REGISTRATION_AXES for sign in (-1.0, 1.0))
"""A millimetre along each axis, both ways: where a registration search also looks (paper: 0.5-1.5 mm)."""


_DECLARED: dict[str, Effect] = {
    e.name: e
    for e in (
        Effect(
            REGISTRATION,
            "The indenter path is offset from where registration says it is (biotac frame).",
            "physics",
            tuple(_mm(axis) for axis in REGISTRATION_AXES),
            ("force", "pdc", "electrodes"),
            path=_registration,
            starts=_REGISTRATION_STARTS,
        ),
        Effect(
            BACKLASH,
            "The robot's tip trails its commanded rest pose by up to `lag` along its last move (backlash: at a "
            "reversal the slack is taken up first), from no lag at the standoff (biotac frame).",
            "physics",
            (EffectParameter("lag", 0.0, 0.0, 0.5e-3, 2e-5, "m"),),
            ("force", "pdc", "electrodes"),
            path=_backlash,
            starts=({"lag": 0.1e-3}, {"lag": 0.25e-3}),
        ),
        Effect(
            COMPLIANCE,
            "The robot's arm and tool give way under the contact load: the tip stands -compliance * F off its "
            "command, F the indenter's force on the skin (biotac frame), so a press falls short by more the "
            "harder it presses.",
            "physics",
            (EffectParameter("compliance", 0.0, 0.0, _COMPLIANCE_UPPER, 5e-6, "m/N"),),
            ("force", "pdc", "electrodes"),
            deflection=_compliance,
        ),
        Effect(
            "time_delay",
            "The F/T stream lags the joint stream by a constant delay.",
            "measurement",
            (EffectParameter("seconds", 0.0, 0.0, 0.5, 0.02, "s"),),
            ("force",),
            wrench=_delay,
            starts=({"seconds": 0.1}, {"seconds": 0.25}),
        ),
        Effect(
            "ft_drift",
            "F/T force bias drifts linearly in time (taring removes only its value at the start).",
            "measurement",
            tuple(EffectParameter(f"f{a}_rate", 0.0, -0.02, 0.02, 2e-4, "N/s") for a in "xyz"),
            ("force",),
            wrench=_drift,
            linear=True,
        ),
        Effect(
            "ft_crosstalk",
            "F/T force channels leak into each other (off-diagonal calibration error, sensor frame).",
            "measurement",
            tuple(EffectParameter(t, 0.0, -0.2, 0.2, 0.01, "1") for t in _CROSSTALK_TERMS),
            ("force",),
            wrench=_crosstalk,
            linear=True,
        ),
        Effect(
            "ft_gain",
            "F/T force calibration scale error (same factor on every force axis).",
            "measurement",
            (EffectParameter("scale", 1.0, 0.5, 1.5, 0.02, "1"),),
            ("force",),
            wrench=_gain,
            linear=True,
        ),
        Effect(
            "ft_calibration",
            "F/T force calibration error as one 3x3 map (sensor frame): per-axis gains and cross-axis terms "
            "together; ft_gain (equal gains) and ft_crosstalk (cross terms only) are its sub-cases.",
            "measurement",
            tuple(_calibration_parameter(t) for t in _CALIBRATION_TERMS),
            ("force",),
            wrench=_calibration,
            linear=True,
        ),
        Effect(
            "ft_saturation",
            "The F/T reading clips at its range: each force axis of the output (bias included, sensor frame) "
            "stays within +-its limit.",
            "measurement",
            tuple(EffectParameter(axis, SATURATION_OFF_N, 0.2, SATURATION_OFF_N, 0.05, "N") for axis in FORCE_AXES),
            ("force",),
            reading=_saturation,
        ),
        Effect(
            "pdc_drift",
            "The PDC read-out drifts linearly in time (taring removes only its value at the start).",
            "measurement",
            (EffectParameter("rate", 0.0, -5.0, 5.0, 0.05, "counts/s"),),
            ("pdc",),
            pdc=_pdc_drift,
            linear=True,
        ),
    )
}
LIBRARY_ORDER = (
    "skin_thickness",
    "skin_modulus",
    "indenter_friction",
    "skin_relaxation",
    "skin_stiffening",
    "trapped_air",
    "fill_volume",
    "registration_offset",
    "robot_backlash",
    "robot_compliance",
    "time_delay",
    "ft_drift",
    "ft_crosstalk",
    "ft_gain",
    "ft_calibration",
    "ft_saturation",
    "pdc_drift",
)
"""The library's order (what `twin effects` lists and the order diagnosis keeps among equal candidates)."""
_LIBRARY = {name: _skin_effect(name, knobs) for name, knobs in SKIN_KNOBS.items()} | _DECLARED
if sorted(_LIBRARY) != sorted(LIBRARY_ORDER):
    raise RuntimeError(f"LIBRARY_ORDER {sorted(LIBRARY_ORDER)} must list exactly the effects {sorted(_LIBRARY)}")
EFFECTS: dict[str, Effect] = {name: _LIBRARY[name] for name in LIBRARY_ORDER}
"""The effect library, keyed by name: the skin effects of the parameter table and those declared here."""

UNLISTED_EFFECTS: dict[str, Effect] = {
    "ft_nonlinearity": Effect(
        "ft_nonlinearity",
        "F/T strain-gauge nonlinearity: each force axis reads f + c f |f| (untared load, sensor frame).",
        "measurement",
        (EffectParameter("coefficient", 0.0, -0.5, 0.5, 0.01, "1/N"),),
        ("force",),
        wrench=_quadratic,
    ),
}
"""Effects a plant can carry but the library (what diagnosis tries) does not list: tests and benchmarks
use them to check that an effect outside the library comes out "unexplained"."""

MEASUREMENT_ORDER = ("time_delay", "ft_crosstalk", "ft_calibration", "ft_gain", "ft_nonlinearity", "ft_drift")
"""Order of the F/T signal chain: the sensor sees a delayed load, mixes and scales it, then drifts."""
READING_ORDER = ("ft_saturation",)
"""Order of the F/T electronics' effects on what the gauges carry (bias and noise included). A resolution is not
an effect: the analysis counts its rounding in the noise (`twin.analysis.readings`)."""
PDC_ORDER = ("pdc_drift",)
"""Order of the PDC read-out's effects (affine in the counts, so a model applies them to the tared change and the
taring removes the rest). A PDC gain is not one: every sensor's PDC gain is a nuisance the residual
profiles out (`twin.analysis.residual.PDC_GAIN_PRIOR`)."""


def get_effect(name: str) -> Effect:
    """The effect called `name` (library or unlisted), or a ValueError listing the library."""
    effect = EFFECTS.get(name) or UNLISTED_EFFECTS.get(name)
    if effect is None:
        raise ValueError(f"unknown effect {name!r}; the library has {sorted(EFFECTS)}")
    return effect


def check_values(values: EffectValues) -> EffectValues:
    """Validate names and bounds; return the values with every parameter of each named effect filled in."""
    return {name: get_effect(name).values(v) for name, v in values.items()}


def apply_skin(skin: SkinParameters, values: EffectValues) -> SkinParameters:
    """Skin parameters with every physics effect on the skin applied."""
    for name, v in check_values(values).items():
        effect = get_effect(name)
        if effect.skin is not None:
            skin = effect.skin(skin, v)
    return skin


def apply_path(tips: np.ndarray, values: EffectValues, loads: np.ndarray | None = None) -> np.ndarray:
    """Indenter tip positions (K, 3) m, biotac frame, with path effects applied, then, given the contact loads
    at the tips (K, 3) N (the indenter's force on the skin, biotac frame; None: unloaded, no deflection), the
    effects that deflect the path under load."""
    checked = check_values(values)
    for name, v in checked.items():
        effect = get_effect(name)
        if effect.path is not None:
            tips = effect.path(tips, v)
    for name, v in checked.items():
        effect = get_effect(name)
        if effect.deflection is not None and loads is not None:
            tips = effect.deflection(tips, loads, v)
    return tips


def measure_wrench(times: np.ndarray, clean: CleanWrench, values: EffectValues) -> np.ndarray:
    """(N, 6) F/T readings at `times` (s) from the clean load `clean`, through the measurement effects."""
    chain = clean
    for effect, v in _in_order(MEASUREMENT_ORDER, values):
        chain = _bind(effect, chain, v)
    return np.asarray(chain(np.asarray(times, dtype=float)))


def _in_order(order: tuple[str, ...], values: EffectValues) -> list[tuple[Effect, dict[str, float]]]:
    """(effect, its checked values) of each effect in `values` that `order` lists, in that order."""
    checked = check_values(values)
    return [(get_effect(name), checked[name]) for name in order if name in checked]


def _bind(effect: Effect, inner: CleanWrench, v: dict[str, float]) -> CleanWrench:
    return lambda t: effect.wrench(t, inner, v)


def read_out(reading: np.ndarray, values: EffectValues) -> np.ndarray:
    """(N, 6) F/T output from what the gauges carry (N, 6: the load through `measure_wrench`, plus bias and
    noise; sensor frame) through the electronics' effects (`READING_ORDER`); a copy when there are none."""
    out = np.array(reading, dtype=float)
    for effect, v in _in_order(READING_ORDER, values):
        out = effect.reading(out, v)
    return out


def read_pdc(times: np.ndarray, pdc: np.ndarray, values: EffectValues) -> np.ndarray:
    """(N,) PDC counts as read out at `times` (s) from the nominal read-out's counts (N,) through the PDC
    effects (`PDC_ORDER`); a copy when there are none."""
    out = np.array(pdc, dtype=float)
    for effect, v in _in_order(PDC_ORDER, values):
        out = effect.pdc(np.asarray(times, dtype=float), out, v)
    return out


def has_reading_effects(values: EffectValues) -> bool:
    """Whether any F/T electronics effect (`READING_ORDER`) is among `values` (its output then depends on the bias)."""
    return any(name in values for name in READING_ORDER)
