"""One emulated Digit 360 fingertip that senses the emulated hand, with the env's simulated sensor model.

:class:`FingertipTouch` samples its fingertip's contact-field row (envs.sensors.digit360, computed by
:meth:`HandPhysics.contact_fields` with the env's own readout) every ``ROW_DT`` seconds of the sensor's device clock,
the env's physics step, so that the rows form a contact track like the env's (envs.sensors.tactile_obs), and keeps the
last ``HISTORY_S`` of them. Everything the sensor outputs is rendered from that track by envs.sensors.digit360_render
with the fingertip's noise key (``finger_key(seed, finger)``) and background, as in the env and the data loader:

- serial streams (:meth:`FingertipTouch.readings`, what the emulator sends on its pty): accelerometer samples at
  400 Hz (``render_imu``, g, already on the 1/4096 g grid of the raw counts) and pressure at 200 Hz
  (``render_pressure``, hPa). A sample at time t depends only on rows at or before t, so the samples up to the next
  row are rendered in one block as soon as a row is taken: one small render per row, nothing per tick. Their
  contact-independent terms (bias, offset, drift, noise: ``imu_terms`` / ``pressure_terms``, the hashing that
  dominates a render's cost) are drawn ``TERMS_AHEAD_S`` ahead in one call;
- camera and microphones (:meth:`FingertipTouch.media_window`, the reader's ``media`` hook,
  rotation.hardware.digit360.reader.Digit360Media): the two frames and the 27,000 audio samples of a window are rendered
  only when a window is asked for, from the stored track, as the env defers its `tactile` observation (a few ms per
  fingertip; the last frames are kept, so a window at 20 Hz usually renders one new frame, not two). Nothing is
  rendered at 30 fps in the background.

Clocks: device time 0 is the emulator's start (:meth:`FingertipTouch.start`, host ``time.monotonic()``); row j holds
the hand as it was when the device clock passed ``j * ROW_DT``, and frame k is at device time k / 30 s (host time
``t0 + k / 30``), as the renderer's grids. The hand's own simulation time is not used: the hand may be held (frozen)
at its grasp while the sensors already stream, and a loaded machine runs it slower than real time; like a real
sensor, the emulated one samples the world as it is when its clock ticks.

Thread-safe: the emulator thread takes rows and serial readings, another thread (the control loop) asks for windows.
"""

from __future__ import annotations

import math
import threading
import time
from collections import OrderedDict
from collections.abc import Callable

import numpy as np

from envs.config import EnvConfig
from envs.sensors.digit360 import FINGERS, NUM_FIELDS
from envs.sensors.digit360_image import render_frames
from envs.sensors.digit360_model import (
    AUDIO_HZ,
    AUDIO_RING_S,
    AUDIO_SAMPLES,
    DEFAULT_MODEL,
    HISTORY_S,
    IMAGE_HZ,
    IMU_HZ,
    INT16_MAX,
    LOOKBACK_S,
    PRESSURE_HZ,
    ContactTrack,
    Digit360Model,
    finger_key,
)
from envs.sensors.digit360_render import WindowIndex
from envs.sensors.digit360_signals import imu_terms, pressure_terms, render_audio, render_imu, render_pressure
from rotation.hardware.digit360.window import WindowNotReady, channel_major
from rotation.sim_hardware.hand_physics import HandPhysics

ROW_DT = EnvConfig.physics_dt
"""Contact rows are sampled at the env's physics step (10 ms): the track the env's model was written for (its
impact threshold is a force rise per physics step)."""
_EPS = 1e-6
"""Tolerance (s) when comparing device times with grid times (as envs.sensors.digit360_render)."""
FRAME_CACHE = 8
"""Rendered frames kept: a window needs frames k-5 and k, and frame k-5 was usually the newest of an earlier window."""
TERMS_AHEAD_S = 1.0
"""Seconds of the serial streams' contact-independent terms drawn in one call."""


def audio_counts(audio: np.ndarray) -> np.ndarray:
    """Rendered audio (2, n) float32 counts (clipped to the int16 range) -> (2, n) int16, as a microphone delivers."""
    return np.clip(np.rint(audio), -INT16_MAX - 1, INT16_MAX).astype(np.int16)


