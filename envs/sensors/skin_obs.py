"""The env's Xela skin: per-env skin state, the `skin` observation group and the per-pad force labels.

With ``EnvConfig.skin`` (on the Xela hand) the core feeds :class:`SkinState` from the pad sensors' history after
every policy step: each physics substep is one 100 Hz skin sample (envs.sensors.xela.SAMPLE_HZ), turned into raw
counts by the reading model (envs.sensors.xela.XelaSkin). The observation's ``skin`` entry is the Sparsh-skin window
(docs/reference/sparsh.md), the last ``WINDOW`` samples, oldest first::

    obs["skin"]    # (N, 10, 368, 6) float32: [..., :3] raw counts (X, Y, Z, around 32768),
                   #                          [..., 3:] taxel positions (m, hand frame) at the same sample

``last_*`` hold every sample of the last policy step (what sessions store) and ``pad_force`` the per-pad contact
force label. Costs nothing when the skin is off: the core then has no SkinState at all.
"""

from __future__ import annotations

from typing import Any

import gymnasium as gym
import numpy as np

from envs.rng import splitmix64
from envs.sensors.xela import DEFAULT_MODEL, NUM_PADS, NUM_TAXELS, WINDOW, XelaModel, XelaSkin, pad_load
from envs.sensors.xela_hand import PadContacts, XelaReadout

CHANNELS = 6
"""Channels per taxel in the `skin` observation: 3 raw counts + 3 position (m)."""


def skin_space() -> gym.spaces.Box:
    """Observation space of one env's `skin` group."""
    return gym.spaces.Box(-np.inf, np.inf, (WINDOW, NUM_TAXELS, CHANNELS), np.float32)


def episode_key(env_key: np.ndarray, episode: np.ndarray) -> np.ndarray:
    """Skin key of each env's episode (uint64), from its env key and episode counter (as the Digit 360 noise)."""
    with np.errstate(over="ignore"):
        return splitmix64(np.asarray(env_key, np.uint64) ^ splitmix64(np.asarray(episode, np.int64).astype(np.uint64)
                                                                        + np.uint64(0x5BD1E995)))


class SkinState:
    """Skin readings of N envs: the reading model, a window ring and the last policy step's samples."""

    def __init__(self, model: Any, num_envs: int, dt: float, substeps: int, xela: XelaModel = DEFAULT_MODEL):
        self.readout = XelaReadout(model)
        self.substeps = int(substeps)
        n = int(num_envs)
        self.skin = XelaSkin(n, dt, xela)
        self.window = np.zeros((n, WINDOW, NUM_TAXELS, CHANNELS), np.float32)
        """(N, WINDOW, 368, 6) the `skin` observation, oldest first."""
        self.last_times = np.zeros((n, self.substeps))
        """(N, S) sample times of the last step's substeps (s since each env's reset)."""
        self.last_counts = np.zeros((n, self.substeps, NUM_TAXELS, 3), np.float32)
        """(N, S, 368, 3) raw counts of the last step's samples."""
        self.last_pos = np.zeros((n, self.substeps, NUM_TAXELS, 3), np.float32)
        """(N, S, 368, 3) taxel positions (m, hand frame) at those samples."""
        self.last_force = np.zeros((n, self.substeps, NUM_PADS, 3), np.float32)
        """(N, S, 18, 3) per-pad label [normal, shear x, shear y] (N, pad frame) at those samples."""

    @property
    def pad_force(self) -> np.ndarray:
        """(N, 18, 3) per-pad contact force label of the latest sample."""
        return self.last_force[:, -1]

    def _samples(self, c: PadContacts) -> tuple[np.ndarray, np.ndarray]:
        """Advance the skins through the S samples of ``c``; returns counts and taxel positions (N, S, 368, 3)."""
        load = pad_load(c.points, c.forces, c.found, self.skin.model)  # (N, S, T, 3)
        counts = self.skin.run(load)
        return counts, c.taxel_pos().astype(np.float32)

    def reset(self, ids: np.ndarray, sensordata: np.ndarray, env_keys: np.ndarray, episodes: np.ndarray) -> None:
        """Start envs ``ids`` on new episodes: the skins start under the reset's load (as if it had been held), and
        that reading fills the window."""
        c = self.readout.read_current(sensordata[ids])
        load = pad_load(c.points, c.forces, c.found, self.skin.model)[:, 0]  # (k, T, 3)
        self.skin.reset(ids, episode_key(env_keys, episodes), load)
        sub = self.skin.sample(load, ids)
        pos = c.taxel_pos()[:, 0].astype(np.float32)
        self.window[ids] = np.concatenate([sub, pos], axis=-1)[:, None]
        self.last_times[ids] = 0.0
        self.last_counts[ids] = sub[:, None]
        self.last_pos[ids] = pos[:, None]
        self.last_force[ids] = c.pad_force()[:, :1].astype(np.float32)

    def push(self, history: np.ndarray) -> None:
        """Read every env's last ``substeps`` samples from the batch's ``history`` (N, nhistory)."""
        c = self.readout.read(history, self.substeps)
        counts, pos = self._samples(c)
        new = np.concatenate([counts, pos], axis=-1)  # (N, S, T, 6)
        s = min(self.substeps, WINDOW)
        self.window = np.concatenate([self.window[:, s:], new[:, -s:]], axis=1)
        self.last_times, self.last_counts, self.last_pos = c.times, counts, pos
        self.last_force = c.pad_force().astype(np.float32)

    def observe(self) -> np.ndarray:
        return self.window.copy()
