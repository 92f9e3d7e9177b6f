"""Never a wrong number marked converged: the presses of issue 17 that came back converged with the force
turned around (-255 N after 955 N) or with the penalty's forces of an indenter sunk into the clamped rim
now either converge with forces that grow with depth and push back on the indenter, or stop with
`converged: false` and the reason (`fe.batched_stepper.BatchedStepper._inadmissible`)."""

import numpy as np
import pytest

from assets.indenters import get_indenter
from fe.sensor import BioTacModel

PRESSES = [
    ("cylinder_long", (-13.5, 0.0, -8.5), 0.0, 6.0, 0.5),
    ("cylinder_long", (-5.0, 0.0, -9.0), 30.0, 6.0, 0.5),
    ("cylinder_long", (-13.5, 7.1, -1.0), 0.0, 5.0, 0.5),
]
"""Indenter, point (mm), tilt (deg), depth (mm), step (mm) of each press the issue reported."""


@pytest.mark.parametrize(("name", "point_mm", "angle_deg", "depth_mm", "step_mm"), PRESSES)
def test_a_press_converges_pushing_back_harder_or_says_it_did_not(
    frictional_biotac: BioTacModel, name: str, point_mm: tuple, angle_deg: float, depth_mm: float, step_mm: float
) -> None:
    model = frictional_biotac
    rows = list(model.indent(name, np.array(point_mm) * 1e-3, depth_mm * 1e-3, step_mm * 1e-3, angle_deg))
    path = model.plan_trajectory(get_indenter(name), np.array(point_mm) * 1e-3, angle_deg, 0.0, 1e-3, 1e-3)
    accepted = [r for r in rows if r.converged]
    assert all(r.converged for r in rows[:-1])  # the stepper stops at the first refusal
    pushes = [float(r.force @ path.direction) for r in accepted]
    magnitudes = [float(np.linalg.norm(r.force)) for r in accepted]
    assert all(p >= 0.9 * m for p, m in zip(pushes, magnitudes, strict=True))  # along the press, into the skin
    assert np.all(np.diff(magnitudes) >= 0.0)  # never less force for a deeper press
    if not rows[-1].converged:
        assert rows[-1].message, "a refused increment says why"


def test_the_clamped_rim_press_is_refused_with_its_reason(frictional_biotac: BioTacModel) -> None:
    """The cylinder across the proximal rim meets the clamped (rigid-base) vertices in its first step: refused
    as inadmissible, not reported at the penalty's hundreds of newtons."""
    name, point, angle, depth, step = PRESSES[0]
    rows = list(frictional_biotac.indent(name, np.array(point) * 1e-3, depth * 1e-3, step * 1e-3, angle))
    assert not rows[-1].converged
    assert "inadmissible" in rows[-1].message and "clamped vertex" in rows[-1].message
