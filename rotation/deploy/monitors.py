"""What the control loop watches and shows while it runs: step timing and lateness (LoopStats), the object's
rotation in emulation, joint temperatures, and the live status line.
"""

from __future__ import annotations

import logging
import math
import threading
from dataclasses import dataclass, field
from typing import TextIO

import numpy as np

from envs.config import EnvConfig
from envs.core import angular_velocity
from rotation.hardware.hand import HandFault

log = logging.getLogger("rotation.deploy.loop")  # the loop's own logger: its messages are the loop's
_ENV = EnvConfig()
"""The env's defaults: the task's rotation axis and fall thresholds, as in simulation."""
ROTATION_AXIS = np.asarray(_ENV.reward.axis, dtype=np.float64)
"""The env's commanded rotation axis, world frame ((0, 0, -1): palm up, clockwise seen from above)."""
FALL_DROP_M = _ENV.fall_drop
"""The object counts as fallen this far (m) below its start height (the env's rule)."""
FALL_DISTANCE_M = _ENV.max_distance
"""... or this far (m) from its start position in any direction (the env's rule)."""


@dataclass
class LoopStats:
    """What the loop measured; complete up to the moment the loop ended, also after a fault."""

    tick_times: list[float] = field(default_factory=list)
    """Host monotonic start time (s) of every control step."""
    late_steps: int = 0
    skipped_slots: int = 0
    held_steps: int = 0
    degraded_steps: int = 0
    """Steps that were late, held, or both (each counted once)."""
    rejected_actions: int = 0
    rotation_rad: float | None = None
    """Object rotation (rad) about ROTATION_AXIS since the start (emulation), up to a fall."""
    object_fell: bool | None = None
    max_temperature_c: float = float("nan")

    def summary(self, period: float) -> dict:
        """Steps, loop rate (Hz), late/held counts, p50/p99 jitter (ms) = |step period - nominal period|."""
        t = np.asarray(self.tick_times)
        periods = np.diff(t)
        jitter = 1e3 * np.abs(periods - period)
        out = {
            "steps": len(t),
            "loop_hz": float(len(periods) / (t[-1] - t[0])) if len(t) > 1 and t[-1] > t[0] else None,
            "late_steps": self.late_steps,
            "skipped_slots": self.skipped_slots,
            "held_steps": self.held_steps,
            "rejected_actions": self.rejected_actions,
            "jitter_p50_ms": float(np.percentile(jitter, 50)) if len(jitter) else None,
            "jitter_p99_ms": float(np.percentile(jitter, 99)) if len(jitter) else None,
            "max_temperature_c": None if math.isnan(self.max_temperature_c) else float(self.max_temperature_c),
            "rotation_rad": self.rotation_rad,
            "object_fell": self.object_fell,
        }
        return out

    def shortfall(self, max_fraction: float) -> str | None:
        """Why the loop did not hold its rate: more than ``max_fraction`` of its slots (steps run + slots skipped)
        were late, held or skipped; None when it did."""
        slots = len(self.tick_times) + self.skipped_slots
        bad = self.degraded_steps + self.skipped_slots
        if slots == 0 or bad <= max_fraction * slots:
            return None
        return (f"{bad} of {slots} control slots were late, held or skipped (more than {max_fraction:.0%}; late "
                f"{self.late_steps}, held {self.held_steps}, skipped {self.skipped_slots}): the policy did not run "
                "as it was trained")


class RotationMeter:
    """Accumulates the object's rotation about ROTATION_AXIS from successive poses (7,); stops at a fall."""

    def __init__(self, pose0: np.ndarray) -> None:
        self.pos0 = pose0[:3].copy()
        self.quat = pose0[3:].copy()
        self.rotation = 0.0
        self.fell = False

    def update(self, pose: np.ndarray) -> None:
        if self.fell:
            return
        pos, quat = pose[:3], pose[3:]
        if pos[2] < self.pos0[2] - FALL_DROP_M or np.linalg.norm(pos - self.pos0) > FALL_DISTANCE_M:
            self.fell = True
            log.warning("the object fell (%.3f m below / %.3f m from its start); rotation counted up to here: "
                        "%+.2f rad", self.pos0[2] - pos[2], np.linalg.norm(pos - self.pos0), self.rotation)
            return
        self.rotation += float(angular_velocity(self.quat, quat, 1.0) @ ROTATION_AXIS)  # rad over this step
        self.quat = quat.copy()


class TemperatureMonitor:
    """Polls ``hand.info()`` every ``every_s`` on a daemon thread; ``max_c`` is the hottest joint seen (C)."""

    def __init__(self, hand, every_s: float, initial_c: float = float("nan")) -> None:
        self.hand = hand
        self.every_s = every_s
        self.max_c = initial_c
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._run, name="deploy-temperature", daemon=True)
        self._thread.start()

    def _run(self) -> None:
        while not self._stop.wait(self.every_s):
            try:
                temps = np.asarray(self.hand.info().temperatures, dtype=np.float64)
            except HandFault:
                return  # the control loop sees the fault at its next read
            except Exception as err:  # a missed poll is not a reason to stop the hand
                if not self._stop.is_set():
                    log.warning("temperature poll failed: %s", err)
                continue
            if np.any(np.isfinite(temps)):
                self.max_c = float(np.nanmax(np.r_[temps, self.max_c]))

    def stop(self) -> None:
        """Ask the thread to stop (does not wait: it may be inside a bus request)."""
        self._stop.set()


class StatusLine:
    """A one-line live status on ``out``: rewritten in place on a terminal, one line per update otherwise."""

    def __init__(self, out: TextIO | None) -> None:
        self.out = out
        self.tty = bool(out is not None and hasattr(out, "isatty") and out.isatty())
        self.shown = False

    def show(self, text: str) -> None:
        if self.out is None:
            return
        self.out.write(("\r\x1b[2K" + text) if self.tty else text + "\n")
        self.out.flush()
        self.shown = True

    def end(self) -> None:
        if self.out is not None and self.tty and self.shown:
            self.out.write("\n")
            self.out.flush()
