"""Small geometric helpers shared by the task, the grasp generator and evaluation (no MuJoCo).

Each takes the array namespace as ``xp`` (numpy by default; the MuJoCo Warp backend passes ``torch``), using only
operations both provide under the same names, so the CPU and GPU backends measure the object the same way.
"""

from __future__ import annotations

from types import ModuleType
from typing import Any

import numpy as np


def quat_mul(a: Any, b: Any, xp: ModuleType = np) -> Any:
    """Hamilton product of (..., 4) quaternions in MuJoCo's (w, x, y, z) order."""
    w1, x1, y1, z1 = a[..., 0], a[..., 1], a[..., 2], a[..., 3]
    w2, x2, y2, z2 = b[..., 0], b[..., 1], b[..., 2], b[..., 3]
    return xp.stack(
        [
            w1 * w2 - x1 * x2 - y1 * y2 - z1 * z2,
            w1 * x2 + x1 * w2 + y1 * z2 - z1 * y2,
            w1 * y2 - x1 * z2 + y1 * w2 + z1 * x2,
            w1 * z2 + x1 * y2 - y1 * x2 + z1 * w2,
        ],
        axis=-1,
    )


def angular_velocity(q0: Any, q1: Any, dt: float, xp: ModuleType = np) -> Any:
    """World-frame angular velocity (rad/s, (..., 3)) taking orientation q0 to q1 in dt seconds."""
    conj = xp.concatenate([q0[..., :1], -q0[..., 1:]], axis=-1)  # (..., 4)
    rel = quat_mul(q1, conj, xp)  # (..., 4), q1 * conj(q0)
    rel = xp.where(rel[..., :1] < 0, -rel, rel)  # shortest arc
    vec = rel[..., 1:]
    s = xp.sqrt((vec * vec).sum(-1))[..., None]  # (..., 1), |vec|
    factor = xp.where(s > 1e-9, 2.0 * xp.arctan2(s, rel[..., :1]) / xp.clip(s, 1e-12, None), 2.0)
    return vec * factor / dt


def tilt_angle(quat: Any, xp: ModuleType = np) -> Any:
    """Angle (rad, (...,)) between the object's body z axis and the world vertical, from (..., 4) (w, x, y, z)
    quaternions. The body z axis is the cup's axis and, for Hora's cylinders (axis along body y), the vertical
    that they rotate about, so 0 means upright for every object."""
    x, y = quat[..., 1], quat[..., 2]
    cos = 1.0 - 2.0 * (x * x + y * y) / xp.clip((quat * quat).sum(-1), 1e-12, None)  # R[2, 2]
    return xp.arccos(xp.clip(cos, -1.0, 1.0))
