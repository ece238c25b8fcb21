"""The simulated Digit 360's audio, IMU and pressure streams, rendered from the contact fields of each physics
step.
"""

from __future__ import annotations

import math
from functools import lru_cache

import numpy as np

from envs.sensors.digit360 import CONTACT_SLOTS, FIELD, contact_frame_force, mean_slip
from envs.sensors.digit360_model import (
    AUDIO_HZ,
    AUDIO_RING_S,
    DEFAULT_MODEL,
    GRAVITY,
    IMU_HZ,
    IMU_LSB_PER_G,
    INT16_MAX,
    LOOKBACK_S,
    PRESSURE_HZ,
    STREAM_FLOOR,
    STREAM_IMU,
    STREAM_IMU_SLIP,
    STREAM_PARAMS,
    STREAM_PRESSURE,
    STREAM_SLIP,
    ContactTrack,
    Digit360Model,
    bandpass_table,
    block_read,
    normal_pair,
    normal_table,
    seeded_uniform,
)


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


def _strongest_point(rows: np.ndarray, dome_radius: float) -> np.ndarray:
    """(T, D) rows -> (T, 3) point of the strongest contact slot (the dome's apex when there is none)."""
    fn = np.stack([rows[:, FIELD[f"c{k}_fn"]] for k in range(CONTACT_SLOTS)], axis=1)  # (T, K)
    best = fn.argmax(axis=1)
    pts = np.stack([np.stack([rows[:, FIELD[f"c{k}_{a}"]] for a in "xyz"], axis=1) for k in range(CONTACT_SLOTS)],
                   axis=1)  # (T, K, 3)
    out = pts[np.arange(len(rows)), best]
    empty = fn.max(axis=1) <= 0
    out[empty] = (0.0, 0.0, dome_radius)
    return out


def render_audio(track: ContactTrack, first_sample: int, num_samples: int, key: int,
                 model: Digit360Model = DEFAULT_MODEL) -> np.ndarray:
    """Two-channel contact audio (2, n) float32 in int16 counts for samples [first, first + n) at 48 kHz.

    Noise floor + ringing impacts + band-limited slip noise, clipped to the int16 range.
    """
    s = first_sample + np.arange(num_samples, dtype=np.int64)
    t_first, t_end = first_sample / AUDIO_HZ, (first_sample + num_samples) / AUDIO_HZ
    track = track.clip(t_first - AUDIO_RING_S - track.dt, t_end)
    out = np.float32(model.audio_floor) * block_read(normal_table(STREAM_FLOOR), int(key), STREAM_FLOOR, s).T

    gains = _mic_gains(_strongest_point(track.rows, model.dome_radius), model)  # (T, C)
    fn = track.normal_force()
    # slip: frictional-power envelope at the physics rate, interpolated causally to 48 kHz, times band noise
    if model.generation >= 2:
        slip, gain = friction_power(track.rows), model.friction_sound_gain  # tangential force x slip speed (W)
    else:
        slip = sum(track.rows[:, FIELD[f"c{k}_fn"]] * track.rows[:, FIELD[f"c{k}_slip"]] for k in range(CONTACT_SLOTS))
        gain = model.slip_gain
    if np.any(slip > 0):
        env = track.causal(s / AUDIO_HZ, np.asarray(slip, np.float64)[:, None] * gains)  # (n, C)
        band = block_read(bandpass_table(STREAM_SLIP, *model.slip_band), int(key), STREAM_SLIP, s)[:, 0]
        out += (gain * env.T * band).astype(np.float32)

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


def friction_power(rows: np.ndarray) -> np.ndarray:
    """(T, D) contact-field rows -> (T,) frictional power (W): the tangential force at the contact times the
    normal-force-weighted slip speed of the dome's contacts (0 without contact). While a contact slides its
    tangential force is the friction coefficient times the normal force, so this is mu x F_n x v."""
    return contact_frame_force(rows)[:, 1].astype(np.float64) * mean_slip(rows)


