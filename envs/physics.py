"""The physical side of an env's config: domain randomization, the contact model, and each hand variant's defaults.

Two physics live here side by side. The 'digit360' and 'xela' hands keep the physics the shipped policies trained
on (Hora's ranges, one friction coefficient for everything, pyramidal cones with impratio 3, one torque limit, no
delay); the 'digit360_v4' hand, the vendor's kinematics, gets the hardware's (HAND_PHYSICS): a friction for the gel
domes and another for links and palm, cups up to ceramic-mug mass and standard-mug size, elliptic cones with the
noslip solver, the vendor's per-joint torque limits, and randomized joint friction, torque scale, action delay and
contact stiffness. `EnvConfig(hand=...)` picks the hand's physics wherever a field is left unset; each value's
source is in its docstring and in the README's model table (experiments/sim_v4 measures what each changes).
"""

from __future__ import annotations

import math
from dataclasses import dataclass, replace
from typing import Literal

import numpy as np

from envs.constants import DEFAULT_HAND
from envs.validation import check_types

MAX_FRICTION = 3.0
"""Highest sliding friction coefficient the contact model holds (the top of Hora's randomization range). Measured
with the cup held under zero action for 3 s (16 envs, nominal physics): the deepest object contact penetrates a
median 0.7 mm at 1.65, 2.4 mm at 3.0, then 3.7 mm at 3.6, 8.9 mm at 5.0, and at 6.6 the cup sinks through the palm
(9 of 16 envs drop it). With pyramidal friction cones, larger coefficients soften the normal direction."""
MAX_OBJECT_MASS = 0.5
"""Heaviest object (kg) the hand is asked to rotate: a 0.5 N m actuator on a ~0.1 m finger pushes ~5 N at the tip,
the weight of 0.5 kg, so a heavier object can only lie on the palm. The shipped teacher's rotation rate falls from
0.30 rad/s to 0.13 at +0.5 kg and to 0.01 at +2 kg (16 envs, 10 s)."""
MAX_ACTION_DELAY = 0.045
"""Longest action delay (s) the env simulates: it must stay inside one 50 ms control period at 20 Hz."""


def _check_range(name: str, lo_hi: tuple[float, float], low: float = -math.inf, high: float = math.inf) -> None:
    allowed = f"a (low, high) pair with low <= high within [{low}, {high}]"
    try:
        if any(isinstance(v, bool | str) for v in lo_hi):  # float() would read True as 1.0 and "0.1" as 0.1
            raise TypeError
        lo, hi = (float(v) for v in lo_hi)
    except (TypeError, ValueError):  # not a pair of numbers: a scalar, one or three values, text
        raise ValueError(f"{name} must be {allowed}, got {lo_hi!r}") from None
    if not (math.isfinite(lo) and math.isfinite(hi)):
        raise ValueError(f"{name} must be finite, got {lo_hi!r}")
    if lo > hi:
        raise ValueError(f"{name} is inverted: low {lo} > high {hi}; expected {allowed}")
    if lo < low or hi > high:
        raise ValueError(f"{name}={lo_hi!r} is outside the allowed interval [{low}, {high}]")


OPTIONAL_RANGES_LIMITS: dict[str, tuple[float, float]] = {
    "link_friction": (0.01, MAX_FRICTION),
    "joint_friction": (0.0, 0.5),
    "torque_scale": (0.1, 10.0),
    "action_delay": (0.0, MAX_ACTION_DELAY),
    "impratio": (1.0, 100.0),
    "contact_timeconst": (0.002, 0.2),
    "surface_friction": (0.05, 1.0),
}
"""The randomization ranges that are off (None) on the shipped physics, with the interval each must lie in."""
OPTIONAL_RANGES = tuple(OPTIONAL_RANGES_LIMITS)


