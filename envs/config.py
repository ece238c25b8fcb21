"""Typed configs of the RotateCup task: physics timing, randomization, reward, perturbations.

Defaults follow Hora's recipe (docs/reference/hora.md). Every config validates itself on construction and raises a
ValueError that names the field and the allowed values; nothing is clamped silently.
"""

from __future__ import annotations

import dataclasses
import math
import numbers
from dataclasses import dataclass, field
from typing import Literal

from envs import constants as C
from envs.constants import DEFAULT_HAND
from envs.objects import OBJECTS
from envs.physics import (  # noqa: F401 (re-exported: the configs' public names)
    MAX_FRICTION,
    MAX_OBJECT_MASS,
    ContactConfig,
    RandomizationConfig,
    default_randomization,
    hand_physics,
)
from envs.validation import check_finite, check_types


@dataclass(frozen=True)
class RewardConfig:
    """Scales of Hora's reward terms (docs/reference/hora.md "Reward"); each scaled term is reported in ``info``."""

    rotate: float = 1.0
    """Rotation about the commanded axis, clip(omega . axis, -rotate_back_clip, rotate_clip) (rad/s)."""
    rotate_clip: float = 0.5
    """Upper clip of the angular velocity term (rad/s): turning faster earns no more."""
    rotate_back_clip: float = 0.5
    """Lower clip (as a positive number, rad/s): turning backward faster than this costs no more. Hora's symmetric
    0.5 lets a policy ratchet: turn forward at the cap, snap back faster than the cap for a fraction of the cost, and
    earn the term with no net rotation (a from-scratch run found it: 70% of the shipped teacher's clipped rotate
    term at 15% of its net rotation; experiments/teacher_scratch). A larger value (e.g. 5) makes that snap cost
    what it undoes; the default keeps the shipped policies' reward."""
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
    tilt: float = -1.0
    """Squared tilt of the object's up axis from the world vertical (rad^2). Hora has none: its cylinders lie
    flat, and a reward that only measures rotation about the vertical axis let a CPU-budget teacher tip the cup onto
    its side against the palm and roll it there; this term (-0.27 per step at 30 degrees) keeps the cup upright."""
    fall: float = -20.0
    """One-off reward when the object falls (dropped, left the hand, or tipped past ``EnvConfig.max_tilt``). Hora
    has none; without it, a CPU-budget teacher learned to drop the
    object early (every other term is a penalty, so ending the episode looked good): ttf fell from 0.7 to 0.2."""
    axis: tuple[float, float, float] = (0.0, 0.0, -1.0)
    """Commanded rotation axis in the world frame (Hora: -z, palm up)."""

    def __post_init__(self) -> None:
        check_types(self, "reward.", skip=("axis",))
        weights = tuple(f for f in self.__dataclass_fields__ if f not in ("axis", "rotate_clip", "rotate_back_clip"))
        check_finite(self, weights, "reward.")  # any sign: a weight is a reward (> 0), a penalty (< 0) or off (0)
        if (not isinstance(self.axis, tuple | list) or not all(isinstance(a, numbers.Real) for a in self.axis)
                or any(isinstance(a, bool) for a in self.axis)):
            raise ValueError(f"reward.axis must be a unit 3-vector, got {self.axis!r}")
        if len(self.axis) != 3 or not math.isclose(math.hypot(*self.axis), 1.0, rel_tol=1e-6):
            raise ValueError(f"reward.axis must be a unit 3-vector, got {self.axis!r}")
        for name in ("rotate_clip", "rotate_back_clip"):
            if not (0 < getattr(self, name) <= 100.0):
                raise ValueError(f"reward.{name} must be > 0 (at most 100 rad/s), got {getattr(self, name)}")


