"""The simulated Digit 360's parameters and shared pieces: rates and shapes of its four streams (the Sparsh-X
input contract), the sensor model's constants (Digit360Model), per-finger deterministic noise, and the contact
track each fingertip keeps between frames.
"""

from __future__ import annotations

from dataclasses import dataclass
from functools import lru_cache

import numpy as np

from envs.rng import splitmix64
from envs.sensors.digit360 import CONTACT_SLOTS, FIELD

IMAGE_HZ = 30.0
"""Camera frame rate (docs/reference/hardware.md section 4)."""
IMAGE_SIZE = 224
"""Contract image side (docs/reference/sparsh.md)."""
FRAME_GAP = 5
"""The contract's two frames are t-5 and t (docs/reference/sparsh.md)."""
AUDIO_HZ = 48000
AUDIO_CHANNELS = 2
AUDIO_SAMPLES = 27000
"""0.5625 s at 48 kHz: 224 Kaldi frames of 240 samples every 120 (docs/reference/sparsh.md)."""
IMU_HZ = 400.0
IMU_SAMPLES = 224
PRESSURE_HZ = 200.0
PRESSURE_SAMPLES = 224
GRAVITY = 9.80665
"""Standard gravity (m/s^2), for accelerometer readings in g."""
IMU_LSB_PER_G = 4096.0
"""Raw accelerometer counts per g (docs/reference/hardware.md section 4: raw / 4096)."""
INT16_MAX = 32767.0

STREAM_IMAGE, STREAM_FLOOR, STREAM_SLIP, STREAM_IMU, STREAM_PRESSURE, STREAM_PARAMS = 11, 12, 13, 14, 15, 16
STREAM_IMU_SLIP = 17
"""Stream numbers of the per-finger deterministic noise (finger_key), one per thing that draws noise."""
_TIME_EPS = 1e-6
"""Tolerance (s) when comparing float simulation times with grid times (0.01 s steps accumulate rounding)."""


@dataclass(frozen=True)
class Digit360Model:
    """Parameters of the rendered streams. Values marked 'chosen' are plausible guesses, not measurements.

    ``generation`` picks the model: 1 is the one the shipped encoder and adapter were trained on (the older hand,
    'digit360', keeps it bit for bit); 2 (:data:`CONTACT_MODEL`, the vendor-kinematics hand 'digit360_v4') makes
    each stream carry what the contact holds: the gel's printed markers move with the tangential displacement of
    its surface (a sticking contact translates them rigidly, a sliding one drags them in the full-slip pattern), the
    slip noise of audio and IMU follows the frictional power (tangential force x slip speed), impacts and slip
    shake the accelerometer above the physics rate, and the pressure follows the normal force through the gel's
    lag. The fields below the ``generation`` line are read by generation 2 only.
    """

    dome_radius: float = 0.014
    """Radius of the elastomer dome (m): the older hand model's 14 mm; Meta's Digit 360 on the vendor-kinematics hand
    is 12 mm (envs.allegro_description.DIGIT360_DOME_RADIUS). Contact sizes and image arcs scale with it."""
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
    """Mean background color in [0, 1]: the released Sparsh-X image mean (docs/reference/sparsh.md)."""
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

    generation: int = 1
    """1: the shipped model; 2: the contact-carrying streams (see the class docstring)."""
    marker_pitch: float = 0.0016
    """Spacing of the printed marker dots on the gel (m of arc at the dome); chosen (vision-based fingertips with
    markers print them 1-2 mm apart)."""
    marker_size: float = 0.00028
    """Gaussian radius (std, m) of a marker dot; chosen."""
    marker_darkness: float = 0.55
    """Fraction of the light a marker's centre absorbs; chosen."""
    slip_threshold: float = 0.002
    """Slip speed (m/s) above which a contact slides (full slip) rather than sticks; chosen, above the creep of a
    held contact under MuJoCo's soft constraints (experiments/sim_v4: 0.01 mm in 5 s)."""
    light_spread: float = 0.12
    """Per-sensor spread of each light's brightness (a gain uniform in 1 +- this, fixed per physical sensor)."""
    vignette_spread: float = 0.15
    """Per-sensor spread of the vignetting strength (uniform in 0.55 x (1 +- this))."""
    friction_sound_gain: float = 4.0e4
    """Slip noise std per watt of frictional power (tangential force N x slip speed m/s), counts; chosen."""
    gel_time_constant: float = 0.04
    """Lag (s) of the gel cavity's pressure behind the normal force (first order); chosen, viscoelastic silicone
    gels relax over tens of milliseconds."""
    imu_mode: tuple[float, float] = (110.0, 0.012)
    """The fingertip's vibration mode seen by the accelerometer: frequency (Hz, below the 200 Hz Nyquist limit of
    the 400 Hz samples) and decay time constant (s); chosen."""
    imu_effective_mass: float = 0.05
    """Mass (kg) an impact's force rise accelerates at the sensor: the fingertip with its sensor (the Digit 360
    body and the distal link are tens of grams); chosen."""
    imu_slip_gain: float = 20.0
    """Vibration (m/s^2 std) per watt of frictional power, band 30-190 Hz; chosen."""

    def __post_init__(self) -> None:
        if self.generation not in (1, 2):
            raise ValueError(f"Digit360Model: generation must be 1 or 2, got {self.generation!r}")
        for name in ("dome_radius", "elastomer_modulus", "marker_pitch", "marker_size", "gel_time_constant",
                     "imu_effective_mass"):
            if not getattr(self, name) > 0:
                raise ValueError(f"Digit360Model: {name} must be > 0, got {getattr(self, name)!r}")
        if not 0 < self.imu_mode[0] < IMU_HZ / 2:
            raise ValueError(f"Digit360Model: the imu_mode frequency must be in (0, {IMU_HZ / 2:g}) Hz, got "
                             f"{self.imu_mode[0]}")


