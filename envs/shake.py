"""Bottle shaking: the hand, on a wrist that moves, holds a closed bottle and shakes it; the fingertips' Digit 360s
feel the contents (envs.shake_contents) through the bottle.

The scene is the held-hand scene (envs.held_hand: the hand on a wrist that follows a scripted motion, the object at
one of its cup grasps) with a bottle: the cup's outer radius and height at the grasp's scale, no handle, a wall of
1.5 mm HDPE, a bottom and a cap, and its contents. The physics step is 2 ms (the smallest grains are 2 mm across).

An episode (:func:`draw_episode`, all from its seed): the content and fill level (uniform unless given), the grasp
(bucket and row), then the shake: the bottle settles for ``settle_s``, the wrist's motion ramps in over ``ramp_s``
and goes on to ``duration_s``: a sinusoid of amplitude ``amplitude`` (m) and frequency ``frequency`` (Hz) along a
random direction (mostly horizontal), and a tilt about a random horizontal axis of ``tilt`` (rad) a quarter period
behind it. With ``motion="strokes"`` the wrist instead travels the same amplitude at a constant speed and reverses
as sharply as ``max_accel`` allows (:func:`stroke`): the way a person shakes a bottle to hear what is inside, the
contents flying across and striking the wall at each reversal instead of swaying with a smooth sinusoid.
:class:`ShakeSim` steps it and returns the fingertips' contact fields at every physics step (the rows the Digit 360
streams are rendered from, envs.sensors.digit360) with the labels.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import mujoco
import numpy as np

from envs.grasp_cache import GraspCache, load_default_cache
from envs.held_hand import OBJECT_CONTYPE, WristRun, check_touch_hand, finish, grip, tilt_quat, wrist_spec
from envs.plug_grip import GRIP_HEIGHT, check_grip, fingertip_grip
from envs.shake_contents import CONTENT_NAMES, CONTENTS, FILL_LEVELS, Grain, Liquid, slosh_model

TIMESTEP = 0.002
"""Physics step (s)."""
WALL = 0.0015
"""Bottle wall thickness (m)."""
WALL_DENSITY = 950.0
"""HDPE (kg/m^3)."""
WALL_SEGMENTS = 16
"""Boxes around the bottle's wall."""
HELD_TOLERANCE = 0.015
"""A bottle that moved more than this (m) relative to the palm by the end was not held."""
MOTIONS = ("sine", "strokes")
"""The wrist's shaking motions (ShakeConfig.motion)."""
BOTTLE_CONTYPE, GRAIN_BIT = OBJECT_CONTYPE, 4
"""Collision bits: the hand collides with the bottle (as with the rotation env's objects), grains with the bottle
and each other, never with the hand."""


@dataclass(frozen=True)
class ShakeConfig:
    """The shaking task's ranges (each drawn uniformly per episode)."""

    hand: str = "digit360_v4"
    """A hand variant with Digit 360 fingertips (envs.scene.HANDS)."""
    duration_s: float = 3.0
    """Episode length (s), settling included."""
    settle_s: float = 0.3
    """The bottle and contents settle in the still hand first."""
    ramp_s: float = 0.3
    """The shake's amplitude ramps in over this (s)."""
    amplitude: tuple[float, float] = (0.005, 0.02)
    """Wrist displacement amplitude (m), at most ``max_accel / (2 pi f)^2``."""
    max_accel: float = 5.0
    """Largest peak acceleration of the wrist (m/s^2): harder shakes throw a full bottle of water out of the
    grasps (a 150 g bottle left the hand at 12 m/s^2)."""
    frequency: tuple[float, float] = (1.5, 4.0)
    """Shake frequency (Hz): a hand shakes a bottle at a few hertz."""
    tilt: tuple[float, float] = (0.0, 0.25)
    """Wrist tilt amplitude (rad)."""
    vertical: float = 0.3
    """Largest vertical part of the shake's direction (unit vector's z)."""
    motion: str = "sine"
    """The wrist's motion along the shake's direction: 'sine' (a sinusoid) or 'strokes' (constant speed, reversals
    at ``max_accel``: :func:`stroke`); the same amplitude, frequency and phase either way."""
    grip: str = "palm"
    """How the bottle is held: 'palm' (at the cup's grasp, on the phalanges and palm) or 'fingertips' (standing on
    the four domes' grip band, squeezed by them alone: envs.plug_grip; what the domes feel of the contents is then
    not shared with the phalanges)."""

    def __post_init__(self) -> None:
        check_touch_hand("shake", self.hand)
        check_grip("shake", self.grip)
        if self.motion not in MOTIONS:
            raise ValueError(f"shake: motion must be one of {', '.join(MOTIONS)}, got {self.motion!r}")
        for name in ("amplitude", "frequency", "tilt"):
            lo, hi = getattr(self, name)
            if not (0 <= lo <= hi and math.isfinite(hi)):
                raise ValueError(f"shake: {name} must be a range 0 <= low <= high, got {(lo, hi)}")
        if not (self.duration_s > self.settle_s + self.ramp_s >= 0 and self.settle_s >= 0 and self.ramp_s >= 0):
            raise ValueError(f"shake: duration_s ({self.duration_s}) must exceed settle_s + ramp_s "
                             f"({self.settle_s} + {self.ramp_s})")


