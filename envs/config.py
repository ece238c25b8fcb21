"""Typed configs of the RotateCup task: physics timing, randomization, reward, perturbations.

Defaults follow Hora's recipe (reference/hora.md). Every config validates itself on construction and raises a
ValueError that names the field and the allowed values; nothing is clamped silently.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

from envs import constants as C
from envs.objects import OBJECTS


def _check_range(name: str, lo_hi: tuple[float, float], low: float = -math.inf, high: float = math.inf) -> None:
    allowed = f"a (low, high) pair with low <= high within [{low}, {high}]"
    try:
        lo, hi = (float(v) for v in lo_hi)
    except (TypeError, ValueError):  # not a pair of numbers: a scalar, one or three values, text
        raise ValueError(f"{name} must be {allowed}, got {lo_hi!r}") from None
    if not (math.isfinite(lo) and math.isfinite(hi)):
        raise ValueError(f"{name} must be finite, got {lo_hi!r}")
    if lo > hi:
        raise ValueError(f"{name} is inverted: low {lo} > high {hi}; expected {allowed}")
    if lo < low or hi > high:
        raise ValueError(f"{name}={lo_hi!r} is outside the allowed interval [{low}, {high}]")


@dataclass(frozen=True)
class RandomizationConfig:
    """Domain randomization (reference/hora.md "Domain randomization"). Ranges are (low, high), sampled uniformly."""

    enabled: bool = True
    """Master switch; when False every env uses the nominal values: the middle scale bucket without jitter, the
    middle of the mass and friction ranges, no CoM offset, the env's kp / kd, no observation noise, no pushes."""
    scales: tuple[float, ...] = (0.70, 0.72, 0.74, 0.76, 0.78, 0.80, 0.82, 0.84, 0.86)
    """Object scale buckets (Hora: 9 values 0.70..0.86), one picked per env at reset."""
    scale_jitter: float = 0.025
    """Uniform +- jitter added to the picked scale bucket."""
    mass: tuple[float, float] = (0.01, 0.25)
    """Object mass (kg)."""
    com: tuple[float, float] = (-0.01, 0.01)
    """Center-of-mass offset per axis (m) in the object frame."""
    friction: tuple[float, float] = (0.3, 3.0)
    """Sliding friction coefficient, the same on hand and object (Hora)."""
    kp: tuple[float, float] = (2.9, 3.1)
    """Per-joint proportional gain (N m / rad), resampled at every reset."""
    kd: tuple[float, float] = (0.09, 0.11)
    """Per-joint damping gain (N m s / rad), resampled at every reset."""
    joint_noise: float = 0.02
    """Joint observation noise, U(-x, x) rad per step."""
    push_prob: float = 0.25
    """Probability per policy step of a random push on the object."""
    push_scale: float = 2.0
    """Push force = N(0, 1) per axis x mass x this (N per kg)."""
    push_decay: float = 0.9
    """Push decay factor per 0.08 s (Hora)."""

    def __post_init__(self) -> None:
        if not self.scales:
            raise ValueError("randomization.scales must list at least one scale")
        if any(not (0.1 <= s <= 3.0) for s in self.scales):
            raise ValueError(f"randomization.scales must lie in [0.1, 3.0], got {self.scales!r}")
        if not (0.0 <= self.scale_jitter < min(self.scales)):
            raise ValueError(f"randomization.scale_jitter must be in [0, {min(self.scales)}), got {self.scale_jitter}")
        _check_range("randomization.mass", self.mass, low=1e-4)
        _check_range("randomization.com", self.com, low=-0.05, high=0.05)
        _check_range("randomization.friction", self.friction, low=0.01)
        _check_range("randomization.kp", self.kp, low=0.01)
        _check_range("randomization.kd", self.kd, low=0.0)
        for name in ("joint_noise", "push_scale"):
            if not (getattr(self, name) >= 0.0 and math.isfinite(getattr(self, name))):
                raise ValueError(f"randomization.{name} must be finite and >= 0, got {getattr(self, name)}")
        if not (0.0 <= self.push_prob <= 1.0):
            raise ValueError(f"randomization.push_prob must be in [0, 1], got {self.push_prob}")
        if not (0.0 <= self.push_decay <= 1.0):
            raise ValueError(f"randomization.push_decay must be in [0, 1], got {self.push_decay}")


@dataclass(frozen=True)
class RewardConfig:
    """Scales of Hora's reward terms (reference/hora.md "Reward"); each scaled term is reported in ``info``."""

    rotate: float = 1.0
    """Rotation about the commanded axis, clip(omega . axis, -rotate_clip, rotate_clip) (rad/s)."""
    rotate_clip: float = 0.5
    """Clip of the angular velocity term (rad/s)."""
    obj_linvel: float = -0.3
    """L1 norm of the object's linear velocity (m/s)."""
    pose_diff: float = -0.1
    """Squared distance of the joints from the episode's initial grasp (rad^2). Hora: -0.3; at that weight a finger
    gait costs more than it earns until it turns the object at about 0.2 rad/s, which a CPU-budget run (tens of
    millions of steps instead of 1.5 billion) did not get past: it learned to hold the object still."""
    torque: float = -0.1
    """Squared norm of the joint torques (N^2 m^2)."""
    work: float = -2.0
    """(tau . qdot)^2, the mechanical power penalty."""
    fall: float = -20.0
    """One-off reward when the object falls. Hora has none; without it, a CPU-budget teacher learned to drop the
    object early (every other term is a penalty, so ending the episode looked good): ttf fell from 0.7 to 0.2."""
    axis: tuple[float, float, float] = (0.0, 0.0, -1.0)
    """Commanded rotation axis in the world frame (Hora: -z, palm up)."""

    def __post_init__(self) -> None:
        if len(self.axis) != 3 or not math.isclose(math.hypot(*self.axis), 1.0, rel_tol=1e-6):
            raise ValueError(f"reward.axis must be a unit 3-vector, got {self.axis!r}")
        if not self.rotate_clip > 0:
            raise ValueError(f"reward.rotate_clip must be > 0, got {self.rotate_clip}")


