"""SimBackend: the testbed in simulation (MuJoCo arms, fe skin, electrode physics, plant noise).

MuJoCo moves the arms (joint targets followed within the velocity limits). Whenever the indenter
comes to rest at a new pose, its tip pose in the `biotac` frame (through `true_biotac_pose`, where
the plant really mounted this sensor, not where registration thinks it is) drives the fe stepper.
The F/T reading is the load the BioTac transmits to the mount, expressed in the sensor frame, plus
the plant's bias and noise; electrodes and PDC come from the electrode physics model of the plant's
sensor. Between solves every channel holds its last value.

What solves the skin is pluggable (`SkinSolver`): by default the fe model's own stepper, one solve at a
time; the batched campaign (`twin.campaign_batched`) instead records the solves the protocol asks for, then
replays their batched results through the same backend.
"""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import dataclass
from typing import Protocol

import numpy as np

from fe.electrodes import N_ELECTRODES, ElectrodeModel
from fe.indentation import IncrementResult
from fe.sensor import BioTacModel
from twin.backend import ARMS, BackendError, Sample, check_arm
from twin.effects import (
    BACKLASH,
    COMPLIANCE,
    EffectValues,
    check_values,
    deflect,
    measure_wrench,
    read_out,
    read_pdc,
    trail,
)
from twin.kinematics import joint_limits, velocity_limits
from twin.plant import MeasurementNoise, PlantSensor
from twin.readout import SensorReadout, ft_load
from twin.scene import TestbedScene

GRAVITY = np.array([0.0, 0.0, -9.81])


@dataclass(frozen=True)
class SimSettings:
    """Numerics of the simulated testbed."""

    pose_tolerance: float = 1e-7
    """Tip motion (m) below which the fe state is not re-solved."""
    rest_tolerance: float = 1e-9
    """Joint distance (rad) to the target below which an arm counts as at rest."""
    mounted_mass: float = 0.12
    """Mass (kg) of BioTac + fixture carried by the F/T sensor (seen untared as a constant load)."""


WRENCH_HISTORY_S = 1.0
"""Seconds of clean-wrench history kept for the measurement effects (the longest time delay is 0.5 s)."""
COMPLIANCE_SOLVES = 8
"""Solves at most per call for the plant's compliance fixed point (`ComplianceSettle`); one left unsettled goes on
at the next sample, where the tip is still off its settled pose."""
RELAXATION_SOLVE_INTERVAL_S = 0.1
"""While the skin relaxes (a viscoelastic skin model), it is re-solved at a held pose this often (s): here
and in the model's replay (twin.analysis.predict) alike."""


class ComplianceSettle:
    """The compliant tip's equilibrium x = commanded - c F(x) at one solve time (`twin.effects.deflect`: c the
    plant's `robot_compliance` in m/N, F(x) the skin's force in N with the tip at x m, all biotac frame), reached
    by solves at the same time: the first at `tip` = commanded (3,) m deflected by `load` (3,) N, the force of the
    solve before; then the Aitken-relaxed fixed point x <- x + w r, r = commanded - c F(x) - x (Irons and Tuck: w
    from the last two residuals; 1 at first and while the residual stands still) until the next move would be
    within `tolerance` (m) or `solves` solves are spent.

    Every solve is an accepted step of the skin, as the real tip settles through its poses: no time passes after
    the first (a relaxing skin's branches take the stress change since then as instantaneous), and the friction's
    stick anchors follow the tip's short travel along the load to its settled pose. One object drives both the
    one-at-a-time backend (`SimBackend`) and the batched campaign (`twin.campaign_batched`), so that their tips
    are the same floating-point values."""

    def __init__(
        self,
        commanded: np.ndarray,
        load: np.ndarray,
        compliance: float,
        tolerance: float,
        solves: int = COMPLIANCE_SOLVES,
    ) -> None:
        self.commanded, self.compliance, self.tolerance = np.array(commanded, dtype=float), compliance, tolerance
        self.tip = deflect(self.commanded, load, compliance)
        """The tip (3,) m to solve at next (the last one `next_tip` gave)."""
        self._left = solves - 1
        self._relaxation, self._previous = 1.0, None

    def next_tip(self, force: np.ndarray) -> np.ndarray | None:
        """After the solve at `tip` gave the indenter's force `force` (3,) N on the skin: the next tip (3,) m to
        solve at the same time, or None when the tip has settled or the solves are spent."""
        if self._left == 0:
            return None
        residual = deflect(self.commanded, force, self.compliance) - self.tip
        if _norm(residual) <= self.tolerance:
            return None
        previous, self._previous = self._previous, residual
        if previous is not None and (change := residual - previous).any():
            self._relaxation = -self._relaxation * float(previous.dot(change)) / float(change.dot(change))
        self.tip = self.tip + self._relaxation * residual
        self._left -= 1
        return self.tip


