"""The one safety layer every hand command passes through.

- joint-limit clamps and a rate limit on targets (:func:`clamp_targets`, pure);
- per-joint torque limits with NaN/inf -> zero (:func:`clamp_torques`, pure);
- NaN/inf rejection of whole commands (the last safe target is held and the rejection logged);
- a policy watchdog: if no command arrives for ``policy_timeout_s`` the hand holds its last target or releases
  (zero effort) until commands resume, when the target restarts from the measured pose;
- :func:`motors_off_on_exit`: motors off on every exit path (context exit, SIGINT, SIGTERM, interpreter exit).

Sensor stalls (no joint feedback) are handled by each driver with its own timeout, because only the driver knows
when feedback is late; the reaction there is always motors off and a :class:`~rotation.hardware.hand.HandFault`.
"""

from __future__ import annotations

import atexit
import logging
import signal
import threading
from collections.abc import Callable, Iterator
from contextlib import contextmanager
from dataclasses import dataclass
from typing import Literal

import numpy as np

from rotation.hardware.hand import JOINT_LOWER, JOINT_UPPER, NUM_JOINTS, TORQUE_LIMITS

log = logging.getLogger(__name__)


@dataclass(frozen=True)
class SafetyConfig:
    """Limits applied to every command; joint vectors (16,) in bus order, Allegro frame."""

    lower: tuple[float, ...] = JOINT_LOWER
    """Lower joint limits (rad); defaults are the Allegro V4 limits (docs/reference/hora.md)."""
    upper: tuple[float, ...] = JOINT_UPPER
    """Upper joint limits (rad)."""
    torque_limits: tuple[float, ...] | None = None
    """Per-joint |torque| limits in the driver's effort unit (Allegro: normalized, PWM / 1200 on a V4); None uses
    the hand's hardware limits (V4: docs/reference/hardware.md section 1 PWM limits). Values above the hardware
    limits are an error, never silently lowered."""
    max_target_rate: float = 1.0
    """Largest target speed the low-level loop will track (rad/s). Hora's policy moves at most 1/24 rad per 50 ms
    = 0.83 rad/s (docs/reference/hora.md "action"), so 1.0 leaves headroom and slows any bigger jump."""
    policy_timeout_s: float = 0.25
    """Watchdog: longest gap between two commands (s) before ``on_policy_stall`` applies (5 policy steps at 20 Hz)."""
    on_policy_stall: Literal["hold", "release"] = "hold"
    """'hold': keep tracking the last target; 'release': zero effort until commands resume."""

    def __post_init__(self) -> None:
        for name in ("lower", "upper", "torque_limits"):
            if getattr(self, name) is not None and len(getattr(self, name)) != NUM_JOINTS:
                raise ValueError(f"SafetyConfig.{name}: expected {NUM_JOINTS} values, got {len(getattr(self, name))}")
        if not all(lo < hi for lo, hi in zip(self.lower, self.upper, strict=True)):
            raise ValueError("SafetyConfig.lower must be below SafetyConfig.upper for every joint")
        if self.torque_limits is not None and not all(t > 0 for t in self.torque_limits):
            raise ValueError("SafetyConfig.torque_limits must be positive")
        if not self.max_target_rate > 0:
            raise ValueError(f"SafetyConfig.max_target_rate must be > 0 rad/s, got {self.max_target_rate}")
        if not self.policy_timeout_s > 0:
            raise ValueError(f"SafetyConfig.policy_timeout_s must be > 0 s, got {self.policy_timeout_s}")
        if self.on_policy_stall not in ("hold", "release"):
            raise ValueError(f"SafetyConfig.on_policy_stall must be 'hold' or 'release', got {self.on_policy_stall!r}")


def clamp_targets(
    target: np.ndarray, previous: np.ndarray, lower: np.ndarray, upper: np.ndarray, max_step: float
) -> np.ndarray:
    """Safe next target: ``previous`` if ``target`` has any NaN/inf, else ``target`` clipped to [lower, upper]
    and moved at most ``max_step`` (rad) per joint from ``previous``; the result is always within the limits."""
    target = np.asarray(target, dtype=np.float64)
    previous = np.asarray(previous, dtype=np.float64)
    if not np.all(np.isfinite(target)):
        return previous.copy()
    goal = np.clip(target, lower, upper)
    step = np.clip(goal - previous, -max_step, max_step)
    return np.clip(previous + step, lower, upper)


def clamp_torques(torque: np.ndarray, limits: np.ndarray) -> np.ndarray:
    """Per-joint torque clamp to [-limits, limits]; NaN/inf entries become 0 (release that joint)."""
    torque = np.asarray(torque, dtype=np.float64)
    return np.clip(np.where(np.isfinite(torque), torque, 0.0), -limits, limits)