@dataclass(frozen=True)
class ShakeEpisode:
    """One episode's draws (:func:`draw_episode`)."""

    seed: int
    content: str
    fill: int
    """Fill level (index into envs.shake_contents.FILL_LEVELS)."""
    bucket: int
    """Grasp cache bucket: the bottle's scale."""
    grasp_u: float
    """Picks the grasp row in the bucket."""
    amplitude: float
    frequency: float
    phase: float
    direction: tuple[float, float, float]
    tilt: float
    tilt_axis: tuple[float, float, float]

    @property
    def content_id(self) -> int:
        return CONTENT_NAMES.index(self.content)


def stroke(u: float, amplitude: float, frequency: float, max_accel: float) -> float:
    """Displacement of a 'strokes' shake over its amplitude (in [-1, 1]) at cycle phase ``u`` (cycles; 0 at the
    middle of the travel, moving up, as sin(2 pi u)): constant speed V between reversals of constant acceleration
    ``max_accel`` lasting tau = 2 V / max_accel, V chosen so that each stroke covers 2 ``amplitude``
    (2 A = V (T - tau) / 2 with T = 1 / ``frequency``). Needs A <= max_accel T^2 / 32 (draw_episode's cap for the
    sinusoid, max_accel / (2 pi f)^2, is below it)."""
    period, a = 1.0 / frequency, max_accel
    disc = period * period - 32.0 * amplitude / a
    if disc < 0:
        raise ValueError(f"shake: strokes of {amplitude * 1e3:.1f} mm at {frequency:g} Hz need more than "
                         f"{max_accel:g} m/s^2")
    speed = (period - math.sqrt(disc)) * a / 4.0
    h = speed / a  # half the reversal (s)
    t = ((u + 0.25) % 1.0) * period  # from the bottom of the travel
    sign = 1.0
    if t >= period / 2:  # the way down mirrors the way up
        t, sign = t - period / 2, -1.0
    if t <= h:
        x = -amplitude + a * t * t / 2
    elif t <= period / 2 - h:
        x = -amplitude + a * h * h / 2 + speed * (t - h)
    else:
        r = period / 2 - t
        x = amplitude - a * r * r / 2
    return sign * x / amplitude if amplitude > 0 else 0.0


