"""Digit 360 streams rendered from contact fields: tactile image, contact audio, IMU and pressure.

Input: one fingertip's :class:`ContactTrack`, the contact-field rows of :mod:`envs.sensors.digit360` at the physics
rate with their times. Output: the four streams on their own clocks (reference/hardware.md section 4; grids start
at session / episode time 0): images at 30 fps (frame k at k/30 s), audio at 48 kHz (2 channels, int16 counts as
floats), accelerometer at 400 Hz (g), pressure at 200 Hz (hPa); and :func:`render_window`, the raw material of one
Sparsh-X input window (reference/sparsh.md "Sparsh-X input contract") ending at an image timestamp.

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
  whose mean color equals the released Sparsh-X image mean (reference/sparsh.md). A cheap stand-in: no optics,
  no real LED layout, no marker texture, no gel hysteresis; the elastomer modulus is a typical value, not measured.
- **Audio**: a noise floor; impacts (rises of the total normal force between substeps) ring a bank of decaying
  modes; slip makes band-limited noise whose amplitude follows normal force x slip speed (frictional power); two
  microphones differ by their distance to the contact. Mode frequencies, decays and gains are chosen to sound
  plausible, not identified from a real sensor. Nothing above the physics rate is physical: ringing is synthesized.
- **IMU**: the simulated accelerometer, interpolated to 400 Hz, in g, with bias, white noise and the 1/4096 g
  quantization of the real sensor's raw counts (reference/hardware.md section 4). No content above 50 Hz.
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
from functools import lru_cache

import numpy as np

from envs.rng import splitmix64
from envs.sensors.digit360 import CONTACT_SLOTS, DOME_RADIUS, FIELD

IMAGE_HZ = 30.0
"""Camera frame rate (reference/hardware.md section 4)."""
IMAGE_SIZE = 224
"""Contract image side (reference/sparsh.md)."""
FRAME_GAP = 5
"""The contract's two frames are t-5 and t (reference/sparsh.md)."""
AUDIO_HZ = 48000
AUDIO_CHANNELS = 2
AUDIO_SAMPLES = 27000
"""0.5625 s at 48 kHz: 224 Kaldi frames of 240 samples every 120 (reference/sparsh.md)."""
IMU_HZ = 400.0
IMU_SAMPLES = 224
PRESSURE_HZ = 200.0
PRESSURE_SAMPLES = 224
GRAVITY = 9.80665
"""Standard gravity (m/s^2), for accelerometer readings in g."""
IMU_LSB_PER_G = 4096.0
"""Raw accelerometer counts per g (reference/hardware.md section 4: raw / 4096)."""
INT16_MAX = 32767.0

_STREAM_IMAGE, _STREAM_FLOOR, _STREAM_SLIP, _STREAM_IMU, _STREAM_PRESSURE, _STREAM_PARAMS = 11, 12, 13, 14, 15, 16
_TIME_EPS = 1e-6
"""Tolerance (s) when comparing float simulation times with grid times (0.01 s steps accumulate rounding)."""


