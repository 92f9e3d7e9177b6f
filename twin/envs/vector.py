"""Many BioTac environments stepped at once through the FE's batch call (`gymnasium.vector.VectorEnv`).

`TactileVectorEnv` holds `num_envs` sub-environments of one task, each on its own slot of one
`IndentationBatch`; every `step` gathers all sub-environments' new indenter poses and makes one
`step_batch` call: the batched FE engine (`fe.batched_stepper`) on the warp `device`, all slots solved
together. Autoreset follows gymnasium's NEXT_STEP mode: the step after an episode
ends resets that sub-environment (its action is ignored; reward 0).
"""

from __future__ import annotations

from pathlib import Path
from typing import Any

import numpy as np
from gymnasium.vector import AutoresetMode, VectorEnv
from gymnasium.vector.utils import batch_space, concatenate, create_empty_array

from twin.envs.base import TactileEnv, slot_increment
from twin.envs.edge import EdgeFollowEnv
from twin.envs.fe_batch import COARSE_MESH_MM, BatchIncrement, IndentationBatch
from twin.envs.press import PressEnv
from twin.envs.sensing import TactileReadout
from twin.fe_models import shared_model


class TactileVectorEnv(VectorEnv):
    """`num_envs` copies of `env_class` (kwargs `env_kwargs`) on one FE batch of the `mesh_mm` (mm) model,
    solved together on the warp `device` ("cpu", "cuda", "cuda:0", ...).

    With render_mode "rerun" the first sub-environment is logged (to `rerun_save` or a spawned viewer);
    "rgb_array" is a stand-alone environment's mode only.
    """

    metadata = {"render_modes": ["rerun"], "autoreset_mode": AutoresetMode.NEXT_STEP}

    def __init__(
        self,
        env_class: type[TactileEnv],
        num_envs: int,
        *,
        mesh_mm: float = COARSE_MESH_MM,
        device: str = "cpu",
        render_mode: str | None = None,
        rerun_save: str | Path | None = None,
        **env_kwargs: Any,
    ) -> None:
        if num_envs < 1:
            raise ValueError(f"num_envs must be >= 1, got {num_envs!r}")
        if render_mode is not None and render_mode not in self.metadata["render_modes"]:
            raise ValueError(f"the vector env's render_mode must be None or one of {self.metadata['render_modes']}")
        indenter = env_kwargs.pop("indenter", env_class.default_indenter)
        self.fe = IndentationBatch(shared_model(mesh_mm), [indenter] * num_envs, device)
        self.readout = TactileReadout(self.fe, env_kwargs.get("sensor_params"), env_kwargs.get("force_noise_n", 0.01))
        self.envs = [
            env_class(
                indenter,
                fe=self.fe,
                slot=k,
                readout=self.readout,
                render_mode=render_mode if k == 0 else None,
                rerun_save=rerun_save if k == 0 else None,
                **env_kwargs,
            )
            for k in range(num_envs)
        ]
        self.num_envs = num_envs
        self.render_mode = render_mode
        self.single_observation_space = self.envs[0].observation_space
        self.single_action_space = self.envs[0].action_space
        self.observation_space = batch_space(self.single_observation_space, num_envs)
        self.action_space = batch_space(self.single_action_space, num_envs)
        self._observations = create_empty_array(self.single_observation_space, num_envs)
        self._autoreset = np.zeros(num_envs, dtype=bool)

    def reset(
        self, *, seed: int | list[int | None] | None = None, options: dict[str, Any] | None = None
    ) -> tuple[dict[str, np.ndarray], dict[str, Any]]:
        """Reset every sub-environment; an int seed seeds sub-environment k with seed + k."""
        if seed is None or isinstance(seed, int):
            seeds = [None if seed is None else seed + k for k in range(self.num_envs)]
        else:
            seeds = list(seed)
            if len(seeds) != self.num_envs:
                raise ValueError(f"need {self.num_envs} seeds, got {len(seeds)}")
        poses = [env.begin_episode(s, options) for env, s in zip(self.envs, seeds, strict=True)]
        self.fe.reset()
        batch, impedances = self._step_fe(poses)
        observations, infos = [], {}
        for k, env in enumerate(self.envs):
            obs, info = env.first_observation(slot_increment(batch, k, impedances[k]))
            observations.append(obs)
            infos = self._add_info(infos, info, k)
        self._autoreset[:] = False
        return self._batch(observations), infos

    def step(
        self, actions: np.ndarray
    ) -> tuple[dict[str, np.ndarray], np.ndarray, np.ndarray, np.ndarray, dict[str, Any]]:
        """One increment of every sub-environment through a single `step_batch` call."""
        actions = np.asarray(actions, dtype=float)
        if actions.shape != (self.num_envs, 3):
            raise ValueError(f"actions must be ({self.num_envs}, 3), got {actions.shape}")
        resetting = self._autoreset.copy()
        poses = [env.begin_episode() if resetting[k] else env.command(actions[k]) for k, env in enumerate(self.envs)]
        if resetting.any():
            self.fe.reset(np.flatnonzero(resetting))
        batch, impedances = self._step_fe(poses)
        observations, infos = [], {}
        rewards = np.zeros(self.num_envs)
        terminated = np.zeros(self.num_envs, dtype=bool)
        truncated = np.zeros(self.num_envs, dtype=bool)
        for k, env in enumerate(self.envs):
            increment = slot_increment(batch, k, impedances[k])
            if resetting[k]:
                obs, info = env.first_observation(increment)
            else:
                obs, rewards[k], terminated[k], truncated[k], info = env.outcome(increment)
            observations.append(obs)
            infos = self._add_info(infos, info, k)
        self._autoreset = terminated | truncated
        return self._batch(observations), rewards, terminated, truncated, infos

    def close_extras(self, **kwargs: Any) -> None:
        """Close the sub-environments (finishes the first one's rerun recording)."""
        for env in self.envs:
            env.close()

    def _step_fe(self, poses: list[tuple[np.ndarray, np.ndarray]]) -> tuple[BatchIncrement, list[np.ndarray | None]]:
        """Every slot's FE answer at its pose, and the relative electrode impedances (19,) of each converged
        slot's skin (None where it failed), evaluated for all of them at once."""
        batch = self.fe.step_batch(np.array([p[0] for p in poses]), np.array([p[1] for p in poses]))
        impedances: list[np.ndarray | None] = [None] * self.num_envs
        converged = np.flatnonzero(batch.converged)
        if converged.size:
            evaluated = self.readout.sensor.relative_impedances(batch.displacement[converged])
            for k, z in zip(converged, evaluated, strict=True):
                impedances[k] = z
        return batch, impedances

    def _batch(self, observations: list[dict[str, np.ndarray]]) -> dict[str, np.ndarray]:
        self._observations = concatenate(self.single_observation_space, observations, self._observations)
        return {k: v.copy() for k, v in self._observations.items()}


def press_vector_env(num_envs: int, **kwargs: Any) -> TactileVectorEnv:
    """`gymnasium.make_vec("BioTacPress-v0", num_envs, vectorization_mode="vector_entry_point")`."""
    return TactileVectorEnv(PressEnv, num_envs, **kwargs)


def edge_vector_env(num_envs: int, **kwargs: Any) -> TactileVectorEnv:
    """`gymnasium.make_vec("BioTacEdgeFollow-v0", num_envs, vectorization_mode="vector_entry_point")`."""
    return TactileVectorEnv(EdgeFollowEnv, num_envs, **kwargs)