def draw_episode(cfg: ShakeConfig, seed: int, grasps: GraspCache, content: str | None = None,
                 fill: int | None = None) -> ShakeEpisode:
    """An episode's draws from its seed (content and fill level uniform unless given)."""
    if content is not None and content not in CONTENTS:
        raise ValueError(f"shake: unknown content {content!r}; contents: {', '.join(CONTENT_NAMES)}")
    if fill is not None and fill not in range(len(FILL_LEVELS)):
        raise ValueError(f"shake: fill must be 0-{len(FILL_LEVELS) - 1} ({', '.join(FILL_LEVELS)}), got {fill}")
    rng = np.random.default_rng([int(seed), 0x5AC3])
    drawn_content = CONTENT_NAMES[int(rng.integers(len(CONTENT_NAMES)))]
    drawn_fill = int(rng.integers(len(FILL_LEVELS)))
    azimuth = rng.uniform(0, 2 * math.pi)
    up = rng.uniform(-cfg.vertical, cfg.vertical)
    flat = math.sqrt(1 - up * up)
    tilt_az = rng.uniform(0, 2 * math.pi)
    amplitude, frequency = float(rng.uniform(*cfg.amplitude)), float(rng.uniform(*cfg.frequency))
    return ShakeEpisode(
        seed=int(seed), content=content if content is not None else drawn_content,
        fill=fill if fill is not None else drawn_fill, bucket=int(rng.integers(len(grasps.scales))),
        grasp_u=float(rng.uniform()), amplitude=min(amplitude, cfg.max_accel / (2 * math.pi * frequency) ** 2),
        frequency=frequency, phase=float(rng.uniform(0, 2 * math.pi)),
        direction=(flat * math.cos(azimuth), flat * math.sin(azimuth), up), tilt=float(rng.uniform(*cfg.tilt)),
        tilt_axis=(math.cos(tilt_az), math.sin(tilt_az), 0.0))


@dataclass
class ShakeRecording:
    """What one episode gives (:meth:`ShakeSim.run`)."""

    episode: ShakeEpisode
    times: np.ndarray
    """(T,) s: the time of every physics step's sensor sample."""
    contact: np.ndarray
    """(4, T, NUM_FIELDS) float32: each fingertip's contact fields (envs.sensors.digit360.CONTACT_FIELDS)."""
    content_mass: float
    """kg."""
    bottle_offset: np.ndarray
    """(T, 3): the bottle's centre relative to the palm, in the palm's frame (m)."""
    held: bool
    """The bottle stayed in the hand (it moved at most HELD_TOLERANCE relative to the palm)."""
    extra: dict = field(default_factory=dict)


def _add_bottle(spec: mujoco.MjSpec, radius: float, height: float, pos: np.ndarray, quat: np.ndarray
                ) -> mujoco.MjsBody:
    bottle = spec.worldbody.add_body(name="bottle", pos=pos.tolist(), quat=quat.tolist())
    bottle.add_freejoint(name="bottle_free")
    common = dict(contype=BOTTLE_CONTYPE, conaffinity=1 | GRAIN_BIT, condim=4, density=WALL_DENSITY,
                  rgba=[0.25, 0.5, 0.8, 1.0])
    half_w = radius * math.tan(math.pi / WALL_SEGMENTS) + WALL / 2  # the boxes overlap a little at the seams
    for i in range(WALL_SEGMENTS):
        a = 2 * math.pi * i / WALL_SEGMENTS
        bottle.add_geom(name=f"bottle_wall{i}", type=mujoco.mjtGeom.mjGEOM_BOX, size=[WALL / 2, half_w, height / 2],
                        pos=[(radius - WALL / 2) * math.cos(a), (radius - WALL / 2) * math.sin(a), 0.0],
                        quat=[math.cos(a / 2), 0.0, 0.0, math.sin(a / 2)], **common)
    for name, z in (("bottle_bottom", -height / 2 + WALL / 2), ("bottle_cap", height / 2 - WALL / 2)):
        bottle.add_geom(name=name, type=mujoco.mjtGeom.mjGEOM_CYLINDER, size=[radius, WALL / 2, 0.0],
                        pos=[0.0, 0.0, z], **common)
    return bottle


