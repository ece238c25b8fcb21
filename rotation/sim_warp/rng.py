"""envs.rng's counter-based streams on torch tensors (int64 with wrapping arithmetic), on any device.

The draws are bit-identical to envs.rng.CounterRNG: env i of a Warp batch seeded s draws exactly what env i of a
CPU batch seeded s draws (its parameters, grasp, pushes and observation noise), which is what lets the two
backends be compared from identical states (tests/sim_warp). torch has no full uint64 arithmetic, so the 64-bit
hash runs on int64: addition and multiplication wrap the same way in two's complement, and the right shifts are
made logical with a mask.
"""

from __future__ import annotations

import numpy as np
import torch

from envs import rng as cpu_rng


def _signed(x: int) -> int:
    """A uint64 constant as the int64 with the same bits."""
    x %= 1 << 64
    return x - (1 << 64) if x >= 1 << 63 else x


_GOLDEN = _signed(int(cpu_rng._GOLDEN))
_M1 = _signed(int(cpu_rng._M1))
_M2 = _signed(int(cpu_rng._M2))


def _shr(z: torch.Tensor, k: int) -> torch.Tensor:
    """Logical right shift of int64 bits."""
    return (z >> k) & ((1 << (64 - k)) - 1)


def splitmix64(x: torch.Tensor) -> torch.Tensor:
    """envs.rng.splitmix64 on int64 tensors holding uint64 bits."""
    z = x + _GOLDEN
    z = (z ^ _shr(z, 30)) * _M1
    z = (z ^ _shr(z, 27)) * _M2
    return z ^ _shr(z, 31)


def env_keys(seed: int, num_envs: int, device: torch.device | str) -> torch.Tensor:
    """envs.rng.env_keys as an int64 tensor (same bits) on ``device``."""
    keys = cpu_rng.env_keys(seed, num_envs)  # (num_envs,) uint64, host
    return torch.from_numpy(keys.view(np.int64).copy()).to(device)


class TorchCounterRNG:
    """Vectorized uniform / normal draws keyed by (env key, episode, step, stream), like envs.rng.CounterRNG, but
    always for every env at once (the Warp core masks instead of indexing, so nothing waits for the host)."""

    def __init__(self, keys: torch.Tensor):
        self.keys = keys

    def uniform(self, episode: torch.Tensor, step: torch.Tensor, stream: int, size: int) -> torch.Tensor:
        """(N, size) float64 in [0, 1)."""
        counter = (episode << 32) ^ step  # (N,) int64
        salt = _signed(stream * int(cpu_rng._GOLDEN))
        base = splitmix64(self.keys ^ splitmix64(counter * _M1 + salt))  # (N,)
        offsets = torch.arange(1, size + 1, dtype=torch.int64, device=self.keys.device) * _GOLDEN  # (size,)
        x = splitmix64(base[:, None] + offsets[None, :])  # (N, size)
        return _shr(x, 11).to(torch.float64) * (1.0 / 9007199254740992.0)

    def normal(self, episode: torch.Tensor, step: torch.Tensor, stream: int, size: int) -> torch.Tensor:
        """(N, size) standard normal draws (Box-Muller), float64."""
        u = self.uniform(episode, step, stream, 2 * size)
        u1, u2 = 1.0 - u[:, :size], u[:, size:]
        return torch.sqrt(-2.0 * torch.log(u1)) * torch.cos(2.0 * np.pi * u2)