@dataclass(frozen=True)
class RandomizationConfig:
    """Domain randomization (docs/reference/hora.md "Domain randomization"). Ranges are (low, high), sampled
    uniformly."""

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
    """Sliding friction coefficient: of every hand and object geom (Hora) when ``link_friction`` is None, otherwise
    of the fingertips' domes (the gel) against the object."""
    friction_log: bool = False
    """Draw the friction log-uniformly in ``friction`` (as many episodes per factor of 2 at the slippery end as at
    the grippy end) instead of uniformly; without randomization the nominal value stays the range's middle."""
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
    link_friction: tuple[float, float] | None = None
    """Sliding friction of the finger links, the sensor housings and the palm against the object, drawn on its own;
    None = one coefficient for every geom (``friction``, Hora's rule and the shipped policies')."""
    joint_friction: tuple[float, float] | None = None
    """Dry friction of every joint (N m, MuJoCo's frictionloss), one draw per joint; None = the hand model's."""
    torque_scale: tuple[float, float] | None = None
    """Newton metres per unit of the hand's normalized torque, one draw per episode: multiplies the PD gains and the
    torque limits together (the unit the real hand's driver speaks is not identified); None = 1."""
    action_delay: tuple[float, float] | None = None
    """Time (s) from the end of a control step to the moment its new joint targets reach the motors, one draw per
    episode, rounded down to whole physics steps; None = no delay."""
    impratio: tuple[float, float] | None = None
    """The contact model's frictional-to-normal impedance ratio, drawn log-uniformly per episode; None = the
    config's ``contact.impratio``."""
    contact_timeconst: tuple[float, float] | None = None
    """Time constant (s) of every contact (MuJoCo's solref[0]: how fast penetration is pushed out), one draw per
    episode; None = the model's 0.02 s."""
    surface_friction: tuple[float, float] | None = None
    """A factor of the cup's surface, one draw per episode, log-uniform: it multiplies the domes' and the links'
    friction together (a wet or oily glaze changes every contact at once, as the perturbation suite's friction
    scale does), so that training reaches the slippery cups the suite tries; None = 1. Only with randomization on."""
    surface_share: float = 1.0
    """Share of episodes whose cup surface is drawn from ``surface_friction``; the others keep the nominal surface
    (factor 1), so a training that reaches slippery cups still practises the nominal one as often as it asks. The
    same uniform draw decides both (below the share: the factor, from that draw rescaled), so no other draw moves."""
    noslip_dropout: float = 0.0
    """Share of episodes run without the noslip solver, where the config's contact model uses it (friction that
    creeps a little, as under MuJoCo's plain solver): a policy must not need one solver to hold the cup."""

    def __post_init__(self) -> None:
        check_types(self, "randomization.", skip=("mass", "com", "friction", "kp", "kd") + OPTIONAL_RANGES)
        if not self.scales:
            raise ValueError("randomization.scales must list at least one scale")
        if any(not (0.1 <= s <= 3.0) for s in self.scales):
            raise ValueError(f"randomization.scales must lie in [0.1, 3.0], got {self.scales!r}")
        if not (0.0 <= self.scale_jitter < min(self.scales)):
            raise ValueError(f"randomization.scale_jitter must be in [0, {min(self.scales)}), got {self.scale_jitter}")
        _check_range("randomization.mass", self.mass, low=1e-4, high=MAX_OBJECT_MASS)
        _check_range("randomization.com", self.com, low=-0.05, high=0.05)
        _check_range("randomization.friction", self.friction, low=0.01, high=MAX_FRICTION)
        _check_range("randomization.kp", self.kp, low=0.01, high=100.0)
        _check_range("randomization.kd", self.kd, low=0.0, high=10.0)
        for name, (low, high) in OPTIONAL_RANGES_LIMITS.items():
            if getattr(self, name) is not None:
                _check_range(f"randomization.{name}", getattr(self, name), low=low, high=high)
        for name, top in (("joint_noise", 1.0), ("push_scale", 100.0)):
            if not (0.0 <= getattr(self, name) <= top):
                raise ValueError(f"randomization.{name} must be finite and >= 0 (at most {top}), "
                                 f"got {getattr(self, name)}")
        if not (0.0 < self.surface_share <= 1.0):
            raise ValueError(f"randomization.surface_share must be in (0, 1], got {self.surface_share}")
        if not (0.0 <= self.noslip_dropout <= 1.0):
            raise ValueError(f"randomization.noslip_dropout must be in [0, 1], got {self.noslip_dropout}")
        if not (0.0 <= self.push_prob <= 1.0):
            raise ValueError(f"randomization.push_prob must be in [0, 1], got {self.push_prob}")
        if not (0.0 <= self.push_decay <= 1.0):
            raise ValueError(f"randomization.push_decay must be in [0, 1], got {self.push_decay}")




@dataclass(frozen=True)
class ContactConfig:
    """MuJoCo's contact model (experiments/contact_creep measures what each setting does to a held cup). The
    defaults are the settings the shipped policies were trained with: under them a still hand's cup sinks about 9 mm
    in 5 s; elliptic cones with impratio 10 and the noslip solver hold it within half a millimetre."""

    cone: Literal["pyramidal", "elliptic"] = "pyramidal"
    """Friction cone: 'pyramidal' (the shipped policies') or 'elliptic' (MuJoCo's usual choice for grasping)."""
    impratio: float = 3.0
    """Ratio of the frictional to the normal constraint impedance: higher makes friction stiffer (less creep)."""
    noslip_iterations: int = 0
    """Iterations of MuJoCo's noslip post-solver (0 = off): it removes the slip of contacts that should stick, at
    about 50% more physics time with 10."""
    timeconst: float | None = None
    """Time constant (s) of every contact (MuJoCo's solref[0]); None = the model's 0.02 s. MuJoCo holds it at two
    physics steps or more."""
    solimp: tuple[float, float, float] | None = None
    """Every contact's impedance (MuJoCo's solimp: dmin, dmax, width in m); None = the model's (0.9, 0.95, 0.001)."""

    def __post_init__(self) -> None:
        check_types(self, "contact.", skip=("timeconst", "solimp"))
        if not (math.isfinite(self.impratio) and 1.0 <= self.impratio <= 100.0):
            raise ValueError(f"contact.impratio must be in [1, 100], got {self.impratio}")
        if not (0 <= self.noslip_iterations <= 100):
            raise ValueError(f"contact.noslip_iterations must be in [0, 100], got {self.noslip_iterations}")
        if self.timeconst is not None and not (isinstance(self.timeconst, int | float) and not isinstance(
                self.timeconst, bool) and math.isfinite(self.timeconst) and 0.002 <= self.timeconst <= 0.2):
            raise ValueError(f"contact.timeconst must be a number in [0.002, 0.2] s or None, got {self.timeconst!r}")
        if self.solimp is not None:
            try:
                dmin, dmax, width = (float(v) for v in self.solimp)
            except (TypeError, ValueError):
                raise ValueError(f"contact.solimp must be 3 numbers (dmin, dmax, width) or None, got "
                                 f"{self.solimp!r}") from None
            if not (0.0 < dmin <= dmax < 1.0 and 0.0 < width <= 0.1):
                raise ValueError(f"contact.solimp must have 0 < dmin <= dmax < 1 and 0 < width <= 0.1 m, got "
                                 f"{self.solimp!r}")


