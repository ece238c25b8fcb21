"""The Warp core as a gymnasium vector env: ``gymnasium.make_vec("rotation.sim_warp:RotateCupWarp-v0",
num_envs=N, vectorization_mode="vector_entry_point", device="cuda")``.

Observations, rewards and flags are torch tensors on the device (not numpy arrays: copying thousands of worlds'
observations to the host every step is what this backend exists to avoid). Finished worlds are reset in the same
step on the device (AutoresetMode.SAME_STEP): the returned observation is the first of the new episode, and
``info["final_obs"]`` / ``info["final_info"]`` hold the last ones of the finished episode.
"""

from __future__ import annotations

from typing import Any

import gymnasium as gym
from gymnasium.vector import AutoresetMode

from envs.config import EnvConfig
from envs.rotate_cup import config_from_kwargs, fresh_seed
from envs.validation import check_seed
from rotation.sim_warp.core import RotateCupWarp, WarpConfig


class RotateCupWarpVectorEnv(gym.vector.VectorEnv):
    """RotateCup-v0 on MuJoCo Warp, N worlds; keyword arguments other than ``device`` reach EnvConfig."""

    metadata = {"autoreset_mode": AutoresetMode.SAME_STEP, "render_modes": []}

    def __init__(self, num_envs: int = 1, cfg: EnvConfig | None = None, device: str = "cuda", **kwargs: Any):
        self.cfg = config_from_kwargs(cfg, **kwargs)
        self.core = RotateCupWarp(self.cfg, num_envs=num_envs, seed=0, warp_cfg=WarpConfig(device=device))
        self._seeded = False
        self.num_envs = num_envs
        self.device = self.core.torch_device
        self.single_observation_space = self.core.single_observation_space
        self.single_action_space = self.core.single_action_space
        self.observation_space = gym.vector.utils.batch_space(self.single_observation_space, num_envs)
        self.action_space = gym.vector.utils.batch_space(self.single_action_space, num_envs)

    def reset(self, *, seed: int | None = None, options: dict | None = None):
        """Seeded: world i starts the episodes of a CPU env seeded seed + i. Unseeded: the next episodes; the first
        reset draws its seed from the OS's entropy."""
        if seed is not None:
            seed = check_seed("seed", seed)
        elif not self._seeded:
            seed = fresh_seed()
        self._seeded = True
        return self.core.reset(seed=seed), {}

    def step(self, actions):
        obs, reward, terminated, truncated, info = self.core.step(actions)
        done = terminated | truncated
        final_obs = {k: v.clone() for k, v in obs.items()}
        final_info = {k: v.clone() for k, v in info.items()}
        self.core.reset_done(done)  # on the device, whether or not any world finished (no host wait)
        obs = self.core._observe()
        info = dict(info, final_obs=final_obs, final_info=final_info, _final_obs=done)
        return obs, reward, terminated, truncated, info

    def close_extras(self, **kwargs: Any) -> None:
        self.core.close()


def _single_env(**kwargs: Any):
    raise ValueError("RotateCupWarp-v0 is batched: use gymnasium.make_vec(\"rotation.sim_warp:RotateCupWarp-v0\", "
                     "num_envs=N, vectorization_mode=\"vector_entry_point\")")


__all__ = ["RotateCupWarpVectorEnv"]