class FingertipTouch:
    """The contact track and the four streams of one fingertip of an emulated hand (see the module docstring).

    Args:
        physics: the emulated hand whose fingertip is sensed.
        finger: one of envs.sensors.digit360.FINGERS.
        seed: session noise key; the fingertip's key is ``finger_key(seed, finger index)``, as in simulated sessions.
        model: the sensor model's parameters (the env's default).
    """

    def __init__(self, physics: HandPhysics, finger: str, seed: int = 0, model: Digit360Model = DEFAULT_MODEL) -> None:
        if finger not in FINGERS:
            raise ValueError(f"FingertipTouch: unknown finger {finger!r}; fingers: {', '.join(FINGERS)}")
        self.physics, self.finger, self.model = physics, finger, model
        self.sensor = FINGERS.index(finger)
        """Fingertip index: picks the contact rows and the static background of the tactile image."""
        self.key = int(finger_key(seed, self.sensor))
        self.dt = ROW_DT
        capacity = int(math.ceil(HISTORY_S / self.dt)) + 2  # a window's history plus the rows interpolation holds
        self._times = np.zeros(capacity)
        self._rows = np.zeros((capacity, NUM_FIELDS), dtype=np.float32)
        self._count = 0  # rows taken so far; row j is at device time j * dt, in slot j % capacity
        self._t0: float | None = None
        self._lock = threading.Lock()
        self._recent: tuple[int, ContactTrack] | None = None  # (row_count, the newest rows) for the serial streams
        self._serial_rows = 3 if model.generation < 2 else 3 + int(math.ceil(LOOKBACK_S / self.dt))
        """Rows a serial sample reads: the two it interpolates between (and one held), plus the look-back of the
        generation-2 model's gel lag and vibration."""
        self._imu = _SerialStream(self, IMU_HZ, render_imu, imu_terms, lambda t, a, b: (t[0], t[1][a:b]))
        self._pressure = _SerialStream(self, PRESSURE_HZ, render_pressure, pressure_terms,
                                       lambda t, a, b: (t[0][a:b], t[1][a:b]))
        self._media_lock = threading.Lock()
        self._frames: OrderedDict[int, np.ndarray] = OrderedDict()  # frame index -> (224, 224, 3) uint8
        self._window: tuple[int, tuple[np.ndarray, np.ndarray]] | None = None  # (frame, (image, audio)) of the last

    @property
    def row_count(self) -> int:
        """Contact rows taken since the start; the newest is at device time ``(row_count - 1) * dt``."""
        return self._count

    @property
    def t0(self) -> float | None:
        """Host time (``time.monotonic()`` s) of device time 0; None before :meth:`start`."""
        return self._t0

    def start(self, t0: float) -> None:
        """Start the device clock at host time ``t0`` (the emulator's start); the track starts empty."""
        with self._lock:
            self._t0, self._count = float(t0), 0
        self._recent = None
        self._imu.reset()
        self._pressure.reset()
        with self._media_lock:
            self._frames.clear()
            self._window = None

    # ------------------------------------------------------------------------------------------ contact track
    def sample_until(self, t: float) -> None:
        """Take the rows due at device times up to ``t`` (s) from the hand. Rows missed while the emulator was
        paused or late all get the hand's current state (the sensor saw nothing in between)."""
        due = int(math.floor(t / self.dt + _EPS)) + 1  # rows j with j * dt <= t
        if due <= self._count:
            return
        row = self.physics.contact_fields()[self.sensor]  # (NUM_FIELDS,)
        with self._lock:
            for j in range(max(self._count, due - len(self._times)), due):
                slot = j % len(self._times)
                self._times[slot], self._rows[slot] = j * self.dt, row
            self._count = due

    def track(self, last: int | None = None) -> ContactTrack:
        """The stored rows (the ``last`` newest, default all) as a ContactTrack, oldest first, on the device clock."""
        with self._lock:
            if self._count == 0:
                raise WindowNotReady(f"emulated digit360 {self.finger}: no contact rows yet")
            n = min(self._count, len(self._times), last or len(self._times))
            slots = np.arange(self._count - n, self._count) % len(self._times)
            return ContactTrack(self._times[slots], self._rows[slots], self.dt)

    def recent(self) -> ContactTrack:
        """The newest rows, as many as a causal serial sample needs (it interpolates between the two newest), built
        once per new row (the emulator thread's view)."""
        if self._recent is None or self._recent[0] != self._count:
            self._recent = (self._count, self.track(last=self._serial_rows))
        return self._recent[1]

    # ------------------------------------------------------------------------------------------ serial streams
    def readings(self, tick: int) -> tuple[np.ndarray, float | None]:
        """The serial readings of IMU tick ``tick`` (device time tick / 400 s): the accelerometer (3,) in g and, on
        even ticks, the pressure sample tick / 2 in hPa (None on odd ticks). Ticks must not go back in time."""
        self.sample_until(tick / IMU_HZ)
        pressure = float(self._pressure.sample(tick // 2)) if tick % 2 == 0 else None  # 200 Hz: every second tick
        return self._imu.sample(tick), pressure

    # ------------------------------------------------------------------------------------------ camera and microphones
    def media_window(self, t_end: float | None = None) -> tuple[np.ndarray, np.ndarray, float]:
        """Image and audio of the window ending at the newest frame at or before ``t_end`` (host s; None: now) that
        the stored rows determine (see rotation.hardware.digit360.reader.Digit360Media): ``image`` (6, 224, 224) uint8
        channel-major [R(t-5), R(t), G(t-5), G(t), B(t-5), B(t)], ``audio`` (2, 27000) int16, the frame's host
        time. WindowNotReady until the track reaches back to the window's first frame and audio sample (and the
        ring-down time before it)."""
        if self._t0 is None:
            raise WindowNotReady(f"emulated digit360 {self.finger}: not started")
        track = self.track()
        t_dev = (time.monotonic() if t_end is None else t_end) - self._t0
        frame = int(math.floor(min(t_dev, track.times[-1]) * IMAGE_HZ + _EPS))
        w = WindowIndex(frame)
        start = min(w.frames[0] / IMAGE_HZ, w.audio_first / AUDIO_HZ - AUDIO_RING_S)  # impacts ring into the audio
        if start < track.times[0] - _EPS:
            raise WindowNotReady(f"emulated digit360 {self.finger}: {track.times[-1] - track.times[0]:.3f} s of "
                                 f"touch history, the image and audio windows need {w.time - start:.3f} s")
        with self._media_lock:
            if self._window is None or self._window[0] != frame:
                pair = np.stack([self._frame(track, int(k)) for k in w.frames])  # (2, 224, 224, 3)
                audio = render_audio(track, w.audio_first, AUDIO_SAMPLES, self.key, self.model)  # (2, 27000)
                self._window = (frame, (channel_major(pair), audio_counts(audio)))
            image, audio = self._window[1]
        return image.copy(), audio.copy(), self._t0 + w.time

    def _frame(self, track: ContactTrack, k: int) -> np.ndarray:
        """Frame ``k`` (224, 224, 3) uint8, rendered once: its row (the last at or before k / 30 s) is final."""
        if k not in self._frames:
            self._frames[k] = render_frames(track, np.array([k]), self.key, self.sensor, self.model)[0]
            while len(self._frames) > FRAME_CACHE:
                self._frames.popitem(last=False)
        return self._frames[k]


class _SerialStream:
    """One serial stream of a fingertip (accelerometer or pressure), rendered from its contact rows.

    ``render(track, samples, key, model, terms=...)`` is render_imu / render_pressure; ``draw(samples, key, model)``
    their contact-independent terms (imu_terms / pressure_terms), and ``cut(terms, a, b)`` the terms of the samples
    a..b-1 of a drawn block.
    """

    def __init__(self, touch: FingertipTouch, rate: float, render: Callable[..., np.ndarray],
                 draw: Callable[..., tuple[np.ndarray, np.ndarray]],
                 cut: Callable[[tuple[np.ndarray, np.ndarray], int, int], tuple[np.ndarray, np.ndarray]]) -> None:
        self.touch, self.rate, self._render, self._draw, self._cut = touch, rate, render, draw, cut
        self.reset()

    def reset(self) -> None:
        self._first, self._values = 0, np.zeros(0, np.float32)  # rendered samples _first.. (n, ...)
        self._terms_first, self._terms_len, self._terms = 0, 0, None  # drawn terms of samples _terms_first..

    def sample(self, index: int) -> np.ndarray:
        """Sample ``index`` (time index / rate on the device clock); its rows must have been taken."""
        if not self._first <= index < self._first + len(self._values):
            # render from ``index`` up to the last sample the rows so far determine: times before the newest row + dt
            # (a causal sample needs only rows at or before its time)
            touch = self.touch
            last = max(index, int(math.ceil(touch.row_count * touch.dt * self.rate - _EPS)) - 1)
            samples = np.arange(index, last + 1)
            self._values = self._render(touch.recent(), samples, touch.key, touch.model,
                                        terms=self._terms_of(index, last + 1))
            self._first = index
        return self._values[index - self._first]

    def _terms_of(self, a: int, b: int) -> tuple[np.ndarray, np.ndarray]:
        """The contact-independent terms of samples a..b-1, from the drawn block (drawing the next block first if
        it does not hold them)."""
        if self._terms is None or a < self._terms_first or b > self._terms_first + self._terms_len:
            self._terms_first = a
            self._terms_len = max(b - a, int(TERMS_AHEAD_S * self.rate))
            samples = np.arange(a, a + self._terms_len)
            self._terms = self._draw(samples, self.touch.key, self.touch.model)
        return self._cut(self._terms, a - self._terms_first, b - self._terms_first)
