"""What raw F/T readings show of the electronics (`twin.analysis.readings`): a clipped range's plateau and a
quantised reading's lattice, found on synthetic readings whose range and step are known, and not found on
continuous noisy ones; the saturation effect itself clips the reading, bias included."""

import numpy as np
import pytest

from twin.analysis.readings import PLATEAU_SAMPLES, lattice_step, plateaus, resolution
from twin.effects import EFFECTS, SATURATION_OFF_N, read_out


def _press(rng: np.random.Generator, n: int = 4000) -> np.ndarray:
    """(n,) a noisy press on a bias: -1.7 N at rest, 1 N deeper at the middle, 10 mN noise (N)."""
    load = -(np.sin(np.linspace(0.0, np.pi, n)) ** 2)
    return -1.7 + load + 0.01 * rng.standard_normal(n)


@pytest.mark.parametrize("step", [0.003, 0.02, 0.05])
def test_a_quantised_reading_gives_its_step(step: float) -> None:
    quantised = step * np.floor(_press(np.random.default_rng(1)) / step + 0.5)
    assert lattice_step(quantised) == pytest.approx(step, rel=1e-9)
    steps = resolution(np.column_stack([quantised, _press(np.random.default_rng(4)), 2.0 * quantised]))
    assert steps[0] == pytest.approx(step, rel=1e-9) and np.isnan(steps[1]) and steps[2] == pytest.approx(2 * step)


def test_a_continuous_or_sparse_reading_has_no_lattice() -> None:
    assert np.isnan(lattice_step(_press(np.random.default_rng(2))))
    # values a whole number of 0.1 N apart but also 0.07 N: no common step
    assert np.isnan(lattice_step(np.r_[0.0, 0.1, 0.2, 0.27, 0.34, 0.5, 0.57]))


def test_a_clipped_axis_shows_a_plateau_and_only_its_samples_are_held() -> None:
    rng = np.random.default_rng(3)
    readings = np.column_stack(
        [0.5 + 0.01 * rng.standard_normal(4000), 0.3 + 0.01 * rng.standard_normal(4000), _press(rng)]
    )
    clipped = np.clip(readings, -2.2, 2.2)
    found = plateaus(clipped)
    assert found.clipped.tolist() == [False, False, True] and found.largest[2] == 2.2
    assert found.held[2] == (readings[:, 2] <= -2.2).sum() >= PLATEAU_SAMPLES
    assert np.array_equal(found.at_limit(clipped), readings[:, 2] <= -2.2)


def test_saturation_clips_each_axis_of_the_reading_at_its_limit_and_is_off_at_its_off_value() -> None:
    reading = np.array([[0.5, -3.0, -1.9, 0.01, 0.02, 0.03], [2.5, 0.2, 1.2, 0.0, 0.0, 0.0]])
    out = read_out(reading, {"ft_saturation": {"fx": 1.0, "fz": 1.5}})
    assert np.array_equal(out[:, :3], [[0.5, -3.0, -1.5], [1.0, 0.2, 1.2]])
    assert np.array_equal(out[:, 3:], reading[:, 3:])  # torques untouched
    assert EFFECTS["ft_saturation"].is_off({"fx": SATURATION_OFF_N})
    assert np.array_equal(read_out(reading, {}), reading)