@dataclass(frozen=True)
class Perturbation:
    """Evaluation perturbations applied on top of the randomized values (friction x, mass +, CoM +)."""

    friction_scale: float = 1.0
    """Multiplies the friction the env would otherwise use."""
    added_mass: float = 0.0
    """Added to the object mass (kg)."""
    com_shift: tuple[float, float, float] = (0.0, 0.0, 0.0)
    """Added to the center-of-mass offset (m, object frame)."""

    def __post_init__(self) -> None:
        if not (math.isfinite(self.friction_scale) and self.friction_scale > 0):
            raise ValueError(f"perturb.friction_scale must be finite and > 0, got {self.friction_scale}")
        if not (math.isfinite(self.added_mass) and self.added_mass >= 0):
            raise ValueError(f"perturb.added_mass must be finite and >= 0 kg, got {self.added_mass}")
        shift = self.com_shift if hasattr(self.com_shift, "__len__") else ()  # a scalar is a bad shift too
        if len(shift) != 3 or not all(math.isfinite(c) and abs(c) <= 0.05 for c in shift):
            raise ValueError(f"perturb.com_shift must be 3 finite values within +-0.05 m, got {self.com_shift!r}")

    @property
    def is_nominal(self) -> bool:
        return self.friction_scale == 1.0 and self.added_mass == 0.0 and not any(self.com_shift)


@dataclass(frozen=True)
class EnvConfig:
    """RotateCup-v0: rotate the object about the vertical axis in a palm-up Allegro hand."""

    object: str = "cup"
    """Object name (see envs.objects.OBJECTS): 'cup' (default), 'cup_small', 'cup_large', Hora's 'cylinder_0'..'8'."""
    physics_dt: float = 0.01
    """Physics step (s). 10 ms with implicitfast integration keeps the PD and contacts stable at 5 substeps."""
    control_hz: float = C.CONTROL_HZ
    """Policy rate (Hz); the number of physics substeps is round(1 / (control_hz * physics_dt))."""
    episode_steps: int = C.EPISODE_STEPS
    """Truncation after this many policy steps (Hora: 400 = 20 s)."""
    action_scale: float = C.ACTION_SCALE
    """Relative target change per unit action (rad); Hora: 1/24."""
    kp: float = C.DEFAULT_KP
    """Nominal proportional gain (N m / rad) when randomization is off."""
    kd: float = C.DEFAULT_KD
    """Nominal damping gain (N m s / rad) when randomization is off."""
    torque_limit: float = C.DEFAULT_TORQUE_LIMIT
    """Actuator torque limit (N m), the real hand's clamp."""
    fall_drop: float = 0.05
    """The object has fallen when its centre is this far (m) below its grasp height."""
    max_distance: float = 0.12
    """The object has also fallen when its centre is this far (m) from where the episode started."""
    grasp_cache: str = ""
    """Path to a grasp cache (.npz) from `rotate grasps`; empty = the cache shipped with the package."""
    tactile: bool = False
    """Simulate the Digit 360 fingertips and add the `tactile` observation group (slower)."""
    randomization: RandomizationConfig = field(default_factory=RandomizationConfig)
    reward: RewardConfig = field(default_factory=RewardConfig)
    perturb: Perturbation = field(default_factory=Perturbation)

    def __post_init__(self) -> None:
        if self.object not in OBJECTS:
            raise ValueError(f"object: unknown object {self.object!r}; known objects: {', '.join(sorted(OBJECTS))}")
        if not (1e-4 <= self.physics_dt <= 0.02):
            raise ValueError(f"physics_dt must be in [1e-4, 0.02] s, got {self.physics_dt}")
        if not (1.0 <= self.control_hz <= 500.0):
            raise ValueError(f"control_hz must be in [1, 500] Hz, got {self.control_hz}")
        sub = 1.0 / (self.control_hz * self.physics_dt)
        if sub < 1 or abs(sub - round(sub)) > 1e-6:
            raise ValueError(
                f"1 / (control_hz * physics_dt) must be a whole number of substeps, got {sub:.4f} "
                f"(control_hz={self.control_hz}, physics_dt={self.physics_dt})"
            )
        if self.episode_steps < 1:
            raise ValueError(f"episode_steps must be >= 1, got {self.episode_steps}")
        for name in ("action_scale", "kp", "torque_limit", "fall_drop", "max_distance"):
            value = getattr(self, name)
            if not (math.isfinite(value) and value > 0):
                raise ValueError(f"{name} must be finite and > 0, got {value}")
        if not (math.isfinite(self.kd) and self.kd >= 0):
            raise ValueError(f"kd must be finite and >= 0, got {self.kd}")
        for name, cls in (("randomization", RandomizationConfig), ("reward", RewardConfig), ("perturb", Perturbation)):
            if not isinstance(getattr(self, name), cls):
                raise ValueError(f"{name} must be a {cls.__name__}, got {type(getattr(self, name)).__name__}")

    @property
    def substeps(self) -> int:
        return round(1.0 / (self.control_hz * self.physics_dt))

    @property
    def control_dt(self) -> float:
        return 1.0 / self.control_hz
