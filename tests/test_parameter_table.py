"""The skin parameter table (`fe.params.SKIN_PARAMETERS`): every field declares its units and range there, the
range is what `SkinParameters` enforces, and every physics effect of the library stays inside it."""

from dataclasses import fields, replace

import pytest

from fe.params import PAPER_CALIBRATION_BOUNDS, SKIN_PARAMETERS, SkinParameters
from twin.analysis.calibrate import CALIBRATED
from twin.effects import EFFECTS, SKIN_KNOBS, apply_skin
from twin.hidden import draw_hidden


def test_every_field_is_declared_once_with_units_and_a_range_holding_its_default() -> None:
    nominal = SkinParameters()
    assert list(SKIN_PARAMETERS) == [f.name for f in fields(SkinParameters)]
    for name, parameter in SKIN_PARAMETERS.items():
        assert parameter.units
        if parameter.physical is not None:
            low, high = parameter.physical
            assert low <= getattr(nominal, name) <= high
            if parameter.paper is not None:
                assert low <= parameter.paper[0] < parameter.paper[1] <= high


@pytest.mark.parametrize("name", [n for n, p in SKIN_PARAMETERS.items() if p.physical is not None])
def test_the_declared_range_is_the_one_enforced(name: str) -> None:
    low, high = SKIN_PARAMETERS[name].physical
    for inside in (low, high):
        assert getattr(replace(SkinParameters(), **{name: inside}), name) == inside
    span = high - low
    for outside in (low - 1e-3 * span, high + 1e-3 * span):
        with pytest.raises(ValueError, match=f"{name}=.* is outside its physical range"):
            replace(SkinParameters(), **{name: outside})


def test_the_paper_calibration_fits_the_fields_with_the_paper_s_bounds() -> None:
    assert CALIBRATED == ("thickness", "mu_nh", "friction", "fluid_temperature")  # the paper's t_s, mu_NH, mu_fr, T_fl
    assert PAPER_CALIBRATION_BOUNDS["thickness"] == (1e-3, 2e-3) and PAPER_CALIBRATION_BOUNDS["mu_nh"] == (1e5, 1e6)


@pytest.mark.parametrize("name", [n for n, e in EFFECTS.items() if e.skin is not None])
def test_each_skin_effect_at_the_ends_of_its_search_range_gives_a_valid_skin(name: str) -> None:
    for parameter in EFFECTS[name].parameters:
        for value in (parameter.lower, parameter.upper):
            skin = apply_skin(SkinParameters(), {name: {parameter.name: value}})  # SkinParameters checks its range
            assert skin != SkinParameters() or value == parameter.off


