"""The batched core as a gymnasium vector env (same-step auto-reset, one core, no per-env loop)."""

from __future__ import annotations

from typing import Any

import gymnasium as gym
import numpy as np
from gymnasium.vector import AutoresetMode

from envs.config import EnvConfig
from envs.core import RotateCupVec
from envs.rotate_cup import config_from_kwargs, fresh_seed
from envs.validation import check_seed


class RotateCupVectorEnv(gym.vector.VectorEnv):
    """`gymnasium.make_vec("envs:RotateCup-v0", num_envs=N, vectorization_mode="vector_entry_point")`.

    Finished envs are reset in the same step (AutoresetMode.SAME_STEP): the returned observation is the first of
    the new episode, and `info["final_obs"]` / `info["final_info"]` hold the last ones of the finished episode.
    """

    metadata = {"autoreset_mode": AutoresetMode.SAME_STEP, "render_modes": []}

    def __init__(self, num_envs: int = 1, cfg: EnvConfig | None = None, nthread: int | None = None, **kwargs: Any):
        self.cfg = config_from_kwargs(cfg, **kwargs)
        self.core = RotateCupVec(self.cfg, num_envs=num_envs, seed=0, nthread=nthread)
        self._seeded = False  # the first reset without a seed draws fresh entropy (gymnasium's convention)
        self.num_envs = num_envs
        self.single_observation_space = self.core.single_observation_space
        self.single_action_space = self.core.single_action_space
        self.observation_space = gym.vector.utils.batch_space(self.single_observation_space, num_envs)
        self.action_space = gym.vector.utils.batch_space(self.single_action_space, num_envs)

    def reset(self, *, seed: int | None = None, options: dict | None = None):
        """Seeded: env i starts the episodes of a single env seeded seed + i. Unseeded: the next episodes; the first
        reset of a fresh vector env draws its seed from the OS's entropy."""
        if seed is not None:
            seed = check_seed("seed", seed)
        elif not self._seeded:
            seed = fresh_seed()
        self._seeded = True
        return self.core.reset(seed=seed), {}

    def step(self, actions):
        obs, reward, terminated, truncated, info = self.core.step(np.asarray(actions))
        done = np.flatnonzero(terminated | truncated)
        if len(done):
            final_obs = {k: v.copy() for k, v in obs.items()}
            final_info = {k: v.copy() for k, v in info.items()}
            self.core._reset_ids(done)
            fresh = self.core._observe()
            for k in obs:
                obs[k][done] = fresh[k][done]
            info = dict(info, final_obs=final_obs, final_info=final_info, _final_obs=terminated | truncated)
        return obs, reward, terminated, truncated, info

    def close_extras(self, **kwargs: Any) -> None:
        self.core.close()