@dataclass(frozen=True)
class Digit360Model:
    """Parameters of the rendered streams. Values marked 'chosen' are plausible guesses, not measurements."""

    fov_half_angle_deg: float = 115.0
    """Half field of view of the fisheye (deg from the dome's apex); chosen so that contacts on the palmar side of
    the tip (about 90-105 deg from the apex, where grasps touch this hand's domes) stay inside the image."""
    elastomer_modulus: float = 0.3e6
    """Effective modulus E* of the elastomer (Pa); chosen: soft silicone gels are 0.1-1 MPa."""
    poisson: float = 0.5
    """Poisson ratio of the (incompressible) elastomer."""
    shading_gain: float = 0.6
    """Intensity change ([0, 1] units) per unit surface slope along a light's direction (chosen)."""
    depth_gain: float = 40.0
    """Brightening per meter of indentation (the coating nears the lights): 0.04 per mm (chosen)."""
    light_azimuths_deg: tuple[float, float, float] = (90.0, 210.0, 330.0)
    """In-plane directions of the red, green and blue lights (deg from the sensor x axis); chosen, 120 deg apart as
    in three-color photometric stereo."""
    background_mean: tuple[float, float, float] = (0.0956, 0.2659, 0.3246)
    """Mean background color in [0, 1]: the released Sparsh-X image mean (reference/sparsh.md)."""
    camera_noise: float = 1.5 / 255
    """Per-pixel read noise (std, [0, 1] units); chosen, about 1.5 gray levels."""
    audio_floor: float = 8.0
    """Microphone noise floor (std, int16 counts, about -72 dBFS); chosen."""
    impact_gain: float = 4000.0
    """Impact amplitude per newton of normal-force rise within one physics step (counts / N); chosen."""
    impact_threshold: float = 0.02
    """Force rises below this (N) per physics step do not ring (steady squeezing is silent); chosen."""
    modes: tuple[tuple[float, float, float], ...] = (
        (1200.0, 0.012, 1.0), (2900.0, 0.006, 0.6), (5300.0, 0.004, 0.4), (8700.0, 0.0025, 0.25))
    """Ringing modes (frequency Hz, decay time constant s, relative amplitude); chosen stand-ins for the dome's and
    the object's vibration modes."""
    slip_gain: float = 2.0e4
    """Slip noise std per watt-like unit (normal force N x slip speed m/s), counts; chosen."""
    slip_band: tuple[float, float] = (1000.0, 8000.0)
    """Pass band of the slip noise (Hz); chosen (stick-slip squeal of soft gels sits in the low kHz)."""
    mic_positions: tuple[tuple[float, float, float], ...] = ((0.006, 0.0, -0.008), (-0.006, 0.0, -0.008))
    """Microphone positions in the sensor frame (m), at the base of the dome; chosen."""
    mic_distance_scale: float = 0.01
    """Gain of a microphone = d0 / (d0 + distance to the contact), d0 in m; chosen."""
    imu_noise: float = 0.004
    """Accelerometer white noise (std, g); chosen: MEMS accelerometers have ~150-300 ug/sqrt(Hz) x 200 Hz band."""
    imu_bias: float = 0.02
    """Per-axis zero-g offset, uniform in +-this (g); chosen within MEMS datasheet ranges (+-20-50 mg)."""
    pressure_rest: float = 1013.25
    """Mean sea-level pressure (hPa, ISO 2533 standard atmosphere); the real sensor reads ~1000 hPa at rest."""
    pressure_offset: float = 15.0
    """Per-session offset (weather, altitude), uniform in +-this (hPa); chosen."""
    pressure_per_newton: float = 4.0
    """Pressure rise per newton of normal force (hPa / N); chosen, order of magnitude only."""
    pressure_noise: float = 0.03
    """White noise (std, hPa); chosen, typical of MEMS barometers in a high-resolution mode."""
    pressure_drift: float = 0.3
    """Amplitude of a slow thermal drift (hPa) with period ``pressure_drift_period``; chosen."""
    pressure_drift_period: float = 120.0
    """Period of the drift (s); chosen."""


DEFAULT_MODEL = Digit360Model()
AUDIO_RING_S = 5.0 * max(decay for _, decay, _ in DEFAULT_MODEL.modes)
"""How far back an impact still rings (s): five decay times of the default model's slowest mode (a model with
slower modes is cut there)."""
HISTORY_S = (PRESSURE_SAMPLES - 1) / PRESSURE_HZ + 1.0 / IMAGE_HZ + AUDIO_RING_S
"""Contact history (s) a window ending at the latest image frame needs behind the current time: the pressure
window (the longest, 1.115 s), the latest frame's lag behind the current time (< 1/30 s) and the ring-down of
impacts just before the window; add two physics steps for the interpolation lag and the row held at the start."""


# ---------------------------------------------------------------------------------------------------- randomness
def finger_key(key: int, finger: int) -> np.uint64:
    """The 64-bit noise key of fingertip ``finger`` (0-3) of a session or env episode keyed ``key``."""
    with np.errstate(over="ignore"):
        x = np.asarray([int(key) & 0xFFFFFFFFFFFFFFFF], dtype=np.uint64)
        return splitmix64(splitmix64(x) + np.uint64(finger + 1))[0]


