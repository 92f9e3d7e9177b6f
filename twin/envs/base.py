"""Shared machinery of the BioTac tactile environments: one episode on one FE slot, seen through the sensor.

An environment moves a rigid indenter against the BioTac skin by bounded tip-displacement increments
(its task says in which frame); after each increment the FE (twin.envs.fe_batch) re-solves the skin
quasi-statically and the sensor model (twin.envs.sensing) reads it. Observations hold only what a real
BioTac gives, tared at the episode's start: 19 electrodes and PDC (counts); with `ft=True` also a
wrist F/T reading of the force on the skin (N, biotac frame); plus the task's own proprioceptive
entries (the commanded tip position, mm). Rewards come from the FE's true state.

Termination: the true indenter force exceeds `force_limit_n` (reward minus `limit_penalty`), or the FE
did not converge (the same penalty; info["fe_failed"]). Truncation: `max_steps` steps.

Stepping is split so that a vector env can step many of these through one batched FE call:
`begin_episode` -> pose, `first_observation(increment)`; `command(action)` -> pose, `outcome(increment)`.
A stand-alone environment owns a one-slot batch and chains them in `reset` and `step`.
"""

from __future__ import annotations

from abc import abstractmethod
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import gymnasium as gym
import numpy as np
from gymnasium import spaces

from fe.electrodes import ADC_MAX, N_ELECTRODES, ElectrodeParameters
from twin.envs.fe_batch import COARSE_MESH_MM, BatchIncrement, IndentationBatch
from twin.envs.sensing import Reading, TactileReadout
from twin.fe_models import shared_model

Pose = tuple[np.ndarray, np.ndarray]
"""Indenter pose: rotation (3, 3) body->biotac and tip position (3,) m."""
FORCE_BOUND_N = 50.0
"""Magnitude (N) at which the F/T observation saturates."""


@dataclass(frozen=True)
class SlotIncrement:
    """One slot's FE answer (SI units, biotac frame): force (3,) N, pressure Pa, displacement (V, 3) m; and the
    skin's relative electrode impedances (19,) when the vector env evaluated every slot's at once (else None)."""

    force: np.ndarray
    pressure: float
    displacement: np.ndarray
    contact_area: float
    converged: bool
    impedance: np.ndarray | None = None


def slot_increment(batch: BatchIncrement, k: int, impedance: np.ndarray | None = None) -> SlotIncrement:
    """Slot `k` of a batched FE answer (with its relative electrode impedances (19,) when evaluated)."""
    return SlotIncrement(
        batch.force[k],
        float(batch.pressure[k]),
        batch.displacement[k],
        float(batch.contact_area[k]),
        bool(batch.converged[k]),
        impedance,
    )


