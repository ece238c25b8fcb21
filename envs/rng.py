"""Counter-based random numbers: per-env streams that do not depend on the batch size.

Env i of a batch draws from a stream keyed by its own 64-bit key, an episode counter, a step counter and a
stream id, hashed with splitmix64. The draws are vectorized over envs (no per-env Python loop) and env i of a
batch seeded s draws exactly what a single env seeded s + i draws.
"""

from __future__ import annotations

import numpy as np

_GOLDEN = np.uint64(0x9E3779B97F4A7C15)
_M1 = np.uint64(0xBF58476D1CE4E5B9)
_M2 = np.uint64(0x94D049BB133111EB)


def splitmix64(x: np.ndarray) -> np.ndarray:
    """The splitmix64 finalizer on a uint64 array (wrapping arithmetic)."""
    with np.errstate(over="ignore"):
        z = x + _GOLDEN
        z = (z ^ (z >> np.uint64(30))) * _M1
        z = (z ^ (z >> np.uint64(27))) * _M2
        return z ^ (z >> np.uint64(31))


def env_keys(seed: int, num_envs: int) -> np.ndarray:
    """Keys of envs seed, seed+1, ... (uint64, (num_envs,)); seeds count modulo 2**64 (envs.validation.MAX_SEED)."""
    with np.errstate(over="ignore"):
        seeds = np.uint64(int(seed) % 2**64) + np.arange(num_envs, dtype=np.uint64)  # wraps past 2**64 - 1
    return splitmix64(splitmix64(seeds))


class CounterRNG:
    """Vectorized uniform / normal draws keyed by (env key, episode, step, stream)."""

    def __init__(self, keys: np.ndarray):
        self.keys = keys.astype(np.uint64)

    def uniform(self, ids: np.ndarray, episode: np.ndarray, step: np.ndarray, stream: int, size: int) -> np.ndarray:
        """(len(ids), size) floats in [0, 1)."""
        with np.errstate(over="ignore"):
            counter = (episode.astype(np.uint64) << np.uint64(32)) ^ step.astype(np.uint64)
            base = splitmix64(self.keys[ids] ^ splitmix64(counter * _M1 + np.uint64(stream) * _GOLDEN))  # (n,)
            x = splitmix64(base[:, None] + np.arange(1, size + 1, dtype=np.uint64)[None, :] * _GOLDEN)  # (n, size)
        return (x >> np.uint64(11)).astype(np.float64) * (1.0 / 9007199254740992.0)

    def normal(self, ids: np.ndarray, episode: np.ndarray, step: np.ndarray, stream: int, size: int) -> np.ndarray:
        """(len(ids), size) standard normal draws (Box-Muller)."""
        u = self.uniform(ids, episode, step, stream, 2 * size)
        u1, u2 = 1.0 - u[:, :size], u[:, size:]
        return np.sqrt(-2.0 * np.log(u1)) * np.cos(2.0 * np.pi * u2)