DEFAULT_MODEL = Digit360Model()
CONTACT_MODEL = Digit360Model(dome_radius=0.012, generation=2)
"""The generation-2 model on Meta's 12 mm domes: what 'digit360_v4' renders (envs.scene.touch_model)."""
AUDIO_RING_S = 5.0 * max(decay for _, decay, _ in DEFAULT_MODEL.modes)
"""How far back an impact still rings (s): five decay times of the default model's slowest mode (a model with
slower modes is cut there)."""
LOOKBACK_S = max(AUDIO_RING_S, 5.0 * CONTACT_MODEL.gel_time_constant, 5.0 * CONTACT_MODEL.imu_mode[1])
"""How far before a stream sample its rows reach (s): the ring-down of impacts and five time constants of the
gel's pressure lag (0.2 s; a model with slower constants is cut there)."""
HISTORY_S = (PRESSURE_SAMPLES - 1) / PRESSURE_HZ + 1.0 / IMAGE_HZ + LOOKBACK_S
"""Contact history (s) a window ending at the latest image frame needs behind the current time: the pressure
window (the longest, 1.115 s), the latest frame's lag behind the current time (< 1/30 s) and the look-back of its
first samples; add two physics steps for the interpolation lag and the row held at the start."""



# ---------------------------------------------------------------------------------------------------- randomness
def finger_key(key: int, finger: int) -> np.uint64:
    """The 64-bit noise key of fingertip ``finger`` (0-3) of a session or env episode keyed ``key``."""
    with np.errstate(over="ignore"):
        x = np.asarray([int(key) & 0xFFFFFFFFFFFFFFFF], dtype=np.uint64)
        return splitmix64(splitmix64(x) + np.uint64(finger + 1))[0]


def seeded_hash(key: np.uint64, stream: int, index: np.ndarray) -> np.ndarray:
    """uint64 hash of (key, stream, index) for an int array of absolute sample indices."""
    with np.errstate(over="ignore"):
        base = splitmix64(np.asarray([key ^ splitmix64(np.asarray([np.uint64(stream)]))[0]]))[0]
        return splitmix64(np.asarray(index, dtype=np.int64).astype(np.uint64) * np.uint64(0x9E3779B97F4A7C15) + base)


def seeded_uniform(key: np.uint64, stream: int, index: np.ndarray) -> np.ndarray:
    """Uniform [0, 1) floats, one per index."""
    return (seeded_hash(key, stream, index) >> np.uint64(11)).astype(np.float64) * (1.0 / 9007199254740992.0)


_NOISE_BLOCK = 4096
_NOISE_TABLE = 1 << 16


@lru_cache(maxsize=8)
def normal_table(stream: int) -> np.ndarray:
    """(65536, 2) standard normals of one stream, shared by all keys: the source of :func:`block_read`."""
    a, b = normal_pair(np.uint64(0x243F6A8885A308D3), stream, np.arange(_NOISE_TABLE))  # fixed key (digits of pi)
    return np.stack([a, b], axis=1).astype(np.float32)


@lru_cache(maxsize=4)
def bandpass_table(stream: int, low: float, high: float) -> np.ndarray:
    """(65536, 2) band-limited noise of unit std: the stream's normal table filtered circularly in [low, high] Hz."""
    white = normal_table(stream).astype(np.float64)
    spectrum = np.fft.rfft(white, axis=0)  # (L/2 + 1, 2)
    freq = np.fft.rfftfreq(_NOISE_TABLE, 1.0 / AUDIO_HZ)
    spectrum[(freq < low) | (freq > high)] = 0.0
    band = np.fft.irfft(spectrum, n=_NOISE_TABLE, axis=0)
    return (band / band.std(axis=0)).astype(np.float32)


def block_read(table: np.ndarray, key: int, stream: int, index: np.ndarray) -> np.ndarray:
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
    offsets = (seeded_hash(np.uint64(key), stream + 1000, blocks) % np.uint64(_NOISE_TABLE)).astype(np.int64)
    parts = []
    for b, off in zip(blocks, offsets, strict=True):
        lo, hi = max(first, b * _NOISE_BLOCK), min(last + 1, (b + 1) * _NOISE_BLOCK)  # this block's share
        start = (off + lo - b * _NOISE_BLOCK) % _NOISE_TABLE
        rows = np.arange(start, start + hi - lo) % _NOISE_TABLE if start + hi - lo > _NOISE_TABLE else None
        parts.append(table[rows] if rows is not None else table[start : start + hi - lo])
    return np.concatenate(parts)


def normal_pair(key: np.uint64, stream: int, index: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Two independent standard normals per index (Box-Muller on the hash's two 32-bit halves)."""
    h = seeded_hash(key, stream, index)
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
