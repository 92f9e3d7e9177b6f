"""The effect library: each effect does what its physics says, off means off, bad values are refused."""

import ast
from pathlib import Path

import numpy as np
import pytest

import twin.effects as effects_module
from fe.params import SkinParameters
from twin.effects import EFFECTS, apply_path, apply_skin, check_values, measure_wrench, read_out, read_pdc


def _step_load(times: np.ndarray) -> np.ndarray:
    """A load that steps from 0 to 1 N (fz) at t = 1 s, plus a constant 0.5 N fx."""
    wrench = np.zeros((len(times), 6))
    wrench[:, 0] = 0.5
    wrench[:, 2] = (times >= 1.0).astype(float)
    return wrench


def test_every_effect_is_off_at_its_off_values() -> None:
    times = np.linspace(0, 3, 301)
    skin = SkinParameters()
    tips = np.array([[1e-3, 0.0, -7e-3]])
    for name, effect in EFFECTS.items():
        values = {name: {p.name: p.off for p in effect.parameters}}
        assert effect.is_off(values[name])
        np.testing.assert_array_equal(measure_wrench(times, _step_load, values), _step_load(times), err_msg=name)
        assert apply_skin(skin, values) == skin
        np.testing.assert_array_equal(apply_path(tips, values), tips)
        np.testing.assert_array_equal(read_out(_step_load(times) + 2.0, values), _step_load(times) + 2.0)
        np.testing.assert_array_equal(read_pdc(times, times * 3.0, values), times * 3.0)
    assert len(EFFECTS) >= 8


def test_time_delay_shifts_the_step() -> None:
    times = np.linspace(0, 3, 301)
    delayed = measure_wrench(times, _step_load, {"time_delay": {"seconds": 0.25}})
    first = times[np.argmax(delayed[:, 2] > 0.5)]
    assert first == pytest.approx(1.25, abs=0.011)


def test_drift_grows_linearly_and_crosstalk_mixes_axes() -> None:
    times = np.array([0.0, 10.0])
    drift = measure_wrench(times, _step_load, {"ft_drift": {"fz_rate": 0.01}})
    assert drift[1, 2] - _step_load(times)[1, 2] == pytest.approx(0.1)
    mixed = measure_wrench(times, _step_load, {"ft_crosstalk": {"zx": 0.1}})
    # fz picks up 10 % of fx; fx itself is unchanged
    assert mixed[:, 2] - _step_load(times)[:, 2] == pytest.approx([0.05, 0.05])
    assert mixed[:, 0] == pytest.approx([0.5, 0.5])


def test_physics_effects_change_skin_and_path() -> None:
    skin = apply_skin(SkinParameters(), {"skin_thickness": {"scale": 1.1}, "indenter_friction": {"scale": 2.0}})
    assert skin.thickness == pytest.approx(1.1 * 1.57e-3)
    assert skin.friction == pytest.approx(2 * 0.186)
    shifted = apply_path(np.zeros((2, 3)), {"registration_offset": {"dx": 1e-3}})
    assert shifted[:, 0] == pytest.approx([1e-3, 1e-3])


def test_backlash_trails_each_rest_pose_by_its_lag_and_takes_up_the_slack_at_a_reversal() -> None:
    """A press of 0.1 mm increments to 0.4 mm and back, a lag of 0.15 mm: loading trails by the lag (the first
    0.15 mm are slack), the first 0.3 mm back are slack again, then it trails by the lag the other way."""
    depth = np.r_[0.0, 0.1, 0.2, 0.3, 0.4, 0.3, 0.2, 0.1, 0.0] * 1e-3
    direction = np.array([0.0, 0.6, -0.8])
    tips = np.array([1e-3, 2e-3, -7e-3]) + np.outer(depth, direction)
    trailed = apply_path(tips, {"robot_backlash": {"lag": 0.15e-3}})
    reached = (trailed - tips[0]) @ direction
    expected = np.r_[0.0, 0.0, 0.05, 0.15, 0.25, 0.25, 0.25, 0.25, 0.15] * 1e-3
    np.testing.assert_allclose(reached, expected, atol=1e-15)
    np.testing.assert_allclose(np.cross(trailed - tips[0], direction), 0.0, atol=1e-15)  # on the press line
    # a registration offset and the backlash commute (the play operator is translation-equivariant)
    both = {"robot_backlash": {"lag": 0.15e-3}, "registration_offset": {"dz": 0.3e-3}}
    np.testing.assert_allclose(apply_path(tips, both), trailed + [0.0, 0.0, 0.3e-3], atol=1e-15)


def test_compliance_shortens_a_press_by_the_compliance_times_the_load() -> None:
    """A press along (0, 0.6, -0.8) loaded with 2 N into the skin and 0.5 N sideways (the indenter's force on the
    skin), 0.05 mm/N: the tip stands 0.05 mm/N times that force back from its command; unloaded, where commanded."""
    direction = np.array([0.0, 0.6, -0.8])
    tips = np.array([[1e-3, 2e-3, -7e-3], [1e-3, 2.3e-3, -7.4e-3]])
    loads = np.array([[0.0, 0.0, 0.0], 2.0 * direction + [0.5, 0.0, 0.0]])
    values = {"robot_compliance": {"compliance": 5e-5}}
    moved = apply_path(tips, values, loads) - tips
    np.testing.assert_allclose(moved[0], 0.0, atol=1e-18)
    np.testing.assert_allclose(moved[1], [-0.025e-3, -0.06e-3, 0.08e-3], atol=1e-15)
    assert moved[1] @ direction == pytest.approx(-0.1e-3)  # 0.1 mm short of the commanded depth
    np.testing.assert_array_equal(apply_path(tips, values), tips)  # no loads given: unloaded


def test_pdc_drift_grows_linearly_in_time() -> None:
    times = np.array([0.0, 10.0, 20.0])
    np.testing.assert_allclose(read_pdc(times, np.full(3, 1600.0), {"pdc_drift": {"rate": -0.3}}), [1600, 1597, 1594])


def test_bad_effect_values_are_refused() -> None:
    with pytest.raises(ValueError, match="unknown effect"):
        check_values({"gremlins": {}})
    with pytest.raises(ValueError, match="outside"):
        check_values({"time_delay": {"seconds": -1.0}})
    with pytest.raises(ValueError, match="no parameters"):
        check_values({"time_delay": {"minutes": 1.0}})


def test_the_library_imports_nothing_from_the_analysis() -> None:
    """The analysis uses the library, never the other way (its data-driven starts live in the analysis:
    `twin.analysis.sensitivity.DATA_STARTS`): no import of `twin.analysis` anywhere in the module, nested or
    type-only ones included."""
    tree = ast.parse(Path(effects_module.__file__).read_text())
    imported = [node.module or "" for node in ast.walk(tree) if isinstance(node, ast.ImportFrom)]
    imported += [alias.name for node in ast.walk(tree) if isinstance(node, ast.Import) for alias in node.names]
    assert [m for m in imported if m.startswith("twin.analysis")] == []
