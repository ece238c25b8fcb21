"""The Xela skin of a held-hand scene (envs.held_hand with a Xela hand): the pads' contacts sampled at the skin's
100 Hz from MuJoCo's contact sensors, through the same reading model as the rotation env's skin
(envs.sensors.xela.XelaSkin, keyed per episode), into the Sparsh-skin window a policy reads and the samples a
demonstration records.

    skin = SkinHistory(model, key, dt=0.002)
    skin.reset(data)                     # the skin starts under the grasp's load, which fills the window
    run.run(steps, wrist, skin.on_step)  # one 100 Hz sample every 1 / (100 dt) physics steps
    skin.window                          # (10, 368, 6): raw counts (X, Y, Z) and taxel positions (m), oldest first
    skin.drain()                         # the samples since the last drain: times (S,), counts and positions
"""

from __future__ import annotations

import mujoco
import numpy as np

from envs.sensors.xela import DEFAULT_MODEL, NUM_TAXELS, REST, SAMPLE_HZ, WINDOW, XelaModel, XelaSkin, pad_load
from envs.sensors.xela_hand import XelaReadout


class SkinHistory:
    """One hand's skin, sampled every ``1 / (SAMPLE_HZ dt)`` physics steps of ``dt`` seconds (see the module
    docstring); ``key`` (uint64) keys its gains, offsets, noise and drift, as a collected session's ``skin_key``."""

    def __init__(self, model: mujoco.MjModel, key: int, dt: float, xela: XelaModel = DEFAULT_MODEL) -> None:
        every = 1.0 / (SAMPLE_HZ * float(dt))
        if abs(every - round(every)) > 1e-9 or round(every) < 1:
            raise ValueError(f"SkinHistory: the physics step {dt} s must divide the skin's {1 / SAMPLE_HZ} s period")
        self.readout = XelaReadout(model)
        self.every, self.key = int(round(every)), int(key)
        self.skin = XelaSkin(1, 1.0 / SAMPLE_HZ, xela)
        self.window = np.zeros((WINDOW, NUM_TAXELS, 6), np.float32)
        """(10, 368, 6) the Sparsh-skin window: raw counts and taxel positions (hand frame), oldest first."""
        self._steps = 0
        self._times: list[float] = []
        self._counts: list[np.ndarray] = []
        self._pos: list[np.ndarray] = []

    @property
    def baseline(self) -> np.ndarray:
        """(368, 3) the reading without load, drift or noise: what a recorded session of this skin key gets as its
        baseline (rotation.data.skin.session_baseline), which the encoder subtracts."""
        return (REST + self.skin.offset[0]).astype(np.float32)

    def _read(self, data: mujoco.MjData) -> tuple[np.ndarray, np.ndarray]:
        """(1, 368, 3) load (counts before gains) and (368, 3) taxel positions of the pads' current contacts."""
        c = self.readout.read_current(np.asarray(data.sensordata)[None])
        return pad_load(c.points, c.forces, c.found, self.skin.model)[:, 0], c.taxel_pos()[0, 0].astype(np.float32)

    def reset(self, data: mujoco.MjData) -> None:
        """A new episode: the skin starts under the current load (as if held), its first reading fills the window
        and is the first recorded sample (at the data's time)."""
        load, pos = self._read(data)
        ids = np.array([0])
        self.skin.reset(ids, np.array([self.key], dtype=np.uint64), load)
        counts = self.skin.sample(load, ids)[0]
        self.window[:] = np.concatenate([counts, pos], axis=-1)[None]
        self._steps = 0
        self._times, self._counts, self._pos = [float(data.time)], [counts], [pos]

    def on_step(self, data: mujoco.MjData) -> None:
        """After each physics step: a skin sample when one is due."""
        self._steps += 1
        if self._steps % self.every:
            return
        load, pos = self._read(data)
        counts = self.skin.sample(load)[0]
        self.window = np.concatenate([self.window[1:], np.concatenate([counts, pos], axis=-1)[None]])
        self._times.append(float(data.time))
        self._counts.append(counts)
        self._pos.append(pos)

    def drain(self) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """The samples since the last drain (or reset): times (S,) s, raw counts (S, 368, 3), positions (S, 368, 3)."""
        out = (np.asarray(self._times, np.float64),
               np.asarray(self._counts, np.float32).reshape(-1, NUM_TAXELS, 3),
               np.asarray(self._pos, np.float32).reshape(-1, NUM_TAXELS, 3))
        self._times, self._counts, self._pos = [], [], []
        return out
