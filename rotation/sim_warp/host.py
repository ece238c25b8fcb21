"""The Warp core behind the CPU core's numpy interface, and the one place that picks a backend.

:class:`HostView` makes a :class:`~rotation.sim_warp.core.RotateCupWarp` look like envs.core.RotateCupVec (numpy
in, numpy out), so code written for the CPU core (evaluation rollouts, student distillation) runs on either
backend unchanged. Each step copies the observations to the host: right for evaluation, not for training at scale
(the GPU PPO in rotation.train.teacher_warp reads the tensors on the device instead).
"""

from __future__ import annotations

from typing import Literal

import numpy as np
import torch

from envs.config import EnvConfig
from envs.core import RotateCupVec

Backend = Literal["cpu", "warp"]
BACKENDS: tuple[str, ...] = ("cpu", "warp")
BACKEND_HELP = ("physics backend: 'cpu' (MuJoCo on mujoco.batch threads, the default) or 'warp' (MuJoCo Warp: "
                "thousands of worlds on a GPU, or Warp's CPU device for tests; needs the [warp] extra). The "
                "simulated Digit 360 touch runs on the cpu backend only.")
"""One sentence for every --backend option's help."""


class HostView:
    """numpy view of a RotateCupWarp: ``reset(seed, ids)`` / ``step(actions)`` return numpy arrays, as
    envs.core.RotateCupVec does (rewards float64, flags bool, info as arrays)."""

    def __init__(self, core) -> None:
        self.core = core
        self.cfg = core.cfg
        self.num_envs = core.num_envs
        self.single_observation_space = core.single_observation_space
        self.single_action_space = core.single_action_space

    @staticmethod
    def _host(x):
        if isinstance(x, dict):
            return {k: HostView._host(v) for k, v in x.items()}
        return x.detach().cpu().numpy() if isinstance(x, torch.Tensor) else x

    def reset(self, seed: int | None = None, ids=None) -> dict[str, np.ndarray]:
        return self._host(self.core.reset(seed=seed, ids=ids))

    def _reset_ids(self, ids) -> None:
        self.core.reset(ids=ids)

    def _observe(self) -> dict[str, np.ndarray]:
        return self._host(self.core._observe())

    def step(self, actions):
        obs, reward, terminated, truncated, info = self.core.step(torch.as_tensor(np.asarray(actions)))
        return (self._host(obs), self._host(reward).astype(np.float64), self._host(terminated),
                self._host(truncated), self._host(info))

    @property
    def params(self) -> dict[str, np.ndarray]:
        return self._host(self.core.params)

    def close(self) -> None:
        self.core.close()


def make_vec(backend: str, cfg: EnvConfig, num_envs: int, seed: int = 0, nthread: int | None = None,
             device: str = "cuda"):
    """The batched env of ``backend`` with the numpy interface of envs.core.RotateCupVec.

    ``nthread`` is for the cpu backend (MuJoCo threads), ``device`` for the warp backend ('cuda' or 'cpu')."""
    if backend == "cpu":
        return RotateCupVec(cfg, num_envs=num_envs, seed=seed, nthread=nthread)
    if backend == "warp":
        from rotation.sim_warp.core import RotateCupWarp, WarpConfig

        return HostView(RotateCupWarp(cfg, num_envs=num_envs, seed=seed, warp_cfg=WarpConfig(device=device)))
    raise ValueError(f"backend: unknown backend {backend!r}; choose one of: {', '.join(BACKENDS)}")
