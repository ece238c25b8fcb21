"""A Digit 360 data channel on a pseudo-terminal: COBS-framed protobuf ``DigitMessage`` frames.

Streams (reference/hardware.md section 4, rates from reference/sparsh.md): a ``system`` message at start and
every second, raw accelerometer IMU frames at 400 Hz (counts, 4096 per g) and pressure frames at 200 Hz (hPa,
about 1000 at rest, rising with contact force). ``ts`` fields are emulated device time in microseconds.

Readings come from ``source(t) -> (force_N, accel_g (3,))``; the default is synthetic (a slow 0..1 N press and
gravity plus a small vibration). The simulated touch of the env can be plugged in as the source later.

Fault switches (``emu.faults``): corrupt frames, a stream pause, and :meth:`disconnect` (the pty closes).
"""

from __future__ import annotations

import logging
import math
import time
from collections.abc import Callable
from dataclasses import dataclass

import numpy as np
from cobs import cobs

from rotation.hardware.digit360 import ACC_PER_G, SENSOR, messages
from rotation.sim_hardware.pty_link import PtyLink
from rotation.sim_hardware.worker import EmulatorThread

log = logging.getLogger(__name__)

IMU_PERIOD_S = 1.0 / 400.0
PRESSURE_EVERY = 2  # pressure at 200 Hz = every second IMU tick
HPA_PER_N = 20.0
"""Emulated pressure rise per newton of contact force (hPa/N), a made-up sensitivity."""
REST_HPA = 1000.0


def synthetic_source(t: float) -> tuple[float, np.ndarray]:
    """Default readings: force 0..1 N at 0.5 Hz; accel = gravity on z plus a 0.01 g 120 Hz vibration (g)."""
    force = 0.5 * (1.0 - math.cos(2.0 * math.pi * 0.5 * t))
    return force, np.array([0.0, 0.01 * math.sin(2.0 * math.pi * 120.0 * t), 1.0])


@dataclass
class Digit360Faults:
    """Fault injection; the driver's documented reaction is in brackets."""

    corrupt_frames: int = 0
    """Corrupt the next N frames [frame dropped and counted, a warning logged]."""
    pause_s: float = 0.0
    """Stop streaming once for this long [window() raises SensorStale after stale_timeout_s]."""


class Digit360Emulator(EmulatorThread):
    """Context manager streaming on ``emu.path`` until closed."""

    def __init__(self, source: Callable[[float], tuple[float, np.ndarray]] = synthetic_source,
                 version: str = "emulated-1.0") -> None:
        self.source = source
        self.version = version
        self.faults = Digit360Faults()
        self.link = PtyLink()
        self.path = self.link.path
        self._msg = messages()["DigitMessage"]
        self._init_worker("digit360-emulator")
        self.frames_out = 0

    def _close_link(self) -> None:
        self.link.close()

    def disconnect(self) -> None:
        """Emulate unplugging the sensor."""
        self.link.disconnect()

    def _emit(self, msg) -> None:
        frame = cobs.encode(msg.SerializeToString())
        if self.faults.corrupt_frames > 0:
            self.faults.corrupt_frames -= 1
            frame = bytes([0x01]) + frame[1:]  # a COBS code byte pointing at the wrong place
        self.link.write(frame + b"\x00")
        self.frames_out += 1

    def _system(self) -> None:
        m = self._msg()
        m.system.version = self.version
        self._emit(m)

    def _run(self) -> None:
        t0 = time.perf_counter()
        k = 0
        self._system()
        while not self._stop.is_set():
            next_t = t0 + (k + 1) * IMU_PERIOD_S
            self.link.read(max(0.0, next_t - time.perf_counter()))  # drain host -> device bytes; also paces
            if time.perf_counter() < next_t:
                continue
            if self.faults.pause_s > 0:  # the device clock runs on; the samples of the pause are lost
                pause, self.faults.pause_s = self.faults.pause_s, 0.0
                self._stop.wait(pause)
                k = int((time.perf_counter() - t0) / IMU_PERIOD_S)
            k += 1
            t = k * IMU_PERIOD_S
            ts = int(t * 1e6) & 0xFFFFFFFF
            try:
                force, accel = self.source(t)
            except Exception:  # a broken source must not kill the stream silently
                log.exception("digit360 emulator: source failed at t=%.3f s", t)
                continue
            m = self._msg()
            m.imu.ts = ts
            m.imu.raw.sensor = SENSOR["ACC"]
            m.imu.raw.x, m.imu.raw.y, m.imu.raw.z = (int(round(a * ACC_PER_G)) for a in accel)
            self._emit(m)
            if k % PRESSURE_EVERY == 0:
                p = self._msg()
                p.pressure.ts = ts
                p.pressure.pressure = REST_HPA + HPA_PER_N * float(force)
                p.pressure.temperature = 30.0
                self._emit(p)
            if k % 400 == 0:
                self._system()
