"""Proprioceptive observation builder, shared by the simulated env and the deploy runtime.

Per step, 32 numbers (Hora): the 16 joint positions scaled to [-1, 1] by the joint limits, then the 16 current
joint targets in radians. The policy reads the last 3 steps (`proprio`, (3, 32)); the adaptation module reads the
last 30 (`proprio_hist`, (30, 32)). At reset the whole history is filled with the reset pose (positions as both q
and target).
"""

from __future__ import annotations

import numpy as np

from envs import constants as C
from envs.task import proprio_frame


class ProprioHistory:
    """A (N, 30, 32) history of proprioceptive frames, newest last."""

    def __init__(self, num_envs: int, steps: int = C.HISTORY_STEPS):
        self.buf = np.zeros((num_envs, steps, C.PROPRIO_DIM), dtype=np.float32)

    @staticmethod
    def frame(q: np.ndarray, targets: np.ndarray) -> np.ndarray:
        """(N, 16) joint positions and targets (rad) -> (N, 32) frame."""
        return proprio_frame(np, q, targets, C.JOINT_LOWER, C.JOINT_UPPER).astype(np.float32)  # envs.task

    def reset(self, ids: np.ndarray, q: np.ndarray) -> None:
        """Fill the history of envs ``ids`` with the pose ``q`` (len(ids), 16)."""
        self.buf[ids] = self.frame(q, q)[:, None, :]

    def push(self, q: np.ndarray, targets: np.ndarray) -> None:
        """Append one frame for every env: (N, 16) positions (noisy, rad) and targets (rad)."""
        self.buf[:, :-1] = self.buf[:, 1:]
        self.buf[:, -1] = self.frame(q, targets)

    @property
    def proprio(self) -> np.ndarray:
        """(N, 3, 32) copy of the last 3 frames."""
        return self.buf[:, -C.PROPRIO_STEPS :].copy()

    @property
    def history(self) -> np.ndarray:
        """(N, 30, 32) copy of the whole history."""
        return self.buf.copy()
