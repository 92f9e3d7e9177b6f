"""The contact-onset estimate's two steps on analytic data (no fe): the shift between a loading curve and a
shifted copy of it, and the offset from the shifts of presses with known normals (twin.analysis.onset).
The fe case (the model measuring its own paths with a known offset) is in tests/test_nuisances.py."""

import numpy as np
import pytest

from twin.analysis.onset import UNSEEN_STD, OnsetEstimate, PathShift, contact_shift, offset_from_shifts
from twin.effects import REGISTRATION, apply_path, registration_values, registration_vector


def hertz(z: np.ndarray, onset: float) -> np.ndarray:
    """A Hertzian loading curve (N) against depth z (m): 2e5 (z - onset)^1.5 past the onset, 0 before."""
    return 2e5 * np.clip(z - onset, 0.0, None) ** 1.5


@pytest.mark.parametrize("shift", [-0.45e-3, 0.0, 0.3e-3, 0.75e-3])
def test_the_shift_between_two_hertzian_curves_is_the_distance_between_their_onsets(shift: float) -> None:
    z = np.r_[-1e-3, np.arange(16) * 1e-4]  # the protocol's standoff, then 0.1 mm steps to 1.5 mm
    error = np.full(len(z), 1e-3)  # N, a mean of about 100 samples of 0.01 N
    rng = np.random.default_rng(3)
    measured = hertz(z, -shift) + error * rng.standard_normal(len(z))
    found, std = contact_shift(z, measured, hertz(z, 0.0), error)
    assert found == pytest.approx(shift, abs=0.02e-3)
    assert 0 < std < 0.1e-3


def test_no_contact_gives_no_shift() -> None:
    z = np.r_[-1e-3, np.arange(5) * 1e-4]
    found, std = contact_shift(z, np.zeros(len(z)), hertz(z, 0.0), np.full(len(z), 1e-3))
    assert np.isnan(found) and std == np.inf


def _press(k: int, normal: np.ndarray, offset: np.ndarray, tilt: np.ndarray | None = None) -> PathShift:
    """A press along -normal (tilted by `tilt`, unnormalised) whose shift is the exact n.o / n.d of `offset`."""
    normal = normal / np.linalg.norm(normal)
    direction = -normal if tilt is None else -normal + tilt
    direction = direction / np.linalg.norm(direction)
    return PathShift(k, float(normal @ offset / (normal @ direction)), 0.02e-3, normal, direction)


def test_presses_at_three_points_give_the_whole_offset() -> None:
    offset = np.array([0.62e-3, -0.78e-3, 0.13e-3])
    normals = [np.array([0.0, 1.0, 0.0]), np.array([0.5, 0.9, 0.0]), np.array([0.0, 0.9, 0.5])]
    shifts = [_press(k, n, offset) for k, n in enumerate(normals)]
    estimate, covariance, unseen = offset_from_shifts(shifts)
    assert estimate == pytest.approx(offset, abs=1e-9)
    assert len(unseen) == 0 and np.all(np.sqrt(np.diag(covariance)) < UNSEEN_STD)


def test_presses_at_one_point_see_only_the_normal_component() -> None:
    """A normal and a 30-degree press at one point: only n.o is seen; the two tangential directions are
    reported, and the estimate has nothing along them."""
    offset = np.array([0.62e-3, -0.78e-3, 0.13e-3])
    normal = np.array([0.06, 0.99, -0.15])
    shifts = [_press(0, normal, offset), _press(1, normal, offset, tilt=np.array([0.5, 0.0, 0.0]))]
    estimate, _, unseen = offset_from_shifts(shifts)
    unit = normal / np.linalg.norm(normal)
    assert unit @ estimate == pytest.approx(unit @ offset, abs=1e-9)
    assert len(unseen) == 2 and np.abs(unseen @ unit).max() < 1e-9
    assert np.abs(unseen @ estimate).max() < 1e-12
    assert offset_from_shifts([])[2].shape == (3, 3), "no press: every direction is unseen"


def test_the_registration_helpers_are_the_offset_the_path_effect_applies() -> None:
    """values <-> (3,) offset, checked against the tips the effect moves; an axis past its 3 mm bound is clipped."""
    values = registration_values(np.array([0.62e-3, -0.78e-3, 4e-3]))
    tips = np.array([[0.0, 0.0, 0.0], [1e-2, -2e-2, 3e-2]])
    moved = apply_path(tips, {REGISTRATION: values}) - tips
    assert moved == pytest.approx(np.tile([0.62e-3, -0.78e-3, 3e-3], (2, 1)), abs=1e-15)
    assert registration_vector(values) == pytest.approx(moved[0], abs=1e-15)
    assert np.all(registration_vector(None) == 0.0), "no values: the effect is off"


def test_the_onset_estimate_moves_the_current_offset_by_what_it_found() -> None:
    estimate = OnsetEstimate(np.array([0.5e-3, 0.0, -0.2e-3]), np.zeros((3, 3)), np.zeros((0, 3)), ())
    moved = estimate.values(registration_values(np.array([0.1e-3, 0.2e-3, 0.0])))
    assert registration_vector(moved) == pytest.approx([0.6e-3, 0.2e-3, -0.2e-3], abs=1e-15)
