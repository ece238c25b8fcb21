"""A Digit 360 data channel on a pseudo-terminal: COBS-framed protobuf ``Digit360Message`` frames of the device's
wire schema (rotation/hardware/digit360/digit360.proto).

Streams (docs/reference/hardware.md section 4, rates from docs/reference/sparsh.md): a ``system_data`` message at
start and every second (firmware version major, minor), raw accelerometer ``imu_data`` frames at 400 Hz (float
counts, 4096 per g: rotation.hardware.digit360.protocol) and ``pressure_data`` frames at 200 Hz (hPa, about 1000 at
rest, rising with contact force). ``ts`` fields are emulated device time in milliseconds, as the device's.

Beside an emulated hand (``physics=``, ``finger=``) the sensor senses that hand's fingertip with the env's simulated
Digit 360 (rotation.sim_hardware.digit360_touch.FingertipTouch): IMU and pressure rendered from the fingertip's
contact history, and ``emu.media``, the camera and microphones that the reader takes instead of devices
(``Digit360(cfg, media=emu.media)``), rendered when a window is asked for. Without a hand, readings come from
``source(t) -> (force_N, accel_g (3,))`` with pressure ``REST_HPA + HPA_PER_N * force``; the default is synthetic
(a slow 0..1 N press and gravity plus a small vibration), and there is no camera or microphone (``media`` None).

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

from envs.scene import touch_model
from rotation.hardware.digit360.protocol import ACC_LSB_PER_G, IMU_TYPE, TS_HZ, messages
from rotation.sim_hardware.digit360_touch import FingertipTouch
from rotation.sim_hardware.hand_physics import HandPhysics
from rotation.sim_hardware.pty_link import PtyLink
from rotation.sim_hardware.worker import EmulatorThread

log = logging.getLogger(__name__)

IMU_PERIOD_S = 1.0 / 400.0
PRESSURE_EVERY = 2  # pressure at 200 Hz = every second IMU tick
BATCH_TICKS = 4
"""IMU ticks written per wake-up (every 10 ms), each with its own device time stamp, as a USB host receives them
in bursts. One wake-up per tick (four sensors: 1,600 a second) kept the interpreter's lock so busy that the
policy's thread in the same process missed its 30 ms budget on a slower 2-core machine."""
HPA_PER_N = 20.0
"""Emulated pressure rise per newton of contact force (hPa/N) of a ``source``, a made-up sensitivity (a hand's
fingertip uses the env's model instead)."""
REST_HPA = 1000.0
"""Pressure of a ``source`` at zero force (hPa)."""


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
    """Stop streaming once for this long [window() raises SensorStale after stale_timeout_s]: the samples of the
    pause's device times are never sent (from ``pause_at``, or from when the emulator's thread sees the request)."""
    pause_at: float | None = None
    """Host time (``time.monotonic()`` s) the pause starts; :meth:`pause` sets it with the request."""
    latency_s: float = 0.0
    """Deliver every sample this long after its device time, from now on (a slower link) [a reader on the host's
    clock (``Digit360Config.host_epoch_s``, as deploy gives its emulated fingertips) sees its windows end that much
    further in the past, and a deploy's touch age grows by it; a reader that learns the clock (a real sensor's)
    takes a delay that stays for its clock and cannot see it]."""

    def pause(self, seconds: float) -> None:
        """Stall the stream for ``seconds`` from now: the samples of those device times are lost, also when the
        emulator's thread runs late (a loaded machine) and sees the request only later."""
        self.pause_at = time.monotonic()
        self.pause_s = seconds


