"""The gel's markers on the simulated Digit 360 image (generation 2): how the elastomer's surface moves sideways
under each contact, drawn as a grid of dark dots that the contact carries along.

Under a contact of radius ``a`` (Hertz) carrying a tangential force ``Q`` the gel's surface moves along ``Q``
(Johnson, *Contact Mechanics*, 1985, chapter 7, for an elastic half-space of shear modulus ``G`` and Poisson ratio
``nu``):

- **sticking** (the contact point's slip speed below ``Digit360Model.slip_threshold``): Mindlin's solution, the
  traction ``Q / (2 pi a sqrt(a^2 - r^2))`` moves the whole contact rigidly by ``delta = (2 - nu) Q / (8 G a)``
  (eq. 7.39);
- **sliding**: the traction is the friction coefficient times the Hertz pressure, ``q0 sqrt(1 - r^2 / a^2)`` with
  ``q0 = 3 Q / (2 pi a^2)``, and the surface moves most at the centre (eq. 7.42 with the Hertz distribution):
  ``u_x = pi q0 / (32 G a) (4 (2 - nu) a^2 - (4 - 3 nu) x^2 - (4 - nu) y^2)``,
  ``u_y = pi q0 / (32 G a) 2 nu x y`` (x along Q), 1.5 delta at the centre and 0.58 delta at the edge along Q.

So the same normal and tangential force look different sticking (the markers in the patch shift together) and
sliding (they fan out, the centre ahead of the rim). Outside the contact both fields fall off as a point force's
1/r, joined to the edge value by ``(2 / pi) asin(a / r)`` (a stand-in for the exact far fields), tapered to zero
between 2.5 and 4 contact radii like the indentation. The markers are a square grid in the image (pitch
``marker_pitch`` of arc at the dome's apex); a marker seen at pixel p came from ``p - shift(p)``. A real Digit 360's
gel carries no printed marker grid (vision-based fingertips such as GelSight's often do): here the dots stand for
whatever texture of the gel the camera can follow, so that the surface's motion is visible at all. The grid is
periodic, so a move of more than half a pitch looks like a smaller one the other way: on the generation-2 gel a
sliding contact's markers move 3.4 px at 1 N and mu 0.5 and 6.8 px at mu 1.0 against a 7.4 px pitch (measured
in experiments/touch_ladder/v5_history, with what a stiffer gel does instead). Not modelled: the
gel's finite thickness (a half-space is more compliant), the contact's ellipticity against a curved object, partial
slip (a contact is sticking or sliding), and hysteresis.
"""

from __future__ import annotations

import math
from functools import lru_cache

import numpy as np

from envs.sensors.digit360 import CONTACT_SLOTS, FIELD
from envs.sensors.digit360_model import Digit360Model


@lru_cache(maxsize=4)
def pixel_rays(size: int, fov_half_angle_deg: float) -> tuple[np.ndarray, np.ndarray]:
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


@lru_cache(maxsize=4)
def _projection(size: int, fov_half_angle_deg: float) -> tuple[np.ndarray, np.ndarray]:
    """Per pixel, how a small move on the dome shows in the image: (S, S, 2, 3) pixels (column, row) per unit of
    angle moved along each sensor axis, and the fisheye's pixels per radian (for arc lengths)."""
    rays, _ = pixel_rays(size, fov_half_angle_deg)
    fov = math.radians(fov_half_angle_deg)
    px_per_rad = (size / 2.0) / fov
    theta = np.arccos(np.clip(rays[..., 2], -1.0, 1.0))
    phi = np.arctan2(rays[..., 1], rays[..., 0])
    e_theta = np.stack([np.cos(theta) * np.cos(phi), np.cos(theta) * np.sin(phi), -np.sin(theta)], -1)
    e_phi = np.stack([-np.sin(phi), np.cos(phi), np.zeros_like(phi)], -1)
    stretch = np.where(theta > 1e-6, theta / np.maximum(np.sin(theta), 1e-6), 1.0)  # rho d(phi) = theta/sin(theta)
    radial = np.stack([np.cos(phi), np.sin(phi)], -1)  # (S, S, 2) image direction of growing theta
    around = np.stack([-np.sin(phi), np.cos(phi)], -1)  # image direction of growing phi
    jac = px_per_rad * (radial[..., :, None] * e_theta[..., None, :]
                        + (stretch[..., None] * around)[..., :, None] * e_phi[..., None, :])
    return jac.astype(np.float32), np.float32(px_per_rad)


def surface_shift(row: np.ndarray, model: Digit360Model, size: int) -> np.ndarray:
    """(S, S, 2) float32 image displacement (pixels: column, row) of the gel's surface under one frame's contacts."""
    return _shift_and_box(row, model, size)[0]


