"""The batched core as a stable-baselines3 VecEnv (lives here because SB3 imports torch; envs never does).

Auto-reset follows SB3's contract: a finished env is reset in the same step, its last observation goes to
`infos[i]["terminal_observation"]`, and a time-limit end sets `infos[i]["TimeLimit.truncated"]` so PPO bootstraps
it. Per-episode statistics (return, length, each reward term, rotation) are reported in `infos[i]["episode"]` when
an episode ends, which SB3's logger and the training callbacks read.

With ``latent_mix`` > 0 every observation also carries the training-only group ``latent_mix`` (N, 1): a weight drawn
when each episode starts, 0 with probability 1 - latent_mix and uniform in [0, 1] otherwise, which
rotation.policy.features.LatentMixExtractor blends the teacher's latent in with.
"""

from __future__ import annotations

from typing import Any

import numpy as np
from gymnasium import spaces
from stable_baselines3.common.vec_env.base_vec_env import VecEnv

from envs.config import EnvConfig
from envs.core import RotateCupVec
from envs.metrics import UPRIGHT_TILT
from rotation.policy.features import LATENT_MIX_GROUP


class RotateCupSB3VecEnv(VecEnv):
    """SB3 view of a :class:`RotateCupVec`; ``reward_scale`` multiplies rewards seen by the learner only."""

    def __init__(self, cfg: EnvConfig, num_envs: int, seed: int = 0, nthread: int | None = None,
                 reward_scale: float = 1.0, obs_groups: tuple[str, ...] | None = None, latent_mix: float = 0.0):
        self.core = RotateCupVec(cfg, num_envs=num_envs, seed=seed, nthread=nthread)
        space = self.core.single_observation_space
        # only the groups the learner reads: PPO's rollout buffer copies every group of every transition, and the
        # teacher's unused 30-step history (960 numbers) would be 90% of that traffic
        self.obs_groups = tuple(space.spaces) if obs_groups is None else tuple(obs_groups)
        unknown = sorted(set(self.obs_groups) - set(space.spaces))
        if unknown or not self.obs_groups:
            raise ValueError(f"obs_groups must name some of the env's groups {sorted(space.spaces)}, got "
                             f"{list(self.obs_groups)}")
        if not 0.0 <= latent_mix <= 1.0:
            raise ValueError(f"latent_mix is a probability in [0, 1], got {latent_mix}")
        self.latent_mix = float(latent_mix)
        groups = {k: space.spaces[k] for k in self.obs_groups}
        if self.latent_mix > 0:
            groups[LATENT_MIX_GROUP] = spaces.Box(0.0, 1.0, (1,), np.float32)
        self._mix_rng = np.random.default_rng([seed, 0x5EED])  # its own stream: the env's episodes stay the same
        self._mix = np.zeros((num_envs, 1), np.float32)
        space = spaces.Dict(groups)
        super().__init__(num_envs, space, self.core.single_action_space)
        self.reward_scale = float(reward_scale)
        self._seed = seed
        self._actions: np.ndarray | None = None
        self._ep_return = np.zeros(num_envs)
        self._ep_terms: dict[str, np.ndarray] = {}
        self._ep_rotation = np.zeros(num_envs)
        self._ep_upright = np.zeros(num_envs)

    # -- VecEnv API
    def reset(self):
        seed = self._seed if self._seed is not None else None
        self._seed = None  # later resets continue the episode counters
        self._draw_mix(np.arange(self.num_envs))
        obs = self._select(self.core.reset(seed=seed))
        self._ep_return[:] = 0
        self._ep_rotation[:] = 0
        self._ep_upright[:] = 0
        self._ep_terms = {}
        return obs

    def step_async(self, actions: np.ndarray) -> None:
        self._actions = np.asarray(actions)

    def step_wait(self):
        assert self._actions is not None, "step_async must come first"
        obs, reward, terminated, truncated, info = self.core.step(self._actions)
        obs = self._select(obs)
        self._ep_return += reward
        self._ep_rotation += info["rotation"]
        self._ep_upright += (info["tilt"] < UPRIGHT_TILT) & ~info["fell"]
        for k, v in info.items():
            if k.startswith("rew_"):
                self._ep_terms.setdefault(k, np.zeros(self.num_envs))
                self._ep_terms[k] += v
        done = terminated | truncated
        infos: list[dict[str, Any]] = [{} for _ in range(self.num_envs)]
        ids = np.flatnonzero(done)
        if len(ids):
            for i in ids:
                steps = int(info["elapsed_steps"][i])
                ep = {"r": float(self._ep_return[i]), "l": steps,
                      "rotation": float(self._ep_rotation[i]),
                      "rotation_rate": float(self._ep_rotation[i] / (steps * self.core.cfg.control_dt)),
                      "ttf": steps / self.core.cfg.episode_steps if terminated[i] else 1.0,
                      "upright": float(self._ep_upright[i] / steps)}
                ep.update({k: float(v[i]) for k, v in self._ep_terms.items()})
                infos[i] = {"terminal_observation": {k: v[i].copy() for k, v in obs.items()},
                            "TimeLimit.truncated": bool(truncated[i] and not terminated[i]), "episode": ep}
            self._ep_return[ids] = 0
            self._ep_rotation[ids] = 0
            self._ep_upright[ids] = 0
            for v in self._ep_terms.values():
                v[ids] = 0
            self.core._reset_ids(ids)
            self._draw_mix(ids)
            obs = self._select(self.core._observe())
        return obs, (reward * self.reward_scale).astype(np.float32), done, infos

    def _select(self, obs: dict[str, np.ndarray]) -> dict[str, np.ndarray]:
        out = {k: obs[k] for k in self.obs_groups}
        if self.latent_mix > 0:
            out[LATENT_MIX_GROUP] = self._mix.copy()
        return out

    def _draw_mix(self, ids: np.ndarray) -> None:
        """A new teacher-latent weight for the episodes starting in envs ``ids`` (0 unless latent_mix > 0)."""
        if self.latent_mix > 0 and len(ids):
            mixed = self._mix_rng.random(len(ids)) < self.latent_mix
            self._mix[ids, 0] = np.where(mixed, self._mix_rng.random(len(ids)), 0.0)

    def close(self) -> None:
        self.core.close()

    def seed(self, seed: int | None = None):
        self._seed = seed
        return [None if seed is None else seed + i for i in range(self.num_envs)]

    def get_attr(self, attr_name: str, indices=None):
        return [getattr(self.core, attr_name) for _ in self._indices(indices)]

    def set_attr(self, attr_name: str, value: Any, indices=None) -> None:
        setattr(self.core, attr_name, value)

    def env_method(self, method_name: str, *method_args, indices=None, **method_kwargs):
        return [getattr(self.core, method_name)(*method_args, **method_kwargs) for _ in self._indices(indices)]

    def env_is_wrapped(self, wrapper_class, indices=None):
        return [False for _ in self._indices(indices)]

    def _indices(self, indices) -> list[int]:
        if indices is None:
            return list(range(self.num_envs))
        if isinstance(indices, int):
            return [indices]
        return list(indices)