def _hash(key: np.uint64, stream: int, index: np.ndarray) -> np.ndarray:
    """uint64 hash of (key, stream, index) for an int array of absolute sample indices."""
    with np.errstate(over="ignore"):
        base = splitmix64(np.asarray([key ^ splitmix64(np.asarray([np.uint64(stream)]))[0]]))[0]
        return splitmix64(np.asarray(index, dtype=np.int64).astype(np.uint64) * np.uint64(0x9E3779B97F4A7C15) + base)


def _uniform(key: np.uint64, stream: int, index: np.ndarray) -> np.ndarray:
    """Uniform [0, 1) floats, one per index."""
    return (_hash(key, stream, index) >> np.uint64(11)).astype(np.float64) * (1.0 / 9007199254740992.0)


_NOISE_BLOCK = 4096
_NOISE_TABLE = 1 << 16


@lru_cache(maxsize=8)
def _normal_table(stream: int) -> np.ndarray:
    """(65536, 2) standard normals of one stream, shared by all keys: the source of :func:`_block_read`."""
    a, b = _normal_pair(np.uint64(0x243F6A8885A308D3), stream, np.arange(_NOISE_TABLE))  # fixed key (digits of pi)
    return np.stack([a, b], axis=1).astype(np.float32)


@lru_cache(maxsize=4)
def _bandpass_table(stream: int, low: float, high: float) -> np.ndarray:
    """(65536, 2) band-limited noise of unit std: the stream's normal table filtered circularly in [low, high] Hz."""
    white = _normal_table(stream).astype(np.float64)
    spectrum = np.fft.rfft(white, axis=0)  # (L/2 + 1, 2)
    freq = np.fft.rfftfreq(_NOISE_TABLE, 1.0 / AUDIO_HZ)
    spectrum[(freq < low) | (freq > high)] = 0.0
    band = np.fft.irfft(spectrum, n=_NOISE_TABLE, axis=0)
    return (band / band.std(axis=0)).astype(np.float32)


