"""Gymnasium environments for tactile policy learning on the BioTac FE twin (docs/envs.md).

Importing `twin` registers them (cheaply: entry points are strings, nothing heavy is imported here):
- `BioTacPress-v0` (twin.envs.press.PressEnv): press at a target location to a target force;
- `BioTacEdgeFollow-v0` (twin.envs.edge.EdgeFollowEnv): slide along an edge whose direction is hidden.
Each also has a vector form, `gymnasium.make_vec(id, num_envs, vectorization_mode="vector_entry_point")`
(twin.envs.vector.TactileVectorEnv), stepping all sub-environments through one batched FE call.
"""

import gymnasium as gym

ENV_IDS = {
    "BioTacPress-v0": ("twin.envs.press:PressEnv", "twin.envs.vector:press_vector_env"),
    "BioTacEdgeFollow-v0": ("twin.envs.edge:EdgeFollowEnv", "twin.envs.vector:edge_vector_env"),
}


def register_envs() -> None:
    """Register every BioTac environment with gymnasium (idempotent)."""
    for env_id, (entry_point, vector_entry_point) in ENV_IDS.items():
        if env_id not in gym.registry:
            gym.register(env_id, entry_point=entry_point, vector_entry_point=vector_entry_point)
