"""The sensor read-out chain (`twin.readout`) against the sensor's physics: the F/T load of a force (statics),
the PDC scale (facts: 12 bits over 0-100 kPa), electrode counts at rest and pressed (facts: counts fall where
the skin approaches), and its held impedance (the same counts as the electrode model, solved once per state)."""

import numpy as np
import pytest

from assets.biotac import electrode_table, make_biotac
from fe.electrodes import ElectrodeModel, ElectrodeParameters
from twin.readout import SensorReadout, ft_load


def _pose(rotation: np.ndarray, origin: np.ndarray) -> np.ndarray:
    pose = np.eye(4)
    pose[:3, :3], pose[:3, 3] = rotation, origin
    return pose


def test_ft_load_is_the_force_and_its_moment_about_the_sensor_origin_in_the_sensor_frame() -> None:
    force, point = np.array([0.0, 0.0, -2.0]), np.array([0.03, 0.0, 0.01])
    at_origin = ft_load(force, point, _pose(np.eye(3), point))
    np.testing.assert_allclose(at_origin, [0.0, 0.0, -2.0, 0.0, 0.0, 0.0], atol=1e-15)  # no lever arm
    # 2 N down at 30 mm along +x: a moment of 0.06 N·m about +y (r x F = (0.03, 0, 0) x (0, 0, -2))
    lever = ft_load(force, point, _pose(np.eye(3), np.array([0.0, 0.0, 0.01])))
    np.testing.assert_allclose(lever, [0.0, 0.0, -2.0, 0.0, 0.06, 0.0], atol=1e-15)
    # the same sensor turned 90 degrees about z: its x axis is the biotac's y, its y axis the biotac's -x
    turned = np.array([[0.0, -1.0, 0.0], [1.0, 0.0, 0.0], [0.0, 0.0, 1.0]])
    rotated = ft_load(force, point, _pose(turned, np.array([0.0, 0.0, 0.01])))
    np.testing.assert_allclose(rotated, [0.0, 0.0, -2.0, 0.06, 0.0, 0.0], atol=1e-15)


@pytest.fixture(scope="module")
def readout() -> SensorReadout:
    geometry = make_biotac(2e-3)
    return SensorReadout(geometry.skin.vertices, ElectrodeModel(geometry, ElectrodeParameters()))


def _pad_pushed_in(reference: np.ndarray, depth_m: float) -> np.ndarray:
    """(V, 3) displacement that pushes the ventral pad (z < 0) in by `depth_m` m toward the core."""
    return np.where(reference[:, 2:] < 0.0, depth_m, 0.0) * np.array([0.0, 0.0, 1.0])


def test_counts_equal_the_offset_at_rest_and_fall_where_the_skin_approaches(readout: SensorReadout) -> None:
    offset = readout.electrodes.params.offset
    np.testing.assert_allclose(readout.electrode_counts(None), offset, atol=1e-9)
    np.testing.assert_allclose(readout.electrode_counts(np.zeros_like(readout.reference)), offset, atol=1e-9)
    pressed = readout.electrode_counts(_pad_pushed_in(readout.reference, 2e-4))
    ventral = electrode_table().normals[:, 2] < -0.5  # electrodes facing the pad
    assert ventral.any() and np.all(pressed[ventral] < offset[ventral] - 1.0)


def test_pdc_is_twelve_bits_over_a_hundred_kilopascals(readout: SensorReadout) -> None:
    assert readout.pdc(0.0) == 0.0 and readout.pdc(100e3) == pytest.approx(4095.0, rel=1e-12)
    assert readout.pdc(200e3) == 4095.0  # clipped to the ADC's range
    changes = readout.pdc_change(np.array([-10e3, 0.0, 50e3]))
    np.testing.assert_allclose(changes, [-409.5, 0.0, 2047.5], rtol=1e-12)  # a change is not clipped
    noisy = [readout.pdc(30e3, np.random.default_rng(seed)) for seed in range(50)]
    assert all(float(v).is_integer() for v in noisy) and 0.0 < np.std(noisy) < 3.0  # ADC rounding, 1 count noise


def test_the_held_impedance_gives_the_electrode_models_counts_and_solves_once_per_skin_state(
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    geometry = make_biotac(2e-3)
    electrodes = ElectrodeModel(geometry, ElectrodeParameters())
    reference = geometry.skin.vertices
    pressed = _pad_pushed_in(reference, 2e-4)
    states = [None, None, pressed, pressed, pressed, np.zeros_like(reference)]
    plain_rng, held_rng = np.random.default_rng(7), np.random.default_rng(7)
    vertices = [reference if d is None else reference + d for d in states]
    expected = [electrodes.counts(v, 10.0 + k, plain_rng) for k, v in enumerate(vertices)]
    assert not np.array_equal(expected[0], expected[2])  # the press changes the counts
    solved = []
    impedance = electrodes.relative_impedance
    monkeypatch.setattr(electrodes, "relative_impedance", lambda v: solved.append(1) or impedance(v))
    readout = SensorReadout(reference, electrodes)
    got = [readout.electrode_counts(d, 10.0 + k, held_rng) for k, d in enumerate(states)]
    np.testing.assert_array_equal(np.array(got), np.array(expected))
    assert len(solved) == 3  # the rest skin, the pressed one, and the zero displacement (a new array)