# The skin effects as they were declared by hand in twin/effects.py before the table built them (session 12,
# 2026-11-26): effect -> (description, channels, probe, ((parameter, off, lower, upper, scale, units, field, acts),
# ...)). Frozen here so that a change to the table that moves any of them fails.
_HAND_WRITTEN_SKIN_EFFECTS = {
    "skin_thickness": (
        "Skin shell thickness differs from the model's (scale factor on t_s).",
        ("force", "pdc", "electrodes"),
        {},
        (("scale", 1.0, 0.6, 1.5, 0.05, "1", "thickness", "scale"),),
    ),
    "skin_modulus": (
        "Skin shear modulus differs from the model's (scale factor on mu_NH).",
        ("force", "pdc", "electrodes"),
        {},
        (("scale", 1.0, 0.5, 2.0, 0.05, "1", "mu_nh", "scale"),),
    ),
    "indenter_friction": (
        "Coulomb friction between indenter and skin differs (scale factor on mu_fr).",
        ("force",),
        {},
        (("scale", 1.0, 0.0, 5.0, 0.25, "1", "friction", "scale"),),
    ),
    "skin_relaxation": (
        "The skin is viscoelastic: one Prony branch relaxes a fraction of its moduli with a time constant.",
        ("force", "pdc", "electrodes"),
        {"fraction": 0.15},
        (
            ("fraction", 0.0, 0.0, 0.6, 0.05, "1", "relaxation_fraction", "set"),
            ("time_s", 1.0, 0.05, 10.0, 0.2, "s", "relaxation_time_s", "set"),
        ),
    ),
    "skin_stiffening": (
        "The skin stiffens with strain beyond Neo-Hookean (Gent, parameter 1/J_m).",
        ("force", "pdc", "electrodes"),
        {},
        (("inverse_jm", 0.0, 0.0, 2.0, 0.1, "1", "gent_inverse_jm", "set"),),
    ),
    "trapped_air": (
        "A gas bubble in the fluid (volume fraction of the cavity) makes the fluid compressible (Boyle).",
        ("force", "pdc", "electrodes"),
        {},
        (("fraction", 0.0, 0.0, 0.5, 0.02, "1", "air_volume_fraction", "set"),),
    ),
    "fill_volume": (
        "The sensor holds more or less fluid than the model (skin pretension; scale on the inflation volume).",
        ("force", "pdc", "electrodes"),
        {},
        (("scale", 1.0, 0.7, 1.4, 0.03, "1", "inflation_volume_scale", "scale"),),
    ),
}
_LIBRARY_ORDER = (
    "skin_thickness", "skin_modulus", "indenter_friction", "skin_relaxation", "skin_stiffening", "trapped_air",
    "fill_volume", "registration_offset", "robot_backlash", "robot_compliance", "time_delay", "ft_drift",
    "ft_crosstalk", "ft_gain", "ft_calibration", "ft_saturation", "pdc_drift",
)  # fmt: skip


def test_the_library_keeps_its_order_and_its_skin_effects_are_exactly_the_hand_written_ones() -> None:
    assert tuple(EFFECTS) == _LIBRARY_ORDER
    assert {n for n, e in EFFECTS.items() if e.skin is not None} == set(_HAND_WRITTEN_SKIN_EFFECTS)


@pytest.mark.parametrize("name", list(_HAND_WRITTEN_SKIN_EFFECTS))
def test_each_skin_effect_has_the_hand_written_numbers_texts_and_mapping(name: str) -> None:
    description, channels, probe, parameters = _HAND_WRITTEN_SKIN_EFFECTS[name]
    effect = EFFECTS[name]
    assert (effect.description, effect.kind, effect.channels, effect.probe) == (description, "physics", channels, probe)
    assert (effect.starts, effect.linear) == ((), False)
    assert (effect.path, effect.deflection, effect.wrench, effect.reading, effect.pdc) == (None,) * 5
    assert [(p.name, p.off, p.lower, p.upper, p.scale, p.units) for p in effect.parameters] == [
        row[:6] for row in parameters
    ]
    # the mapping onto the skin: a value inside the range, away from the off value, lands on the named field
    # (set: the value itself; scale: the value times the nominal), and no other field moves
    nominal = SkinParameters()
    values = {p[0]: p[2] + 0.3 * (p[3] - p[2]) for p in parameters}
    expected = {
        field: value if acts == "set" else getattr(nominal, field) * value
        for (*_, field, acts), value in zip(parameters, values.values(), strict=True)
    }
    assert apply_skin(nominal, {name: values}) == replace(nominal, **expected)


@pytest.mark.parametrize("name", list(SKIN_KNOBS))
def test_a_hidden_skin_effect_is_drawn_inside_its_search_range_at_its_declared_distance_from_off(name: str) -> None:
    effect = EFFECTS[name]
    for seed in range(40):
        drawn = draw_hidden(name, seed)[name]
        assert effect.values(drawn) == drawn  # every parameter drawn, inside the search bounds (values() checks)
        for parameter, (_, knob) in zip(effect.parameters, SKIN_KNOBS[name], strict=True):
            low, high = knob.hidden
            size = abs(drawn[parameter.name] - parameter.off) if knob.hidden_both_ways else drawn[parameter.name]
            assert low <= size <= high
            assert drawn[parameter.name] != parameter.off