class Digit360Emulator(EmulatorThread):
    """Context manager streaming on ``emu.path`` until closed.

    Args:
        source: readings without a hand, ``source(t) -> (force_N, accel_g (3,))`` (see the module docstring).
        version: the firmware version (major, minor) the ``system_data`` messages report.
        physics: an emulated hand: sense its fingertip ``finger`` instead of ``source`` (and provide ``media``).
        finger: the fingertip of ``physics`` (envs.sensors.digit360.FINGERS).
        seed: noise key of the emulated session (the fingertip's key is derived from it, as in the env).
        epoch: host time (``time.monotonic()`` s) of device time 0; default: when the emulator starts. The sensors of
            one hand share one, so that they sample the hand at the same instants and one computation of the hand's
            contact fields serves them all (HandPhysics caches it per physics step).
    """

    def __init__(self, source: Callable[[float], tuple[float, np.ndarray]] = synthetic_source,
                 version: tuple[int, int] = (1, 22), *, physics: HandPhysics | None = None, finger: str = "index",
                 seed: int = 0, epoch: float | None = None, linacc: bool = False) -> None:
        if physics is not None and source is not synthetic_source:
            raise ValueError("Digit360Emulator: give a source or a hand's physics, not both")
        self.source = source
        self.linacc = bool(linacc)
        self.version = version
        self.epoch = epoch
        # the emulated hand's own sensor model (dome radius and generation: envs.scene.touch_model)
        sensor = touch_model(physics.hand) if physics is not None else None
        self.touch = FingertipTouch(physics, finger, seed, sensor) if physics is not None else None
        """The sensed fingertip of ``physics`` (None with a ``source``)."""
        self.faults = Digit360Faults()
        self.link = PtyLink()
        self.path = self.link.path
        self._msg = messages()["Digit360Message"]
        self._init_worker("digit360-emulator")
        self.frames_out = 0

    def _close_link(self) -> None:
        self.link.close()

    @property
    def media(self) -> FingertipTouch | None:
        """Emulated camera and microphones for the reader (``Digit360(cfg, media=emu.media)``); None without a
        hand."""
        return self.touch

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
        m.system_data.version_major, m.system_data.version_minor = self.version
        self._emit(m)

    def _readings(self, k: int) -> tuple[np.ndarray, float | None]:
        """IMU tick ``k`` (device time k / 400 s): accelerometer (3,) g, and pressure (hPa) on pressure ticks."""
        if self.touch is not None:
            return self.touch.readings(k)
        force, accel = self.source(k * IMU_PERIOD_S)
        return np.asarray(accel), (REST_HPA + HPA_PER_N * float(force) if k % PRESSURE_EVERY == 0 else None)

    def _run(self) -> None:
        t0 = time.monotonic() if self.epoch is None else self.epoch  # device time 0 in host time (frame stamps)
        if self.touch is not None:
            self.touch.start(t0)
        k = 0
        self._system()
        while not self._stop.is_set():
            t0_late = t0 + self.faults.latency_s  # a sample leaves latency_s after its device time
            next_t = t0_late + (k + BATCH_TICKS) * IMU_PERIOD_S
            self.link.read(max(0.0, next_t - time.monotonic()))  # drain host -> device bytes; also paces
            if time.monotonic() < next_t:
                continue
            k = self._send_due(k, t0_late)
            if self.faults.pause_s > 0:
                k = self._pause(k, t0_late)

    def _send_due(self, k: int, t0_late: float) -> int:
        """Send every tick after ``k`` whose sending time has come, up to a pause's request; returns the last one
        sent."""
        due = int((time.monotonic() - t0_late) / IMU_PERIOD_S)
        while k < due and not self._stop.is_set() and self.faults.pause_s <= 0:
            k += 1
            self._tick(k)
        return k

    def _pause(self, k: int, t0_late: float) -> int:
        """A requested pause: the device clock runs on and the ticks of the pause's device times are lost. First
        every tick due before the pause starts, so that a thread running late (a loaded machine) loses only the
        pause's own samples, not the backlog it was catching up on; nothing is sent until the pause has ended.
        Returns the last tick taken as sent (the pause's last)."""
        faults = self.faults
        start = faults.pause_at if faults.pause_at is not None else time.monotonic()
        pause, faults.pause_s, faults.pause_at = faults.pause_s, 0.0, None
        first = int((start - t0_late) / IMU_PERIOD_S)  # the last tick due before the pause
        while k < first and not self._stop.is_set():
            k += 1
            self._tick(k)
        self._stop.wait(max(0.0, start + pause - time.monotonic()))
        return max(k, int((start + pause - t0_late) / IMU_PERIOD_S))

    def _tick(self, k: int) -> None:
        """Write IMU tick ``k`` (and its pressure sample, and every 400th tick a ``system`` message)."""
        t = k * IMU_PERIOD_S
        ts = int(t * TS_HZ) & 0xFFFFFFFF  # the device's millisecond clock
        try:
            accel, pressure = self._readings(k)
        except Exception:  # a broken source must not kill the stream silently
            log.exception("digit360 emulator: source failed at t=%.3f s", t)
            return
        m = self._msg()
        m.imu_data.ts = ts
        m.imu_data.raw.sensor = IMU_TYPE["ACC"]
        m.imu_data.raw.ts_ght = k
        m.imu_data.raw.x, m.imu_data.raw.y, m.imu_data.raw.z = (float(a) * ACC_LSB_PER_G for a in accel)
        self._emit(m)
        if self.linacc:
            gravity = (self.touch.physics.gravity_in_sensor(self.touch.finger) if self.touch is not None
                       else np.array([0.0, 0.0, -1.0]))
            lin = self._msg()
            lin.imu_data.ts = ts
            lin.imu_data.raw.sensor = IMU_TYPE["AUX_IMU"]
            lin.imu_data.raw.ts_ght = k
            lin.imu_data.raw.x, lin.imu_data.raw.y, lin.imu_data.raw.z = (
                float(a) * ACC_LSB_PER_G for a in np.asarray(accel) + gravity)
            self._emit(lin)
        if pressure is not None:
            p = self._msg()
            p.pressure_data.ts = ts
            p.pressure_data.pressure = pressure
            p.pressure_data.temperature = 30.0
            self._emit(p)
        if k % 400 == 0:
            self._system()
