"""A closed Neo-Hookean sphere inflated by volume control follows membrane theory within 1%."""

import numpy as np

from fe.balloon import inflate_balloon


def test_balloon_follows_membrane_theory_through_the_pressure_maximum() -> None:
    ratios = [1.2, 1.6, 2.2, 7**0.5, 3.0, 3.375]  # stretch up to 1.5, peak at lambda = 7^(1/6)
    points = inflate_balloon(
        radius=0.01, thickness=1e-4, mu=1e5, volume_ratios=ratios, subdivisions=3, max_volume_step=0.25
    )
    assert all(p.converged for p in points)
    errors = [abs(p.pressure_pa / p.analytic_pressure_pa - 1) for p in points]
    assert max(errors) < 0.01, errors
    pressures = np.array([p.pressure_pa for p in points])
    peak = int(np.argmax(pressures))
    assert 0 < peak < len(points) - 1, "volume control must pass the pressure maximum"
    assert abs(points[peak].stretch - 7 ** (1 / 6)) < 0.02