def _grain_slots(grain: Grain, inner_r: float, inner_h: float, count: int, rng: np.random.Generator
                 ) -> np.ndarray | None:
    """(count, 3) start positions (bottle frame, from the bottom up) of grains lying along x, in rows along y whose
    layers are stacked like hexagonal rows in the y-z plane (every other layer shifted half a row, layers
    sqrt(3)/2 rows apart: neighbouring grains' axes one grain width plus a gap apart); None when fewer fit."""
    gap = 0.0005
    dx, dyz = 2 * (grain.half_length + grain.radius) + gap, 2 * grain.radius + gap
    reach = inner_r - gap
    slots = []
    z, layer_index = -inner_h / 2 + grain.radius + gap, 0
    while z < inner_h / 2 - grain.radius and len(slots) < count:
        layer = []
        shift = dyz / 2 if layer_index % 2 else 0.0
        for y in np.arange(-reach + grain.radius + shift, reach - grain.radius + 1e-9, dyz):
            half = math.sqrt(max(reach**2 - (abs(y) + grain.radius) ** 2, 0.0)) - grain.half_length - grain.radius
            layer += [(x, y, z) for x in np.arange(-half, half + 1e-9, dx)]
        rng.shuffle(layer)
        slots += layer
        z, layer_index = z + dyz * math.sqrt(3) / 2, layer_index + 1
    return np.asarray(slots[:count]) if len(slots) >= count else None


def parcels(content: Grain, inner_r: float, inner_h: float, level: int, rng: np.random.Generator
            ) -> tuple[Grain, np.ndarray]:
    """The parcels of a granular fill (envs.shake_contents) and their start positions: ``content.parcels[level]``
    of them, fewer where that many would be smaller than a real grain, more (up to four times) where their
    start lattice has no room for them (smaller parcels fit a round bottle better); together they carry the
    fill's mass."""
    mass = content.fill_mass(inner_r, inner_h, level)
    count = max(1, min(content.parcels[level], int(round(mass / content.mass))))
    for n in range(count, 4 * count + 1):
        k = max(1.0, (mass / n / content.mass) ** (1 / 3))
        parcel = Grain(content.radius * k, content.half_length * k, content.density, content.friction)
        slots = _grain_slots(parcel, inner_r, inner_h, n, rng)
        if slots is not None:
            return parcel, slots
    raise ValueError(f"shake: a {mass * 1e3:.0f} g fill of {4 * count} parcels does not fit in a bottle of inner "
                     f"radius {inner_r * 1e3:.0f} mm and height {inner_h * 1e3:.0f} mm")


def _add_contents(spec: mujoco.MjSpec, bottle: mujoco.MjsBody, episode: ShakeEpisode, pos: np.ndarray,
                  quat: np.ndarray, inner_r: float, inner_h: float, rng: np.random.Generator) -> float:
    """Add the episode's contents; returns their mass (kg)."""
    content = CONTENTS[episode.content]
    if isinstance(content, Liquid):
        slosh = slosh_model(content, inner_r, content.fills[episode.fill] * inner_h)
        centroid = -inner_h / 2 + slosh.depth / 2
        bottle.add_geom(name="liquid_fixed", type=mujoco.mjtGeom.mjGEOM_SPHERE, size=[0.003, 0, 0],
                        pos=[0, 0, centroid], mass=slosh.mass - slosh.moving_mass, contype=0, conaffinity=0,
                        rgba=[0.3, 0.6, 1.0, 0.3])
        pivot = bottle.add_body(name="slosh", pos=[0, 0, centroid + slosh.length])
        for axis, name in (([1, 0, 0], "slosh_x"), ([0, 1, 0], "slosh_y")):
            pivot.add_joint(name=name, type=mujoco.mjtJoint.mjJNT_HINGE, axis=axis, range=[-math.pi / 3, math.pi / 3],
                            limited=True, damping=slosh.hinge_damping, armature=1e-7)
        pivot.add_geom(name="slosh_mass", type=mujoco.mjtGeom.mjGEOM_SPHERE, size=[0.003, 0, 0],
                       pos=[0, 0, -slosh.length], mass=slosh.moving_mass, contype=0, conaffinity=0,
                       rgba=[0.3, 0.6, 1.0, 0.5])
        return slosh.mass
    parcel, slots = parcels(content, inner_r, inner_h, episode.fill, rng)
    rot = np.zeros(9)
    mujoco.mju_quat2Mat(rot, quat)
    for i, local in enumerate(slots):
        grain = spec.worldbody.add_body(name=f"grain{i}", pos=(pos + rot.reshape(3, 3) @ local).tolist(),
                                        quat=quat.tolist())
        grain.add_freejoint()
        along_x = [math.cos(math.pi / 4), 0.0, math.sin(math.pi / 4), 0.0]  # the capsule's axis z -> x
        kind = mujoco.mjtGeom.mjGEOM_CAPSULE if content.half_length > 0 else mujoco.mjtGeom.mjGEOM_SPHERE
        grain.add_geom(type=kind, size=[parcel.radius, parcel.half_length, 0], quat=along_x,
                       density=content.density, friction=[content.friction, 0.005, 0.0001], condim=3,
                       contype=GRAIN_BIT, conaffinity=GRAIN_BIT, solref=[2 * TIMESTEP, 1.0],
                       rgba=[0.9, 0.85, 0.6, 1.0])
    return len(slots) * parcel.mass