class TactileEnv(gym.Env[dict[str, np.ndarray], np.ndarray]):
    """Base of the BioTac environments (see the module docstring); tasks implement the abstract hooks.

    sensor_params: the BioTac's read-out (`ElectrodeParameters`; None: nominal; `ElectrodeParameters.sample`
    draws a plausible other unit); force_noise_n: white noise (N) of the F/T observation.
    fe, slot, readout: set by `TactileVectorEnv` so that sub-environments share one FE batch; left
    None, the environment builds a one-slot batch on the shared model with `mesh_mm` edges (mm) on the
    warp `device` ("cpu", "cuda", "cuda:0", ...).
    render_mode: "rerun" (logged to `rerun_save`, else a spawned viewer) or "rgb_array" (`render` returns
    an offscreen MuJoCo frame (`render_height`, `render_width`, 3) uint8 of the last state: twin.envs.render).
    """

    metadata = {"render_modes": ["rerun", "rgb_array"], "render_fps": 10}
    default_indenter: str
    """The indenter a task uses unless told otherwise."""
    tip_bound_mm = 20.0
    """Bound (mm) of each entry of the `tip` observation."""

    def __init__(
        self,
        indenter: str,
        *,
        mesh_mm: float = COARSE_MESH_MM,
        device: str = "cpu",
        ft: bool = False,
        max_steps: int = 20,
        max_step_mm: float = 0.3,
        force_limit_n: float = 4.0,
        limit_penalty: float = 10.0,
        sensor_params: ElectrodeParameters | None = None,
        force_noise_n: float = 0.01,
        render_mode: str | None = None,
        rerun_save: str | Path | None = None,
        render_width: int = 320,
        render_height: int = 240,
        fe: IndentationBatch | None = None,
        slot: int = 0,
        readout: TactileReadout | None = None,
    ) -> None:
        if render_mode is not None and render_mode not in self.metadata["render_modes"]:
            raise ValueError(f"render_mode must be None or one of {self.metadata['render_modes']}, got {render_mode!r}")
        if max_steps < 1 or not max_step_mm > 0.0 or not force_limit_n > 0.0 or limit_penalty < 0.0:
            raise ValueError("need max_steps >= 1, max_step_mm > 0, force_limit_n > 0 and limit_penalty >= 0")
        self.fe = fe if fe is not None else IndentationBatch(shared_model(mesh_mm), [indenter], device)
        if not 0 <= slot < self.fe.n or self.fe.indenters[slot] != indenter:
            raise ValueError(f"slot {slot} of the FE batch must exist and carry indenter {indenter!r}")
        self.indenter, self.slot = indenter, slot
        self.readout = readout if readout is not None else TactileReadout(self.fe, sensor_params, force_noise_n)
        self.ft, self.max_steps, self.max_step_mm = ft, int(max_steps), float(max_step_mm)
        self.force_limit_n, self.limit_penalty = float(force_limit_n), float(limit_penalty)
        self.render_mode = render_mode
        self.action_space = spaces.Box(-1.0, 1.0, (3,), np.float32)
        entries = {
            "electrodes": spaces.Box(-ADC_MAX, ADC_MAX, (N_ELECTRODES,), np.float32),
            "pdc": spaces.Box(-ADC_MAX, ADC_MAX, (1,), np.float32),
            "tip": spaces.Box(-self.tip_bound_mm, self.tip_bound_mm, (3,), np.float32),
        }
        if ft:
            entries["force"] = spaces.Box(-FORCE_BOUND_N, FORCE_BOUND_N, (3,), np.float32)
        entries.update(self._task_spaces())
        self.observation_space = spaces.Dict(entries)
        self._viewer = None
        if render_mode == "rerun":
            from twin.view.scene import SkinScene, open_recording

            recording = open_recording("biotac-twin-env", Path(rerun_save) if rerun_save else None, rerun_save is None)
            self._viewer = SkinScene(
                recording, self.fe.reference, self.fe.model.geometry.skin.triangles, self.readout.electrode_positions
            )
            self._viewer.set_indenter(indenter)
        self._painter = None
        if render_mode == "rgb_array":
            from twin.envs.render import SkinRenderer

            geometry = self.fe.model.geometry
            core = (geometry.core.vertices, geometry.core.triangles)
            self._painter = SkinRenderer(
                self.fe.reference, geometry.skin.triangles, core, indenter, render_width, render_height
            )
        self._tare: Reading | None = None
        self._last_increment: SlotIncrement | None = None
        self._last_obs: dict[str, np.ndarray] | None = None
        self._steps = 0
        self._frame = 0
        self._previous_tip = np.zeros(3)
        self.tip_mm = np.zeros(3)
        """The commanded tip in the task's action frame (mm)."""

    # -- task hooks ------------------------------------------------------------------------------
    @abstractmethod
    def _task_spaces(self) -> dict[str, spaces.Box]:
        """Extra observation entries of the task."""

    @abstractmethod
    def _sample_episode(self, options: dict[str, Any] | None) -> None:
        """Draw the episode's task (from self.np_random) and set the start `tip_mm`."""

    @abstractmethod
    def _workspace_mm(self) -> tuple[np.ndarray, np.ndarray]:
        """(lower, upper) bounds (3,) mm of `tip_mm`; commands are clipped into them."""

    @abstractmethod
    def _pose(self) -> Pose:
        """The indenter pose of the current `tip_mm`."""

    @abstractmethod
    def _task_observation(self) -> dict[str, np.ndarray]:
        """The task's extra observation entries now."""

    @abstractmethod
    def _task_reward(self, force: np.ndarray, previous_tip_mm: np.ndarray) -> tuple[float, dict[str, Any]]:
        """Reward of a converged step with true force (3,) N, and the task's info entries."""

    # -- episode ---------------------------------------------------------------------------------
    def begin_episode(self, seed: int | None = None, options: dict[str, Any] | None = None) -> Pose:
        """Seed (gymnasium's rule), draw a new task, and return the start pose (indenter off the skin)."""
        super().reset(seed=seed, options=options)
        self._sample_episode(options)
        self._steps = 0
        self._tare = None
        return self._pose()

    def first_observation(self, increment: SlotIncrement) -> tuple[dict[str, np.ndarray], dict[str, Any]]:
        """Tare the sensor at the start pose's reading and return the first observation and info."""
        if not increment.converged:
            raise RuntimeError("the FE did not converge at the episode's start pose")
        self._tare = self._read(increment)
        return self._observe(self._tare, increment), self._info(increment)

    def command(self, action: np.ndarray) -> Pose:
        """Move the commanded tip by `action` (3,) in [-1, 1] times `max_step_mm` (clipped to the
        workspace) and return the new pose."""
        if self._tare is None:
            raise RuntimeError("call reset() before step()")
        action = np.asarray(action, dtype=float)
        if action.shape != (3,) or not np.all(np.isfinite(action)):
            raise ValueError(f"an action is 3 finite numbers in [-1, 1], got {action!r}")
        self._previous_tip = self.tip_mm.copy()
        low, high = self._workspace_mm()
        self.tip_mm = np.clip(self.tip_mm + np.clip(action, -1.0, 1.0) * self.max_step_mm, low, high)
        self._steps += 1
        return self._pose()

    def outcome(self, increment: SlotIncrement) -> tuple[dict[str, np.ndarray], float, bool, bool, dict[str, Any]]:
        """Observation, reward, terminated, truncated and info after the FE answered the last command."""
        truncated = self._steps >= self.max_steps
        info = self._info(increment)
        if not increment.converged:
            info["fe_failed"] = True
            return self._last_obs, -self.limit_penalty, True, truncated, info
        obs = self._observe(self._read(increment), increment)
        reward, task_info = self._task_reward(increment.force, self._previous_tip)
        info.update(task_info)
        terminated = bool(np.linalg.norm(increment.force) > self.force_limit_n)
        if terminated:
            reward -= self.limit_penalty
        return obs, float(reward), terminated, truncated, info

    # -- gymnasium API (stand-alone) -------------------------------------------------------------
    def reset(
        self, *, seed: int | None = None, options: dict[str, Any] | None = None
    ) -> tuple[dict[str, np.ndarray], dict[str, Any]]:
        """Start an episode (see `begin_episode`); the FE slot is back at the inflated state."""
        pose = self.begin_episode(seed, options)
        self._own_fe().reset([self.slot])
        return self.first_observation(self._solve(pose))

    def step(self, action: np.ndarray) -> tuple[dict[str, np.ndarray], float, bool, bool, dict[str, Any]]:
        """Apply one tip increment, re-solve the skin, observe, reward."""
        return self.outcome(self._solve(self.command(action)))

    def render(self) -> np.ndarray | None:
        """render_mode "rgb_array": a frame (H, W, 3) uint8 of the last state (skin, indenter, force arrow).
        With "rerun" every reset and step is logged as it happens: nothing to do here (None)."""
        if self._painter is None:
            return None
        if self._last_increment is None:
            raise RuntimeError("call reset() before render()")
        rotation, tip = self._pose()
        increment = self._last_increment
        return self._painter.render(increment.displacement, rotation, tip, increment.force)

    def close(self) -> None:
        """Finish the rerun recording (render_mode "rerun") so that a saved .rrd is complete; free the
        offscreen renderer ("rgb_array")."""
        if self._painter is not None:
            self._painter.close()
            self._painter = None
        if self._viewer is not None:
            self._viewer.recording.flush()
            self._viewer.recording.disconnect()
            self._viewer = None

    def _own_fe(self) -> IndentationBatch:
        if self.fe.n != 1:
            raise RuntimeError("this environment is a slot of a vector env: step it through TactileVectorEnv")
        return self.fe

    def _solve(self, pose: Pose) -> SlotIncrement:
        return slot_increment(self._own_fe().step_batch(pose[0][None], pose[1][None]), 0)

    # -- sensing ---------------------------------------------------------------------------------
    def _read(self, increment: SlotIncrement) -> Reading:
        return self.readout.read(
            increment.displacement, increment.pressure, increment.force, self.np_random, increment.impedance
        )

    def _observe(self, reading: Reading, increment: SlotIncrement) -> dict[str, np.ndarray]:
        """The observation dict (float32, clipped to its space) of a reading; logs the state when rendering."""
        electrodes = reading.electrodes - self._tare.electrodes
        obs = {
            "electrodes": electrodes,
            "pdc": np.array([reading.pdc - self._tare.pdc]),
            "tip": self.tip_mm,
        }
        if self.ft:
            obs["force"] = reading.force
        obs.update(self._task_observation())
        obs = {
            k: np.clip(v, self.observation_space[k].low, self.observation_space[k].high).astype(np.float32)
            for k, v in obs.items()
        }
        self._last_obs, self._last_increment = obs, increment
        if self._viewer is not None:
            self._log(increment, electrodes, reading.pdc - self._tare.pdc)
        return obs

    def _info(self, increment: SlotIncrement) -> dict[str, Any]:
        return {
            "force_n": np.array(increment.force),
            "contact_area_mm2": increment.contact_area * 1e6,
            "steps": self._steps,
        }

    def _log(self, increment: SlotIncrement, electrodes: np.ndarray, pdc: float) -> None:
        self._viewer.recording.set_time("step", sequence=self._frame)
        self._frame += 1
        rotation, tip = self._pose()
        self._viewer.log_state(
            increment.displacement, rotation, tip, increment.force, electrodes, increment.pressure, pdc
        )
