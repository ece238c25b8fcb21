"""RotateCup on MuJoCo Warp (GPU worlds, torch tensors on the device); see docs/warp.md.

Importing this package registers `RotateCupWarp-v0` (vector entry point only) with gymnasium:
``gymnasium.make_vec("rotation.sim_warp:RotateCupWarp-v0", num_envs=N, vectorization_mode="vector_entry_point",
device="cuda")``. MuJoCo Warp itself is imported only when a Warp env is built (the [warp] extra).
"""

from __future__ import annotations

import gymnasium as gym

WARP_ENV_ID = "RotateCupWarp-v0"

if WARP_ENV_ID not in gym.registry:
    gym.register(
        id=WARP_ENV_ID,
        entry_point="rotation.sim_warp.vector:_single_env",
        vector_entry_point="rotation.sim_warp.vector:RotateCupWarpVectorEnv",
        max_episode_steps=None,  # the env truncates itself at EnvConfig.episode_steps
    )
