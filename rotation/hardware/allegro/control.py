"""Allegro host-side control pieces, free of I/O: the driver config, cycle assembly and the PD law.

Tested on hand-made frames (tests/hardware); :mod:`rotation.hardware.allegro.driver` wires them to the bus.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Literal

import numpy as np

from rotation.hardware.hand import NUM_JOINTS
from rotation.hardware.safety import SafetyConfig


@dataclass(frozen=True)
class AllegroConfig:
    """Driver settings; gains in normalized torque units (PWM / 1200 on a V4, = N m in simulation)."""

    hand_id: int = 0
    """Low two bits of every CAN ID (0 unless several hands share a bus)."""
    protocol: Literal["auto", "v4", "v5"] = "auto"
    """Hand generation; 'auto' reads it from HAND_INFO, an explicit value must agree with it."""
    kp: float = 3.0
    """Proportional gain, torque per rad (Hora's deployment 3600 PWM/rad = 3.0, docs/reference/hora.md)."""
    kd: float = 0.1
    """Derivative gain, torque per rad/s (Hora: 120 PWM s/rad = 0.1)."""
    velocity_smoothing: float = 0.7
    """EMA weight of the previous velocity estimate: qdot = s qdot + (1 - s) dq/dt (a deployment uses 0.7)."""
    period_ms: int = 3
    """Position stream period requested with SET_PERIOD (ms); the hand's clock runs at 333 Hz."""
    reply_timeout_s: float = 0.1
    """Wait for one reply to a request (s)."""
    request_retries: int = 3
    """Attempts per request before HandNotResponding."""
    feedback_timeout_s: float = 0.1
    """No complete position cycle for this long (s, ~33 cycles) -> motors off and HandFault."""
    send_timeout_s: float = 0.01
    """Longest wait for the adapter to take one frame (s); a PD cycle is 3 ms, so this stays short."""
    max_send_errors: int = 3
    """Consecutive failed sends tolerated (each logged, next cycle retries) before motors off."""
    max_recv_errors: int = 10
    """Consecutive receive errors (adapter or parse errors) tolerated before motors off."""
    enable_motors: bool = True
    """False: never send SYSTEM_ON or torques (read-only, e.g. for ``rotate hand-info``)."""
    safety: SafetyConfig = field(default_factory=SafetyConfig)
    """Joint limits, torque limits, target rate limit and the policy watchdog."""

    def __post_init__(self) -> None:
        if not 0 <= self.hand_id <= 3:
            raise ValueError(f"AllegroConfig.hand_id must be 0..3, got {self.hand_id}")
        if self.protocol not in ("auto", "v4", "v5"):
            raise ValueError(f"AllegroConfig.protocol must be auto, v4 or v5, got {self.protocol!r}")
        if self.kp < 0 or self.kd < 0:
            raise ValueError(f"AllegroConfig gains must be >= 0, got kp={self.kp} kd={self.kd}")
        if not 0 <= self.velocity_smoothing < 1:
            raise ValueError(f"AllegroConfig.velocity_smoothing must be in [0, 1), got {self.velocity_smoothing}")
        if not 1 <= self.period_ms <= 100:
            raise ValueError(f"AllegroConfig.period_ms must be 1..100, got {self.period_ms}")
        for name in ("reply_timeout_s", "feedback_timeout_s", "send_timeout_s"):
            if not getattr(self, name) > 0:
                raise ValueError(f"AllegroConfig.{name} must be > 0, got {getattr(self, name)}")
        if self.feedback_timeout_s < 2e-3 * self.period_ms:
            raise ValueError(f"AllegroConfig.feedback_timeout_s={self.feedback_timeout_s} is shorter than two "
                             f"stream periods ({2 * self.period_ms} ms)")
        for name in ("request_retries", "max_send_errors", "max_recv_errors"):
            if getattr(self, name) < 1:
                raise ValueError(f"AllegroConfig.{name} must be >= 1, got {getattr(self, name)}")


class CycleAssembler:
    """Collects the four FINGER_POSE frames of one hand cycle into a (16,) joint vector.

    The hand sends a cycle's frames in finger order, index (0) first. A cycle restarts at finger 0 or at a
    repeated finger, so after a lost frame the next complete cycle is again one tick of the hand (positions of
    two ticks are never mixed); the broken cycle is counted in ``incomplete``.
    """

    def __init__(self) -> None:
        self.q = np.zeros(NUM_JOINTS)
        self.mask = 0
        self.incomplete = 0

    def add(self, finger: int, q4: np.ndarray) -> np.ndarray | None:
        """Store one finger's 4 angles (rad); returns a copy of the full (16,) vector when the cycle completes."""
        if self.mask and (finger == 0 or self.mask & (1 << finger)):
            self.incomplete += 1
            self.mask = 0
        self.q[4 * finger: 4 * finger + 4] = q4
        self.mask |= 1 << finger
        if self.mask == 0xF:
            self.mask = 0
            return self.q.copy()
        return None


class VelocityFilter:
    """Finite-difference joint velocity with an exponential moving average: qdot = s qdot + (1 - s) dq/dt."""

    def __init__(self, smoothing: float, nominal_dt: float) -> None:
        self.smoothing = smoothing
        self.min_dt = 0.25 * nominal_dt  # frames delivered in a burst must not blow the estimate up
        self.q_prev: np.ndarray | None = None
        self.qdot = np.zeros(NUM_JOINTS)

    def update(self, q: np.ndarray, dt: float) -> np.ndarray:
        """Velocity estimate (rad/s) after measuring ``q`` (rad), ``dt`` s after the previous measurement."""
        if self.q_prev is not None:
            raw = (q - self.q_prev) / max(dt, self.min_dt)
            self.qdot = self.smoothing * self.qdot + (1.0 - self.smoothing) * raw
        self.q_prev = q.copy()
        return self.qdot.copy()


def pd_torque(q: np.ndarray, qdot: np.ndarray, target: np.ndarray, kp: float, kd: float) -> np.ndarray:
    """Host PD law (before the safety clamps): tau = kp (target - q) - kd qdot, normalized torque units."""
    return kp * (target - q) - kd * qdot