class SafetyLayer:
    """Thread-safe holder of the commanded goal and the tracked target, used by both hand drivers.

    The caller's thread calls :meth:`accept`; the driver's low-level loop calls :meth:`reset` once with the
    measured pose, then :meth:`step` every cycle and :meth:`torques` before every torque write.
    """

    def __init__(self, cfg: SafetyConfig, hardware_torque_limits: np.ndarray | tuple[float, ...] = TORQUE_LIMITS,
                 name: str = "hand") -> None:
        self.cfg = cfg
        self.name = name
        self.lower = np.asarray(cfg.lower, dtype=np.float64)
        self.upper = np.asarray(cfg.upper, dtype=np.float64)
        hw = np.asarray(hardware_torque_limits, dtype=np.float64)
        if cfg.torque_limits is None:
            self.torque_limits = hw.copy()
        else:
            self.torque_limits = np.asarray(cfg.torque_limits, dtype=np.float64)
            above = np.flatnonzero(self.torque_limits > hw + 1e-12)
            if above.size:
                raise ValueError(f"{name}: SafetyConfig.torque_limits exceed the hardware limits at joints "
                                 f"{above.tolist()} ({self.torque_limits[above].tolist()} > {hw[above].tolist()})")
        self._lock = threading.Lock()
        self._goal: np.ndarray | None = None
        self._target: np.ndarray | None = None
        self._last_command: float | None = None  # None: watchdog not armed until the first command
        self._stalled = False
        self.rejected = 0
        """Commands rejected for NaN/inf since start."""

    def reset(self, q_measured: np.ndarray) -> np.ndarray:
        """Start holding the measured pose (clipped to the limits); returns the initial target."""
        with self._lock:
            self._target = np.clip(np.asarray(q_measured, dtype=np.float64), self.lower, self.upper)
            self._goal = self._target.copy()
            return self._target.copy()

    def accept(self, q: np.ndarray, now: float) -> bool:
        """Take a new goal (16,) rad; False (goal unchanged, logged) if it holds NaN/inf."""
        q = np.asarray(q, dtype=np.float64)
        if q.shape != (NUM_JOINTS,):
            raise ValueError(f"{self.name}: targets must have shape ({NUM_JOINTS},), got {q.shape}")
        with self._lock:
            self._last_command = now
            if not np.all(np.isfinite(q)):
                self.rejected += 1
                bad = np.flatnonzero(~np.isfinite(q)).tolist()
                log.error("%s: rejected non-finite targets at joints %s; holding the last safe target", self.name, bad)
                return False
            self._goal = np.clip(q, self.lower, self.upper)
            return True

    def step(self, q_measured: np.ndarray, dt: float, now: float) -> tuple[np.ndarray, bool]:
        """Advance the tracked target by one loop period ``dt`` (s); returns (target, release).

        ``release`` is True while the policy watchdog has expired with ``on_policy_stall='release'``.
        """
        with self._lock:
            if self._target is None or self._goal is None:
                raise RuntimeError("SafetyLayer.step before reset()")
            stalled = self._last_command is not None and now - self._last_command > self.cfg.policy_timeout_s
            if stalled != self._stalled:
                if stalled:
                    log.error("%s: no command for %.0f ms (> %.0f ms): %s", self.name,
                              1e3 * (now - self._last_command), 1e3 * self.cfg.policy_timeout_s,
                              "releasing (zero effort)" if self.cfg.on_policy_stall == "release" else "holding")
                else:
                    log.warning("%s: commands resumed after a stall", self.name)
                    if self.cfg.on_policy_stall == "release":  # restart from where the released hand is now
                        self._target = np.clip(np.asarray(q_measured, dtype=np.float64), self.lower, self.upper)
                self._stalled = stalled
            release = stalled and self.cfg.on_policy_stall == "release"
            max_step = self.cfg.max_target_rate * max(dt, 0.0)
            self._target = clamp_targets(self._goal, self._target, self.lower, self.upper, max_step)
            return self._target.copy(), release

    def torques(self, torque: np.ndarray) -> np.ndarray:
        """Clamp efforts to the per-joint limits (NaN/inf -> 0, logged)."""
        torque = np.asarray(torque, dtype=np.float64)
        if not np.all(np.isfinite(torque)):
            log.error("%s: non-finite torque at joints %s set to 0", self.name,
                      np.flatnonzero(~np.isfinite(torque)).tolist())
        return clamp_torques(torque, self.torque_limits)


@contextmanager
def motors_off_on_exit(
    off: Callable[[], None], request_off: Callable[[], None] | None = None, name: str = "hand"
) -> Iterator[Callable[[], None]]:
    """Run ``off`` exactly once on leaving the block, at interpreter exit, or after SIGINT/SIGTERM.

    A signal handler must not take the locks ``off`` needs (the main thread may hold them), so on a signal it
    only calls ``request_off`` (non-blocking: e.g. tell the driver's own loop to switch the motors off at its
    next cycle) and then raises ``KeyboardInterrupt`` (SIGINT) or ``SystemExit(128 + signum)`` (SIGTERM), which
    unwinds the ``with`` blocks and runs ``off``. Signal handlers are installed only from the main thread (a
    Python rule); elsewhere the atexit hook and the context exit still apply. Yields the idempotent ``off``.
    """
    lock = threading.Lock()
    done = False

    def off_once(reason: str = "exit") -> None:
        nonlocal done
        with lock:
            if done:
                return
            done = True
        log.info("%s: motors off (%s)", name, reason)
        off()

    def on_signal(signum: int, frame: object) -> None:
        if request_off is not None:
            try:
                request_off()
            except Exception:  # a handler must reach the raise below
                log.exception("%s: request_off failed in the signal handler", name)
        prev = previous.get(signum)
        if callable(prev) and prev is not signal.default_int_handler:
            prev(signum, frame)  # another hand's handler: let it request its own off, then raise
        if signum == signal.SIGINT:
            raise KeyboardInterrupt
        raise SystemExit(128 + signum)

    previous: dict[int, object] = {}
    if threading.current_thread() is threading.main_thread():
        for sig in (signal.SIGINT, signal.SIGTERM):
            previous[sig] = signal.getsignal(sig)
            signal.signal(sig, on_signal)
    else:
        log.warning("%s: not in the main thread, so no SIGINT/SIGTERM handlers; atexit and context exit only", name)
    atexit.register(off_once, "interpreter exit")
    try:
        yield off_once
    finally:
        try:
            off_once("context exit")
        finally:
            atexit.unregister(off_once)
            for sig, prev in previous.items():
                if signal.getsignal(sig) is on_signal:
                    signal.signal(sig, prev)  # type: ignore[arg-type]
                else:
                    log.warning("%s: signal %d handler replaced meanwhile; not restoring it", name, sig)