@dataclass(frozen=True)
class Perturbation:
    """Evaluation perturbations applied on top of the randomized values (friction x, mass +, CoM +).

    Physical limits (checked by EnvConfig, which knows the randomization they apply on top of): the friction in force
    (the randomization's highest friction x friction_scale) must stay at or below MAX_FRICTION = 3.0, beyond which
    the contact model lets the object sink into the palm (x3 on the default 0.3-3.0 range sank the cup); the
    heaviest object (the randomization's highest mass + added_mass) must stay at or below MAX_OBJECT_MASS = 0.5 kg,
    what the 0.5 N m actuators can lift. With the default randomization: friction_scale in (0, 1],
    added_mass in [0, 0.25] kg.
    """

    friction_scale: float = 1.0
    """Multiplies the friction the env would otherwise use (see the class docstring for the limit)."""
    added_mass: float = 0.0
    """Added to the object mass (kg; see the class docstring for the limit)."""
    com_shift: tuple[float, float, float] = (0.0, 0.0, 0.0)
    """Added to the center-of-mass offset (m, object frame)."""

    def __post_init__(self) -> None:
        check_types(self, "perturb.", skip=("com_shift",))
        if not (math.isfinite(self.friction_scale) and self.friction_scale > 0):
            raise ValueError(f"perturb.friction_scale must be finite and > 0, got {self.friction_scale}")
        if not (math.isfinite(self.added_mass) and self.added_mass >= 0):
            raise ValueError(f"perturb.added_mass must be finite and >= 0 kg, got {self.added_mass}")
        if self.added_mass > MAX_OBJECT_MASS:  # too heavy whatever the randomization; friction: see EnvConfig
            raise ValueError(f"perturb.added_mass must be in [0, {MAX_OBJECT_MASS}] kg (what the 0.5 N m actuators "
                             f"can lift), got {self.added_mass}")
        shift = self.com_shift if isinstance(self.com_shift, tuple | list) else ()  # a scalar is a bad shift too
        if len(shift) != 3 or not all(isinstance(c, numbers.Real) and not isinstance(c, bool) and math.isfinite(c)
                                      and abs(c) <= 0.05 for c in shift):
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
    """Actuator torque limit (N m) of every joint, with joint_torque_limits 'uniform'."""
    joint_torque_limits: Literal["uniform", "vendor"] | None = None
    """'uniform': torque_limit on every joint (what the shipped policies trained with); 'vendor': the real hand's
    per-joint limits, 0.225-0.562 N m (envs.constants.TORQUE_LIMITS: the vendor driver's PWM limits / 1200);
    None = the hand's (envs.physics.HAND_PHYSICS)."""
    fall_drop: float = 0.05
    """The object has fallen when its centre is this far (m) below its grasp height."""
    max_distance: float = 0.12
    """The object has also fallen when its centre is this far (m) from where the episode started."""
    max_tilt: float = 0.7
    """The object has also fallen when its up axis tilts this far (rad, 0.7 = 40 degrees) from the world vertical:
    a tipped cup has not done the job, whatever it still earns (evaluation's `upright` counts 30 degrees)."""
    grasp_cache: str = ""
    """Path to a grasp cache (.npz) from `rotate grasps`; empty = the cache shipped with the package."""
    tactile: bool = False
    """Simulate the Digit 360 fingertips and add the `tactile` observation group (slower); on a Digit 360 hand."""
    hand: Literal["digit360", "xela", "digit360_v4", "xela_v4"] = DEFAULT_HAND
    """Hand variant: 'digit360' (Digit 360 fingertips) or 'xela' (stock-length fingertips, 18 Xela skin pads on
    fingertips, phalanges and palm; docs/skin.md), both on the physics the shipped policies trained on, or
    'digit360_v4' (the vendor's kinematics with Meta's Digit 360 mount) and 'xela_v4' (the vendor's kinematics with
    the Xela shells and pads on its own links), both on the hardware's physics (envs.physics.V4_PHYSICS). Each has
    its own grasp caches; the fields left None take the hand's physics. Move a config to another hand with
    :meth:`with_hand` (dataclasses.replace would keep the old hand's physics)."""
    skin: bool = False
    """Simulate the Xela skin (needs hand='xela' or 'xela_v4') and add the `skin` observation group
    (docs/skin.md)."""
    randomization: RandomizationConfig | None = None
    """Domain randomization; None = the hand's (envs.physics.default_randomization)."""
    reward: RewardConfig = field(default_factory=RewardConfig)
    perturb: Perturbation = field(default_factory=Perturbation)
    contact: ContactConfig | None = None
    """The contact model; None = the hand's (envs.physics.HAND_PHYSICS)."""

    def __post_init__(self) -> None:
        check_types(self)
        physics = hand_physics(self.hand)
        for name in ("randomization", "contact", "joint_torque_limits"):  # unset: the hand's physics
            if getattr(self, name) is None:
                object.__setattr__(self, name, getattr(physics, name))
        if self.skin and self.hand not in ("xela", "xela_v4"):
            raise ValueError(f"skin: the Xela skin needs hand='xela' or 'xela_v4', got hand={self.hand!r}")
        if self.tactile and self.hand not in ("digit360", "digit360_v4"):
            raise ValueError(f"tactile: the Digit 360 touch needs hand='digit360' or 'digit360_v4', got "
                             f"hand={self.hand!r}")
        if self.skin and self.physics_dt != 0.01:  # one Xela sample per physics step (envs.sensors.xela.SAMPLE_HZ)
            raise ValueError(f"skin: the Xela skin samples at 100 Hz, one sample per physics step; it needs "
                             f"physics_dt=0.01, got {self.physics_dt}")
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
        if self.episode_steps > 10**7:  # about 6 days at 20 Hz
            raise ValueError(f"episode_steps must be at most 10**7, got {self.episode_steps}")
        for name in ("action_scale", "kp", "torque_limit", "fall_drop", "max_distance", "max_tilt"):
            value = getattr(self, name)
            if not (math.isfinite(value) and value > 0):
                raise ValueError(f"{name} must be finite and > 0, got {value}")
        if not (math.isfinite(self.kd) and self.kd >= 0):
            raise ValueError(f"kd must be finite and >= 0, got {self.kd}")
        # ceilings far above any sensible value, which catch unit slips (mm for m, deg for rad) and typos
        for name, top, unit in (("action_scale", 1.0, "rad"), ("kp", 100.0, "N m / rad"), ("kd", 10.0, "N m s / rad"),
                                ("torque_limit", 10.0, "N m"), ("fall_drop", 1.0, "m"), ("max_distance", 1.0, "m"),
                                ("max_tilt", math.pi, "rad")):
            if getattr(self, name) > top:
                raise ValueError(f"{name} must be at most {top:g} {unit}, got {getattr(self, name)}")
        for name, cls in (("randomization", RandomizationConfig), ("reward", RewardConfig), ("perturb", Perturbation),
                          ("contact", ContactConfig)):
            if not isinstance(getattr(self, name), cls):
                raise ValueError(f"{name} must be a {cls.__name__}, got {type(getattr(self, name)).__name__}")
        self._check_physical_limits()

    def _check_physical_limits(self) -> None:
        """The friction and mass in force (randomization with the perturbation on top) within what the model holds."""
        rc, p = self.randomization, self.perturb
        friction = (rc.friction[1] if rc.enabled else sum(rc.friction) / 2) * p.friction_scale
        if friction > MAX_FRICTION * (1 + 1e-9):
            top = MAX_FRICTION / (friction / p.friction_scale)
            raise ValueError(
                f"perturb.friction_scale {p.friction_scale:g} makes the friction reach {friction:.3g}, above "
                f"{MAX_FRICTION}, the most the contact model holds (objects sink into the palm beyond it); with this "
                f"randomization friction_scale must be in (0, {top:.3g}]")
        mass = (rc.mass[1] if rc.enabled else sum(rc.mass) / 2) + p.added_mass
        if mass > MAX_OBJECT_MASS * (1 + 1e-9):
            top = MAX_OBJECT_MASS - (mass - p.added_mass)
            raise ValueError(
                f"perturb.added_mass {p.added_mass:g} kg makes the object weigh up to {mass:.3g} kg, above "
                f"{MAX_OBJECT_MASS} kg, what the 0.5 N m actuators can lift; with this randomization added_mass must "
                f"be in [0, {top:.3g}] kg")

    def with_hand(self, hand: str) -> EnvConfig:
        """This config on another hand with that hand's physics (randomization on or off as here, its contact model
        and torque limits: envs.physics.HAND_PHYSICS); the task fields (object, timing, reward, perturbation)
        stay."""
        physics = hand_physics(hand)
        rc = dataclasses.replace(physics.randomization, enabled=self.randomization.enabled)
        return dataclasses.replace(self, hand=hand, contact=physics.contact,
                                   joint_torque_limits=physics.joint_torque_limits, randomization=rc)

    @property
    def substeps(self) -> int:
        return round(1.0 / (self.control_hz * self.physics_dt))

    @property
    def control_dt(self) -> float:
        return 1.0 / self.control_hz