@dataclass(frozen=True)
class HandPhysics:
    """A hand variant's physics: what EnvConfig uses for the fields it leaves unset."""

    randomization: RandomizationConfig
    contact: ContactConfig
    joint_torque_limits: Literal["uniform", "vendor"]


SHIPPED_PHYSICS = HandPhysics(RandomizationConfig(), ContactConfig(), "uniform")
"""The physics the shipped policies trained on (hands 'digit360' and 'xela'), Hora's."""

V4_PHYSICS = HandPhysics(
    RandomizationConfig(
        # cup radius 28..44 mm (+-1 mm jitter): from the shipped cups' smallest to a standard 85-90 mm mug
        scales=(0.70, 0.75, 0.80, 0.85, 0.90, 0.95, 1.00, 1.05, 1.10),
        # an empty paper cup to a filled ceramic mug (0.25-0.4 kg, issue 72's figure)
        mass=(0.02, 0.40),
        # gel domes: MuJoCo Playground's fingertip range 0.5-1.0 (docs/reference/hora.md) widened to a glazed mug
        # (0.4) and a grippy plastic one (1.2), log-uniform so the slippery half is not undersampled
        friction=(0.4, 1.2), friction_log=True,
        # links, sensor housings and palm: hard plastic and anodized aluminium; no published figure for the
        # Allegro's covers, so a range that brackets hard plastics on glazed ceramic or plastic (an assumption)
        link_friction=(0.2, 0.5),
        # unidentified on the real hand: up to 0.05 N m of dry joint friction (-10% rotation on the shipped teacher,
        # issue 72) and a torque unit of 0.7-1.3 N m per normalized unit
        joint_friction=(0.0, 0.05), torque_scale=(0.7, 1.3),
        # deploy's budget: the policy may take 0.6 of a 50 ms period (30 ms, rotation.deploy.config's
        # policy_budget) before its targets leave, plus the bus cycle
        action_delay=(0.0, 0.04),
        # contact stiffness around the chosen model (elliptic, impratio 10, noslip): impratio 3-30 log-uniform,
        # time constant from MuJoCo's floor of two physics steps to twice that; a quarter of episodes without noslip
        impratio=(3.0, 30.0), contact_timeconst=(0.02, 0.04), noslip_dropout=0.25,
    ),
    ContactConfig(cone="elliptic", impratio=10.0, noslip_iterations=10),
    "vendor",
)
"""The hardware's physics, for the vendor-kinematics hands 'digit360_v4' and 'xela_v4': see each value's comment
(on the Xela hand the skin's silicone takes the gel domes' friction range)."""

HAND_PHYSICS: dict[str, HandPhysics] = {"digit360": SHIPPED_PHYSICS, "xela": SHIPPED_PHYSICS,
                                        "digit360_v4": V4_PHYSICS, "xela_v4": V4_PHYSICS}
"""Hand variant -> its physics (the hands of envs.scene.VARIANTS)."""


def hand_physics(hand: str) -> HandPhysics:
    """The physics of a hand variant; a ValueError names the known hands."""
    if hand not in HAND_PHYSICS:
        raise ValueError(f"unknown hand {hand!r}; hands: {', '.join(HAND_PHYSICS)}")
    return HAND_PHYSICS[hand]


def default_randomization(hand: str = DEFAULT_HAND, enabled: bool = True) -> RandomizationConfig:
    """The randomization a hand's policies train with, or with ``enabled=False`` its nominal physics (the ranges'
    middles)."""
    rc = hand_physics(hand).randomization
    return rc if enabled else replace(rc, enabled=False)


def object_friction(friction, link_friction):
    """The object's own sliding coefficient when the gel domes (``friction``, the cup's randomized coefficient) and
    the links and palm (``link_friction``) have their own: MuJoCo gives a contact the larger of its two geoms'
    coefficients, so the object holds the smaller of the two and each contact reads the hand material it touches
    (domes: ``friction``, links: ``link_friction``). Scalars or arrays (numpy broadcasting). The one place of this
    rule: the batched env (envs.core), the emulated hand (rotation.sim_hardware.hand_physics) and what reads it back."""
    return np.minimum(friction, link_friction)
