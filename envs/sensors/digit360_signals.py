"""The simulated Digit 360's audio, IMU and pressure streams, rendered from the contact fields of each physics
step.
"""

from __future__ import annotations

import math
from functools import lru_cache

import numpy as np

from envs.sensors.digit360 import CONTACT_SLOTS, FIELD
from envs.sensors.digit360_model import (
    AUDIO_HZ,
    AUDIO_RING_S,
    DEFAULT_MODEL,
    GRAVITY,
    IMU_HZ,
    IMU_LSB_PER_G,
    INT16_MAX,
    PRESSURE_HZ,
    STREAM_FLOOR,
    STREAM_IMU,
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
    slip = sum(track.rows[:, FIELD[f"c{k}_fn"]] * track.rows[:, FIELD[f"c{k}_slip"]] for k in range(CONTACT_SLOTS))
    if np.any(slip > 0):
        env = track.causal(s / AUDIO_HZ, np.asarray(slip, np.float64)[:, None] * gains)  # (n, C)
        band = block_read(bandpass_table(STREAM_SLIP, *model.slip_band), int(key), STREAM_SLIP, s)[:, 0]
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
