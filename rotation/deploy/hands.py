"""Open the hand named on the command line: a real Allegro (CAN) or LEAP (Dynamixel), or its emulator.

``sim-allegro`` / ``sim-leap`` start the MuJoCo-backed emulator (:mod:`rotation.sim_hardware`) holding the cup at a
grasp of the shipped cache at the env's nominal scale (:meth:`HandPhysics.at_grasp`), and connect the REAL driver
to it over the real protocol: a python-can virtual bus or an SLCAN adapter on a pseudo-terminal for the Allegro,
a Dynamixel servo bus on a pseudo-terminal for LEAP. Only this module knows whether the hand is emulated; the
control loop sees the :class:`rotation.hardware.Hand` protocol plus two optional emulator-only views (the object
pose, and what the emulated motors saw at the end).

Every command passes the driver's safety layer (joint limits, torque limits, target rate limit, NaN rejection);
deploy configures its watchdog to hold the last target when no command arrives for ``WATCHDOG_PERIODS`` control
periods (the control loop itself sends one every period, even while the policy is late).
"""

from __future__ import annotations

import contextlib
import logging
import time
from collections.abc import Callable
from dataclasses import dataclass
from typing import TYPE_CHECKING, Any, Literal

import numpy as np

from envs.constants import DEFAULT_HAND
from rotation.hardware.hand import Hand
from rotation.hardware.safety import SafetyConfig

if TYPE_CHECKING:
    from rotation.sim_hardware.hand_physics import HandPhysics

log = logging.getLogger(__name__)

HANDS = ("allegro", "leap", "sim-allegro", "sim-leap")
WATCHDOG_PERIODS = 5
"""Driver watchdog: hold the last target after this many control periods without a command (250 ms at 20 Hz,
the safety layer's default)."""


@dataclass(frozen=True)
class HandSetup:
    """How to reach the hand (the deploy CLI's hand options)."""

    hand: Literal["allegro", "leap", "sim-allegro", "sim-leap"]
    """Real hand or its emulator."""
    can: str = "socketcan:can0"
    """Allegro bus as INTERFACE:CHANNEL."""
    port: str = "/dev/ttyUSB0"
    """LEAP serial device."""
    baud: int = 4_000_000
    """LEAP baud rate."""
    gain_scale: float = 1.0
    """Factor (0, 1] on the driver's default gains (Allegro kp/kd, LEAP position P/D)."""
    control_hz: float = 20.0
    """Policy rate (Hz); sets the driver watchdog (WATCHDOG_PERIODS periods)."""
    object: str = "cup"
    """Emulation: object in the hand (a shipped grasp cache must exist)."""
    grasp: int = 0
    """Emulation: grasp cache row to start from."""
    sim_transport: Literal["virtual", "slcan"] = "virtual"
    """Emulated Allegro: python-can virtual bus or SLCAN adapter on a pty."""
    sim_hand: str = DEFAULT_HAND
    """Emulation: the simulated hand variant (envs.scene.HANDS) whose body the emulator drives: the policy's."""
    sim_object: tuple[tuple[str, float | tuple[float, ...]], ...] = ()
    """Emulation: (property, value) pairs of the emulated object (mass kg, friction, com m; HandPhysics.set_object);
    empty: the model's nominal object."""

    @property
    def kind(self) -> str:
        """'allegro' or 'leap'."""
        return "allegro" if self.hand.endswith("allegro") else "leap"

    @property
    def emulated(self) -> bool:
        return self.hand.startswith("sim-")


class OpenedHand:
    """A started hand (motors on, holding its pose) and, in emulation, its emulator."""

    def __init__(self, setup: HandSetup, emulator: Any = None) -> None:
        self.setup = setup
        self.hand: Hand | None = None
        """The driver (set once it has started)."""
        self.driver: Any = None
        """The driver from before its start-up on: whether it switched the motors on and whether the hand confirmed
        them off can be read even when the start-up failed half way."""
        self.emulator = emulator
        self.physics = emulator.physics if emulator is not None else None
        self.emulator_saw_motors_off: bool | None = None
        """Emulation: what :meth:`emulated_motors_off` found after the driver exited (None on a real hand)."""

    @property
    def kind(self) -> str:
        return self.setup.kind

    @property
    def source(self) -> str:
        """'sim' for an emulated hand, 'real' otherwise (the session format's ``source``)."""
        return "sim" if self.emulator is not None else "real"

    def object_pose(self) -> np.ndarray | None:
        """(7,) object position (m) + quaternion wxyz, world frame, where known (emulation); None on a real hand."""
        return None if self.physics is None else self.physics.object_pose()

    def emulated_motors_off(self, timeout_s: float = 2.0) -> bool | None:
        """Emulation: True once the emulator has seen the motors switched off (Allegro SYSTEM_OFF; LEAP torque
        disabled at every servo), polled for up to ``timeout_s`` (an emulator paused by an injected fault
        processes the queued frames when it resumes); None on a real hand."""
        emu = self.emulator
        if emu is None:
            return None
        if self.kind == "allegro":
            def off() -> bool:
                return not emu.servo_on
        else:
            def off() -> bool:
                return all(emu.register(i, "torque_enable") == 0 for i in emu.ids)
        deadline = time.monotonic() + timeout_s
        while not off():
            if time.monotonic() > deadline:
                return False
            time.sleep(0.01)
        return True

    def _check_emulator_after_exit(self) -> None:
        self.emulator_saw_motors_off = self.emulated_motors_off()
        if not self.emulator_saw_motors_off:
            log.error("the emulated %s did NOT see its motors switched off", self.kind)


