"""The skin parameter table (`fe.params.SKIN_PARAMETERS`): every field declares its units and range there, the
range is what `SkinParameters` enforces, and every physics effect of the library stays inside it."""

from dataclasses import fields, replace

import pytest

from fe.params import PAPER_CALIBRATION_BOUNDS, SKIN_PARAMETERS, SkinParameters
from twin.analysis.calibrate import CALIBRATED
from twin.effects import EFFECTS, apply_skin


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