def _block_read(table: np.ndarray, key: int, stream: int, index: np.ndarray) -> np.ndarray:
    """Rows of a (65536, C) noise table at consecutive absolute sample indices ``index`` (a contiguous range).

    Each block of 4096 consecutive indices reads a contiguous run of the table at an offset hashed from (key, block
    number), so the values are a pure function of (key, stream, index): cheap for long audio windows, and no
    per-key table is built.
    """
    index = np.asarray(index, dtype=np.int64)
    if len(index) == 0:
        return table[:0]
    first, last = int(index[0]), int(index[-1])
    blocks = np.arange(first // _NOISE_BLOCK, last // _NOISE_BLOCK + 1)
    offsets = (_hash(np.uint64(key), stream + 1000, blocks) % np.uint64(_NOISE_TABLE)).astype(np.int64)
    parts = []
    for b, off in zip(blocks, offsets, strict=True):
        lo, hi = max(first, b * _NOISE_BLOCK), min(last + 1, (b + 1) * _NOISE_BLOCK)  # this block's share
        start = (off + lo - b * _NOISE_BLOCK) % _NOISE_TABLE
        rows = np.arange(start, start + hi - lo) % _NOISE_TABLE if start + hi - lo > _NOISE_TABLE else None
        parts.append(table[rows] if rows is not None else table[start : start + hi - lo])
    return np.concatenate(parts)


def _normal_pair(key: np.uint64, stream: int, index: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Two independent standard normals per index (Box-Muller on the hash's two 32-bit halves)."""
    h = _hash(key, stream, index)
    u1 = ((h >> np.uint64(32)).astype(np.float64) + 0.5) * (1.0 / 4294967296.0)
    u2 = ((h & np.uint64(0xFFFFFFFF)).astype(np.float64) + 0.5) * (1.0 / 4294967296.0)
    r = np.sqrt(-2.0 * np.log(u1))
    return r * np.cos(2.0 * np.pi * u2), r * np.sin(2.0 * np.pi * u2)


# ---------------------------------------------------------------------------------------------------- contact track
@dataclass
class ContactTrack:
    """One fingertip's contact-field rows (T, NUM_FIELDS) at times (T,) (s, increasing), physics step ``dt`` (s)."""

    times: np.ndarray
    rows: np.ndarray
    dt: float

    def __post_init__(self) -> None:
        self.times = np.asarray(self.times, dtype=np.float64)
        self.rows = np.asarray(self.rows, dtype=np.float32)
        if self.times.ndim != 1 or self.rows.ndim != 2 or len(self.times) != len(self.rows) or len(self.times) == 0:
            raise ValueError(f"ContactTrack: need times (T,) and rows (T, D) with T >= 1, got {self.times.shape} "
                             f"and {self.rows.shape}")
        if not self.dt > 0:
            raise ValueError(f"ContactTrack: dt must be > 0, got {self.dt}")
        steps = np.diff(self.times)
        if np.any(steps <= 0) or np.any(steps > self.dt * (1 + 1e-6) + _TIME_EPS):
            # causal interpolation below relies on rows at most dt apart
            raise ValueError(f"ContactTrack: times must increase by at most dt={self.dt} s (one row per physics step)")

    def last_row(self, t: np.ndarray) -> np.ndarray:
        """Index of the last row at or before each time t (the first row before the track starts)."""
        return np.maximum(np.searchsorted(self.times, np.asarray(t) + _TIME_EPS, side="right") - 1, 0)

    def clip(self, t0: float, t1: float) -> ContactTrack:
        """The rows a stream window over [t0, t1] can use: those in it plus the last row before t0 (held)."""
        i0 = int(self.last_row(np.asarray(t0 - _TIME_EPS)))
        i1 = int(np.searchsorted(self.times, t1 + _TIME_EPS, side="right"))
        i1 = max(i1, i0 + 1)
        return ContactTrack(self.times[i0:i1], self.rows[i0:i1], self.dt)

    def causal(self, t: np.ndarray, values: np.ndarray) -> np.ndarray:
        """``values`` (T,) or (T, C) linearly interpolated at times ``t - dt`` (held before the first and after the
        last row): rows are at most dt apart, so the later row of each interpolation is at or before ``t``."""
        tq = np.asarray(t, dtype=np.float64) - self.dt
        values = np.asarray(values, dtype=np.float64)
        if values.ndim == 1:
            return np.interp(tq, self.times, values)
        return np.stack([np.interp(tq, self.times, values[:, c]) for c in range(values.shape[1])], axis=-1)

    def normal_force(self) -> np.ndarray:
        """(T,) total normal force on the dome (N): the sum over contact slots."""
        return sum(self.rows[:, FIELD[f"c{k}_fn"]] for k in range(CONTACT_SLOTS)).astype(np.float64)


# ---------------------------------------------------------------------------------------------------- image
@lru_cache(maxsize=4)
def _pixel_rays(size: int, fov_half_angle_deg: float) -> tuple[np.ndarray, np.ndarray]:
    """Unit view direction of every pixel in the sensor frame (size, size, 3) and the in-circle mask.

    Equidistant fisheye around the sensor z axis: the distance from the image centre is proportional to the angle
    from the axis, the image circle (radius size/2) at ``fov_half_angle_deg``; column ~ sensor x, row ~ sensor y.
    """
    c = (size - 1) / 2.0
    j, i = np.meshgrid(np.arange(size), np.arange(size))  # (S, S) column, row
    x, y = (j - c) / (size / 2.0), (i - c) / (size / 2.0)
    rho = np.hypot(x, y)
    theta = rho * math.radians(fov_half_angle_deg)
    phi = np.arctan2(y, x)
    rays = np.stack([np.sin(theta) * np.cos(phi), np.sin(theta) * np.sin(phi), np.cos(theta)], axis=-1)
    return rays, rho <= 1.0


@lru_cache(maxsize=16)
def _background(size: int, model: Digit360Model, sensor: int) -> np.ndarray:
    """Static illuminated background (size, size, 3) in [0, 1]: vignetting, one-sided light gradients, a fixed grain
    texture of this physical sensor (``sensor``: the fingertip index), dark outside the image circle; scaled so the
    mean color is ``model.background_mean``."""
    rays, inside = _pixel_rays(size, model.fov_half_angle_deg)
    c = (size - 1) / 2.0
    j, i = np.meshgrid(np.arange(size), np.arange(size))
    x, y = (j - c) / (size / 2.0), (i - c) / (size / 2.0)
    rho = np.hypot(x, y)
    vignette = np.clip(1.0 - 0.55 * rho**2, 0.0, None)  # (S, S) brighter centre
    bg = np.empty((size, size, 3))
    for ch, az in enumerate(model.light_azimuths_deg):
        a = math.radians(az)
        bg[..., ch] = vignette * (1.0 + 0.35 * (x * math.cos(a) + y * math.sin(a)))  # brighter toward each light
    grain = _uniform(np.uint64(sensor + 1), _STREAM_PARAMS, np.arange(size * size)).reshape(size, size)
    bg *= (1.0 + 0.06 * (grain - 0.5))[..., None]
    bg[~inside] = 0.05 * bg[~inside]
    bg *= np.asarray(model.background_mean) / bg.reshape(-1, 3).mean(axis=0)
    return bg.astype(np.float32)


def _hertz_profile(rho: np.ndarray) -> np.ndarray:
    """Hertz surface displacement / central depth at r / a = rho (Johnson 1985, eqs. 3.41a-b), tapered to 0 at 4a.

    Inside (rho <= 1): 1 - rho^2 / 2; outside: ((2 - rho^2) asin(1 / rho) + sqrt(rho^2 - 1)) / pi.
    (Normalized by the central displacement a^2 / R.)
    """
    inside = 1.0 - 0.5 * rho**2
    r = np.maximum(rho, 1.0)
    outside = ((2.0 - r**2) * np.arcsin(1.0 / r) + np.sqrt(r**2 - 1.0)) / np.pi
    taper = np.clip((4.0 - rho) / 1.5, 0.0, 1.0) ** 2  # smooth cut of the 1/r tail between 2.5 a and 4 a
    return np.where(rho <= 1.0, inside, outside) * taper


def _indentation(row: np.ndarray, model: Digit360Model, size: int) -> np.ndarray:
    """Elastomer indentation (m, (size, size)) of one frame's contact-field row: Hertz patches, shifted by shear."""
    rays, _ = _pixel_rays(size, model.fov_half_angle_deg)
    disp = np.zeros((size, size))
    fns = [float(row[FIELD[f"c{k}_fn"]]) for k in range(CONTACT_SLOTS)]
    total_fn = sum(fns)
    if total_fn <= 0.0:
        return disp
    e_star = model.elastomer_modulus
    shear_modulus = e_star * (1.0 - model.poisson**2) / (2.0 * (1.0 + model.poisson))  # G = E / 2(1 + nu)
    force = np.array([row[FIELD["force_x"]], row[FIELD["force_y"]], -row[FIELD["force_n"]]], dtype=np.float64)
    half, fov = size / 2.0, math.radians(model.fov_half_angle_deg)
    for k, fn in enumerate(fns):
        if fn <= 0.0 or row[FIELD[f"c{k}_found"]] <= 0:
            continue
        p = np.array([row[FIELD[f"c{k}_{a}"]] for a in "xyz"], dtype=np.float64)
        norm = np.linalg.norm(p)
        if norm < 1e-9:
            continue
        c = p / norm
        a = (3.0 * fn * DOME_RADIUS / (4.0 * e_star)) ** (1.0 / 3.0)  # Hertz contact radius (m)
        depth = a * a / DOME_RADIUS
        # Mindlin: this contact's share of the tangential force drags the patch, at most by its radius
        f_t = (force - force.dot(c) * c) * (fn / total_fn)
        shift = min(3.0 * (2.0 - model.poisson) * np.linalg.norm(f_t) / (8.0 * shear_modulus * a), a)
        if shift > 0:
            c = c + f_t / (np.linalg.norm(f_t) + 1e-12) * shift / DOME_RADIUS
            c /= np.linalg.norm(c)
        theta = math.acos(float(np.clip(c[2], -1.0, 1.0)))
        if theta > fov + 4.0 * a / DOME_RADIUS:
            continue  # behind the camera's view
        # pixel box around the patch: 4 contact radii, converted from arc length to pixels
        rho_c = theta / fov * half
        col = (size - 1) / 2.0 + rho_c * math.cos(math.atan2(c[1], c[0]))
        row_px = (size - 1) / 2.0 + rho_c * math.sin(math.atan2(c[1], c[0]))
        reach = 4.0 * a / DOME_RADIUS / fov * half * max(1.0, theta / max(math.sin(theta), 1e-3)) + 2.0
        r0, r1 = max(0, int(row_px - reach)), min(size, int(row_px + reach) + 2)
        c0, c1 = max(0, int(col - reach)), min(size, int(col + reach) + 2)
        if r0 >= r1 or c0 >= c1:
            continue
        chord = DOME_RADIUS * np.linalg.norm(rays[r0:r1, c0:c1] - c, axis=-1)  # (h, w) ~ arc distance (m)
        disp[r0:r1, c0:c1] += depth * _hertz_profile(chord / a)
    return disp


@lru_cache(maxsize=4)
def _noise_table(size: int) -> np.ndarray:
    """Zero-mean uniform noise (4 size^2,) float32 of unit std; each frame reads a slice at a hashed offset."""
    u = _uniform(np.uint64(0x13198A2E03707344), _STREAM_IMAGE, np.arange(4 * size * size))  # fixed key
    return ((u - 0.5) * math.sqrt(12.0)).astype(np.float32)


def render_frame(row: np.ndarray, frame_index: int, key: int, sensor: int = 0, model: Digit360Model = DEFAULT_MODEL,
                 size: int = IMAGE_SIZE) -> np.ndarray:
    """One tactile image (size, size, 3) uint8 from the contact-field row the camera sees at frame ``frame_index``;
    ``key`` keys the read noise, ``sensor`` (the fingertip index) the static background."""
    disp = _indentation(np.asarray(row), model, size)
    img = _background(size, model, int(sensor)).copy()  # (S, S, 3) float32
    if disp.any():
        # surface slope from the displacement field; one pixel spans this much arc on the dome (m)
        arc_per_px = DOME_RADIUS * math.radians(model.fov_half_angle_deg) / (size / 2.0)
        gy, gx = np.gradient(disp.astype(np.float32), np.float32(arc_per_px))  # (S, S) each, dimensionless slopes
        for ch, az in enumerate(model.light_azimuths_deg):
            a = math.radians(az)
            slope = np.float32(math.cos(a)) * gx + np.float32(math.sin(a)) * gy  # (S, S) along light ch
            img[..., ch] += np.float32(model.shading_gain) * slope
        img += np.float32(model.depth_gain) * disp[..., None].astype(np.float32)
    # read noise: a slice of this sensor's noise table at a pseudo-random offset per frame
    n = size * size
    offset = int(_hash(np.uint64(key), _STREAM_IMAGE, np.array([frame_index]))[0] % np.uint64(3 * n))
    img += np.float32(model.camera_noise) * _noise_table(size)[offset : offset + n].reshape(size, size, 1)
    img *= 255.0
    np.rint(img, out=img)
    return np.clip(img, 0, 255).astype(np.uint8)


def render_frames(track: ContactTrack, frames: np.ndarray, key: int, sensor: int = 0,
                  model: Digit360Model = DEFAULT_MODEL, size: int = IMAGE_SIZE) -> np.ndarray:
    """Images (K, size, size, 3) uint8 at frame indices ``frames`` (frame k at k / 30 s), from the last contact row
    at or before each frame time."""
    frames = np.asarray(frames, dtype=np.int64)
    rows = track.rows[track.last_row(frames / IMAGE_HZ)]  # (K, D)
    return np.stack([render_frame(r, int(k), key, sensor, model, size) for r, k in zip(rows, frames, strict=True)])


# ---------------------------------------------------------------------------------------------------- audio
@lru_cache(maxsize=4)
def _ring_template(model: Digit360Model) -> np.ndarray:
    """(n,) float32 impulse response of the mode bank over AUDIO_RING_S: sum of a exp(-t / tau) sin(2 pi f t)."""
    tau = np.arange(int(AUDIO_RING_S * AUDIO_HZ)) / AUDIO_HZ
    return sum(a * np.exp(-tau / d) * np.sin(2 * np.pi * f * tau) for f, d, a in model.modes).astype(np.float32)


def _mic_gains(points: np.ndarray, model: Digit360Model) -> np.ndarray:
    """(..., 3) contact points (sensor frame, m) -> (..., channels) microphone gains d0 / (d0 + distance)."""
    mics = np.asarray(model.mic_positions)  # (C, 3)
    dist = np.linalg.norm(points[..., None, :] - mics, axis=-1)
    return model.mic_distance_scale / (model.mic_distance_scale + dist)


def _strongest_point(rows: np.ndarray) -> np.ndarray:
    """(T, D) rows -> (T, 3) point of the strongest contact slot (the dome's apex when there is none)."""
    fn = np.stack([rows[:, FIELD[f"c{k}_fn"]] for k in range(CONTACT_SLOTS)], axis=1)  # (T, K)
    best = fn.argmax(axis=1)
    pts = np.stack([np.stack([rows[:, FIELD[f"c{k}_{a}"]] for a in "xyz"], axis=1) for k in range(CONTACT_SLOTS)],
                   axis=1)  # (T, K, 3)
    out = pts[np.arange(len(rows)), best]
    empty = fn.max(axis=1) <= 0
    out[empty] = (0.0, 0.0, DOME_RADIUS)
    return out


def render_audio(track: ContactTrack, first_sample: int, num_samples: int, key: int,
                 model: Digit360Model = DEFAULT_MODEL) -> np.ndarray:
    """Two-channel contact audio (2, n) float32 in int16 counts for samples [first, first + n) at 48 kHz.

    Noise floor + ringing impacts + band-limited slip noise, clipped to the int16 range.
    """
    s = first_sample + np.arange(num_samples, dtype=np.int64)
    t_first, t_end = first_sample / AUDIO_HZ, (first_sample + num_samples) / AUDIO_HZ
    track = track.clip(t_first - AUDIO_RING_S - track.dt, t_end)
    out = np.float32(model.audio_floor) * _block_read(_normal_table(_STREAM_FLOOR), int(key), _STREAM_FLOOR, s).T

    gains = _mic_gains(_strongest_point(track.rows), model)  # (T, C)
    fn = track.normal_force()
    # slip: frictional-power envelope at the physics rate, interpolated causally to 48 kHz, times band noise
    slip = sum(track.rows[:, FIELD[f"c{k}_fn"]] * track.rows[:, FIELD[f"c{k}_slip"]] for k in range(CONTACT_SLOTS))
    if np.any(slip > 0):
        env = track.causal(s / AUDIO_HZ, np.asarray(slip, np.float64)[:, None] * gains)  # (n, C)
        band = _block_read(_bandpass_table(_STREAM_SLIP, *model.slip_band), int(key), _STREAM_SLIP, s)[:, 0]
        out += (model.slip_gain * env.T * band).astype(np.float32)

    # impacts: force rises between consecutive physics rows ring the modes from the row's time on
    rise = np.diff(fn, prepend=fn[:1]) - model.impact_threshold
    ring = _ring_template(model)
    for i in np.flatnonzero(rise > 0):
        onset = int(math.ceil(track.times[i] * AUDIO_HZ - 1e-6))
        lo, hi = max(onset, first_sample), min(onset + len(ring), first_sample + num_samples)
        if lo < hi:
            amp = (model.impact_gain * rise[i] * gains[i]).astype(np.float32)[:, None]  # (C, 1)
            out[:, lo - first_sample : hi - first_sample] += amp * ring[lo - onset : hi - onset]
    return np.clip(out, -INT16_MAX - 1, INT16_MAX)


# ---------------------------------------------------------------------------------------------------- IMU, pressure
def imu_terms(samples: np.ndarray, key: int, model: Digit360Model = DEFAULT_MODEL) -> tuple[np.ndarray, np.ndarray]:
    """The accelerometer's contact-independent terms at 400 Hz sample indices ``samples``: the per-axis bias (3,) and
    the white noise (n, 3), in g. Pure functions of (key, sample index), so a live emulator can draw them ahead in
    blocks and pass them to :func:`render_imu`."""
    samples = np.asarray(samples, dtype=np.int64)
    bias = model.imu_bias * (2.0 * _uniform(np.uint64(key), _STREAM_PARAMS, np.arange(3)) - 1.0)
    n0, n1 = _normal_pair(np.uint64(key), _STREAM_IMU, samples)
    n2, _ = _normal_pair(np.uint64(key), _STREAM_IMU, samples + (1 << 50))
    return bias, model.imu_noise * np.stack([n0, n1, n2], axis=1)


def render_imu(track: ContactTrack, samples: np.ndarray, key: int, model: Digit360Model = DEFAULT_MODEL,
               terms: tuple[np.ndarray, np.ndarray] | None = None) -> np.ndarray:
    """Accelerometer (n, 3) float32 in g at 400 Hz sample indices ``samples`` (sample i at i / 400 s).

    ``terms``: ``imu_terms(samples, key, model)`` when already drawn (the same values; computed here otherwise).
    """
    samples = np.asarray(samples, dtype=np.int64)
    acc = track.causal(samples / IMU_HZ, track.rows[:, FIELD["acc_x"] : FIELD["acc_z"] + 1].astype(np.float64))
    bias, noise = imu_terms(samples, key, model) if terms is None else terms
    g = acc / GRAVITY + bias + noise
    return (np.rint(g * IMU_LSB_PER_G) / IMU_LSB_PER_G).astype(np.float32)


def pressure_terms(samples: np.ndarray, key: int,
                   model: Digit360Model = DEFAULT_MODEL) -> tuple[np.ndarray, np.ndarray]:
    """The barometer's contact-independent terms at 200 Hz sample indices ``samples``: the no-contact level (n,)
    (rest + per-session offset + drift) and the white noise (n,), in hPa. Pure functions of (key, sample index),
    like :func:`imu_terms`."""
    samples = np.asarray(samples, dtype=np.int64)
    t = samples / PRESSURE_HZ
    u = _uniform(np.uint64(key), _STREAM_PARAMS, np.arange(3, 5))
    offset = model.pressure_offset * (2.0 * u[0] - 1.0)
    drift = model.pressure_drift * np.sin(2.0 * np.pi * (t / model.pressure_drift_period + u[1]))
    noise, _ = _normal_pair(np.uint64(key), _STREAM_PRESSURE, samples)
    return model.pressure_rest + offset + drift, model.pressure_noise * noise


def render_pressure(track: ContactTrack, samples: np.ndarray, key: int, model: Digit360Model = DEFAULT_MODEL,
                    terms: tuple[np.ndarray, np.ndarray] | None = None) -> np.ndarray:
    """Pressure (n,) float32 in hPa at 200 Hz sample indices ``samples`` (sample i at i / 200 s).

    ``terms``: ``pressure_terms(samples, key, model)`` when already drawn (the same values; computed here otherwise).
    """
    samples = np.asarray(samples, dtype=np.int64)
    force = track.causal(samples / PRESSURE_HZ, track.normal_force())
    level, noise = pressure_terms(samples, key, model) if terms is None else terms
    p = level + model.pressure_per_newton * force + noise
    return p.astype(np.float32)


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
    track = track.clip(w.start_time - AUDIO_RING_S - 2 * track.dt, w.time)  # the rows this window can use
    return {
        "image": render_frames(track, w.frames, key, sensor, model, size),
        "audio": render_audio(track, w.audio_first, AUDIO_SAMPLES, key, model),
        "imu": render_imu(track, w.imu, key, model),
        "pressure": render_pressure(track, w.pressure, key, model),
    }


def pack_image(frames: np.ndarray) -> np.ndarray:
    """(2, H, W, 3) uint8 frames [t-5, t] -> (6, H, W) float32 in [0, 1], channels
    [R(t-5), R(t), G(t-5), G(t), B(t-5), B(t)] (the released Sparsh-X pairing, reference/sparsh.md)."""
    x = np.asarray(frames, dtype=np.float32) / 255.0  # (2, H, W, 3)
    x = x.transpose(3, 0, 1, 2)  # (3, 2, H, W): color-major, then time
    return np.ascontiguousarray(x.reshape(6, *x.shape[2:]))  # (6, H, W)