def _shift_and_box(row: np.ndarray, model: Digit360Model, size: int) -> tuple[np.ndarray, list[int] | None]:
    """:func:`surface_shift` and the pixel box [r0, r1, c0, c1] outside which it is zero (None: zero everywhere)."""
    row = np.asarray(row, dtype=np.float64)
    shift = np.zeros((size, size, 2), np.float32)
    box: list[int] | None = None
    fns = [float(row[FIELD[f"c{k}_fn"]]) for k in range(CONTACT_SLOTS)]
    total_fn = sum(fns)
    if total_fn <= 0.0:
        return shift, box
    rays, _ = pixel_rays(size, model.fov_half_angle_deg)
    jac, px_per_rad = _projection(size, model.fov_half_angle_deg)
    nu, e_star = model.poisson, model.elastomer_modulus
    g = e_star * (1.0 - nu**2) / (2.0 * (1.0 + nu))
    force = np.array([row[FIELD["force_x"]], row[FIELD["force_y"]], -row[FIELD["force_n"]]])
    half, fov = size / 2.0, math.radians(model.fov_half_angle_deg)
    for k, fn in enumerate(fns):
        if fn <= 0.0 or row[FIELD[f"c{k}_found"]] <= 0:
            continue
        p = np.array([row[FIELD[f"c{k}_{a}"]] for a in "xyz"])
        if np.linalg.norm(p) < 1e-9:
            continue
        c = p / np.linalg.norm(p)
        f_t = (force - force.dot(c) * c) * (fn / total_fn)  # this contact's share of the tangential force
        q = float(np.linalg.norm(f_t))
        if q < 1e-9:
            continue
        a = (3.0 * fn * model.dome_radius / (4.0 * e_star)) ** (1.0 / 3.0)
        theta = math.acos(float(np.clip(c[2], -1.0, 1.0)))
        if theta > fov + 4.0 * a / model.dome_radius:
            continue
        rho_c = theta / fov * half
        ang = math.atan2(c[1], c[0])
        col, row_px = (size - 1) / 2.0 + rho_c * math.cos(ang), (size - 1) / 2.0 + rho_c * math.sin(ang)
        reach = 4.0 * a / model.dome_radius / fov * half * max(1.0, theta / max(math.sin(theta), 1e-3)) + 2.0
        r0, r1 = max(0, int(row_px - reach)), min(size, int(row_px + reach) + 2)
        c0, c1 = max(0, int(col - reach)), min(size, int(col + reach) + 2)
        if r0 >= r1 or c0 >= c1:
            continue
        ex = f_t / q  # along the force, tangent at the contact
        ey = np.cross(c, ex)
        d = model.dome_radius * (rays[r0:r1, c0:c1] - c)  # (h, w, 3) ~ offset on the dome (m)
        x, y = d @ ex, d @ ey
        r = np.hypot(x, y) / a
        sliding = max(float(row[FIELD[f"c{k}_slip"]]), 0.0) > model.slip_threshold
        if sliding:
            q0 = 3.0 * q / (2.0 * math.pi * a * a)
            unit = math.pi * q0 / (32.0 * g * a)
            xs, ys = np.where(r <= 1.0, x, x / np.maximum(r, 1.0)), np.where(r <= 1.0, y, y / np.maximum(r, 1.0))
            ux = unit * (4.0 * (2.0 - nu) * a * a - (4.0 - 3.0 * nu) * xs**2 - (4.0 - nu) * ys**2)
            uy = unit * 2.0 * nu * xs * ys
        else:
            ux = np.full_like(x, (2.0 - nu) * q / (8.0 * g * a))
            uy = np.zeros_like(x)
        outside = np.where(r > 1.0, (2.0 / math.pi) * np.arcsin(1.0 / np.maximum(r, 1.0)), 1.0)
        taper = np.clip((4.0 - r) / 1.5, 0.0, 1.0) ** 2
        weight = outside * taper / model.dome_radius  # a move of u on the dome is u / R radians
        u = [(ux * ex[a] + uy * ey[a]) * weight for a in range(3)]  # (h, w) m / R per sensor axis
        j = jac[r0:r1, c0:c1]  # the Jacobian turns radians into pixels
        for i in range(2):
            shift[r0:r1, c0:c1, i] += j[..., i, 0] * u[0] + j[..., i, 1] * u[1] + j[..., i, 2] * u[2]
        box = [r0, r1, c0, c1] if box is None else [min(box[0], r0), max(box[1], r1), min(box[2], c0),
                                                      max(box[3], c1)]
    return shift, box


@lru_cache(maxsize=4)
def _marker_grid(size: int, model: Digit360Model) -> tuple[float, float]:
    """The marker grid's pitch and dot radius in pixels (arc lengths at the dome's apex)."""
    px_per_m = (size / 2.0) / (math.radians(model.fov_half_angle_deg) * model.dome_radius)
    return model.marker_pitch * px_per_m, model.marker_size * px_per_m


def marker_layer(row: np.ndarray, model: Digit360Model, size: int) -> np.ndarray:
    """(S, S) float32 transmission of the marker layer (1 between markers, 1 - darkness at a marker's centre),
    each marker moved with the gel's surface under the frame's contacts."""
    shift, box = _shift_and_box(row, model, size)
    layer = rest_layer(size, model).copy()
    if box is not None:
        r0, r1, c0, c1 = box
        layer[r0:r1, c0:c1] = _dots(np.arange(c0, c1, dtype=np.float32)[None, :] - shift[r0:r1, c0:c1, 0],
                                    np.arange(r0, r1, dtype=np.float32)[:, None] - shift[r0:r1, c0:c1, 1],
                                    size, model)
    return layer


@lru_cache(maxsize=4)
def rest_layer(size: int, model: Digit360Model) -> np.ndarray:
    """The marker layer without contact."""
    j = np.arange(size, dtype=np.float32)
    return _dots(j[None, :], j[:, None], size, model)


def _dots(u: np.ndarray, v: np.ndarray, size: int, model: Digit360Model) -> np.ndarray:
    """Transmission at rest-frame pixel coordinates (u column, v row): Gaussian dots on the grid."""
    pitch, sigma = _marker_grid(size, model)
    du = (u - (size - 1) / 2.0) / pitch
    dv = (v - (size - 1) / 2.0) / pitch
    du, dv = (du - np.round(du)) * pitch, (dv - np.round(dv)) * pitch  # offset to the nearest grid point (px)
    dots = np.exp(-(du * du + dv * dv) / np.float32(2.0 * sigma * sigma))
    return (1.0 - np.float32(model.marker_darkness) * dots).astype(np.float32)
