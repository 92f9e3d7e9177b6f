"""`robot_compliance`: the model deflects its path by the measured loads, with the sign and frame the plant's F/T
reading has; the plant's tip settles where the skin's force deflects it (checked by an independent solve there).

The plant cases press sensor 2 with sphere_small on a frictionless skin (its fe state then depends on the pose
only, not on the path that led there), one normal press of the quick campaign, with and without compliance."""

from dataclasses import dataclass, replace

import numpy as np
import pytest

from fe.params import SkinParameters
from fe.results import IncrementResult
from twin.analysis.data import TrajectoryRecord
from twin.analysis.predict import measured_loads
from twin.campaign import QUICK_CONFIG, CampaignWorker, plan_campaign, simulate_trajectory
from twin.controller import Recording
from twin.effects import COMPLIANCE, apply_path
from twin.plant import Plant, make_plant, rigid_transform
from twin.readout import ft_load

COMPLIANCE_M_PER_N = 8e-5
"""The plant's compliance in these cases (0.08 mm/N, within the hidden draws)."""
CONFIG = replace(QUICK_CONFIG, sensors=(2,), indenters=("sphere_small",))
SETTLED_N = 1e-4
"""How far (N) the plant's settled force may be from the force at its settled pose: the plant stops within its pose
tolerance (0.1 um), which the skin's stiffness (under 1 N/mm on these presses) turns into at most 0.1 mN."""


def _record(wrench: np.ndarray, increment: np.ndarray, sensor_in_biotac: np.ndarray) -> TrajectoryRecord:
    """A trajectory with the raw F/T readings `wrench` (T, 6, sensor frame) at the path labels `increment` (T,)."""
    n = len(increment)
    raw = Recording(
        np.arange(n) * 0.01, np.zeros((n, 7)), wrench, np.zeros((n, 19)), np.zeros(n), np.zeros(n), increment, True, ""
    )
    eye = np.eye(4)
    return TrajectoryRecord(
        2, 0, "sphere_small", "left", 0.0, np.eye(3), np.zeros(3), np.array([0.0, 0.0, -1.0]), eye, eye,
        sensor_in_biotac, True, raw, {},
    )  # fmt: skip


def test_the_model_deflects_each_path_index_by_the_force_measured_at_its_end_back_along_the_press() -> None:
    """Readings made as the plant makes them (`ft_load` of the indenter's force on the skin, sensor frame, plus a
    bias) on a sensor turned and set off from the biotac frame: each path index's load is the force on the skin at
    its last sample (biotac frame), and the press along -z falls short by compliance times it."""
    sensor_in_biotac = rigid_transform(np.array([0.3, -1.1, 0.7]), np.array([0.01, -0.02, 0.03]))
    increment = np.array([-1, -1, 0, 0, 0, 1, 1])
    force = np.array([[0, 0, 0], [0, 0, 0], [0, 0, -0.2], [0.1, 0, -0.5], [0.1, 0, -0.6], [0, 0.05, -1], [0, 0, -1.5]])
    tips = np.array([0.0, 0.0, -1e-3]) * np.arange(len(increment))[:, None]
    bias = np.array([0.4, -0.3, 1.2, 0.01, 0.02, -0.01])
    wrench = np.array([ft_load(f, tip, sensor_in_biotac) for f, tip in zip(force, tips, strict=True)]) + bias
    loads = measured_loads(_record(wrench, increment, sensor_in_biotac))
    np.testing.assert_allclose(loads, force[[1, 4, 6]], atol=1e-12)
    commanded = np.array([[0.0, 0.0, 1e-3], [0.0, 0.0, 0.0], [0.0, 0.0, -0.5e-3]])
    deflected = apply_path(commanded, {COMPLIANCE: {"compliance": 5e-5}}, loads)
    np.testing.assert_allclose((deflected - commanded)[:, 2], [0.0, 0.03e-3, 0.075e-3], atol=1e-15)


def _plant(compliance: float) -> Plant:
    effects = {COMPLIANCE: {"compliance": compliance}} if compliance else {}
    nominal = SkinParameters(friction=0.0)
    return make_plant([2], CONFIG.seed, nominal, 0.0, mount_rotation_error=0.0, mount_translation_error=0.0,
                      effects=effects, exact_registration=True)  # fmt: skip


@dataclass
class _Logged:
    """A `SkinSolver` that notes the pose (rotation (3,3), tip (3,) m, biotac frame) of each solve it passes on."""

    stepper: object
    poses: list[tuple[np.ndarray, np.ndarray]]

    @property
    def relaxes(self) -> bool:
        return self.stepper.relaxes

    def step(self, rotation: np.ndarray, translation: np.ndarray, time_s: float | None = None) -> IncrementResult:
        self.poses.append((np.array(rotation), np.array(translation)))
        return self.stepper.step(rotation, translation, time_s)


@dataclass(frozen=True)
class _Press:
    """One press simulated on a plant: the time (s), pose (rotation, tip m) and result of each solve, in order."""

    times: list[float]
    poses: list[tuple[np.ndarray, np.ndarray]]
    results: list[IncrementResult]
    worker: CampaignWorker

    def settled(self, time_s: float) -> IncrementResult:
        """The state kept at time `time_s`: its last solve."""
        return [r for t, r in zip(self.times, self.results, strict=True) if t == time_s][-1]


@pytest.fixture(scope="module")
def presses() -> dict[float, _Press]:
    """The quick campaign's normal press, simulated without compliance and with it."""
    plan = plan_campaign(CONFIG, _plant(0.0))
    job = next(j for j in plan.planned if j.kept and j.spec.angle == 0.0)
    out = {}
    for compliance in (0.0, COMPLIANCE_M_PER_N):
        worker = CampaignWorker(CONFIG, _plant(compliance))
        poses: list[tuple[np.ndarray, np.ndarray]] = []
        backend, recording = simulate_trajectory(
            worker, job, 0, solver=lambda name, w=worker, p=poses: _Logged(w.sensor(2)[0].stepper(name), p)
        )
        assert recording.complete
        out[compliance] = _Press([t for t, _ in backend.solve_log], poses, [r for _, r in backend.solve_log], worker)
    return out


def test_a_compliant_plant_presses_less_hard_and_its_tip_settles_where_its_force_puts_it(
    presses: dict[float, _Press],
) -> None:
    """At each rest pose of the rigid plant's press (its solve's pose is the commanded one), the compliant plant's
    force F along the press is smaller, and a fresh solve with the tip at commanded - c F gives F back."""
    rigid, compliant = presses[0.0], presses[COMPLIANCE_M_PER_N]
    assert len(compliant.times) > len(rigid.times)  # the compliant tip settles through more solves
    model = compliant.worker.sensor(2)[0]
    pressed, deepest = 0, (0.0, 0.0)
    for time_s, (rotation, commanded), stiff in zip(rigid.times, rigid.poses, rigid.results, strict=True):
        force = compliant.settled(time_s).force
        press = -rotation[:, 2]  # the indenter presses along its body's -z
        if stiff.force @ press < 0.1:
            continue
        pressed += 1
        deepest = max(deepest, (stiff.force @ press, force @ press))
        assert force @ press < stiff.force @ press
        again = model.stepper("sphere_small").step(rotation, commanded - COMPLIANCE_M_PER_N * force, 0.0)
        assert again.converged
        np.testing.assert_allclose(again.force, force, atol=SETTLED_N)
    assert pressed >= 10
    assert deepest[1] < 0.97 * deepest[0], deepest  # 0.79 -> 0.73 N at 1 mm (measured)