def _contact_direction(rows: np.ndarray) -> np.ndarray:
    """(T, 3) unit vector from the dome's centre to its strongest contact (sensor frame; +z without contact)."""
    p = _strongest_point(np.asarray(rows), 1.0)
    return p / np.maximum(np.linalg.norm(p, axis=1, keepdims=True), 1e-12)


IMU_SLIP_BAND = (30.0, 190.0)
"""Pass band (Hz) of the slip shake the accelerometer sees: below its 200 Hz Nyquist limit; chosen."""


@lru_cache(maxsize=1)
def _imu_band_table() -> np.ndarray:
    """(65536, 2) unit-std noise band-limited to IMU_SLIP_BAND at the 400 Hz sample rate."""
    white = normal_table(STREAM_IMU_SLIP).astype(np.float64)
    spectrum = np.fft.rfft(white, axis=0)
    freq = np.fft.rfftfreq(len(white), 1.0 / IMU_HZ)
    spectrum[(freq < IMU_SLIP_BAND[0]) | (freq > IMU_SLIP_BAND[1])] = 0.0
    band = np.fft.irfft(spectrum, n=len(white), axis=0)
    return (band / band.std(axis=0)).astype(np.float32)


@lru_cache(maxsize=4)
def _imu_ring(frequency: float, decay: float) -> np.ndarray:
    """(n,) unit-peak-ish response of the fingertip's mode at the 400 Hz samples over five decay times."""
    tau = np.arange(int(math.ceil(5.0 * decay * IMU_HZ))) / IMU_HZ
    return np.exp(-tau / decay) * np.sin(2 * np.pi * frequency * tau + np.pi / 2)  # an impulse starts at its peak


def _imu_vibration(track: ContactTrack, samples: np.ndarray, key: int, model: Digit360Model) -> np.ndarray:
    """(n, 3) m/s^2 of vibration at the 400 Hz ``samples`` (generation 2): each rise of the normal force rings the
    fingertip's mode along the contact's normal with amplitude rise / effective mass, and sliding shakes it across
    the contact with band noise whose amplitude follows the frictional power. Causal: a row rings from its own time
    on; both read only rows at or before each sample."""
    freq, decay = model.imu_mode
    out = np.zeros((len(samples), 3))
    if len(samples) == 0:
        return out
    rows = track.rows
    fn = track.normal_force()
    direction = _contact_direction(rows)
    rise = np.diff(fn, prepend=fn[:1]) - model.impact_threshold
    ring = _imu_ring(float(freq), float(decay))
    first = int(samples[0])
    rising = np.flatnonzero(rise > 0)
    if len(rising):  # every rise rings from its onset sample on, all rows at once (the dome is pushed inward)
        onsets = np.ceil(track.times[rising] * IMU_HZ - 1e-6).astype(np.int64)
        lag = (first + np.arange(len(samples)))[None, :] - onsets[:, None]  # (rows, n) samples since each onset
        inside = (lag >= 0) & (lag < len(ring))
        amplitude = rise[rising] / model.imu_effective_mass
        rings = np.where(inside, ring[np.clip(lag, 0, len(ring) - 1)], 0.0) * amplitude[:, None]
        out += rings.T @ -direction[rising]
    tangential = contact_frame_force(rows)[:, 1].astype(np.float64)
    power = tangential * mean_slip(rows)  # friction_power, with the tangential force kept for the axis below
    if np.any(power > 0):
        env = track.causal(samples / IMU_HZ, power)  # (n,)
        # the shake runs across the contact: along the net force's tangential part
        force = np.stack([rows[:, FIELD["force_x"]], rows[:, FIELD["force_y"]], -rows[:, FIELD["force_n"]]], 1)
        across = force - (force * direction).sum(1, keepdims=True) * direction
        across /= np.maximum(np.linalg.norm(across, axis=1, keepdims=True), 1e-9)
        across[tangential <= 0] = 0.0
        axis = track.causal(samples / IMU_HZ, across)  # (n, 3)
        band = block_read(_imu_band_table(), int(key), STREAM_IMU_SLIP, samples)[:, 0]
        out += (model.imu_slip_gain * env * band)[:, None] * axis
    return out