class ShakeSim:
    """One shaking episode (see the module docstring): the model is built for its bottle and contents."""

    def __init__(self, cfg: ShakeConfig, episode: ShakeEpisode, grasps: GraspCache | None = None) -> None:
        self.cfg, self.episode = cfg, episode
        grasps = grasps if grasps is not None else load_default_cache("cup", "", cfg.hand)
        g = grip(grasps, episode.bucket, episode.grasp_u)
        spec, self._palm_quat0 = wrist_spec(cfg.hand, TIMESTEP)
        radius, height, targets = g.radius, g.height, None
        if cfg.grip == "fingertips":  # the bottle stands on the domes' grip band (at least GRIP_HEIGHT tall)
            height = max(g.height, GRIP_HEIGHT)
            g, targets, radius = fingertip_grip(spec, g, height)
        self.grasp_q = g.q
        bottle = _add_bottle(spec, radius, height, g.pose[:3], g.pose[3:])
        rng = np.random.default_rng([episode.seed, 0x607])
        self.content_mass = _add_contents(spec, bottle, episode, g.pose[:3], g.pose[3:], radius - WALL,
                                          height - 2 * WALL, rng)
        # the hand's contact model without the noslip solver: with tens of grains it halved the rate, and the
        # bottle's drift in the hand over an episode was the same with and without it (3.2-3.4 mm)
        self.model = finish(spec, cfg.hand, "bottle_", noslip=False)
        self._run = WristRun(self.model, g, self._palm_quat0, "bottle", targets)
        self.data = self._run.data

    def _wrist(self, t: float) -> tuple[np.ndarray, np.ndarray]:
        """The wrist's mocap position and quaternion at time ``t``."""
        cfg, ep = self.cfg, self.episode
        ramp = min(max((t - cfg.settle_s) / cfg.ramp_s, 0.0), 1.0) if cfg.ramp_s > 0 else float(t >= cfg.settle_s)
        w = 2 * math.pi * ep.frequency * t + ep.phase
        along = (stroke(w / (2 * math.pi), ep.amplitude, ep.frequency, cfg.max_accel) if cfg.motion == "strokes"
                 else math.sin(w))
        pos = ramp * ep.amplitude * along * np.asarray(ep.direction)
        return pos, tilt_quat(self._palm_quat0, np.asarray(ep.tilt_axis), ramp * ep.tilt * math.sin(w - math.pi / 2))

    def reset(self) -> None:
        """The episode's start: the grasp, the bottle and contents where the model put them, all at rest."""
        self._run.reset(*self._wrist(0.0))

    def run(self, reset: bool = True, on_step=None) -> ShakeRecording:
        """Step the episode (from its start, or with ``reset=False`` from the state :meth:`reset` left and the caller
        may have changed); the contact fields of every physics step and the labels. ``on_step(data)`` is called
        after every physics step (MjData: to look at what the fields do not hold)."""
        if reset:
            self.reset()
        try:
            times, rows, offset = self._run.run(int(round(self.cfg.duration_s / TIMESTEP)), self._wrist, on_step)
        except FloatingPointError as err:
            raise FloatingPointError(f"shake: episode seed {self.episode.seed}: {err}") from None
        held = bool(np.linalg.norm(offset[-1] - offset[0]) <= HELD_TOLERANCE)
        return ShakeRecording(self.episode, times, rows, self.content_mass, offset, held)
