"""The simulated Digit 360 camera image: the elastomer's indentation under the contacts, shaded as an
illuminated gel with its background, noise, and packing into the Sparsh-X image contract.
"""

from __future__ import annotations

import math
from functools import lru_cache

import numpy as np

from envs.sensors.digit360 import CONTACT_SLOTS, FIELD
from envs.sensors.digit360_markers import marker_layer, pixel_rays, rest_layer
from envs.sensors.digit360_model import (
    DEFAULT_MODEL,
    IMAGE_HZ,
    IMAGE_SIZE,
    STREAM_IMAGE,
    STREAM_PARAMS,
    ContactTrack,
    Digit360Model,
    seeded_hash,
    seeded_uniform,
)


# ---------------------------------------------------------------------------------------------------- image
@lru_cache(maxsize=16)
def _background(size: int, model: Digit360Model, sensor: int) -> np.ndarray:
    """Static illuminated background (size, size, 3) in [0, 1]: vignetting, one-sided light gradients, a fixed grain
    texture of this physical sensor (``sensor``: the fingertip index), dark outside the image circle; scaled so the
    mean color is ``model.background_mean``."""
    rays, inside = pixel_rays(size, model.fov_half_angle_deg)
    c = (size - 1) / 2.0
    j, i = np.meshgrid(np.arange(size), np.arange(size))
    x, y = (j - c) / (size / 2.0), (i - c) / (size / 2.0)
    rho = np.hypot(x, y)
    gains, strength = np.ones(3), 0.55
    if model.generation >= 2:  # this physical sensor's own LEDs and lens: fixed per sensor, not per session
        u = seeded_uniform(np.uint64(sensor + 1), STREAM_PARAMS, np.arange(10, 14))
        gains = 1.0 + model.light_spread * (2.0 * u[:3] - 1.0)
        strength = 0.55 * (1.0 + model.vignette_spread * (2.0 * u[3] - 1.0))
    vignette = np.clip(1.0 - strength * rho**2, 0.0, None)  # (S, S) brighter centre
    bg = np.empty((size, size, 3))
    for ch, az in enumerate(model.light_azimuths_deg):
        a = math.radians(az)
        bg[..., ch] = gains[ch] * vignette * (1.0 + 0.35 * (x * math.cos(a) + y * math.sin(a)))  # toward each light
    grain = seeded_uniform(np.uint64(sensor + 1), STREAM_PARAMS, np.arange(size * size)).reshape(size, size)
    bg *= (1.0 + 0.06 * (grain - 0.5))[..., None]
    bg[~inside] = 0.05 * bg[~inside]
    seen = bg * rest_layer(size, model)[..., None] if model.generation >= 2 else bg  # what the camera sees at rest
    bg *= np.asarray(model.background_mean) / seen.reshape(-1, 3).mean(axis=0)
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
    rays, _ = pixel_rays(size, model.fov_half_angle_deg)
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
        a = (3.0 * fn * model.dome_radius / (4.0 * e_star)) ** (1.0 / 3.0)  # Hertz contact radius (m)
        depth = a * a / model.dome_radius
        # Mindlin: this contact's share of the tangential force drags the patch, at most by its radius (generation
        # 2 draws that displacement on the gel's markers instead: envs.sensors.digit360_markers)
        f_t = (force - force.dot(c) * c) * (fn / total_fn)
        shift = min(3.0 * (2.0 - model.poisson) * np.linalg.norm(f_t) / (8.0 * shear_modulus * a), a)
        if shift > 0 and model.generation < 2:
            c = c + f_t / (np.linalg.norm(f_t) + 1e-12) * shift / model.dome_radius
            c /= np.linalg.norm(c)
        theta = math.acos(float(np.clip(c[2], -1.0, 1.0)))
        if theta > fov + 4.0 * a / model.dome_radius:
            continue  # behind the camera's view
        # pixel box around the patch: 4 contact radii, converted from arc length to pixels
        rho_c = theta / fov * half
        col = (size - 1) / 2.0 + rho_c * math.cos(math.atan2(c[1], c[0]))
        row_px = (size - 1) / 2.0 + rho_c * math.sin(math.atan2(c[1], c[0]))
        reach = 4.0 * a / model.dome_radius / fov * half * max(1.0, theta / max(math.sin(theta), 1e-3)) + 2.0
        r0, r1 = max(0, int(row_px - reach)), min(size, int(row_px + reach) + 2)
        c0, c1 = max(0, int(col - reach)), min(size, int(col + reach) + 2)
        if r0 >= r1 or c0 >= c1:
            continue
        chord = model.dome_radius * np.linalg.norm(rays[r0:r1, c0:c1] - c, axis=-1)  # (h, w) ~ arc distance (m)
        disp[r0:r1, c0:c1] += depth * _hertz_profile(chord / a)
    return disp


@lru_cache(maxsize=4)
def _noise_table(size: int) -> np.ndarray:
    """Zero-mean uniform noise (4 size^2,) float32 of unit std; each frame reads a slice at a hashed offset."""
    u = seeded_uniform(np.uint64(0x13198A2E03707344), STREAM_IMAGE, np.arange(4 * size * size))  # fixed key
    return ((u - 0.5) * math.sqrt(12.0)).astype(np.float32)


def render_frame(row: np.ndarray, frame_index: int, key: int, sensor: int = 0, model: Digit360Model = DEFAULT_MODEL,
                 size: int = IMAGE_SIZE) -> np.ndarray:
    """One tactile image (size, size, 3) uint8 from the contact-field row the camera sees at frame ``frame_index``;
    ``key`` keys the read noise, ``sensor`` (the fingertip index) the static background."""
    disp = _indentation(np.asarray(row), model, size)
    img = _background(size, model, int(sensor)).copy()  # (S, S, 3) float32
    if disp.any():
        # surface slope from the displacement field; one pixel spans this much arc on the dome (m)
        arc_per_px = model.dome_radius * math.radians(model.fov_half_angle_deg) / (size / 2.0)
        gy, gx = np.gradient(disp.astype(np.float32), np.float32(arc_per_px))  # (S, S) each, dimensionless slopes
        for ch, az in enumerate(model.light_azimuths_deg):
            a = math.radians(az)
            slope = np.float32(math.cos(a)) * gx + np.float32(math.sin(a)) * gy  # (S, S) along light ch
            img[..., ch] += np.float32(model.shading_gain) * slope
        img += np.float32(model.depth_gain) * disp[..., None].astype(np.float32)
    if model.generation >= 2:
        img *= marker_layer(row, model, size)[..., None]
    # read noise: a slice of this sensor's noise table at a pseudo-random offset per frame
    n = size * size
    offset = int(seeded_hash(np.uint64(key), STREAM_IMAGE, np.array([frame_index]))[0] % np.uint64(3 * n))
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


def pack_image(frames: np.ndarray) -> np.ndarray:
    """(2, H, W, 3) uint8 frames [t-5, t] -> (6, H, W) float32 in [0, 1], channels
    [R(t-5), R(t), G(t-5), G(t), B(t-5), B(t)] (the released Sparsh-X pairing, docs/reference/sparsh.md)."""
    x = np.asarray(frames, dtype=np.float32) / 255.0  # (2, H, W, 3)
    x = x.transpose(3, 0, 1, 2)  # (3, 2, H, W): color-major, then time
    return np.ascontiguousarray(x.reshape(6, *x.shape[2:]))  # (6, H, W)