def _safety(setup: HandSetup) -> SafetyConfig:
    return SafetyConfig(policy_timeout_s=WATCHDOG_PERIODS / setup.control_hz, on_policy_stall="hold")


def _allegro(setup: HandSetup, spec: str):
    from rotation.hardware.allegro.driver import AllegroConfig, AllegroHand

    base = AllegroConfig()
    gains = dict(kp=base.kp * setup.gain_scale, kd=base.kd * setup.gain_scale, safety=_safety(setup))
    if not setup.emulated:
        return AllegroHand(spec, AllegroConfig(**gains))
    if setup.sim_transport == "slcan":
        # python-can's slcan reader parses byte by byte in Python, in this process, next to the emulator and the
        # policy: a 6 ms stream and longer timeouts keep the rehearsal stable on a loaded machine
        return AllegroHand(spec, AllegroConfig(period_ms=6, feedback_timeout_s=0.5, reply_timeout_s=0.3,
                                               send_timeout_s=0.1, max_send_errors=5, **gains))
    # the emulator shares this process's CPU and GIL with the driver and the policy: a longer feedback timeout
    return AllegroHand(spec, AllegroConfig(feedback_timeout_s=0.3, reply_timeout_s=0.2, **gains))


def _leap(setup: HandSetup, port: str):
    from rotation.hardware.leap.driver import LeapConfig, LeapHand

    base = LeapConfig()
    options: dict[str, Any] = dict(baudrate=setup.baud, p_gain=int(round(base.p_gain * setup.gain_scale)),
                                   d_gain=int(round(base.d_gain * setup.gain_scale)), safety=_safety(setup))
    if setup.emulated:
        # the emulator shares this process's CPU and GIL with the busy-polling SDK: more retries, longer timeout
        options.update(feedback_timeout_s=0.5, max_retries=6)
    return LeapHand(port, LeapConfig(**options))


def emulated_physics(setup: HandSetup) -> HandPhysics | None:
    """The emulated hand's world (a HandPhysics holding ``setup.object`` at grasp ``setup.grasp``, frozen until the
    driver holds it), or None for a real hand. Made before anything starts, so that the emulated touch sensors
    (opened before the hand) sense the same hand that :func:`open_hand` then drives."""
    if not setup.emulated:
        return None
    from rotation.sim_hardware.hand_physics import HandPhysics

    physics = HandPhysics.at_grasp(setup.object, setup.grasp, hold=True, hand=setup.sim_hand)
    if setup.sim_object:
        physics.set_object(**dict(setup.sim_object))
    return physics


def open_hand(setup: HandSetup, stack: contextlib.ExitStack,
              created: Callable[[OpenedHand], None] | None = None,
              physics: HandPhysics | None = None) -> OpenedHand:
    """Start the hand (and its emulator) inside ``stack``; leaving the stack switches the motors off, then stops
    the emulator. Raises what the driver raises when the hand does not come up (HandFault, CAN/serial errors).

    ``created`` receives the :class:`OpenedHand` as soon as its driver exists, before the start-up: a caller learns
    whether the motors were switched on (and confirmed off) also when the start-up fails. ``physics``: the emulated
    hand's world from :func:`emulated_physics` (default: a new one); ignored for a real hand.
    """
    emulator = None
    if setup.emulated:
        physics = physics if physics is not None else emulated_physics(setup)
        if setup.kind == "allegro":
            from rotation.sim_hardware.allegro_emulator import AllegroEmulator

            emulator = stack.enter_context(AllegroEmulator(transport=setup.sim_transport, physics=physics))
            address = emulator.spec
        else:
            from rotation.sim_hardware.leap_emulator import LeapEmulator

            emulator = stack.enter_context(LeapEmulator(physics=physics))
            address = emulator.path
        log.info("emulated %s on %s: %s at grasp %d of the shipped cache, scale %.2f", setup.kind, address,
                 setup.object, setup.grasp, physics.scale)
    else:
        address = setup.can if setup.kind == "allegro" else setup.port
    opened = OpenedHand(setup, emulator)
    if emulator is not None:  # runs after the driver's exit (motors off) and before the emulator stops
        stack.callback(opened._check_emulator_after_exit)
    driver = _allegro(setup, address) if setup.kind == "allegro" else _leap(setup, address)
    opened.driver = driver
    if created is not None:
        created(opened)
    opened.hand = stack.enter_context(driver)
    if opened.physics is not None:
        opened.physics.release()  # the driver holds the grasp now: let the emulated world move
    return opened
