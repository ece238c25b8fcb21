"""The common hand contract shared by the Allegro and LEAP drivers (and what ``rotate deploy`` programs against).

Frames and units: joint vectors are (16,) float64 in the Allegro bus order (index 0-3, middle 4-7, ring 8-11,
thumb 12-15; each finger [abduction, MCP, PIP, DIP]), radians and rad/s, in the Allegro joint frame. The LEAP
driver converts (LEAP angle = Allegro angle + pi, docs/reference/hardware.md section 2) so callers never see it.

Joint limits and torque limits are repeated here (not imported from ``envs``, whose package imports MuJoCo);
``tests/hardware`` checks they equal ``envs.constants``.
"""

from __future__ import annotations

import threading
from dataclasses import dataclass, field
from typing import Protocol, runtime_checkable

import numpy as np

NUM_JOINTS = 16
FINGERS = ("index", "middle", "ring", "thumb")

# Joint limits (rad), public Allegro V4 description (docs/reference/hora.md "Allegro hand facts"); = envs.constants.
_FINGER_LOWER = (-0.47, -0.196, -0.174, -0.227)
_FINGER_UPPER = (0.47, 1.61, 1.709, 1.618)
_THUMB_LOWER = (0.263, -0.105, -0.189, -0.162)
_THUMB_UPPER = (1.396, 1.163, 1.644, 1.719)
JOINT_LOWER: tuple[float, ...] = _FINGER_LOWER * 3 + _THUMB_LOWER
JOINT_UPPER: tuple[float, ...] = _FINGER_UPPER * 3 + _THUMB_UPPER

# Per-joint torque limits of the V4 hand in normalized torque units (= PWM / 1200; N m in simulation),
# docs/reference/hardware.md section 1 "PWM limits"; = envs.constants.TORQUE_LIMITS.
TORQUE_LIMITS: tuple[float, ...] = (0.312, 0.562, 0.375, 0.237) * 3 + (0.438, 0.338, 0.225, 0.225)


class HandFault(RuntimeError):
    """The driver stopped commanding the hand (motors off) after a fault; the cause is chained and logged."""


class HandNotResponding(HandFault):
    """The hand did not answer a request within the configured timeout (powered? cabled? bitrate/baud?)."""


@dataclass(frozen=True)
class HandState:
    """One snapshot of the hand, all joint vectors (16,) in bus order.

    ``q`` rad and ``qdot`` rad/s (Allegro frame); ``torque`` is the joint effort in the driver's
    ``torque_unit`` (Allegro: the commanded torque after the safety clamps, normalized units = PWM / 1200 on a
    V4; LEAP: the measured motor current in A; neither hand has a torque sensor); ``target`` is the joint
    target the low-level loop is tracking now (after clamps and the rate limit, rad). ``t_host`` is the host
    ``time.monotonic()`` (s) when the feedback was complete; ``seq`` counts feedback cycles since start.
    """

    q: np.ndarray
    qdot: np.ndarray
    torque: np.ndarray
    target: np.ndarray
    t_host: float
    seq: int


@dataclass(frozen=True)
class HandInfo:
    """Identity and health of a hand. Temperatures in degrees C (NaN where the hand does not report one)."""

    kind: str
    """'allegro-v4', 'allegro-v5' or 'leap'."""
    firmware: str
    hardware: str
    serial: str
    temperatures: np.ndarray
    """(16,) per-joint temperature, degrees C, bus order."""
    extra: dict = field(default_factory=dict)
    """Hand-specific fields (Allegro: hand type, board temperature, status bits; LEAP: voltages, model numbers)."""


@runtime_checkable
class Hand(Protocol):
    """What a runtime needs from a hand: ``with hand: hand.set_targets(q); hand.read_state()``.

    ``__enter__`` runs the start-up sequence and leaves the hand holding its current pose; ``__exit__`` (and
    SIGINT/SIGTERM/atexit through :func:`rotation.hardware.safety.motors_off_on_exit`) switches the motors off.
    After a fault every call raises :class:`HandFault`.
    """

    torque_unit: str

    def __enter__(self) -> Hand: ...

    def __exit__(self, *exc: object) -> None: ...

    def set_targets(self, q: np.ndarray) -> bool:
        """Command joint targets (16,) rad; returns False if the safety layer rejected them (held the last)."""
        ...

    def read_state(self) -> HandState: ...

    def info(self) -> HandInfo: ...


class FeedbackMixin:
    """What every driver shares: the latest feedback under a lock, a fault that ends all further calls, and whether
    the motors were switched on and whether the hand confirmed they went off again.

    Drivers set ``name``, ``_lock``, ``_state`` (None until the first feedback) and ``_fault`` in their constructor,
    ``_motors_switched_on`` just before they send the command that enables the motors, and ``_off_confirmed`` from
    the hand's own answer to the motors-off command (never from the mere absence of a send error: with the bus off
    or the cable out, frames go nowhere without any error).
    """

    name: str
    _lock: threading.Lock
    _state: HandState | None
    _fault: HandFault | None
    _motors_switched_on: bool = False
    _off_confirmed: bool | None = None

    @property
    def motors_switched_on(self) -> bool:
        """True once the driver sent the command that enables the motors (it may have reached the hand even if the
        start-up failed afterwards); False for read-only use or a start-up that failed before it."""
        return self._motors_switched_on

    @property
    def motors_off_confirmed(self) -> bool | None:
        """After the last motors-off command: True if the hand answered that its motors are off, False if it did not
        (the motors may still be on: cut the hand's power); None if none was sent since the motors were last on."""
        return self._off_confirmed

    def read_state(self) -> HandState:
        """Latest complete feedback (see :class:`HandState`)."""
        self._raise_if_fault()
        with self._lock:
            if self._state is None:
                raise RuntimeError(f"{self.name}: no feedback yet; use the hand inside `with`")
            return self._state

    @property
    def fault(self) -> HandFault | None:
        """The fault that stopped the driver (motors already off), or None."""
        return self._fault

    def _raise_if_fault(self) -> None:
        if self._fault is not None:
            raise self._fault