# ---------------------------------------------------------------------------------------------------- IMU, pressure
def imu_terms(samples: np.ndarray, key: int, model: Digit360Model = DEFAULT_MODEL) -> tuple[np.ndarray, np.ndarray]:
    """The accelerometer's contact-independent terms at 400 Hz sample indices ``samples``: the per-axis bias (3,) and
    the white noise (n, 3), in g. Pure functions of (key, sample index), so a live emulator can draw them ahead in
    blocks and pass them to :func:`render_imu`."""
    samples = np.asarray(samples, dtype=np.int64)
    bias = model.imu_bias * (2.0 * seeded_uniform(np.uint64(key), STREAM_PARAMS, np.arange(3)) - 1.0)
    n0, n1 = normal_pair(np.uint64(key), STREAM_IMU, samples)
    n2, _ = normal_pair(np.uint64(key), STREAM_IMU, samples + (1 << 50))
    return bias, model.imu_noise * np.stack([n0, n1, n2], axis=1)


def render_imu(track: ContactTrack, samples: np.ndarray, key: int, model: Digit360Model = DEFAULT_MODEL,
               terms: tuple[np.ndarray, np.ndarray] | None = None) -> np.ndarray:
    """Accelerometer (n, 3) float32 in g at 400 Hz sample indices ``samples`` (sample i at i / 400 s).

    ``terms``: ``imu_terms(samples, key, model)`` when already drawn (the same values; computed here otherwise).
    """
    samples = np.asarray(samples, dtype=np.int64)
    acc = track.causal(samples / IMU_HZ, track.rows[:, FIELD["acc_x"] : FIELD["acc_z"] + 1].astype(np.float64))
    if model.generation >= 2:
        acc = acc + _imu_vibration(track.clip(samples[0] / IMU_HZ - LOOKBACK_S, samples[-1] / IMU_HZ), samples,
                                   key, model) if len(samples) else acc
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
    u = seeded_uniform(np.uint64(key), STREAM_PARAMS, np.arange(3, 5))
    offset = model.pressure_offset * (2.0 * u[0] - 1.0)
    drift = model.pressure_drift * np.sin(2.0 * np.pi * (t / model.pressure_drift_period + u[1]))
    noise, _ = normal_pair(np.uint64(key), STREAM_PRESSURE, samples)
    return model.pressure_rest + offset + drift, model.pressure_noise * noise


def gel_lag(track: ContactTrack, model: Digit360Model) -> np.ndarray:
    """(T,) the normal force seen through the gel's first-order lag, on the track's rows: each row a weighted mean
    of the rows of the last LOOKBACK_S (weights exp(-age / gel_time_constant), normalized; the first row held
    before the track starts). A finite window, so that a value depends only on rows within LOOKBACK_S before it and
    two windows cut from one track agree wherever both hold that look-back."""
    fn = track.normal_force()
    taps = max(1, int(round(LOOKBACK_S / track.dt)))
    w = np.exp(-np.arange(taps) * track.dt / model.gel_time_constant)
    w /= w.sum()
    padded = np.concatenate([np.full(taps - 1, fn[0]), fn])
    return np.convolve(padded, w, mode="valid")  # row i: sum_j w_j fn[i - j]


def render_pressure(track: ContactTrack, samples: np.ndarray, key: int, model: Digit360Model = DEFAULT_MODEL,
                    terms: tuple[np.ndarray, np.ndarray] | None = None) -> np.ndarray:
    """Pressure (n,) float32 in hPa at 200 Hz sample indices ``samples`` (sample i at i / 200 s).

    ``terms``: ``pressure_terms(samples, key, model)`` when already drawn (the same values; computed here otherwise).
    """
    samples = np.asarray(samples, dtype=np.int64)
    fn = track.normal_force()
    if model.generation >= 2:
        fn = gel_lag(track, model)
    force = track.causal(samples / PRESSURE_HZ, fn)
    level, noise = pressure_terms(samples, key, model) if terms is None else terms
    p = level + model.pressure_per_newton * force + noise
    return p.astype(np.float32)
