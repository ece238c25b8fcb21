"""Simulation side of the stack (MuJoCo + numpy, no torch): the RotateCup-v0 task and its batched core.

Importing this package registers `RotateCup-v0` with gymnasium, so both `gymnasium.make("envs:RotateCup-v0")`
and, after `import envs`, `gymnasium.make("RotateCup-v0")` work; keyword arguments reach `EnvConfig`.
`gymnasium.make_vec("envs:RotateCup-v0", num_envs=N, vectorization_mode="vector_entry_point")` returns the
batched env.
"""

from __future__ import annotations

import os
import sys

# MuJoCo picks its OpenGL platform when it is imported: every rendering here is offscreen, so on Linux (most often
# a headless workstation or server) use EGL unless the user chose one (MUJOCO_GL=osmesa, glfw, ...).
if sys.platform.startswith("linux"):
    os.environ.setdefault("MUJOCO_GL", "egl")

import gymnasium as gym  # noqa: E402

from envs.config import EnvConfig, Perturbation, RandomizationConfig, RewardConfig  # noqa: E402
from envs.core import RotateCupVec  # noqa: E402

ENV_ID = "RotateCup-v0"

__all__ = ["ENV_ID", "EnvConfig", "Perturbation", "RandomizationConfig", "RewardConfig", "RotateCupVec",
           "RotateCupEnv", "RotateCupVectorEnv"]


def __getattr__(name: str):
    # the gymnasium wrappers import lazily so that `import envs` stays light
    if name == "RotateCupEnv":
        from envs.rotate_cup import RotateCupEnv

        return RotateCupEnv
    if name == "RotateCupVectorEnv":
        from envs.vector import RotateCupVectorEnv

        return RotateCupVectorEnv
    raise AttributeError(name)


if ENV_ID not in gym.registry:
    gym.register(
        id=ENV_ID,
        entry_point="envs.rotate_cup:RotateCupEnv",
        vector_entry_point="envs.vector:RotateCupVectorEnv",
        max_episode_steps=None,  # the env truncates itself at EnvConfig.episode_steps
    )