class SkinSolver(Protocol):
    """What drives the skin for one indenter: `fe.indentation.IndentationStepper` (`BioTacModel.stepper`) or a
    stand-in with the same contract (records or replays solves, `twin.campaign_batched`)."""

    @property
    def relaxes(self) -> bool:
        """Whether the skin is viscoelastic (then a held pose is re-solved as time passes)."""
        ...

    def step(self, rotation: np.ndarray, translation: np.ndarray, time_s: float | None = None) -> IncrementResult:
        """Solve at the pose (rotation (3,3) indenter body -> biotac, tip (3,) m) at time `time_s` (s); a
        RuntimeError when it refuses to go on (after a failed step)."""
        ...


class SimBackend:
    """The `Backend` of the simulated testbed for one plant sensor; `time_s` starts at `start_time_s`.

    joint_offsets: arm -> (7,) real joint zero offsets (rad): joints are commanded and read in the
    nominal model, while the arm's true shape (MuJoCo, the tool pose) is the model at joints + offset.
    solver: indenter name -> the `SkinSolver` of a newly attached indenter (default `fe_model.stepper`).
    electrode_counts: False for a run whose electrode and PDC readings nobody reads (the batched campaign's
    schedule pass): they are NaN, not computed, while their noise is drawn all the same (as many normals as
    `ElectrodeModel.counts` and `pdc_counts` draw), so every other reading is that of a backend computing them.
    """

    def __init__(
        self,
        scene: TestbedScene,
        true_biotac_pose: np.ndarray,
        sensor: PlantSensor,
        fe_model: BioTacModel,
        electrodes: ElectrodeModel,
        noise: MeasurementNoise,
        rng: np.random.Generator,
        start_time_s: float = 0.0,
        settings: SimSettings = SimSettings(),
        effects: EffectValues | None = None,
        joint_offsets: dict[str, np.ndarray] | None = None,
        solver: Callable[[str], SkinSolver] | None = None,
        electrode_counts: bool = True,
    ) -> None:
        if fe_model.reference is None:
            raise ValueError("the fe model must be inflated before it drives a SimBackend")
        self.scene = scene
        self.sensor = sensor
        self.fe_model = fe_model
        self._solver = solver if solver is not None else fe_model.stepper
        self.electrodes = electrodes
        self._readout = SensorReadout(fe_model.reference, electrodes)
        self.noise = noise
        self.rng = rng
        self.electrode_counts = electrode_counts
        self.settings = settings
        self.time_s = start_time_s
        self.joint_offsets = {arm: np.asarray((joint_offsets or {}).get(arm, np.zeros(7)), float) for arm in ARMS}
        self.true_biotac_pose = np.asarray(true_biotac_pose, dtype=float)
        self._biotac_from_robot = np.linalg.inv(self.true_biotac_pose)
        self._velocity = {arm: velocity_limits(arm) for arm in ARMS}
        self._limits = {arm: joint_limits(arm) for arm in ARMS}
        self._placed: dict[str, bytes | None] = dict.fromkeys(ARMS)
        """The joints (their bytes) whose true joints each arm was last placed at in the scene."""
        self._tip_poses: dict[str, np.ndarray] = {}
        """Each arm's tip pose in the biotac frame while its joints and tool stay as they are."""
        self._sensor_in_biotac = np.linalg.inv(scene.biotac_pose) @ scene.ft_sensor_pose
        self._joints = {arm: self._reachable(arm, scene.joints(arm)) for arm in ARMS}
        self._targets = {arm: self._joints[arm].copy() for arm in ARMS}
        self._tools: dict[str, str | None] = dict.fromkeys(ARMS)
        self._stepper: SkinSolver | None = None
        self._stepper_arm: str | None = None
        self._last_tip: np.ndarray | None = None
        self._trailing: np.ndarray | None = None
        """Where the tip stands with the plant's backlash (`twin.effects.trail`; m, biotac frame; None: at the next
        rest pose, as commanded)."""
        self._load = np.zeros(3)
        """The indenter's force on the skin (N, biotac frame) of the last solve (zero on the rest skin)."""
        self._clean = self._rest_signals()
        self.solve_log: list[tuple[float, IncrementResult]] = []
        """Every fe solve as (simulated time s, result), in time order."""
        self.effects = check_values(effects or {})
        self._wrench_history: list[tuple[float, np.ndarray]] = [(-np.inf, self._clean["wrench"])]

    # -- Backend ---------------------------------------------------------------------------------
    def attach_tool(self, arm: str, tool: str | None) -> None:
        """Mount `tool` (indenter name, "pin" or None) on `arm`; a new indenter starts from the rest skin."""
        check_arm(arm)
        self.scene.attach_tool(arm, tool)
        self._tip_poses.pop(arm, None)
        self._tools[arm] = tool
        if tool is not None and tool != "pin":
            self._stepper = self._solver(tool)
            self._stepper_arm = arm
            self._last_tip, self._trailing, self._load = None, None, np.zeros(3)
            self._clean = self._rest_signals()
            self._record_wrench()

    def command_joints(self, arm: str, joints: np.ndarray) -> None:
        """Set the joint target (rad); outside the joint limits is refused with BackendError."""
        check_arm(arm)
        q = np.asarray(joints, dtype=float)
        limits = self._limits[arm]
        if q.shape != (7,) or not np.all(np.isfinite(q)):
            raise BackendError(f"joint target for {arm} must be 7 finite numbers, got {q!r}")
        if np.any(q < limits[:, 0]) or np.any(q > limits[:, 1]):
            raise BackendError(f"joint target for {arm} is outside the joint limits: {np.round(q, 4)}")
        self._targets[arm] = self._reachable(arm, q)  # where the arm will stop: at a joint stop, short of q

    def advance(self, dt: float) -> None:
        """Move both arms toward their targets for `dt` s, then re-solve the skin if the indenter rests."""
        if dt < 0:
            raise ValueError(f"dt must be >= 0, got {dt!r}")
        for arm in ARMS:
            target, joints = self._targets[arm], self._joints[arm]
            if target.tobytes() == joints.tobytes():  # at rest: the clipped step is +0.0
                self._joints[arm] = joints + 0.0
            else:
                reach = self._velocity[arm] * dt
                self._joints[arm] = joints + np.clip(target - joints, -reach, reach)
            self._place(arm)
        self.time_s += dt
        arm = self._stepper_arm
        if arm is not None and np.abs(self._targets[arm] - self._joints[arm]).max() <= self.settings.rest_tolerance:
            self._solve_if_moved(arm)

    def read(self) -> Sample:
        """Noisy readings of every channel at the current simulated time."""
        # one draw for the encoders (7 a arm), the force (3) and the torque (3), the same normals as a draw each
        # (without its electrode counts, the electrodes' 19 and the PDC's one as well)
        z = self.rng.standard_normal(len(ARMS) * 7 + 6 + (0 if self.electrode_counts else N_ELECTRODES + 1))
        joints = {arm: self._joints[arm] + self.noise.encoder * z[7 * i : 7 * i + 7] for i, arm in enumerate(ARMS)}
        k = len(ARMS) * 7
        wrench_noise = np.concatenate([self.noise.force * z[k : k + 3], self.noise.torque * z[k + 3 : k + 6]])
        carried = self._measured_wrench() + self.sensor.ft_bias + wrench_noise  # what the gauges carry
        wrench = read_out(carried[None], self.effects)[0]
        if not self.electrode_counts:
            return Sample(self.time_s, joints, wrench, np.full(N_ELECTRODES, np.nan), np.nan)
        electrodes = self._readout.electrode_counts(self._clean["displacement"], self.time_s, self.rng)
        pdc = read_pdc(
            np.array([self.time_s]), np.array([self._readout.pdc(self._clean["pressure"], self.rng)]), self.effects
        )
        return Sample(self.time_s, joints, wrench, electrodes, float(pdc[0]))

    def close(self) -> None:
        """Nothing to release in simulation."""

    def _true_joints(self, arm: str) -> np.ndarray:
        """The arm's true joint angles (rad): its readings plus its joints' zero offsets."""
        return self._joints[arm] + self.joint_offsets[arm]

    def _reachable(self, arm: str, joints: np.ndarray) -> np.ndarray:
        """Joint readings `joints` (rad) clipped to where the true joints (reading + zero offset) stay inside the joint
        range: a joint that meets its hard stop stops there, and its encoder with it, so a target past it is never
        reached (`move_to` then faults) and the readings say where the arm really stopped. Clipping the true joints
        alone (before session 31) let the readings run on past the stop: data whose kinematics no analysis can
        follow (a realistic plant's press 4 mrad past a limit left 3.9x the noise at the plant's own values)."""
        limits, offset = self._limits[arm], self.joint_offsets[arm]
        return np.clip(joints, limits[:, 0] - offset, limits[:, 1] - offset)

    def _place(self, arm: str) -> None:
        """Put the scene's arm at its true joints; MuJoCo's kinematics run only when the joints differ (bit for
        bit) from those the arm was last placed for (a resting arm, most of every pause, costs none)."""
        joints = self._joints[arm].tobytes()
        if joints != self._placed[arm]:
            self.scene.set_joints(arm, self._true_joints(arm))
            self._placed[arm] = joints
            self._tip_poses.pop(arm, None)

    def _measured_wrench(self) -> np.ndarray:
        """Noise-free F/T reading now: the clean load history through the plant's measurement effects."""
        if not self.effects:
            return self._clean["wrench"]
        times = np.array([t for t, _ in self._wrench_history])
        values = np.array([w for _, w in self._wrench_history])

        def clean_at(t: np.ndarray) -> np.ndarray:
            return values[np.clip(np.searchsorted(times, t, side="right") - 1, 0, None)]

        return measure_wrench(np.array([self.time_s]), clean_at, self.effects)[0]

    # -- simulation state ------------------------------------------------------------------------
    def tip_pose_biotac(self, arm: str) -> np.ndarray:
        """True 4x4 pose of `arm`'s tool tip in the biotac frame."""
        if arm not in self._tip_poses:
            self._tip_poses[arm] = self._biotac_from_robot @ self.scene.tool_pose(arm)
        return self._tip_poses[arm].copy()

    def _solve_if_moved(self, arm: str) -> None:
        """Solve the skin where the resting tip stands, if it moved or the skin relaxes: its pose with the plant's
        backlash (`trail`) and, with `robot_compliance`, deflected by the load of the last solve, then settled
        at the same time (`ComplianceSettle`)."""
        pose = self.tip_pose_biotac(arm)
        if BACKLASH in self.effects:  # the tip trails its rest poses, from none at the first (the standoff)
            start = pose[:3, 3] if self._trailing is None else self._trailing
            self._trailing = trail(start, pose[:3, 3], self.effects[BACKLASH]["lag"])
            pose[:3, 3] = self._trailing
        settle = self._settle(pose[:3, 3])
        if settle is not None:
            pose[:3, 3] = settle.tip
        moved = self._last_tip is None or _norm(pose[:3, 3] - self._last_tip) > self.settings.pose_tolerance
        relaxing = (
            self._stepper.relaxes
            and bool(self.solve_log)
            and self.time_s - self.solve_log[-1][0] >= RELAXATION_SOLVE_INTERVAL_S - 1e-9
        )
        if not (moved or relaxing):
            return
        result = self._step(pose)
        while settle is not None and (tip := settle.next_tip(result.force)) is not None:
            pose[:3, 3] = tip
            result = self._step(pose)
        self._last_tip = pose[:3, 3].copy()
        self._load = np.array(result.force, dtype=float)
        self._clean = self._signals(result, pose[:3, 3])
        self._record_wrench()

    def _settle(self, commanded: np.ndarray) -> ComplianceSettle | None:
        """With `robot_compliance`, the settle of a tip commanded to `commanded` (3,) m (biotac frame) from under the
        load of the last solve; None without it."""
        if COMPLIANCE not in self.effects:
            return None
        compliance = self.effects[COMPLIANCE]["compliance"]
        return ComplianceSettle(commanded, self._load, compliance, self.settings.pose_tolerance)

    def _step(self, pose: np.ndarray) -> IncrementResult:
        """Solve the skin at `pose` (4x4 indenter body -> biotac frame, m) now and log the solve; BackendError when
        the skin model stops or does not converge."""
        try:
            result = self._stepper.step(pose[:3, :3], pose[:3, 3], self.time_s)
        except RuntimeError as exc:  # the stepper refuses to go on after a failed step
            raise BackendError(f"the skin model is stopped: {exc}") from exc
        if not result.converged:
            raise BackendError(f"the skin model did not converge at this pose ({result.message})")
        self.solve_log.append((self.time_s, result))
        return result

    def _record_wrench(self) -> None:
        """Append the clean wrench now to the history the measurement effects read; entries older than
        the longest delay an effect may have (plus the newest one before that) are dropped."""
        self._wrench_history.append((self.time_s, self._clean["wrench"]))
        horizon = self.time_s - WRENCH_HISTORY_S
        while len(self._wrench_history) > 1 and self._wrench_history[1][0] <= horizon:
            self._wrench_history.pop(0)

    def _rest_signals(self) -> dict:
        """The clean state of the rest skin: no displacement (None), the inflated pressure (Pa), the untared
        wrench (sensor frame)."""
        return {
            "displacement": None,
            "pressure": self.fe_model.pressure,
            "wrench": self._wrench(np.zeros(3), np.zeros(3)),
        }

    def _signals(self, result: IncrementResult, tip: np.ndarray) -> dict:
        """The clean state of a solve: skin displacement (V, 3) m, pressure (Pa), untared wrench (sensor frame)
        of its force at the tip (3,) m."""
        return {
            "displacement": result.displacement,
            "pressure": result.pressure,
            "wrench": self._wrench(result.force, tip),
        }

    def _wrench(self, force_biotac: np.ndarray, point_biotac: np.ndarray) -> np.ndarray:
        """Untared, noise-free F/T reading (sensor frame): the indenter load plus the mounted weight."""
        weight_biotac = self.true_biotac_pose[:3, :3].T @ (self.settings.mounted_mass * GRAVITY)
        weight = ft_load(weight_biotac, self._sensor_in_biotac[:3, 3], self._sensor_in_biotac)
        return ft_load(force_biotac, point_biotac, self._sensor_in_biotac) + weight


def _norm(vector: np.ndarray) -> float:
    """The Euclidean norm of a 1-D float array, as `np.linalg.norm` computes it (sqrt of its dot with itself,
    the same bits) without its per-call overhead (it is asked every sample)."""
    return math.sqrt(vector.dot(vector))
