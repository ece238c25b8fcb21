"""Digit 360 streams rendered from contact fields: tactile image, contact audio, IMU and pressure.

Input: one fingertip's :class:`ContactTrack`, the contact-field rows of :mod:`envs.sensors.digit360` at the physics
rate with their times. Output: the four streams on their own clocks (docs/reference/hardware.md section 4; grids start
at session / episode time 0): images at 30 fps (frame k at k/30 s), audio at 48 kHz (2 channels, int16 counts as
floats), accelerometer at 400 Hz (g), pressure at 200 Hz (hPa); and :func:`render_window`, the raw material of one
Sparsh-X input window (docs/reference/sparsh.md "Sparsh-X input contract") ending at an image timestamp.

The model, honestly:

- **Physical** (from MuJoCo): contact locations on the dome, normal and shear forces, normal and slip velocities at
  the contact point, the dome's specific force (accelerometer), all at the physics rate (100 Hz by default).
- **Image**: each contact indents the elastomer with the Hertz solution for a sphere of the dome's radius on an
  elastic half-space (Johnson, *Contact Mechanics*, 1985, section 3.4, eqs. 3.39-3.42): contact radius
  ``a = (3 F R / 4 E*)^(1/3)``, depth ``a^2 / R`` and the surface displacement inside and outside the contact;
  shear shifts the patch by the Mindlin tangential compliance ``3 (2 - nu) F_t / (8 G a)`` (ibid. section 7.2).
  The displacement field is seen through an equidistant fisheye (the site's z axis is the optical axis) and shaded
  like a photometric-stereo elastomer (Johnson & Adelson, "Retrographic sensing", CVPR 2009): three colored light
  directions, intensity change proportional to the surface slope along each, over a static illuminated background
  whose mean color equals the released Sparsh-X image mean (docs/reference/sparsh.md). A cheap stand-in: no optics,
  no real LED layout, no marker texture, no gel hysteresis; the elastomer modulus is a typical value, not measured.
- **Audio**: a noise floor; impacts (rises of the total normal force between substeps) ring a bank of decaying
  modes; slip makes band-limited noise whose amplitude follows normal force x slip speed (frictional power); two
  microphones differ by their distance to the contact. Mode frequencies, decays and gains are chosen to sound
  plausible, not identified from a real sensor. Nothing above the physics rate is physical: ringing is synthesized.
- **IMU**: the simulated accelerometer, interpolated to 400 Hz, in g, with bias, white noise and the 1/4096 g
  quantization of the real sensor's raw counts (docs/reference/hardware.md section 4). No content above 50 Hz.
- **Pressure**: a barometric reading around 1000 hPa that rises with the normal force, with a per-session offset, a
  slow drift and white noise. The force-to-pressure gain is a guess of the right order, not a calibration.

Causality: a stream sample at time t depends only on contact rows with times <= t (continuous quantities are
interpolated with a one-physics-step lag, images hold the last row). Determinism: every random number is a pure
function of (key, stream, absolute sample index), drawn from counter-based hashes (envs.rng.splitmix64) or from
fixed noise tables read at hashed offsets, so two overlapping windows agree on their overlap and nothing depends on
the order in which windows are rendered.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from envs.sensors.digit360_image import render_frames
from envs.sensors.digit360_model import (
    AUDIO_HZ,
    AUDIO_SAMPLES,
    DEFAULT_MODEL,
    FRAME_GAP,
    IMAGE_HZ,
    IMAGE_SIZE,
    IMU_HZ,
    IMU_SAMPLES,
    LOOKBACK_S,
    PRESSURE_HZ,
    PRESSURE_SAMPLES,
    ContactTrack,
    Digit360Model,
)
from envs.sensors.digit360_signals import render_audio, render_imu, render_pressure


# ---------------------------------------------------------------------------------------------------- windows
@dataclass(frozen=True)
class WindowIndex:
    """Sample indices of one Sparsh-X window ending at image frame ``frame`` (time frame / 30 s)."""

    frame: int

    @property
    def time(self) -> float:
        return self.frame / IMAGE_HZ

    @property
    def frames(self) -> np.ndarray:
        """The two frames, oldest first: [t-5, t]."""
        return np.array([self.frame - FRAME_GAP, self.frame], dtype=np.int64)

    @property
    def audio_first(self) -> int:
        """First audio sample: the window is [last - 26999, last], last = the sample at the frame time."""
        return self.frame * AUDIO_HZ // int(IMAGE_HZ) - AUDIO_SAMPLES + 1

    @property
    def imu(self) -> np.ndarray:
        last = int(math.floor(self.frame * IMU_HZ / IMAGE_HZ + 1e-9))
        return np.arange(last - IMU_SAMPLES + 1, last + 1, dtype=np.int64)

    @property
    def pressure(self) -> np.ndarray:
        last = int(math.floor(self.frame * PRESSURE_HZ / IMAGE_HZ + 1e-9))
        return np.arange(last - PRESSURE_SAMPLES + 1, last + 1, dtype=np.int64)

    @property
    def start_time(self) -> float:
        """Time of the earliest sample the window holds (s): the pressure window's first sample."""
        return min(self.pressure[0] / PRESSURE_HZ, self.audio_first / AUDIO_HZ, self.imu[0] / IMU_HZ,
                   self.frames[0] / IMAGE_HZ)


def render_window(track: ContactTrack, frame: int, key: int, sensor: int = 0, model: Digit360Model = DEFAULT_MODEL,
                  size: int = IMAGE_SIZE) -> dict[str, np.ndarray]:
    """Raw streams of one window ending at image ``frame``: ``image`` (2, size, size, 3) uint8 [t-5, t],
    ``audio`` (2, 27000) float32 counts, ``imu`` (224, 3) float32 g, ``pressure`` (224,) float32 hPa.

    Uses only contact rows at or before the frame time; before the track starts, its first row is held.
    """
    w = WindowIndex(int(frame))
    track = track.clip(w.start_time - LOOKBACK_S - 2 * track.dt, w.time)  # the rows this window can use
    return {
        "image": render_frames(track, w.frames, key, sensor, model, size),
        "audio": render_audio(track, w.audio_first, AUDIO_SAMPLES, key, model),
        "imu": render_imu(track, w.imu, key, model),
        "pressure": render_pressure(track, w.pressure, key, model),
    }
