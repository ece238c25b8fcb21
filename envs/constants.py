"""Hand constants shared by simulation, training and hardware.

Everything here is in the Allegro bus order (index 0-3, middle 4-7, ring 8-11, thumb 12-15; each finger
[abduction, MCP, PIP, DIP]), in SI units. Sources: docs/reference/hora.md ("Allegro hand facts", "Timing and
actuation").
"""

from __future__ import annotations

import numpy as np

NUM_JOINTS = 16
FINGERS = ("index", "middle", "ring", "thumb")
"""Finger names in bus order; finger f owns joints 4f .. 4f+3."""

JOINT_NAMES = tuple(f"{finger}_{j}" for finger in FINGERS for j in range(4))
ACTUATOR_NAMES = tuple(f"act_{name}" for name in JOINT_NAMES)
FINGERTIP_SITES = tuple(f"{finger}_tip" for finger in FINGERS)
"""One site per Digit 360 fingertip, at the centre of the dome (sensor frame: z out of the dome)."""

# Joint limits (rad), public Allegro V4 description (docs/reference/hora.md).
_FINGER_LOWER = (-0.47, -0.196, -0.174, -0.227)
_FINGER_UPPER = (0.47, 1.61, 1.709, 1.618)
_THUMB_LOWER = (0.263, -0.105, -0.189, -0.162)
_THUMB_UPPER = (1.396, 1.163, 1.644, 1.719)
JOINT_LOWER = np.array(_FINGER_LOWER * 3 + _THUMB_LOWER, dtype=np.float64)
JOINT_UPPER = np.array(_FINGER_UPPER * 3 + _THUMB_UPPER, dtype=np.float64)

# The hand model every job uses unless told another (envs.scene.HANDS): the one the shipped policies trained on.
DEFAULT_HAND = "digit360_v4"

# Vendor home pose (deg -> rad), docs/reference/hora.md.
HOME_POSE = np.deg2rad([0, -10, 45, 45, 0, -10, 45, 45, 5, -5, 50, 45, 60, 25, 15, 45]).astype(np.float64)

# Host PD law of the real hand, normalized torque units = N m in simulation (docs/reference/hora.md).
DEFAULT_KP = 3.0
DEFAULT_KD = 0.1
DEFAULT_TORQUE_LIMIT = 0.5

# Per-joint torque limits of the real V4 hand (PWM limits / 1200), docs/reference/hardware.md section 1.
TORQUE_LIMITS = np.array([0.312, 0.562, 0.375, 0.237] * 3 + [0.438, 0.338, 0.225, 0.225], dtype=np.float64)

CONTROL_HZ = 20.0
"""Policy rate (Hora: 20 Hz)."""
ACTION_SCALE = 1.0 / 24.0
"""Relative target step per unit action (rad), Hora: target += action / 24."""
EPISODE_STEPS = 400
"""Policy steps per episode: 20 s at 20 Hz."""

PROPRIO_DIM = 2 * NUM_JOINTS
"""Per-step proprioception: 16 joint positions scaled to [-1, 1] + 16 targets (rad)."""
PROPRIO_STEPS = 3
HISTORY_STEPS = 30
PRIV_DIM = 9
PRIV_FIELDS = ("pos_x", "pos_y", "pos_z", "scale", "mass", "friction", "com_x", "com_y", "com_z")
"""Layout of the privileged vector (Hora): object position (3, m, hand frame), scale, mass (kg), friction,
CoM offset (3, m)."""


def scale_joints(q: np.ndarray) -> np.ndarray:
    """Joint positions (rad, ..., 16) -> [-1, 1] by the joint limits."""
    return 2.0 * (q - JOINT_LOWER) / (JOINT_UPPER - JOINT_LOWER) - 1.0


def unscale_joints(x: np.ndarray) -> np.ndarray:
    """Inverse of :func:`scale_joints`."""
    return JOINT_LOWER + (x + 1.0) * 0.5 * (JOINT_UPPER - JOINT_LOWER)
