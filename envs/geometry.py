"""Small geometric helpers shared by the task, the grasp generator and evaluation (numpy, no MuJoCo)."""

from __future__ import annotations

import numpy as np


def tilt_angle(quat: np.ndarray) -> np.ndarray:
    """Angle (rad, (...,)) between the object's body z axis and the world vertical, from (..., 4) (w, x, y, z)
    quaternions. The body z axis is the cup's axis and, for Hora's cylinders (axis along body y), the vertical
    that they rotate about, so 0 means upright for every object."""
    x, y = quat[..., 1], quat[..., 2]
    cos = 1.0 - 2.0 * (x * x + y * y) / np.maximum(np.sum(quat * quat, axis=-1), 1e-12)  # R[2, 2]
    return np.arccos(np.clip(cos, -1.0, 1.0))
