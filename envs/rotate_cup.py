"""RotateCup-v0 as a gymnasium env: the batched core with N = 1."""

from __future__ import annotations

import dataclasses
from typing import Any

import gymnasium as gym
import numpy as np

from envs.config import EnvConfig, Perturbation, RandomizationConfig, RewardConfig
from envs.core import RotateCupVec
from envs.validation import check_seed


def config_from_kwargs(cfg: EnvConfig | None = None, **kwargs: Any) -> EnvConfig:
    """Build an EnvConfig from keyword arguments; nested configs may be given as dicts. Unknown keys -> ValueError."""
    if cfg is not None and kwargs:
        return dataclasses.replace(cfg, **_nested(kwargs))
    if cfg is not None:
        return cfg
    return EnvConfig(**_nested(kwargs))


def fresh_seed() -> int:
    """A seed drawn from the OS's entropy (gymnasium's rule for the first reset without a seed)."""
    return int(np.random.SeedSequence().entropy) % 2**64


def _nested(kwargs: dict[str, Any]) -> dict[str, Any]:
    names = {f.name for f in dataclasses.fields(EnvConfig)}
    unknown = set(kwargs) - names
    if unknown:
        raise ValueError(f"unknown RotateCup option(s) {sorted(unknown)}; known: {sorted(names)}")
    out = dict(kwargs)
    for key, cls in (("randomization", RandomizationConfig), ("reward", RewardConfig), ("perturb", Perturbation)):
        if isinstance(out.get(key), dict):
            known = {f.name for f in dataclasses.fields(cls)}
            unknown = set(out[key]) - known
            if unknown:  # the dataclass would raise a TypeError that names neither the option nor the choices
                raise ValueError(f"unknown RotateCup option(s) {sorted(f'{key}.{k}' for k in unknown)}; "
                                 f"known {key} options: {sorted(known)}")
            out[key] = cls(**out[key])
    return out


class RotateCupEnv(gym.Env):
    """Rotate the object about the vertical axis in a palm-up Allegro hand with Digit 360 fingertips.

    Observation: dict with `proprio` (3, 32), `proprio_hist` (30, 32), `priv` (9) (and `tactile` with touch on).
    Action: 16 numbers in [-1, 1]; joint targets move by action x action_scale rad, clamped to the joint limits.
    Reward terms, rotation this step (rad), height and other diagnostics are in `info`.
    """

    metadata = {"render_modes": ["rgb_array"], "render_fps": 20}

    def __init__(self, cfg: EnvConfig | None = None, render_mode: str | None = None, **kwargs: Any):
        self.cfg = config_from_kwargs(cfg, **kwargs)
        if render_mode not in (None, "rgb_array"):
            raise ValueError(f"render_mode must be None or 'rgb_array', got {render_mode!r}")
        self.render_mode = render_mode
        self.core = RotateCupVec(self.cfg, num_envs=1, seed=0, nthread=1)
        self._seeded = False  # the first reset without a seed draws fresh entropy (gymnasium's convention)
        self.observation_space = self.core.single_observation_space
        self.action_space = self.core.single_action_space
        self._renderer = None

    def reset(self, *, seed: int | None = None, options: dict | None = None):
        """Seeded: reproducible (the same episodes as env i of a batch seeded seed - i). Unseeded: the next episode
        of this env's stream, which the first reset of a fresh env draws from the OS's entropy, so separate
        instances (e.g. the copies in a SyncVectorEnv) differ."""
        if seed is not None:
            seed = check_seed("seed", seed)
        elif not self._seeded:
            seed = fresh_seed()
        super().reset(seed=seed)
        self._seeded = True
        obs = self.core.reset(seed=seed)
        return {k: v[0] for k, v in obs.items()}, {}

    def step(self, action):
        a = np.asarray(action, dtype=np.float64)
        if a.shape != self.action_space.shape:
            raise ValueError(f"action must have shape {self.action_space.shape}, got {a.shape}")
        obs, reward, terminated, truncated, info = self.core.step(a[None])
        return (
            {k: v[0] for k, v in obs.items()},
            float(reward[0]),
            bool(terminated[0]),
            bool(truncated[0]),
            {k: (v[0].item() if np.ndim(v[0]) == 0 else v[0]) for k, v in info.items()},
        )

    def render(self, camera: str = "front", width: int = 480, height: int = 480):
        if self.render_mode != "rgb_array":
            return None
        from envs.render import offscreen_renderer, render_frame

        if self._renderer is None:
            self._renderer = offscreen_renderer(self.core.model, height, width, "render()")
        return render_frame(self._renderer, self.core, 0, camera)

    def close(self):
        if self._renderer is not None:
            self._renderer.close()
            self._renderer = None
